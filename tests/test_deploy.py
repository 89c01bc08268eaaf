"""The deployments of ``prefect.yaml`` as a pipeline engineer meets them: the commands the README and the file's
header give, the pull step that finds the project, the data root that takes relative paths, one description per
flow parameter, and the deployments' defaults against the flows'. The slow test runs it all on a real server and
a process worker started from another folder."""

from __future__ import annotations

import inspect
import logging
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
FLOWS = {"rebuild-dataset": ("flows.rebuild_dataset", "rebuild_dataset"),
         "reconstruct-shot": ("flows.reconstruct_shot", "reconstruct_shot"),
         "capture-session": ("flows.capture_session", "capture_session")}


def _flow(name: str):
    import importlib

    module, attr = FLOWS[name]
    return getattr(importlib.import_module(module), attr)


def _readme_orchestration() -> str:
    text = (ROOT / "README.md").read_text()
    start = text.index("## Orchestration")
    return text[start:text.index("\n## ", start + 1)]


def _readme_commands() -> list[str]:
    blocks = re.findall(r"```\n(.*?)```", _readme_orchestration(), re.S)
    block = next(b for b in blocks if "prefect worker start" in b)
    return [line.strip() for line in block.splitlines() if line.strip()]


def _header_commands() -> list[str]:
    lines = (ROOT / "prefect.yaml").read_text().splitlines()
    header = lines[:next(k for k, line in enumerate(lines) if not line.startswith("#"))]
    return [line.lstrip("# ").strip() for line in header if line.startswith("#   prefect ")]


def test_readme_and_prefect_yaml_give_the_same_two_commands() -> None:
    commands = _readme_commands()
    assert len(commands) == 2 and commands == _header_commands(), (commands, _header_commands())
    assert "deploy --all" in commands[0] and commands[1].startswith("prefect worker start --pool lgi-process")


def test_every_flow_parameter_has_its_own_description() -> None:
    from prefect.utilities.callables import parameter_schema

    for name in FLOWS:
        props = parameter_schema(_flow(name)).model_dump()["properties"]
        docs = {p: (v.get("description") or "").strip() for p, v in props.items()}
        assert all(docs.values()), (name, [p for p, d in docs.items() if not d])
        shared = {d: [p for p in docs if docs[p] == d] for d in docs.values()}
        assert all(len(ps) == 1 for ps in shared.values()), (name, [ps for ps in shared.values() if len(ps) > 1])


class _TwoInOne:
    """Options documented as the job options are (a module-level class: its docstring's entries at 4 spaces).

    Attributes
    ----------
    a, b : int
        Both at once.
    """


def test_described_refuses_two_parameters_with_one_description() -> None:
    from lgi.orchestration.params import described

    def f(a: int = 0, b: int = 0) -> None:
        """A flow."""

    with pytest.raises(TypeError, match="sharing one description"):
        described(_TwoInOne)(f)


def test_deployment_defaults_equal_the_flows_or_are_listed_in_the_readme() -> None:
    config = yaml.safe_load((ROOT / "prefect.yaml").read_text())
    overrides: dict[str, set[str]] = {}
    for d in config["deployments"]:
        sig = inspect.signature(_flow(d["name"]))
        assert set(d["parameters"]) <= set(sig.parameters), d["name"]
        for p, value in d["parameters"].items():
            default = sig.parameters[p].default
            if default is not inspect.Parameter.empty and value != default:
                overrides.setdefault(d["name"], set()).add(p)
    line = re.search(r"Overrides of the flows'\s+defaults in `prefect.yaml`:(.*?)\. ", _readme_orchestration(), re.S)
    assert line, "the README lists no overrides"
    listed = {m[0]: set(re.findall(r"`(\w+)`", m[1]))
              for m in re.findall(r"`([\w-]+)`:((?:\s*`\w+`,?)+)", line[1])}
    assert listed == overrides


def test_pull_step_finds_the_project_or_says_what_to_set(tmp_path: Path, monkeypatch) -> None:
    from lgi.orchestration.deploy import ProjectDirectoryError, project_directory, record_project

    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("LGI_PROJECT_DIR", raising=False)
    monkeypatch.delenv("PREFECT__FLOW_RUN_ID", raising=False)
    with pytest.raises(ProjectDirectoryError, match="prefect deploy runs from the lgi repository root"):
        record_project()
    for recorded in ("", str(tmp_path / "moved")):
        with pytest.raises(ProjectDirectoryError, match="set LGI_PROJECT_DIR"):
            project_directory(recorded)
    assert Path.cwd() == tmp_path
    assert project_directory(str(ROOT)) == {"directory": str(ROOT)} and Path.cwd() == ROOT
    # A wrong override is an error, not passed over for the recorded folder.
    monkeypatch.setenv("LGI_PROJECT_DIR", str(tmp_path))
    with pytest.raises(ProjectDirectoryError, match=r"\$LGI_PROJECT_DIR\) lacks prefect.yaml"):
        project_directory(str(ROOT))
    monkeypatch.chdir(ROOT)
    recorded = record_project()
    assert recorded["directory"] == str(ROOT) and (Path(recorded["shipped"]) / "markers_ict.csv").is_file()


def test_relative_paths_go_under_the_data_root(tmp_path: Path) -> None:
    from lgi.errors import InputError
    from lgi.orchestration.deploy import PathResolver

    at = PathResolver(tmp_path / "root")
    assert at("datasets/ict", "out") == str(tmp_path / "root" / "datasets" / "ict")
    assert at("/abs/file.csv", "bundles") == "/abs/file.csv"
    assert at("auto", "jaw", ("auto", "none")) == "auto" and at(None, "calib") is None
    with pytest.raises(InputError, match="leaves the data root"):
        at("../elsewhere", "out")
    assert PathResolver(None)("datasets/ict", "out") == "datasets/ict"  # outside a deployment: as given


def test_outputs_stay_under_the_data_root_after_links(tmp_path: Path) -> None:
    from lgi.errors import InputError
    from lgi.orchestration.deploy import PathResolver

    root, extra, outside = tmp_path / "root", tmp_path / "extra", tmp_path / "outside"
    for d in (root, extra, outside):
        d.mkdir()
    (root / "escape").symlink_to(outside)  # a link inside the root that leads out of it
    at = PathResolver(root, [extra])
    assert at("shots/a/recon", "out", output=True) == str(root / "shots" / "a" / "recon")
    assert at(str(extra / "x"), "out", output=True) == str(extra / "x")  # an output root from the Variable
    assert at(str(outside / "in.csv"), "bundles") == str(outside / "in.csv")  # inputs may be read anywhere
    for value, says in (("escape/recon", "parameter out: the output 'escape/recon' leads to"),
                        (str(outside / "recon"), "outside the data root"), ("", "parameter out: an empty path"),
                        (".", "is the data root"), ("~/recon", "names a home folder"),
                        ("../x", "leaves the data root")):
        with pytest.raises(InputError, match=re.escape(says)):
            at(value, "out", output=True)


def test_a_deployment_run_refuses_an_output_outside_its_root(prefect_harness, tmp_path: Path, monkeypatch) -> None:
    """The reconstruct-shot flow run as a deployment's run would be (its parameters resolved under the data root):
    an output that a link inside the root takes out of it is refused before any work, naming the parameter."""
    from prefect.variables import Variable

    import lgi.orchestration.deploy as deploy
    from lgi.errors import InputError
    from lgi.orchestration.reconstruct import reconstruct_shot

    root, outside = tmp_path / "root", tmp_path / "outside"
    outside.mkdir()
    (root / "shots").mkdir(parents=True)
    (root / "shots" / "escape").symlink_to(outside)
    Variable.set(deploy.DATA_ROOT_VARIABLE, str(root), overwrite=True)
    monkeypatch.setattr(deploy, "in_deployment", lambda: True)
    with pytest.raises(InputError, match="parameter out: the output 'shots/escape/recon' leads to"):
        reconstruct_shot("index", "shots/bundles.csv", "shots/escape/recon")
    with pytest.raises(InputError, match="parameter scan_region: the relative path '../v.json' leaves"):
        reconstruct_shot("index", "shots/bundles.csv", "shots/recon", scan_region="../v.json")
    assert not list(outside.iterdir())


def test_data_root_from_the_variable(prefect_harness, caplog) -> None:
    from prefect.variables import Variable

    from lgi.errors import InputError
    from lgi.orchestration.deploy import DATA_ROOT_VARIABLE, data_root

    Variable.unset(DATA_ROOT_VARIABLE)
    with caplog.at_level(logging.WARNING, logger="lgi"):
        assert data_root() == Path("~/lgi-data").expanduser()
    assert "lgi_data_root is not set" in caplog.text
    try:
        Variable.set(DATA_ROOT_VARIABLE, "/srv/lgi", overwrite=True)
        assert data_root() == Path("/srv/lgi")
        Variable.set(DATA_ROOT_VARIABLE, "relative/root", overwrite=True)
        with pytest.raises(InputError, match="absolute path"):
            data_root()
        Variable.set(DATA_ROOT_VARIABLE, str(ROOT / "datasets"), overwrite=True)
        with pytest.raises(InputError, match="inside the lgi source tree"):
            data_root()
    finally:
        Variable.unset(DATA_ROOT_VARIABLE)


# --- the whole path on a real server ----------------------------------------------------------------------


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _bin(name: str) -> str:
    exe = Path(sys.executable).with_name(name)
    return str(exe) if exe.exists() else shutil.which(name) or name


def _healthy(api: str) -> bool:
    try:
        return httpx.get(f"{api}/health", timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


def _start(argv: list[str] | str, cwd: Path, env: dict, log: Path) -> subprocess.Popen:
    with open(log, "w") as out:
        return subprocess.Popen(argv, cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT, shell=isinstance(
            argv, str), start_new_session=True)


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def _run_deployment(api: str, name: str, parameters: dict, timeout: float = 600) -> dict:
    """Create a run of deployment ``name`` with ``parameters`` (as ``prefect deployment run -p`` does) and wait
    for it to end; returns the run."""
    dep = httpx.get(f"{api}/deployments/name/{name}/{name}", timeout=10).json()
    run = httpx.post(f"{api}/deployments/{dep['id']}/create_flow_run", json={"parameters": parameters},
                     timeout=10).json()
    deadline = time.time() + timeout
    while time.time() < deadline:
        run = httpx.get(f"{api}/flow_runs/{run['id']}", timeout=10).json()
        if run["state"]["type"] in ("COMPLETED", "FAILED", "CRASHED", "CANCELLED"):
            return run
        time.sleep(1)
    pytest.fail(f"{name}: run not finished within {timeout} s: {run['state']}")


def _logs(api: str, run: dict) -> str:
    rows = httpx.post(f"{api}/logs/filter", json={"logs": {"flow_run_id": {"any_": [run["id"]]}}}, timeout=10).json()
    return "\n".join(r["message"] for r in rows)


@pytest.mark.slow  # about 90 s: a server, prefect deploy, two workers, three runs
def test_deployments_run_from_prefect_yaml_on_a_worker_elsewhere(tmp_path: Path, obj_folder: Path) -> None:
    from lgi.cli import main
    from lgi.orchestration import artifact_key

    assert main(["synth", "--out", str(tmp_path / "s"), "--vertices", "1500", "--frames", "12", "-q"]) == 0
    data, elsewhere = tmp_path / "data", tmp_path / "elsewhere"
    elsewhere.mkdir()
    (data / "shots" / "shot001").mkdir(parents=True)
    shutil.copyfile(tmp_path / "s" / "bundles.csv", data / "shots" / "shot001" / "bundles.csv")

    port = _free_port()
    api = f"http://127.0.0.1:{port}/api"
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PREFECT_", "LGI_PROJECT_DIR"))}
    # The README's server on a free port (4200 may be taken), and its PREFECT_API_URL.
    env.update(PREFECT_HOME=str(tmp_path / "home"), PREFECT_SERVER_ANALYTICS_ENABLED="false",
               PREFECT_SERVER_API_PORT=str(port))
    server = _start([_bin("prefect"), "server", "start"], tmp_path, env, tmp_path / "server.log")
    env["PREFECT_API_URL"] = api
    worker = None
    try:
        deadline = time.time() + 240
        while not _healthy(api):
            assert server.poll() is None, (tmp_path / "server.log").read_text()[-3000:]
            assert time.time() < deadline, "the Prefect server did not start within 240 s"
            time.sleep(1)
        deploy, start_worker = _readme_commands()
        r = subprocess.run([_bin("prefect"), "variable", "set", "lgi_data_root", str(data)], env=env,
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        t0 = time.time()
        r = subprocess.run(deploy, shell=True, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
        print(f"deploy: {time.time() - t0:.1f} s")
        # Started as the README says, from another folder, without LGI_PROJECT_DIR.
        worker = _start(start_worker, elsewhere, env, tmp_path / "worker.log")

        t0 = time.time()
        run = _run_deployment(api, "rebuild-dataset", {"shapes_dir": str(obj_folder), "rigid_vertices": "auto",
                                                       "markers": str(tmp_path / "s" / "markers.csv")})
        print(f"rebuild-dataset: {run['state']['type']} in {time.time() - t0:.1f} s")
        assert run["state"]["type"] == "COMPLETED", (run["state"], (tmp_path / "worker.log").read_text()[-4000:])
        out = data / "datasets" / "ict"  # the deployment's out, under the data root
        assert (out / "index" / "manifest.json").is_file() and (out / "verification" / "errors.png").is_file()
        assert not [p.name for p in out.iterdir() if p.name.endswith(".lock")]

        t0 = time.time()
        run = _run_deployment(api, "reconstruct-shot", {})  # the deployment's parameters as they are
        print(f"reconstruct-shot: {run['state']['type']} in {time.time() - t0:.1f} s")
        assert run["state"]["type"] == "COMPLETED", (run["state"], (tmp_path / "worker.log").read_text()[-4000:])
        recon = data / "shots" / "shot001" / "recon"
        for name in ("meshes.npz", "diagnostics.csv", "per_frame.csv", "shot.usdc", "per_frame.png"):
            assert (recon / name).is_file(), name
        # Nothing where the worker runs, nothing in the source tree.
        assert not list(elsewhere.iterdir()) and not (ROOT / "datasets").exists() and not (ROOT / "shots").exists()
        keys = {a["key"] for a in httpx.post(f"{api}/artifacts/filter", json={}, timeout=10).json()}
        assert None not in keys, keys
        for key in (artifact_key("rebuild-report", out), artifact_key("verification", out),
                    artifact_key("shot-report", recon), artifact_key("shot-progress", recon)):
            assert key in keys, (key, keys)

        # A worker told a wrong project folder: the run fails with the message naming what to set.
        _stop(worker)
        wrong = dict(env, LGI_PROJECT_DIR=str(tmp_path / "nowhere"))
        worker = _start(start_worker, elsewhere, wrong, tmp_path / "worker2.log")
        run = _run_deployment(api, "reconstruct-shot", {})
        assert run["state"]["type"] == "FAILED", run["state"]
        assert "set LGI_PROJECT_DIR" in run["state"]["message"] and "nowhere" in run["state"]["message"]
        assert "set LGI_PROJECT_DIR" in _logs(api, run)
    finally:
        if worker is not None:
            _stop(worker)
        _stop(server)
