"""The capture session's tasks (defined in :mod:`lgi.orchestration.capture` and :mod:`lgi.orchestration.rig`)."""

from lgi.orchestration.capture import calibrate_session, export_shot
from lgi.orchestration.rig import rig_solve_shot

__all__ = ["calibrate_session", "export_shot", "rig_solve_shot"]
