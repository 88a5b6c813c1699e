"""One evaluation, as its own process: ``python -m orchestrator.board.evaluate --matrix FILE --out DIR``.

Runs the matrix (the challenge with the submission as its only brain) with the matrix runner into ``DIR`` and
exits; the server reads ``DIR/results.sqlite``. Its own process because it runs in the submission's code folder
(the brain module is importable from there, as from ``drivebench run``'s folder), and so that a server killed by
SIGKILL takes it along (it watches its parent) instead of leaving it to write results nobody asked for.

Every brain launch goes through :func:`brain_launch_of`, the one place a submission's brain host is set up.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from orchestrator.matrix.load import load_matrix
from orchestrator.matrix.plan import PlannedEpisode
from orchestrator.matrix.runner import MatrixRunner, RunOptions
from orchestrator.stack.launcher import BrainLaunch
from protocol.deploy.runtime import exit_on_sigterm, exit_with_parent


def _brain_sandbox(launch: BrainLaunch, *, scratch_dir: Path) -> BrainLaunch:
    """The submitted brain's launch inside the sandbox (bubblewrap: ``orchestrator.stack.sandbox``), its own
    scratch folder the only place it may write."""
    from orchestrator.stack.sandbox import Sandbox

    scratch_dir.mkdir(parents=True, exist_ok=True)
    return dataclasses.replace(launch, sandbox=Sandbox.default(scratch_dir=scratch_dir))


def brain_launch_of(launch: BrainLaunch, *, out_dir: Path, sandboxed: bool) -> BrainLaunch:
    """``launch`` as the evaluation starts it: sandboxed unless the server was told ``--unsafe-no-sandbox``."""
    return _brain_sandbox(launch, scratch_dir=out_dir / "scratch") if sandboxed else launch


class BoardRunner(MatrixRunner):
    """The matrix runner, every brain launch set up by :func:`brain_launch_of`."""

    sandboxed = True

    def _launches(self, episode: PlannedEpisode) -> list[BrainLaunch]:
        launches = super()._launches(episode)
        return [brain_launch_of(launch, out_dir=self.out_dir, sandboxed=self.sandboxed) for launch in launches]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m orchestrator.board.evaluate")
    parser.add_argument("--matrix", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--unsafe-no-sandbox", action="store_true")
    args = parser.parse_args(argv)
    exit_on_sigterm()
    exit_with_parent()  # DRIVEBENCH_PARENT_PID: the server
    matrix = load_matrix(args.matrix)
    runner = BoardRunner(matrix, args.out, RunOptions(workers=1))
    runner.sandboxed = not args.unsafe_no_sandbox
    progress = runner.run()
    print(f"evaluation: {progress.done} done, {progress.failed} failed", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
