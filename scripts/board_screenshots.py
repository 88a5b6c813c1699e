"""Screenshots of a challenge's page for the guide (docs/guides/challenge.md), from a real server and real
evaluations:

    python scripts/board_screenshots.py --out docs/screenshots     # a few minutes on two cores

serves a tiny challenge (``drivebench board serve``, sandboxed where bubblewrap is there) from a temporary data
folder, submits two brains (one driving straight at 3 m/s, one at 1 m/s) with ``drivebench board submit --wait``,
and writes ``board-leaderboard.png`` (the page at ``/``) and ``board-submission.png`` (the faster one's page) with
headless Chromium, as ``scripts/browser_check.py`` does.
"""

from __future__ import annotations

import argparse
import json
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

from browser_check import chromium, screenshot

CONDITIONS = """\
name: screenshots
limits: {laps: 1, max_sim_seconds: 4}
camera: 160x120
parts:
  public: {circuits: [simple]}
  hidden: {draw: {count: 4, circuits: [random, twisty]}}
"""
BRAIN = """\
from brains.base import Action


class Straight:
    def reset(self, *, seed: int) -> None:
        pass

    def act(self, observation) -> Action:
        return Action(speed_mps=SPEED, yaw_rate_radps=0.0)
"""
BRAINS = {"fast-pilot": 3.0, "slow-pilot": 1.0}  # name: speed (m/s)
START_TIMEOUT_S = 60
HEIGHTS_PX = {"board-leaderboard.png": 1000, "board-submission.png": 1100}


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def drivebench(*args: str) -> list[str]:
    return [sys.executable, "-m", "orchestrator.cli", *args]


def serve(folder: Path) -> tuple[subprocess.Popen, str]:
    """The server on a free loopback port, once it answers: (process, URL)."""
    (folder / "conditions.yaml").write_text(CONDITIONS)
    port = free_port()
    sandboxed = shutil.which("bwrap") is not None  # as a challenge runs; otherwise the page says it is not
    argv = drivebench("board", "serve", "--data", str(folder / "data"), "--port", str(port))
    argv += ["--conditions", str(folder / "conditions.yaml"), *([] if sandboxed else ["--unsafe-no-sandbox"])]
    with open(folder / "server.log", "wb") as log:
        server = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=log)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + START_TIMEOUT_S
    while server.poll() is None and time.monotonic() < deadline:
        try:
            urllib.request.urlopen(url + "/api/leaderboard", timeout=5).close()
            return server, url
        except OSError:
            time.sleep(0.2)  # polling a server that starts
    server.kill()
    raise SystemExit(f"board_screenshots: the server did not start: {(folder / 'server.log').read_text()[-1000:]}")


def submit(url: str, folder: Path, *, name: str, speed_mps: float) -> dict:
    path = folder / f"{name.replace('-', '_')}.py"
    path.write_text(BRAIN.replace("SPEED", repr(speed_mps)))
    done = subprocess.run(
        drivebench("board", "submit", str(path), "--server", url, "--name", name, "--wait", "--json"),
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        raise SystemExit(f"board_screenshots: {name} did not score: {done.stderr.strip()} {done.stdout[-500:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("docs/screenshots"), help="folder for the PNGs")
    args = parser.parse_args()
    browser = chromium()
    if browser is None:
        print("board_screenshots: no chromium (Debian: apt-get install chromium)", file=sys.stderr)
        return 1
    with tempfile.TemporaryDirectory(prefix="board-screenshots-") as temporary:
        folder = Path(temporary)
        server, url = serve(folder)
        try:
            finals = [submit(url, folder, name=name, speed_mps=speed) for name, speed in BRAINS.items()]
            pages = {"board-leaderboard.png": "/", "board-submission.png": f"/submissions/{finals[0]['id']}"}
            for name, path in pages.items():
                screenshot(browser, url + path, args.out / name, height_px=HEIGHTS_PX[name])
                print(f"{args.out / name}: {url + path}")
        finally:
            server.terminate()
            server.wait(timeout=60)
    return 0


if __name__ == "__main__":
    sys.exit(main())
