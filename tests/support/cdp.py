"""Headless Chromium driven over the DevTools protocol (a real WebSocket, ``websockets``' sync client): what a
page test needs that ``--dump-dom`` cannot do, such as choosing a file in a form and watching a page change.

    with Browser.start(chromium_path, profile=tmp_path / "profile") as browser:
        browser.navigate(url)
        browser.evaluate("document.title")
"""

from __future__ import annotations

import contextlib
import json
import subprocess
import time
from pathlib import Path
from typing import Any

from websockets.sync.client import ClientConnection, connect

from support.waits import wait_for

START_TIMEOUT_S = 60
CALL_TIMEOUT_S = 60


class Browser:
    """One Chromium process and its first page; every call waits for its answer (events are dropped)."""

    def __init__(self, process: subprocess.Popen, socket: contextlib.AbstractContextManager[ClientConnection]):
        self.process, self._next_id = process, 0
        self._closing = contextlib.ExitStack()
        self.socket = self._closing.enter_context(socket)  # entered: what every websockets version accepts

    @classmethod
    def start(cls, chromium: str, *, profile: Path, window_px: tuple[int, int] = (1280, 900)) -> Browser:
        width, height = window_px
        # --no-sandbox: CI runs as root, where Chromium's own sandbox refuses to start. Port 0: Chromium picks a
        # free one and writes it to DevToolsActivePort in the profile.
        argv = [chromium, "--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run",
                f"--window-size={width},{height}", f"--user-data-dir={profile}", "--remote-debugging-port=0",
                "about:blank"]  # fmt: skip
        process = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        active = profile / "DevToolsActivePort"

        def dead() -> str | None:
            return None if process.poll() is None else f"chromium exited {process.returncode}"

        port = wait_for(
            lambda: active.is_file() and active.read_text().split("\n")[0].strip(),
            timeout_s=START_TIMEOUT_S,
            what="chromium's DevTools port",
            alive=dead,
        )
        page = wait_for(lambda: _page_target(int(port)), timeout_s=START_TIMEOUT_S, what="chromium's first page")
        browser = cls(process, connect(page, max_size=None, open_timeout=START_TIMEOUT_S))
        browser.call("Page.enable")
        browser.call("DOM.enable")
        return browser

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._closing.close()
        self.process.terminate()
        try:
            self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        """Send one command and return its result (an AssertionError with the protocol's error otherwise)."""
        self._next_id += 1
        self.socket.send(json.dumps({"id": self._next_id, "method": method, "params": params}))
        deadline = time.monotonic() + CALL_TIMEOUT_S
        while True:
            message = json.loads(self.socket.recv(timeout=max(0.1, deadline - time.monotonic())))
            if message.get("id") == self._next_id:
                assert "error" not in message, f"{method}: {message['error']}"
                return message.get("result", {})

    def evaluate(self, expression: str) -> Any:
        """The value of a JavaScript expression in the page (JSON-serialisable values only)."""
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        assert "exceptionDetails" not in result, f"{expression}: {result['exceptionDetails']}"
        return result["result"].get("value")

    def navigate(self, url: str, *, timeout_s: float = 60) -> None:
        self.call("Page.navigate", url=url)
        wait_for(
            lambda: self.evaluate("location.href + ' ' + document.readyState") == f"{url} complete",
            timeout_s=timeout_s,
            what=f"{url} to load",
        )

    def choose_file(self, selector: str, path: Path) -> None:
        """Put ``path`` in the file input at ``selector``, as a person choosing it in the file dialog would."""
        root = self.call("DOM.getDocument")["root"]["nodeId"]
        node = self.call("DOM.querySelector", nodeId=root, selector=selector)["nodeId"]
        assert node, f"no {selector} in the page"
        self.call("DOM.setFileInputFiles", nodeId=node, files=[str(path)])


def _page_target(port: int) -> str | None:
    import urllib.request

    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=5) as response:
            targets = json.loads(response.read())
    except OSError:
        return None
    return next((t["webSocketDebuggerUrl"] for t in targets if t.get("type") == "page"), None)
