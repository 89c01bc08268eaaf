"""The rig solve as a flow task: ``lgi rig-solve`` on a reconstructed shot, with the command line's options."""

from __future__ import annotations

from prefect import task
from prefect.cache_policies import NO_CACHE

from lgi.jobs.rig_solve import RigSolveOptions, rig_solve


@task(name="rig-solve-shot", cache_policy=NO_CACHE, persist_result=False, timeout_seconds=6 * 3600)
def rig_solve_shot(recon: str, rig_dir: str, out: str, usd: str | None, rig_usd: str | None, options: dict) -> dict:
    """Solve a reconstructed shot onto the actor's rig (``lgi rig-solve``): curves, residuals, error map and, with
    ``usd``, the animation over ``rig_usd``."""
    return rig_solve(recon, rig_dir, out, RigSolveOptions(**options), usd=usd, rig_usd=rig_usd)
