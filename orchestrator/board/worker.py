"""The evaluation queue: worker threads that take the oldest queued submission, check it against the brain contract
(``drivebench brains check``, a process of its own), run its evaluation (``orchestrator.board.evaluate``, a process
of its own) and write scores or a typed rejection for the attempt they claimed.

Everything a submission's code does runs in a child process whose output goes to the submission's folder in the
data folder, never to the server's log: the server logs ids and states only.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import threading
from dataclasses import dataclass
from pathlib import Path

from brains.sandbox_exit import SandboxExit
from orchestrator.board.challenge import Challenge, digest
from orchestrator.board.intake import Brain, Kind
from orchestrator.board.scoring import REJECTION_OF_FAILURE, verdict
from orchestrator.board.store import BoardStore, Rejection, State, Submission
from orchestrator.matrix.results import ResultStore
from orchestrator.stack import processes, sandbox
from orchestrator.stack.sandbox import Sandbox
from protocol import environment

log = logging.getLogger("drivebench.board")
CHECK_TIMEOUT_S = 120.0  # the contract's ~700 frames; a brain that needs longer is too slow for the episodes too
CHECK_MEMORY_STEPS = 50  # frames of the checker's memory-growth check: enough for a leak that keeps every frame
EVALUATION_TIMEOUT_S = 1800.0  # a wall guard over the whole matrix (each episode has its own guard too)
IDLE_POLL_S = 0.5
# A stack that failed on the server's side (a start timeout on a loaded machine) is not the brain's fault: the
# evaluation runs again, from scratch, up to this many attempts in all, before the submission ends ``error``.
MAX_ATTEMPTS = 3


@dataclass(frozen=True)
class Folders:
    """Where a submission's files are: ``DIR/submissions/<id>/`` and one evaluation folder per attempt."""

    data_dir: Path

    def submission(self, submission_id: str) -> Path:
        return self.data_dir / "submissions" / submission_id

    def evaluation(self, submission: Submission) -> Path:
        return self.submission(submission.id) / f"attempt-{submission.attempt}"

    def hidden_from(self, submission_id: str) -> tuple[Path, ...]:
        """Everything in ``DIR`` but the way to this submission's code: the store, the secret seed, the other
        submissions, this one's evaluations (they name the hidden conditions). A second wall: ``serve`` already
        refuses a ``DIR`` inside a folder the sandbox binds in, where nothing of ``DIR`` but the code is seen."""
        folder, hidden = self.data_dir, []
        for part in (Path("submissions") / submission_id / "code").parts:
            hidden += [entry for entry in sorted(folder.iterdir()) if entry.name != part]
            folder = folder / part
        return tuple(hidden)


def brain_of(submission: Submission, *, folders: Folders) -> Brain:
    """The brain an evaluation runs, as :func:`orchestrator.board.intake.unpack` wrote it (brain.json)."""
    folder = folders.submission(submission.id)
    written = json.loads((folder / "brain.json").read_text())
    return Brain(kind=Kind(written["kind"]), entry=written["entry"], code_dir=folder / "code")


class Workers:
    """``count`` worker threads over the store's queue; :meth:`stop` ends them (children too) and waits."""

    def __init__(self, *, store: BoardStore, challenge: Challenge, folders: Folders, count: int, sandboxed: bool):
        self.store, self.challenge, self.folders, self.sandboxed = store, challenge, folders, sandboxed
        self._stopping = threading.Event()
        self._children: set[subprocess.Popen] = set()
        self._lock = threading.Lock()
        self._threads = [
            threading.Thread(target=self._loop, name=f"board-worker-{i}", daemon=True) for i in range(count)
        ]

    def start(self) -> None:
        for thread in self._threads:
            thread.start()

    def stop(self) -> None:
        self._stopping.set()
        with self._lock:
            for child in self._children:
                child.terminate()
        for thread in self._threads:
            thread.join(timeout=30)

    def _loop(self) -> None:
        while not self._stopping.is_set():
            submission = self.store.claim()
            if submission is None:
                self._stopping.wait(IDLE_POLL_S)
                continue
            try:
                self._evaluate(submission)
            except Exception:  # one submission's trouble never stops the queue
                log.exception("submission %s: evaluation failed on the server's side", submission.id)
                self.store.advance(submission, State.ERROR, detail="the server could not evaluate it")

    def _evaluate(self, submission: Submission) -> None:
        log.info("submission %s: checking (attempt %d)", submission.id, submission.attempt)
        brain = brain_of(submission, folders=self.folders)
        folder = self.folders.evaluation(submission)
        folder.mkdir(parents=True, exist_ok=True)
        rejection = self._check(brain, folder=folder, submission_id=submission.id)
        if self._stopping.is_set():
            return  # left checking: the next start puts it back in the queue
        if rejection is not None:
            self.store.advance(submission, State.REJECTED, reason=rejection[0], detail=rejection[1])
            log.info("submission %s: rejected (%s)", submission.id, rejection[0])
            return
        if not self.store.advance(submission, State.RUNNING):
            return
        log.info("submission %s: running", submission.id)
        self._run(submission, brain, folder=folder)

    def _check(self, brain: Brain, *, folder: Path, submission_id: str) -> tuple[Rejection, str] | None:
        """The brain contract, in a process of its own: None when it passes, else (reason, one line)."""
        argv = ["brains", "check", brain.entry["name"], "--json", "--memory-steps", str(CHECK_MEMORY_STEPS)]
        if "weights" in brain.entry:
            argv += ["--weights", brain.entry["weights"]]
        box = None
        if self.sandboxed:
            box = Sandbox.default(
                scratch_dir=folder / "check-scratch", hidden_paths=self.folders.hidden_from(submission_id)
            )
        argv = self._confined(argv, brain=brain, box=box)
        try:
            code = self._child(
                argv, cwd=brain.code_dir, log_path=folder / "check.log", timeout_s=CHECK_TIMEOUT_S, stdout="check.json"
            )
        except subprocess.TimeoutExpired:
            return Rejection.TOO_SLOW, f"the brain contract's checks took over {CHECK_TIMEOUT_S:g} s"
        return _check_outcome(folder / "check.json", code=code, box=box)

    def _run(self, submission: Submission, brain: Brain, *, folder: Path) -> None:
        text = self.challenge.matrix_text(brain=brain.entry)
        (folder / "evaluation.yaml").write_text(text)  # the exact config of the scores (secret: it names the seed)
        argv = [*processes.python_module("orchestrator.board.evaluate"), "--matrix", str(folder / "evaluation.yaml")]
        argv += ["--out", str(folder / "matrix"), *([] if self.sandboxed else ["--unsafe-no-sandbox"])]
        argv += [f"--hide={path}" for path in self.folders.hidden_from(submission.id)]
        try:
            self._child(argv, cwd=brain.code_dir, log_path=folder / "evaluate.log", timeout_s=EVALUATION_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self.store.advance(submission, State.ERROR, detail="the evaluation ran past its wall guard")
            return
        if self._stopping.is_set():
            return
        self._score(submission, folder=folder, config_text=text)

    def _score(self, submission: Submission, *, folder: Path, config_text: str) -> None:
        with ResultStore(folder / "matrix", create=False) as results:
            outcome = verdict(results.results())
        if outcome.scores is not None:
            state, fields = State.SCORED, {"scores": outcome.scores, "config_sha256": digest(config_text)}
        elif outcome.rejection is not None:
            state, fields = State.REJECTED, {"reason": outcome.rejection, "detail": outcome.detail}
        elif submission.attempt < MAX_ATTEMPTS:
            state, fields = State.QUEUED, {"detail": f"attempt {submission.attempt}: {outcome.detail}; again"}
        else:
            state, fields = State.ERROR, {"detail": outcome.detail}
        if self.store.advance(submission, state, **fields):
            log.info("submission %s: %s", submission.id, state)

    def _child(self, argv: list[str], *, cwd: Path, log_path: Path, timeout_s: float, stdout: str = "") -> int:
        """Run ``argv`` in ``cwd``, its stderr (and stdout, unless ``stdout`` names a file beside it) into
        ``log_path``; it stops by itself if this server dies."""
        env = {**os.environ, environment.PARENT_PID.name: str(os.getpid())}
        out_path = log_path.with_name(stdout) if stdout else log_path
        with open(log_path, "wb") as errors, open(out_path, "ab") as output:
            child = subprocess.Popen(argv, cwd=cwd, stdout=output, stderr=errors, env=env)
        with self._lock:
            self._children.add(child)
        try:
            return child.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()
            raise
        finally:
            with self._lock:
                self._children.discard(child)

    def _confined(self, argv: list[str], *, brain: Brain, box: Sandbox | None) -> list[str]:
        """``drivebench ARGV`` as a process of its own: in ``box`` (no bus, no network; the submission's code
        readable and importable), or as it is without one (``--unsafe-no-sandbox``)."""
        if box is None:
            return [*processes.python_module("orchestrator.cli"), *argv]
        command = [sandbox.interpreter(), "-m", "orchestrator.cli", *argv]
        return sandbox.command_argv(box, command=command, readable=[brain.code_dir], importable=[brain.code_dir])


def _check_outcome(json_path: Path, *, code: int, box: Sandbox | None) -> tuple[Rejection, str] | None:
    """The checker's JSON array (its stdout; a brain that prints puts lines before it) as a rejection, or None
    when it passed. In a sandbox (``box``), a check the brain failed by meeting one of its walls (its error's
    ``wall``, or the signal of a limit that ended the checker) is that wall's rejection, whatever the check."""
    text = json_path.read_text(errors="replace")
    start = text.find("[\n")
    try:
        checks = json.loads(text[start:]) if start >= 0 else None
    except json.JSONDecodeError:
        checks = None
    if checks is None:
        ended = sandbox.classify_exit(code, sandbox=box) if box is not None else None
        if ended is not None:
            return REJECTION_OF_FAILURE[ended[0]], f"the brain contract's check: {ended[1]}"
        return Rejection.DOES_NOT_LOAD, f"the brain contract's check did not finish (exit code {code})"
    failed = [check for check in checks if check["status"] == "fail"]
    if not failed:
        return None
    first = failed[0]
    line = f"{first['name']}: {first['detail']}"
    if box is not None and first.get("wall"):
        wall = SandboxExit[first["wall"].upper()]
        return (Rejection.EXCEEDED_LIMIT if wall.is_limit else Rejection.SANDBOX_VIOLATION), line
    if first["name"] == "make":
        return Rejection.DOES_NOT_LOAD, line
    if first["name"] == "answer time":
        return Rejection.TOO_SLOW, line
    return Rejection.BREAKS_CONTRACT, line
