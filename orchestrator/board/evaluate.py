"""One evaluation, as its own process: ``python -m orchestrator.board.evaluate --matrix FILE --out DIR``.

Runs the matrix (the challenge with the submission as its only brain) with the matrix runner into ``DIR`` and
exits; the server reads ``DIR/results.sqlite``. Its own process because it runs in the submission's code folder
(the brain module is importable from there, as from ``drivebench run``'s folder), and so that a server killed by
SIGKILL takes it along (it watches its parent) instead of leaving it to write results nobody asked for.

Every brain host runs in the sandbox (``RunOptions.sandbox``) unless the server was told ``--unsafe-no-sandbox``;
``--hide`` names what the brain must not see even where a folder it needs is bound in (the challenge's data).

With ``DRIVEBENCH_BOARD_RAY`` set (``drivebench board serve --ray ADDRESS``), the episodes run on that Ray cluster
through :class:`~orchestrator.matrix.ray_runner.RayMatrixRunner`, one task per episode, with the same options: each
node runs the brain host in its own sandbox. The submission's code folder (this process's folder) travels to the
nodes as the job's working directory, so its brain imports there as it does here.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from orchestrator.matrix.load import Matrix, load_matrix
from orchestrator.matrix.runner import MatrixProgress, MatrixRunner, RunOptions
from orchestrator.stack.sandbox import Sandbox
from protocol import environment
from protocol.deploy.runtime import exit_on_sigterm, exit_with_parent


def evaluation_options(*, out_dir: Path, sandboxed: bool, hidden: tuple[Path, ...]) -> RunOptions:
    """One worker, a fresh stack per episode (a sandboxed host's CPU seconds count per process), every brain host
    sandboxed unless told otherwise."""
    sandbox = Sandbox.default(scratch_dir=out_dir / "scratch", hidden_paths=hidden) if sandboxed else None
    return RunOptions(workers=1, fresh_stacks=True, sandbox=sandbox)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m orchestrator.board.evaluate")
    parser.add_argument("--matrix", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--hide", type=Path, action="append", default=[], help="a path the brain must not see")
    parser.add_argument("--unsafe-no-sandbox", action="store_true")
    args = parser.parse_args(argv)
    exit_on_sigterm()
    exit_with_parent()  # DRIVEBENCH_PARENT_PID: the server
    options = evaluation_options(out_dir=args.out, sandboxed=not args.unsafe_no_sandbox, hidden=tuple(args.hide))
    matrix, ray_address = load_matrix(args.matrix), environment.BOARD_RAY.value()
    progress = run(matrix, out_dir=args.out, options=options, ray_address=ray_address)
    print(f"evaluation: {progress.done} done, {progress.failed} failed", file=sys.stderr)
    return 0


def run(matrix: Matrix, *, out_dir: Path, options: RunOptions, ray_address: str) -> MatrixProgress:
    """The matrix here, or on the Ray cluster at ``ray_address`` (one task per episode, as ``fresh_stacks``)."""
    if not ray_address:
        return MatrixRunner(matrix, out_dir, options).run()
    from orchestrator.matrix.ray_options import RayOptions, import_ray
    from orchestrator.matrix.ray_runner import RayMatrixRunner

    # The brain is a module of this folder (the submission's code): Ray ships it to each node's workers as their
    # working directory, where the brain host (in its sandbox, bound read-only) imports it.
    import_ray().init(address=ray_address, runtime_env={"working_dir": str(Path.cwd())}, log_to_driver=False)
    return RayMatrixRunner(matrix, out_dir, options, ray_options=RayOptions(address=ray_address)).run()


if __name__ == "__main__":
    sys.exit(main())
