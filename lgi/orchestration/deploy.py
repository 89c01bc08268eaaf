"""What ``prefect.yaml``'s deployments need around the flows: where the project is, and where a deployment run's
relative paths go.

* :func:`record_project` is a build step: ``prefect deploy`` runs it in the project's directory and the
  deployment stores what it returns (the directory, the shared data folder, the shipped files' folder).
* :func:`project_directory` is the pull step: on the worker, before the flow is loaded, it moves into the
  project directory (``$LGI_PROJECT_DIR`` when set, else the one recorded at deploy time), or fails with one
  message naming what to set. A process worker starts each run in a temporary folder, where ``flows/`` is not.
* :func:`data_root` and :func:`deployment_path`: a deployment run takes its relative paths under the data root,
  the Prefect Variable ``lgi_data_root`` (default ``~/lgi-data``), never under the folder the worker happens to
  run in (a worker started in the source tree would otherwise write its nightly rebuild there). Runs outside a
  deployment (the command line's ``--flow``, a flow called from Python) read paths as given.
"""

from __future__ import annotations

import logging
import os
from datetime import timedelta
from pathlib import Path
from uuid import UUID

from lgi.errors import InputError
from lgi.paths import REPO_ROOT, shared_data, shipped

#: The Prefect Variable holding the folder a deployment run's relative paths are taken under.
DATA_ROOT_VARIABLE = "lgi_data_root"
#: Its value when the Variable is not set (``~``: the home folder of the user the worker runs as).
DEFAULT_DATA_ROOT = "~/lgi-data"
#: The Prefect Variable listing, besides the data root, the folders a deployment run may write into (a JSON list
#: of absolute paths; unset: the data root alone).
OUTPUT_ROOTS_VARIABLE = "lgi_output_roots"
#: The environment variable that overrides the project directory recorded at deploy time.
PROJECT_ENV = "LGI_PROJECT_DIR"
#: Files that make a folder the lgi project: the deployments' entry points.
_MARKERS = ("prefect.yaml", "flows/rebuild_dataset.py", "flows/reconstruct_shot.py", "flows/capture_session.py")

log = logging.getLogger("lgi.orchestration")


class ProjectDirectoryError(RuntimeError):
    """The project directory a deployment run needs is missing or is not the lgi project."""


def _missing(directory: Path) -> list[str]:
    return [m for m in _MARKERS if not (directory / m).is_file()]


def record_project() -> dict[str, str]:
    """Build step of ``prefect.yaml``: the project directory (where ``prefect deploy`` runs), the shared data
    folder (``$LGI_SHARED_DATA`` or ``../shared/data``) and the folder of the shipped marker layouts, as
    absolute paths for the deployments' pull step and parameters (``{{ project.directory }}`` and so on).

    Raises
    ------
    ProjectDirectoryError
        ``prefect deploy`` was not run from the lgi repository root (the entry points would not be found).
    """
    here = Path.cwd().resolve()
    if missing := _missing(here):
        raise ProjectDirectoryError(f"prefect deploy runs from the lgi repository root (the folder holding "
                                    f"prefect.yaml and flows/); {here} lacks {', '.join(missing)}")
    return {"directory": str(here), "shared_data": str(shared_data("").resolve()),
            "shipped": str(shipped("markers_ict.csv").parent)}


# Seconds between a flow run's heartbeats (PREFECT_FLOWS_HEARTBEAT_FREQUENCY in the deployments' environment),
# and how long the server waits for the next before it calls the run crashed.
HEARTBEAT_SECONDS = 30
SILENT_SECONDS = 3 * HEARTBEAT_SECONDS
SILENT_RUNS_AUTOMATION = "lgi: crash silent flow runs"


def crash_silent_runs() -> dict[str, str]:
    """Build step: the server marks a flow run Crashed when its heartbeats stop for ``SILENT_SECONDS`` (its
    process killed with the worker's, a node lost). Without it such a run stays Running for ever, and the
    rebuild's concurrency limit of one would then queue every later nightly rebuild behind it. Made once (an
    automation of that name already there is left as it is); returns its id."""

    from prefect.automations import Automation, ChangeFlowRunState, EventTrigger, Posture
    from prefect.client.schemas.objects import StateType

    try:
        existing = Automation.read(name=SILENT_RUNS_AUTOMATION)
    except ValueError:
        existing = None
    if existing is not None:
        return {"automation": str(existing.id)}
    ends = {f"prefect.flow-run.{s}" for s in ("Completed", "Failed", "Cancelled", "Crashed")}
    made = Automation(
        name=SILENT_RUNS_AUTOMATION,
        description=f"A flow run with no heartbeat for {SILENT_SECONDS} s is marked Crashed (lgi prefect.yaml).",
        trigger=EventTrigger(after={"prefect.flow-run.heartbeat"}, expect={"prefect.flow-run.heartbeat", *ends},
                             match={"prefect.resource.id": ["prefect.flow-run.*"]},
                             for_each={"prefect.resource.id"}, posture=Posture.Proactive, threshold=1,
                             within=timedelta(seconds=SILENT_SECONDS)),
        actions=[ChangeFlowRunState(state=StateType.CRASHED, message=f"no heartbeat for {SILENT_SECONDS} s: its "
                                    "process is gone (a killed worker or a lost node); run it again")],
    ).create()
    return {"automation": str(made.id)}


def project_directory(recorded: str) -> dict[str, str]:
    """Pull step of ``prefect.yaml``: move into the project directory before Prefect loads the flow from its
    entry point (``flows/...``): ``$LGI_PROJECT_DIR`` when the worker's environment sets it, else ``recorded``,
    the directory ``prefect deploy`` ran in. Returns ``{"directory": ...}``, which Prefect also moves into.

    Raises
    ------
    ProjectDirectoryError
        The directory does not exist or lacks the entry points: the message names the directory, where it came
        from and what to set (a wrong ``$LGI_PROJECT_DIR`` is an error, never passed over for ``recorded``).
    """
    try:
        return _enter_project(recorded)
    except ProjectDirectoryError as exc:
        _tell_the_run(str(exc))
        raise


def _enter_project(recorded: str) -> dict[str, str]:
    override = os.environ.get(PROJECT_ENV, "").strip()
    source = f"${PROJECT_ENV}" if override else "the directory recorded when prefect deploy ran"
    directory = Path(override or recorded).expanduser()
    if not str(recorded).strip() and not override:
        raise ProjectDirectoryError(f"no lgi project directory: set {PROJECT_ENV} in the worker's environment to "
                                    "the lgi repository root (the folder holding prefect.yaml and flows/), or run "
                                    "prefect deploy --all again from it")
    if not directory.is_dir() or (missing := _missing(directory)):
        what = "does not exist" if not directory.is_dir() else f"lacks {', '.join(missing)}"
        from lgi.paths import REPO_ROOT

        # An editable install names its checkout: most likely the folder meant.
        hint = "" if _missing(REPO_ROOT) else f" (the lgi installed for this worker is the project at {REPO_ROOT})"
        raise ProjectDirectoryError(
            f"lgi project directory {directory} ({source}) {what}: set {PROJECT_ENV} in the worker's environment "
            f"to the lgi repository root (the folder holding prefect.yaml and flows/){hint}, or run prefect deploy "
            "--all again from it")
    directory = directory.resolve()
    os.chdir(directory)
    return {"directory": str(directory)}


def _tell_the_run(message: str) -> None:
    """Put ``message`` in the flow run's own log and end the run Failed with it as the state's message (the UI's
    and ``prefect flow-run inspect``'s): Prefect 3.8.8 shows a failed pull step's error only on the worker's
    console, and the run then ends Crashed with "Process exited with status code: 1" and an unrelated
    FileNotFoundError in its log. The worker's Crashed state that follows is refused by the server (a Failed
    run's state is final)."""
    run_id = os.environ.get("PREFECT__FLOW_RUN_ID")
    if not run_id:
        return
    try:
        from prefect.client.orchestration import get_client
        from prefect.logging.loggers import flow_run_logger
        from prefect.states import Failed

        flow_run_logger(flow_run_id=UUID(run_id)).error("lgi deployment: %s", message)
        for handler in logging.getLogger("prefect.flow_runs").handlers:
            handler.flush()  # the process ends with the error: send the record now
        with get_client(sync_client=True) as client:
            client.set_flow_run_state(UUID(run_id), Failed(message=message))
    except Exception as exc:  # noqa: BLE001 - the error is raised anyway; the worker's console shows it
        log.warning("could not report the error to the flow run: %s", exc)


def in_deployment() -> bool:
    """True inside a flow run created from a deployment (not a subflow, not a flow called from Python)."""
    from prefect.context import FlowRunContext

    ctx = FlowRunContext.get()
    return bool(ctx and ctx.flow_run and ctx.flow_run.deployment_id)


def data_root() -> Path:
    """The folder a deployment run's relative paths are taken under: the Prefect Variable ``lgi_data_root``, or
    ``~/lgi-data`` with a warning when it is not set. Must be absolute (``~`` allowed) and outside the source
    tree lgi runs from."""
    from prefect.variables import Variable

    value = Variable.get(DATA_ROOT_VARIABLE, default=None)
    if value is None:
        log.warning("Prefect variable %s is not set: relative paths go under %s (set it with: prefect variable "
                    "set %s /path/to/data)", DATA_ROOT_VARIABLE, Path(DEFAULT_DATA_ROOT).expanduser(),
                    DATA_ROOT_VARIABLE)
        value = DEFAULT_DATA_ROOT
    if not isinstance(value, str) or not value.strip():
        raise InputError(f"Prefect variable {DATA_ROOT_VARIABLE} must be a folder path (a string), not {value!r}")
    root = Path(value.strip()).expanduser()
    if not root.is_absolute():
        raise InputError(f"Prefect variable {DATA_ROOT_VARIABLE} must be an absolute path, not {value!r}")

    # A nightly run writing into the source tree is what the root is there to prevent.
    if (REPO_ROOT / "prefect.yaml").is_file() and Path(os.path.realpath(root)).is_relative_to(REPO_ROOT):
        raise InputError(f"Prefect variable {DATA_ROOT_VARIABLE} ({root}) is inside the lgi source tree {REPO_ROOT}: "
                         "set it to a folder outside it")
    return root


def output_roots() -> list[Path]:
    """The folders besides the data root a deployment run may write into (Prefect Variable
    :data:`OUTPUT_ROOTS_VARIABLE`), each absolute."""
    from prefect.variables import Variable

    value = Variable.get(OUTPUT_ROOTS_VARIABLE, default=None)
    if value is None:
        return []
    if isinstance(value, str):
        import json

        try:
            value = json.loads(value)
        except ValueError:
            value = [value]
    if not isinstance(value, list) or not all(isinstance(v, str) and Path(v).is_absolute() for v in value):
        raise InputError(f"Prefect variable {OUTPUT_ROOTS_VARIABLE} must be a list of absolute folder paths, not "
                         f"{value!r}")
    return [Path(v) for v in value]


def run_paths() -> PathResolver:
    """The path resolver of the current flow run: relative paths under :func:`data_root` in a deployment's run,
    outputs kept under it or :func:`output_roots`; as given elsewhere."""
    if not in_deployment():
        return PathResolver(None)
    root = data_root()
    log.info("deployment run: relative paths are taken under %s (Prefect variable %s)", root, DATA_ROOT_VARIABLE)
    return PathResolver(root, output_roots())


class PathResolver:
    """Resolves a flow's path parameters. With a ``root`` (a deployment's run): a relative path goes under it; an
    output (``output=True``), after its symbolic links are followed, must stay under the root or one of
    ``allowed`` (a deployment's parameters never make the worker write wherever it may); an input may be
    absolute; ``~`` and empty paths are refused. Without a root, paths are left as given."""

    def __init__(self, root: Path | None, allowed: list[Path] | tuple[Path, ...] = ()) -> None:
        self.root = root
        self.allowed = tuple(allowed)

    def __call__(self, value: str | None, name: str, keywords: tuple[str, ...] = (),
                 output: bool = False) -> str | None:
        """``value`` of the parameter ``name`` resolved; None, and the ``keywords`` it may take instead of a
        path (``auto``, ``none``), as given."""
        if self.root is None or value is None or not isinstance(value, str) or value in keywords:
            return value
        if not value.strip():
            raise InputError(f"parameter {name}: an empty path (it would be the data root {self.root} itself)")
        if value.startswith("~"):
            raise InputError(f"parameter {name}: {value!r} names a home folder, which a deployment's run does not "
                             f"take: give a path under the data root {self.root}")
        path = Path(value)
        full = Path(os.path.normpath(path if path.is_absolute() else self.root / path))
        if not path.is_absolute() and not full.is_relative_to(os.path.normpath(self.root)):
            raise InputError(f"parameter {name}: the relative path {value!r} leaves the data root {self.root} "
                             f"(Prefect variable {DATA_ROOT_VARIABLE}); give an absolute path")
        if output:
            real = Path(os.path.realpath(full))
            roots = [Path(os.path.realpath(r)) for r in (self.root, *self.allowed)]
            if not any(real == r or real.is_relative_to(r) for r in roots):
                where = f"the data root {self.root}" + (f" or {', '.join(map(str, self.allowed))}" if self.allowed
                                                         else "")
                raise InputError(f"parameter {name}: the output {value!r} leads to {real}, outside {where}: a "
                                 f"deployment's run writes only there (Prefect variables {DATA_ROOT_VARIABLE}, "
                                 f"{OUTPUT_ROOTS_VARIABLE})")
            if real == roots[0]:
                raise InputError(f"parameter {name}: the output {value!r} is the data root {self.root} itself: "
                                 "give a folder inside it")
        return str(full)
