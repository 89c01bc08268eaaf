"""The reconstruct job composed once: its checks, the reconstruction, the comparison with scans, the review page
and the removal of an earlier run's stale outputs, in that order, whoever runs it.

``lgi reconstruct`` runs it with :class:`InProcess`; the reconstruct-shot flow (and ``lgi reconstruct --flow``)
with the flow's runner (:class:`lgi.orchestration.reconstruct.FlowSteps`), which runs the reconstruction as
chunk tasks (on Prefect's threads or on Dask) and the comparison and the page as tasks. A runner does the steps;
:meth:`ReconstructJob.run` decides which run, and when.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from lgi.errors import collected_warnings
from lgi.jobs.reconstruct.options import ReconstructOptions


class Steps(Protocol):
    """How a :class:`ReconstructJob`'s steps are run."""

    def before(self, job: ReconstructJob) -> None:
        """After the outputs are checked, before the shot is read (the flow tracks its footage here)."""

    def reconstruct(self, job: ReconstructJob) -> dict[str, Any]:
        """The shot's outputs into ``job.out`` (both passes with observations); returns the summary, with the
        warnings logged by work done in other processes as ``chunk_warnings`` (those logged here are seen)."""

    def compare(self, job: ReconstructJob, pairs: list[tuple[int, Path]]) -> dict[str, Any]:
        """The meshes against the scans (:func:`lgi.jobs.compare.compare_shot`)."""

    def review(self, job: ReconstructJob, summary: dict[str, Any], scans: str | None, warnings: list[str]) -> str:
        """The review page in ``job.out/review``; returns its path."""


@dataclass(frozen=True)
class ReconstructJob:
    """One reconstruct job: the shot (``index_dir``, ``bundles``), the output folder ``out`` and its options;
    ``scans``: the comparison with scans (:func:`lgi.jobs.compare.shot_scan_options`, None: none); ``review``:
    write the review page; ``inputs``: other files the run reads (footage, a calibration), which its outputs
    must not replace."""

    index_dir: str
    bundles: str
    out: str
    options: ReconstructOptions
    scans: Any = None
    review: bool = False
    inputs: tuple[Any, ...] = ()

    def all_inputs(self) -> tuple[Any, ...]:
        """Every file the run reads, for the output checks."""
        from lgi.jobs.compare import scan_inputs

        o = self.options
        return (self.index_dir, self.bundles, o.jaw, o.observations, o.calib, o.contours, *self.inputs,
                *scan_inputs(self.scans))

    def check(self) -> list[tuple[int, Path]] | None:
        """Refuse, before any work, outputs that cannot be written and scans that are not there; returns the scans'
        ``(frame, file)`` pairs (None without scans)."""
        from lgi.jobs import compare
        from lgi.jobs.reconstruct.outputs import check_outputs

        check_outputs(self.out, self.all_inputs())
        if self.scans is None:
            return None
        pairs = compare.checked_pairs(self.scans)
        compare.check_outputs(self.out, self.scans, pairs)
        return pairs

    def run(self, steps: Steps) -> dict[str, Any]:
        """Check, reconstruct, compare with the scans, write or remove the review page; returns the summary
        (``compare`` and ``review`` added when asked). The caller holds the output folder
        (:func:`lgi.io.atomic.output_lock`)."""
        from lgi.jobs.compare import IN_SHOT, check_scan_frames, remove_outputs
        from lgi.jobs.reconstruct.chunks import prepared_shot
        from lgi.jobs.review import remove_review

        pairs = self.check()
        steps.before(self)
        # Preparing the shot logs what it could not do as asked (the noise, gaps): the page lists it.
        with collected_warnings() as warned:
            if pairs:
                # The shot is prepared once: the reconstruction in this process starts from this one.
                check_scan_frames(pairs, prepared_shot(self.index_dir, self.bundles, self.options).frames,
                                  self.scans)
            summary = steps.reconstruct(self)
            if self.scans is not None:
                summary["compare"] = steps.compare(self, pairs)
        warned += summary.pop("chunk_warnings", [])
        failed = self.scans is not None and summary["compare"]["status"] != "done"
        if self.scans is None:
            remove_outputs(Path(self.out) / IN_SHOT)  # an earlier run's distances were measured on other meshes
        if self.review:
            # Once each: two passes, or chunks seen here and in their parts, log the same warning again.
            notes = [*dict.fromkeys(warned),
                     *([f"scan comparison failed: {summary['compare']['error']}"] if failed else [])]
            scans_dir = self.scans.out if self.scans is not None and not failed else None
            summary["review"] = steps.review(self, {**summary, "options": self.options.to_json()}, scans_dir, notes)
        else:
            remove_review(self.out)  # an earlier run's page would show that run, not this one
        return summary


@dataclass
class InProcess:
    """The steps in this process (``lgi reconstruct``): :func:`lgi.jobs.reconstruct.reconstruct`, the compare
    job, the review page."""

    show_progress: bool = False

    def before(self, job: ReconstructJob) -> None:
        pass

    def reconstruct(self, job: ReconstructJob) -> dict[str, Any]:
        from lgi.jobs.reconstruct.run import reconstruct

        return reconstruct(job.index_dir, job.bundles, job.out, job.options, show_progress=self.show_progress)

    def compare(self, job: ReconstructJob, pairs: list[tuple[int, Path]]) -> dict[str, Any]:
        from lgi.jobs.compare import compare_shot

        return compare_shot(job.out, job.scans, pairs)

    def review(self, job: ReconstructJob, summary: dict[str, Any], scans: str | None, warnings: list[str]) -> str:
        from lgi.jobs.review import ReviewOptions, review_beside

        return review_beside(job.out, job.index_dir, summary, ReviewOptions(fps=job.options.fps, scans=scans),
                             warnings)["page"]
