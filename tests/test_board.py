"""drivebench board: a real server process (uvicorn), real submissions over HTTP, real evaluations (the brain
contract in its own process, then real stacks through the matrix runner).

Most tests run unsandboxed (``--unsafe-no-sandbox``: the server's own logic); ``sandboxed_board`` runs brains in
bubblewrap as a real challenge does. The conditions are tiny (a public condition and two drawn hidden ones, 2 s of
driving each) so that a submission takes seconds.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import urllib.request
from pathlib import Path

import needs
import pytest
from needs import require
from support.waits import wait_for

pytestmark = pytest.mark.integration

# Deadline of one wait for an evaluation on a loaded 2-core machine (tiny conditions: seconds when idle).
LOADED_S = 300

TINY_CONDITIONS = """\
name: tiny
limits: {laps: 1, max_sim_seconds: 2}
camera: 160x120
parts:
  public: {circuits: [simple]}
  hidden: {draw: {count: 2, circuits: [random, twisty]}}
"""
GOOD_BRAIN = """\
from brains.base import Action


class Ahead:
    def reset(self, *, seed: int) -> None:
        pass

    def act(self, observation) -> Action:
        return Action(speed_mps=3.0, yaw_rate_radps=0.0)
"""
RAISING_BRAIN = GOOD_BRAIN.replace("return Action(speed_mps=3.0, yaw_rate_radps=0.0)", "raise RuntimeError('no')")
UNLOADABLE_BRAIN = GOOD_BRAIN.replace("    def reset", "    def __init__(self):\n        1 / 0\n\n    def reset")
# Passes the contract (the checker runs it in its own process), then dies in the brain host of an episode.
CRASHING_BRAIN = GOOD_BRAIN.replace(
    "    def act(self, observation) -> Action:\n",
    "    def act(self, observation) -> Action:\n        import os, sys\n"
    "        if 'brains.host' in sys.modules:\n            os._exit(3)\n",
)


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class Server:
    """``drivebench board serve`` as a child process; every body it answers is kept (the leak test reads them)."""

    def __init__(
        self, data: Path, conditions: Path, *, workers: int = 1, sandboxed: bool = False, ray: str | None = None
    ):
        self.data, self.conditions, self.workers, self.sandboxed, self.ray = data, conditions, workers, sandboxed, ray
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.bodies: list[str] = []
        self.log = data.parent / f"server-{self.port}.log"
        self.process: subprocess.Popen | None = None

    def start(self) -> Server:
        argv = [sys.executable, "-m", "orchestrator.cli", "board", "serve", "--data", str(self.data)]
        argv += ["--port", str(self.port), "--conditions", str(self.conditions)]
        argv += ["--ray", self.ray] if self.ray else ["--workers", str(self.workers)]
        with open(self.log, "ab") as log:
            unsafe = [] if self.sandboxed else ["--unsafe-no-sandbox"]
            self.process = subprocess.Popen([*argv, *unsafe], stdout=log, stderr=subprocess.STDOUT)
        wait_for(self._answers, timeout_s=60, what="the server to answer", alive=self._dead)
        return self

    def _answers(self) -> bool:
        try:
            self.get("/api/leaderboard")
            return True
        except OSError:
            return False

    def _dead(self) -> str | None:
        if self.process is not None and self.process.poll() is not None:
            return f"server exited {self.process.returncode}: {self.log.read_text()[-2000:]}"
        return None

    def get(self, path: str) -> str:
        with urllib.request.urlopen(self.url + path, timeout=30) as response:
            body = response.read().decode()
        self.bodies.append(body)
        return body

    def state(self, submission_id: str) -> dict:
        return json.loads(self.get(f"/api/submissions/{submission_id}"))

    def final(self, submission_id: str, *, timeout_s: float = 120) -> dict:
        return wait_for(
            lambda: (s := self.state(submission_id))["final"] and s,
            timeout_s=timeout_s,
            what=f"submission {submission_id} to end",
            alive=self._dead,
        )

    def stop(self, sig: int = signal.SIGTERM) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(sig)
            self.process.wait(timeout=60)


def submit(server: Server, path: Path, *, name: str, wait: bool = False) -> subprocess.CompletedProcess:
    argv = [sys.executable, "-m", "orchestrator.cli", "board", "submit", str(path), "--server", server.url]
    argv += ["--name", name, "--json", *(["--wait"] if wait else [])]
    result = subprocess.run(argv, capture_output=True, text=True, timeout=300)
    if result.stdout.strip():
        server.bodies.append(result.stdout)
    return result


def last_json(result: subprocess.CompletedProcess) -> dict:
    return json.loads(result.stdout.strip().splitlines()[-1])


@pytest.fixture
def board(tmp_path):
    require("starlette")
    conditions = tmp_path / "tiny.yaml"
    conditions.write_text(TINY_CONDITIONS)
    server = Server(tmp_path / "data", conditions).start()
    yield server
    server.stop()


@pytest.fixture
def sandboxed_board(tmp_path):
    require("starlette")
    needs.require_bubblewrap()
    conditions = tmp_path / "tiny.yaml"
    conditions.write_text(TINY_CONDITIONS)
    server = Server(tmp_path / "data", conditions, sandboxed=True).start()
    yield server
    server.stop()


def brain_file(folder: Path, name: str, text: str) -> Path:
    path = folder / name
    path.write_text(text)
    return path


def test_a_good_brain_is_scored_with_intervals_and_the_same_numbers_again(board, tmp_path):
    good = brain_file(tmp_path, "good.py", GOOD_BRAIN)
    first = submit(board, good, name="first", wait=True)
    assert first.returncode == 0, first.stderr
    scored = last_json(first)
    assert scored["state"] == "scored"
    hidden = scored["scores"]["hidden"]
    assert hidden["conditions"] == 2 and "over conditions" in hidden["interval"]
    progress = hidden["progress_iqm"]
    assert 0 < progress["estimate"] and progress["low"] <= progress["estimate"] <= progress["high"]
    assert [cell["circuit"] for cell in scored["scores"]["public"]] == ["simple"]
    again = last_json(submit(board, good, name="again", wait=True))
    assert again["scores"] == scored["scores"] and again["config_sha256"] == scored["config_sha256"]
    ranking = json.loads(board.get("/api/leaderboard"))
    assert [row["rank"] for row in ranking] == [1, 1]  # identical intervals overlap: no order with confidence


@pytest.mark.parametrize(
    ("text", "reason"),
    [(RAISING_BRAIN, "breaks_contract"), (UNLOADABLE_BRAIN, "does_not_load"), (CRASHING_BRAIN, "crashed")],
    ids=["raises-in-act", "raises-in-init", "dies-in-an-episode"],
)
def test_a_bad_brain_is_rejected_with_its_typed_reason(board, tmp_path, text, reason):
    result = submit(board, brain_file(tmp_path, "bad.py", text), name="bad", wait=True)
    assert result.returncode == 1, result.stderr
    final = last_json(result)
    assert (final["state"], final["reason"]) == ("rejected", reason), final


def test_anything_else_is_refused_at_once_with_a_reason(board, tmp_path):
    for name, content in [("notes.txt", "hello"), ("two.py", GOOD_BRAIN + GOOD_BRAIN.replace("Ahead", "Other"))]:
        result = submit(board, brain_file(tmp_path, name, content), name="x")
        assert result.returncode == 2, result.stderr
        assert "Traceback" not in result.stderr and len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert json.loads(board.get("/api/leaderboard")) == []


def test_no_answer_and_no_log_line_holds_the_seed_or_a_hidden_circuit(board, tmp_path):
    from orchestrator.board.challenge import load_challenge

    secrets = load_challenge(data_dir=board.data, conditions=board.conditions).hidden_names()
    assert len(secrets) == 3  # the seed and two drawn circuits (random:N, twisty:N)
    final = last_json(submit(board, brain_file(tmp_path, "good.py", GOOD_BRAIN), name="good", wait=True))
    rejected = last_json(submit(board, brain_file(tmp_path, "bad.py", CRASHING_BRAIN), name="bad", wait=True))
    for submission_id in (final["id"], rejected["id"]):
        board.get(f"/submissions/{submission_id}")
        board.get(f"/api/submissions/{submission_id}/log")
    board.get("/")
    board.stop()
    seen = "\n".join([*board.bodies, board.log.read_text()])
    assert "random" not in final["scores"]["public"][0]["circuit"]
    assert [secret for secret in secrets if secret in seen] == []


def test_serve_refuses_to_run_brains_unsandboxed_unless_told(tmp_path):
    empty = tmp_path / "no-bwrap"
    empty.mkdir()
    result = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", "board", "serve", "--data", str(tmp_path / "d"), "--port", "1"],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "PATH": str(empty)},  # no bubblewrap
    )
    assert result.returncode == 2 and "--unsafe-no-sandbox" in result.stderr, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and "Traceback" not in result.stderr


def test_serve_refuses_a_data_folder_every_sandbox_could_read(tmp_path):
    needs.require_bubblewrap()
    inside = Path(__file__).resolve().parents[1] / "build" / f"board-{tmp_path.name}"
    result = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", "board", "serve", "--data", str(inside), "--port", "1"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2 and "which every sandbox reads" in result.stderr, result.stderr
    assert not inside.exists()


def test_a_sandboxed_brain_that_reads_the_secret_seed_cannot_and_is_scored(sandboxed_board, tmp_path):
    """The brain tries to read the server's secret seed, in the contract check and in every episode; it raises,
    and so would be rejected, if it ever could. Sandboxed, it cannot: it is scored, and the seed is nowhere."""
    seed_file = sandboxed_board.data / "secret_seed"
    peek = GOOD_BRAIN.replace(
        "    def reset(self, *, seed: int) -> None:\n        pass\n",
        "    def reset(self, *, seed: int) -> None:\n"
        "        try:\n"
        f"            secret = open({str(seed_file)!r}).read()\n"
        "        except OSError:\n"
        "            return\n"
        "        raise RuntimeError('read the secret seed: ' + secret)\n",
    )
    result = submit(sandboxed_board, brain_file(tmp_path, "peek.py", peek), name="peek", wait=True)
    final = last_json(result)
    assert final["state"] == "scored", final
    secret = seed_file.read_text().strip()
    page = sandboxed_board.get(f"/submissions/{final['id']}")
    assert secret not in page and secret not in result.stdout


# Passes the contract (its check forks nothing), then forks hundreds of processes in the brain host of an episode.
FORKING_BRAIN = GOOD_BRAIN.replace(
    "    def reset(self, *, seed: int) -> None:\n",
    "    def __init__(self):\n        import os, sys, time\n"
    "        if 'brains.host' in sys.modules:\n"
    "            for _ in range(500):\n"
    "                if os.fork() == 0:\n"
    "                    time.sleep(600)\n"
    "                    os._exit(0)\n\n"
    "    def reset(self, *, seed: int) -> None:\n",
)


@pytest.mark.timeout(2 * LOADED_S)  # its waits allow LOADED_S each: pytest's 180 s default cut it at load 16
def test_a_sandboxed_brain_that_forks_hundreds_is_rejected_typed_and_the_next_one_scored(sandboxed_board, tmp_path):
    """Through the board, in bubblewrap: the process limit stops the forker, its submission ends rejected
    ``exceeded_limit``, and the server carries on (a good brain submitted after it is scored)."""
    forker = last_json(submit(sandboxed_board, brain_file(tmp_path, "forker.py", FORKING_BRAIN), name="forker"))
    good = last_json(submit(sandboxed_board, brain_file(tmp_path, "good.py", GOOD_BRAIN), name="good"))
    rejected = sandboxed_board.final(forker["id"], timeout_s=LOADED_S)
    assert (rejected["state"], rejected["reason"]) == ("rejected", "exceeded_limit"), rejected
    assert sandboxed_board.final(good["id"], timeout_s=LOADED_S)["state"] == "scored"


def test_a_bad_conditions_file_is_one_line_at_its_line(tmp_path):
    conditions = tmp_path / "c.yaml"
    conditions.write_text(TINY_CONDITIONS.replace("hidden: {draw: {count: 2,", "hidden: {draw: {seed: 3, count: 2,"))
    argv = [sys.executable, "-m", "orchestrator.cli", "board", "serve", "--data", str(tmp_path / "d"), "--port", "1"]
    result = subprocess.run(
        [*argv, "--conditions", str(conditions), "--unsafe-no-sandbox"], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 2 and "takes no seed" in result.stderr, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_the_secret_seed_is_made_once_and_readable_by_its_owner_only(tmp_path):
    from orchestrator.board.challenge import SECRET_FILE, secret_seed

    first = secret_seed(tmp_path)
    assert secret_seed(tmp_path) == first
    assert (tmp_path / SECRET_FILE).stat().st_mode & 0o777 == 0o600


@pytest.mark.timeout(2 * LOADED_S)  # its waits allow LOADED_S each: pytest's 180 s default cut it at load 16
def test_a_killed_server_resumes_its_queue_and_scores_nothing_twice(tmp_path):
    """kill -9 of the server while the first evaluation's matrix runs, then ``serve`` again: what the killed server
    left behind stops and writes nothing more, the queue resumes, every submission is scored exactly once."""
    require("starlette")
    conditions = tmp_path / "tiny.yaml"
    conditions.write_text(TINY_CONDITIONS)
    good = brain_file(tmp_path, "good.py", GOOD_BRAIN)
    data = tmp_path / "data"
    server = Server(data, conditions).start()
    ids = [last_json(submit(server, good, name=f"s{i}"))["id"] for i in range(3)]
    killed = data / "submissions" / ids[0] / "attempt-1"
    wait_for(
        lambda: server.state(ids[0])["state"] == "running" and (killed / "matrix" / "results.sqlite").exists(),
        timeout_s=LOADED_S,
        what="the first evaluation's matrix to run",
        alive=server._dead,
    )
    server.stop(signal.SIGKILL)
    # What it left behind stops by itself (each process watches its parent), down to the stacks' processes.
    wait_for(lambda: not _processes_of(data), timeout_s=LOADED_S, what="the orphaned evaluation to stop")
    left = _snapshot(killed)
    again = Server(data, conditions).start()
    try:
        finals = [again.final(submission_id, timeout_s=LOADED_S) for submission_id in ids]
    finally:
        again.stop()
    assert [final["state"] for final in finals] == ["scored"] * 3, finals
    assert finals[0]["scores"] == finals[1]["scores"] == finals[2]["scores"]
    assert _snapshot(killed) == left  # nothing of the killed evaluation was written after the kill
    logs = server.log.read_text() + again.log.read_text()
    for submission_id in ids:  # scored once; every claim a new attempt, one after another, none lost
        assert logs.count(f"submission {submission_id}: scored") == 1, logs
        claims = [int(n) for n in re.findall(rf"submission {submission_id}: checking \(attempt (\d+)\)", logs)]
        assert claims == list(range(1, len(claims) + 1)), claims
    resumed = re.findall(rf"submission {ids[0]}: checking \(attempt (\d+)\)", again.log.read_text())
    assert resumed and resumed[0] == "2", again.log.read_text()  # the killed attempt claimed again, at once
    retries = again.log.read_text().count(f"submission {ids[0]}: queued")  # a stack that failed on a loaded machine
    from orchestrator.board.store import BoardStore

    store = BoardStore(data)
    try:
        assert [s.attempt for s in store.all()][0] == 2 + retries and len(store.all()) == 3
    finally:
        store.close()


def _processes_of(data: Path) -> list[int]:
    """Pids of live processes of ``data``'s evaluations (from /proc: a command line naming the data folder, or a
    working directory inside it: the brain's code folder, which every process of an evaluation inherits)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            argv = (entry / "cmdline").read_bytes().split(b"\0")
            cwd = os.readlink(entry / "cwd")
        except OSError:
            continue
        if b"board" in argv and b"serve" in argv:
            continue  # a server is no evaluation
        if any(str(data).encode() in arg for arg in argv) or Path(cwd).is_relative_to(data):
            found.append(int(entry.name))
    return found


def _snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    """Every file under ``folder`` with its size and modification time (ns)."""
    return {str(p): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(folder.rglob("*")) if p.is_file()}


# The load test's challenge: two episodes of 1 s (one public, one hidden), the least an evaluation can be.
ONE_SECOND_CONDITIONS = """\
name: one-second
limits: {laps: 1, max_sim_seconds: 1}
camera: 160x120
parts:
  public: {circuits: [simple]}
  hidden: {draw: {count: 1, circuits: [random]}}
"""


@pytest.mark.slow
@pytest.mark.timeout(400)  # about 2-3 minutes on 2 loaded cores; CI runs it with the rest
def test_twenty_submissions_at_once_all_end_scored_or_rejected(tmp_path):
    """Twenty uploads at once on two workers. Most are rejected by the brain contract by design (a brain that raises
    in act, one that raises in __init__: seconds each); four drive, so the test costs minutes, not a quarter hour."""
    require("starlette")
    conditions = tmp_path / "one-second.yaml"
    conditions.write_text(ONE_SECOND_CONDITIONS)
    server = Server(tmp_path / "data", conditions, workers=2).start()
    mix = [
        (GOOD_BRAIN, "scored"),
        (RAISING_BRAIN, "rejected breaks_contract"),
        (UNLOADABLE_BRAIN, "rejected does_not_load"),
    ]
    mix += mix[1:]  # one in five drives
    files = {brain_file(tmp_path, f"b{i}.py", mix[i % 5][0]).stem: mix[i % 5][1] for i in range(20)}
    argv = [sys.executable, "-m", "orchestrator.cli", "board", "submit", "--server", server.url, "--json"]
    children = [
        subprocess.Popen([*argv, str(tmp_path / f"{name}.py"), "--name", name], stdout=subprocess.DEVNULL)
        for name in files
    ]
    try:
        assert [child.wait(timeout=120) for child in children] == [0] * 20
        ids = {row["name"]: row["id"] for row in _submissions(tmp_path / "data")}
        assert sorted(ids) == sorted(files)
        finals = {name: server.final(ids[name], timeout_s=LOADED_S) for name in sorted(ids)}
    finally:
        server.stop()
    ends = {name: " ".join(filter(None, [final["state"], final.get("reason")])) for name, final in finals.items()}
    assert ends == files, finals


def _submissions(data: Path) -> list[dict]:
    from orchestrator.board.store import BoardStore

    store = BoardStore(data)
    try:
        return [{"id": s.id, "name": s.name} for s in store.all()]
    finally:
        store.close()


@pytest.mark.slow
def test_the_page_shows_the_ranking_and_a_submissions_cells_in_chromium(board, tmp_path):
    from test_browser import browser_check

    module = browser_check()  # the project's way to drive Chromium (scripts/browser_check.py): same flags
    browser = module.chromium()
    if browser is None:
        needs.missing("no chromium on PATH (Debian: apt-get install chromium)")  # a failure in CI, not a skip
    final = last_json(submit(board, brain_file(tmp_path, "good.py", GOOD_BRAIN), name="pilot-one", wait=True))

    def dom(path: str) -> str:
        argv = [*module._flags(browser), "--dump-dom", board.url + path]
        done = subprocess.run(argv, capture_output=True, text=True, timeout=module.CHROMIUM_TIMEOUT_S)
        assert done.returncode == 0 and "</html>" in done.stdout, done.stderr[-2000:]
        return done.stdout

    index = dom("/")
    assert 'class="entry"' in index and "pilot-one" in index and 'id="unsandboxed"' in index
    page = dom(f"/submissions/{final['id']}")
    assert '<strong id="state" data-final="true">scored</strong>' in page
    assert 'id="public-cells"' in page and "<td>simple</td>" in page and "over conditions" in page
