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
bundles file of markers seen by one camera), :mod:`~lgi.jobs.reconstruct.chunks` (the flow's chunk stages),
:mod:`~lgi.jobs.reconstruct.outputs` (the writer), :mod:`~lgi.jobs.reconstruct.summary`,
:mod:`~lgi.jobs.reconstruct.run` (the reconstruction in this process) and :mod:`~lgi.jobs.reconstruct.job` (the
job composed once: checks, reconstruction, scans, review page, for the command line and the flow).
"""

import importlib
from typing import Any

# The names below are loaded from their modules on first use: the command line imports the options to build its
# parser, and the job's other modules (pandas among them) would make every `lgi --help` 0.6 s slower.
_WHERE = {
    "ReconstructJob": "job", "InProcess": "job", "ReconstructOptions": "options", "parse_far_field": "options",
    "read_jaw_file": "options", "OUTPUTS": "outputs", "OUTPUT_CONTENTS": "outputs", "check_outputs": "outputs",
    "per_frame_table": "outputs", "plot_per_frame": "outputs", "resume_key": "outputs",
    "write_reconstruction": "outputs", "CONSTRAINED": "rays", "RAY_COLUMNS": "rays", "read_constraints": "rays",
    "reconstruct": "run", "Shot": "shot", "chunk_needs": "shot", "constrain_to_rays": "shot", "assemble": "chunks",
    "choose_chunk": "chunks", "finish_chunk": "chunks", "forget_parts": "chunks", "forget_shots": "chunks",
    "load_choices": "chunks", "load_part": "chunks", "preflight": "chunks", "prepared_shot": "chunks",
    "replace_outputs": "chunks", "save_choices": "chunks", "save_part": "chunks", "report_lines": "summary",
    "summarise": "summary"
}


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_WHERE])


__all__ = sorted(_WHERE)
