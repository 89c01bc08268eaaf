"""A small WebDriver BiDi client for Firefox, for the review page's browser tests.

Playwright drives only its own patched Firefox, and geckodriver is not packaged by Debian; Firefox itself
(128 and later) speaks WebDriver BiDi, the W3C protocol, on ``--remote-debugging-port``. This client sends the
few commands the tests need over the ``websockets`` package (installed with Prefect): open a session, navigate,
evaluate a script, take a screenshot, and collect the console's error entries.

Headless Firefox finds no GL driver without an X display ("Exhausted GL driver options"), so WebGL needs one:
the client starts a private ``Xvfb`` (Debian's ``xvfb``) when ``$DISPLAY`` is not set, and Mesa's llvmpipe then
renders on the CPU.
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import socket
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

FIREFOX = shutil.which("firefox-esr") or shutil.which("firefox") or "/usr/bin/firefox-esr"

# Prefs of a throwaway profile: WebGL on the CPU (a headless machine has no GPU and Firefox would otherwise
# block its software renderer), and nothing that phones home at start-up.
PREFS = {
    "webgl.force-enabled": True,
    "webgl.disabled": False,
    "gfx.webrender.software": True,
    "browser.shell.checkDefaultBrowser": False,
    "datareporting.policy.dataSubmissionEnabled": False,
    "toolkit.telemetry.reportingpolicy.firstRun": False,
    "app.update.disabledForTesting": True,
    "browser.startup.homepage_override.mstone": "ignore",
}


class BiDiError(RuntimeError):
    """A command the browser answered with an error, or a browser that did not start."""


def _start_xvfb() -> tuple[subprocess.Popen, str]:
    """A private X server on a free display (Xvfb picks it and writes its number to a pipe)."""
    xvfb = shutil.which("Xvfb")
    if xvfb is None:
        raise BiDiError("WebGL in headless Firefox needs an X display and there is neither $DISPLAY nor Xvfb "
                        "(apt-get install -y xvfb)")
    read, write = os.pipe()
    proc = subprocess.Popen([xvfb, "-displayfd", str(write), "-screen", "0", "1600x1200x24", "-nolisten", "tcp"],
                            pass_fds=(write,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(write)
    with os.fdopen(read) as f:
        number = f.readline().strip()
    if not number:
        proc.kill()
        raise BiDiError("Xvfb did not start")
    return proc, f":{number}"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Firefox:
    """Headless Firefox with one tab, driven over WebDriver BiDi.

    ``errors`` collects the console's error entries and uncaught exceptions of every page loaded.
    """

    def __init__(self, width: int = 1100, height: int = 760, timeout: float = 60.0) -> None:
        from websockets.sync.client import connect

        self.profile = Path(tempfile.mkdtemp(prefix="lgi-firefox-"))
        (self.profile / "user.js").write_text(
            "".join(f"user_pref({json.dumps(k)}, {json.dumps(v)});\n" for k, v in PREFS.items()))
        self.xvfb = None
        env = dict(os.environ)
        if not env.get("DISPLAY"):
            self.xvfb, env["DISPLAY"] = _start_xvfb()
        port = _free_port()
        self.proc = subprocess.Popen([FIREFOX, "--headless", "--no-remote", "--profile", str(self.profile),
                                      f"--remote-debugging-port={port}", f"--width={width}", f"--height={height}",
                                      "about:blank"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
        self.errors: list[str] = []
        self._id = 0
        deadline = time.monotonic() + timeout
        while True:
            try:
                self.ws = connect(f"ws://127.0.0.1:{port}/session", max_size=None, open_timeout=5)
                break
            except OSError:
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    err = self.proc.stderr.read().decode(errors="replace")[-2000:] if self.proc.stderr else ""
                    self.close()
                    raise BiDiError(f"firefox did not start: {err}") from None
                time.sleep(0.2)
        self.timeout = timeout
        self.send("session.new", {"capabilities": {}})
        self.send("session.subscribe", {"events": ["log.entryAdded"]})
        self.context = self.send("browsingContext.getTree", {})["contexts"][0]["context"]
        self.send("browsingContext.setViewport", {"context": self.context,
                                                  "viewport": {"width": width, "height": height}})

    def send(self, method: str, params: dict[str, Any]) -> dict[str, Any]:
        """Send a command and wait for its result; events that arrive meanwhile are recorded."""
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        deadline = time.monotonic() + self.timeout
        while True:
            msg = json.loads(self.ws.recv(timeout=max(deadline - time.monotonic(), 0.1)))
            if msg.get("type") == "event":
                self._event(msg)
            elif msg.get("id") == self._id:
                if msg.get("type") == "error":
                    raise BiDiError(f"{method}: {msg.get('error')}: {msg.get('message')}")
                return msg["result"]

    def _event(self, msg: dict[str, Any]) -> None:
        if msg.get("method") == "log.entryAdded":
            entry = msg["params"]
            if entry.get("level") == "error":
                self.errors.append(entry.get("text") or json.dumps(entry))

    def goto(self, url: str) -> None:
        self.send("browsingContext.navigate", {"context": self.context, "url": url, "wait": "complete"})

    def evaluate(self, expression: str) -> Any:
        """The value of a JavaScript expression (awaited when it is a promise), as JSON gives it back."""
        # JSON.stringify on the page side: BiDi's own serialisation of objects is a tree of typed nodes.
        r = self.send("script.evaluate", {
            "expression": f"(async () => JSON.stringify(await ({expression})))()",
            "target": {"context": self.context}, "awaitPromise": True})
        if r.get("type") == "exception":
            raise BiDiError(f"{expression}: {r['exceptionDetails'].get('text')}")
        value = r["result"].get("value")
        return None if value is None else json.loads(value)

    def wait_for(self, expression: str, timeout: float = 60.0) -> Any:
        """Poll until ``expression`` is truthy; its value."""
        deadline = time.monotonic() + timeout
        while True:
            value = self.evaluate(expression)
            if value:
                return value
            if time.monotonic() > deadline:
                raise BiDiError(f"timed out waiting for {expression}")
            time.sleep(0.1)

    def screenshot(self, clip_element: str | None = None) -> bytes:
        """A PNG of the viewport, or of the element matched by the CSS selector ``clip_element``."""
        params: dict[str, Any] = {"context": self.context}
        if clip_element:
            box = self.evaluate(f"(() => {{ const r = document.querySelector({json.dumps(clip_element)})"
                                ".getBoundingClientRect(); return [r.x, r.y, r.width, r.height]; })()")
            params["clip"] = {"type": "box", "x": box[0], "y": box[1], "width": box[2], "height": box[3]}
        return base64.b64decode(self.send("browsingContext.captureScreenshot", params)["data"])

    def close(self) -> None:
        try:
            if getattr(self, "ws", None) is not None:
                try:
                    self.send("browser.close", {})
                except Exception:  # noqa: BLE001 - the browser may already be gone; it is killed below
                    pass
                self.ws.close()
        finally:
            if self.proc.poll() is None:
                self.proc.terminate()
                try:
                    self.proc.wait(10)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
            if self.xvfb is not None:
                self.xvfb.terminate()
                self.xvfb.wait(10)
            shutil.rmtree(self.profile, ignore_errors=True)
