"""The nightly rebuild's schedule fires: a local Prefect server with its scheduler, ``prefect deploy --all`` of the
repository's ``prefect.yaml``, and the scheduler's runs of the rebuild-dataset deployment found at 03:00 UTC.

Prefect 3.8.8's scheduler fails every cycle with SQLAlchemy 2.1 (``Can't evaluate bulk DML statement``) and
creates no runs; pyproject pins SQLAlchemy below 2.1, and this test fails if that pin is lost."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _prefect() -> str:
    exe = Path(sys.executable).with_name("prefect")
    return str(exe) if exe.exists() else shutil.which("prefect") or "prefect"


@pytest.mark.slow  # 43 s: a real Prefect server, deploy and scheduler
def test_nightly_rebuild_schedule_creates_runs(tmp_path: Path) -> None:
    port = _free_port()
    api = f"http://127.0.0.1:{port}/api"
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env.update(PREFECT_HOME=str(tmp_path / "home"), PREFECT_API_URL=api, PREFECT_SERVER_ANALYTICS_ENABLED="false",
               PREFECT_SERVER_SERVICES_SCHEDULER_LOOP_SECONDS="1", LGI_PROJECT_DIR=str(ROOT))
    log = tmp_path / "server.log"
    with open(log, "w") as out:
        server = subprocess.Popen([_prefect(), "server", "start", "--host", "127.0.0.1", "--port", str(port)],
                                  env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.time() + 240
        while time.time() < deadline:
            assert server.poll() is None, log.read_text()[-3000:]
            try:
                if httpx.get(f"{api}/health", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(1)
        else:
            pytest.fail("the Prefect server did not start within 240 s")
        for argv in (["work-pool", "create", "lgi-process", "--type", "process"], ["deploy", "--all"]):
            r = subprocess.run([_prefect(), "--no-prompt", *argv], cwd=ROOT, env=env, capture_output=True, text=True,
                               timeout=300)
            assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
        deployments = {d["name"]: d for d in httpx.post(f"{api}/deployments/filter", json={}, timeout=10).json()}
        assert sorted(deployments) == ["capture-session", "rebuild-dataset", "reconstruct-shot"]
        rebuild = deployments["rebuild-dataset"]
        limit = rebuild.get("concurrency_limit") or (rebuild.get("global_concurrency_limit") or {}).get("limit")
        assert limit == 1, rebuild
        assert (rebuild.get("concurrency_options") or {}).get("collision_strategy") == "ENQUEUE", rebuild
        runs: list[dict] = []
        deadline = time.time() + 120
        while time.time() < deadline and not runs:
            r = httpx.post(f"{api}/flow_runs/filter", timeout=10, json={
                "deployments": {"name": {"any_": ["rebuild-dataset"]}}, "flow_runs": {"state": {"type": {
                    "any_": ["SCHEDULED"]}}}})
            r.raise_for_status()
            runs = r.json()
            time.sleep(1)
        server_log = log.read_text()
        assert "InvalidRequestError" not in server_log, server_log[-3000:]
        assert runs, "the scheduler made no runs of the rebuild-dataset deployment"
        starts = sorted(run["expected_start_time"] for run in runs)
        assert all("T03:00:00" in s for s in starts), starts
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)
