"""The reconstruct job: a shot's bundles to meshes, diagnostics and optional OBJ/USD/plot outputs.

One implementation, three schedules:

- :func:`reconstruct` runs the whole shot in this process (``lgi reconstruct``);
- the reconstruct-shot flow runs the same stages as tasks: :func:`choose_chunk` over consecutive chunks
  of frames, each starting from the last choice of the chunk before (so the choice is the one a single
  pass makes), :func:`finish_chunk` over chunks in parallel (a frame's surface depends only on the
  choices in its smoothing windows), then :func:`assemble` writes the outputs;
- both write through :func:`write_reconstruction`.

Results do not depend on the schedule: any chunk size, task runner or ``--flow`` gives the same files
(tested).

The package's modules follow the job: :mod:`~lgi.jobs.reconstruct.options` (the flags and their checks),
:mod:`~lgi.jobs.reconstruct.shot` (a prepared shot and its stages), :mod:`~lgi.jobs.reconstruct.rays` (the
bundles file of markers seen by one camera), :mod:`~lgi.jobs.reconstruct.stages` (the flow's chunk stages),
:mod:`~lgi.jobs.reconstruct.outputs` (the writer), :mod:`~lgi.jobs.reconstruct.summary` and
:mod:`~lgi.jobs.reconstruct.run` (the whole job in this process).
"""

from lgi.jobs.reconstruct.options import ReconstructOptions, parse_far_field, read_jaw_file
from lgi.jobs.reconstruct.outputs import (
                                          OUTPUT_CONTENTS,
                                          OUTPUTS,
                                          check_outputs,
                                          per_frame_table,
                                          plot_per_frame,
                                          resume_key,
                                          write_reconstruction,
)
from lgi.jobs.reconstruct.rays import CONSTRAINED, RAY_COLUMNS, read_constraints
from lgi.jobs.reconstruct.run import reconstruct
from lgi.jobs.reconstruct.shot import Shot, chunk_needs, constrain_to_rays
from lgi.jobs.reconstruct.stages import (
                                          assemble,
                                          choose_chunk,
                                          finish_chunk,
                                          forget_parts,
                                          forget_shots,
                                          load_choices,
                                          load_part,
                                          preflight,
                                          prepared_shot,
                                          replace_outputs,
                                          save_choices,
                                          save_part,
)
from lgi.jobs.reconstruct.summary import report_lines, summarise

__all__ = ["CONSTRAINED", "OUTPUTS", "OUTPUT_CONTENTS", "RAY_COLUMNS", "ReconstructOptions", "Shot", "assemble",
           "check_outputs", "choose_chunk", "chunk_needs", "constrain_to_rays", "finish_chunk", "forget_parts",
           "forget_shots", "load_choices", "load_part", "parse_far_field", "per_frame_table", "plot_per_frame",
           "preflight", "prepared_shot", "read_constraints", "read_jaw_file", "reconstruct", "replace_outputs",
           "report_lines", "resume_key", "save_choices", "save_part", "summarise", "write_reconstruction"]
