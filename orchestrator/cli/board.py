"""``drivebench board``: serve a challenge, and submit a brain to one.

    drivebench board serve --data DIR --port N [--host 127.0.0.1] [--conditions FILE] [--workers N | --ray ADDRESS]
                           [--unsafe-no-sandbox]
    drivebench board submit FILE --server URL --name NAME [--wait] [--json]

``serve`` keeps its state in ``DIR`` (``board.sqlite``, the secret seed, each submission's files) and resumes the
queue where a stopped server left it. With ``--ray``, each evaluation's episodes run on that Ray cluster (the
``cluster`` extra), every brain host sandboxed on its node. ``submit --wait --json`` prints the submission's final
state as JSON on its last stdout line: its scores with intervals, or its typed reason. Needs the ``board`` extra
(Starlette, uvicorn, python-multipart).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import urllib.error
import urllib.request
import uuid
from pathlib import Path
from typing import Any

from orchestrator.cli.errors import EXIT_FAILED, EXIT_OK, CommandFailed, UsageError, require_file

WAIT_POLL_S = 1.0
# With --ray, evaluations at once: the cluster runs each one's episodes side by side; a second one lets the next
# submission's contract check (on this machine) overlap the cluster's episodes.
RAY_EVALUATIONS = 2
NOT_SANDBOXED = (
    "drivebench board serve: no sandbox for submitted brains (install Debian's bubblewrap), or start with "
    "--unsafe-no-sandbox to run them unsandboxed (trusted local use only)"
)


def add(commands: argparse._SubParsersAction) -> None:
    board = commands.add_parser("board", help="a challenge server: a leaderboard anyone can submit a brain to")
    sub = board.add_subparsers(dest="board_command", required=True)
    serve = sub.add_parser("serve", help="serve the page, the submission API and the evaluation queue")
    serve.add_argument("--data", type=Path, required=True, metavar="DIR", help="state folder (created)")
    serve.add_argument("--port", type=int, required=True, metavar="N")
    serve.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    serve.add_argument(
        "--conditions",
        type=_optional_path,
        metavar="FILE",
        help="matrix-style file: parts public and hidden (default, or empty: built in)",
    )
    serve.add_argument("--workers", type=int, metavar="N", help="evaluations at once on this machine (default 1)")
    serve.add_argument(
        "--ray", metavar="ADDRESS", help="run the evaluations' episodes on this Ray cluster (auto, HOST:PORT)"
    )
    serve.add_argument(
        "--unsafe-no-sandbox", action="store_true", help="run submitted brains without a sandbox (trusted use only)"
    )
    serve.set_defaults(func=run_serve)
    submit = sub.add_parser("submit", help="submit a brain file, wheel or ONNX network to a challenge server")
    submit.add_argument("file", type=Path, metavar="FILE")
    submit.add_argument("--server", required=True, metavar="URL", help="e.g. http://127.0.0.1:8000")
    submit.add_argument("--name", required=True, help="the name the leaderboard shows")
    submit.add_argument("--wait", action="store_true", help="wait for the final state (scored or rejected)")
    submit.add_argument("--json", action="store_true", help="the final state as one JSON line on stdout")
    submit.set_defaults(func=run_submit)


def _optional_path(text: str) -> Path | None:
    """A path, or None for an empty value: compose passes ``--conditions "${BOARD_CONDITIONS:-}"``."""
    return Path(text) if text else None


def run_serve(args: argparse.Namespace) -> int:
    """Serve until Ctrl-C or SIGTERM; the queue's workers stop with the server."""
    if args.ray is not None and args.workers is not None:
        raise UsageError("--workers and --ray: one or the other (with --ray the cluster runs the episodes)")
    count = RAY_EVALUATIONS if args.ray is not None else 1 if args.workers is None else args.workers
    if count < 1:
        raise UsageError(f"--workers must be at least 1, got {args.workers}")
    if not args.unsafe_no_sandbox:
        _require_sandbox(data_dir=args.data)
    if args.ray is not None:
        _require_cluster(args.ray, sandboxed=not args.unsafe_no_sandbox)
    board = _open_board(args)
    from orchestrator.board.web import make_app
    from protocol.deploy.runtime import setup_logging

    setup_logging("board")
    from orchestrator.board.worker import Workers

    requeued = board.store.requeue_interrupted()
    print(f"drivebench board: {requeued} interrupted submission(s) back in the queue", file=sys.stderr)
    workers = Workers(
        store=board.store,
        challenge=board.challenge,
        folders=board.folders,
        count=count,
        sandboxed=board.sandboxed,
    )
    workers.start()
    try:
        _serve(make_app(board), host=args.host, port=args.port)
    finally:
        workers.stop()
        board.store.close()
    return EXIT_OK


def _require_sandbox(*, data_dir: Path) -> None:
    """bubblewrap must be there: without it the server refuses to start unless told --unsafe-no-sandbox. And the
    data folder must lie outside what every sandbox binds in (this Python, the project): a brain would see it."""
    from orchestrator.stack.sandbox import SandboxUnavailable, python_paths, require_bubblewrap

    try:
        require_bubblewrap()
    except SandboxUnavailable as error:
        raise UsageError(f"{NOT_SANDBOXED}: {error}") from None
    data = data_dir.resolve()
    project = Path(__file__).resolve().parents[2]
    for bound in [project, *python_paths()]:
        if data.is_relative_to(bound):
            raise UsageError(
                f"--data {data_dir}: inside {bound}, which every sandbox reads; a submitted brain could read the "
                "secret seed there: give a folder outside it"
            )


def _require_cluster(address: str, *, sandboxed: bool) -> None:
    """The cluster can evaluate (one line otherwise); then every evaluation, a child process of this server, runs
    its episodes there (it reads the address from the environment it inherits)."""
    from orchestrator.matrix.ray_options import ClusterError
    from protocol import environment

    try:
        from orchestrator.board.cluster import check_cluster

        check_cluster(address, sandboxed=sandboxed)
    except ClusterError as error:
        raise UsageError(str(error)) from None
    os.environ[environment.BOARD_RAY.name] = address


def _open_board(args: argparse.Namespace) -> Any:
    try:
        from orchestrator.board.challenge import Redactor, load_challenge
        from orchestrator.board.store import BoardStore, StoreError
        from orchestrator.board.web import Board
        from orchestrator.board.worker import Folders
    except ModuleNotFoundError as error:  # the board extra
        raise UsageError(f"drivebench board needs the board extra: pip install 'drivebench[board]' ({error})") from None
    from orchestrator.matrix.plan import MatrixError

    if args.conditions is not None:
        require_file(args.conditions, option="--conditions")
    args.data.mkdir(parents=True, exist_ok=True)
    try:
        challenge = load_challenge(data_dir=args.data, conditions=args.conditions)
        store = BoardStore(args.data)
    except (MatrixError, StoreError) as error:
        raise UsageError(str(error)) from None
    return Board(
        store=store,
        challenge=challenge,
        folders=Folders(args.data),
        redact=Redactor(challenge.hidden_names()),
        sandboxed=not args.unsafe_no_sandbox,
    )


def _serve(app: Any, *, host: str, port: int) -> None:
    import uvicorn

    print(f"drivebench board: serving http://{host}:{port}/", file=sys.stderr, flush=True)
    uvicorn.run(app, host=host, port=port, log_level="info")


def run_submit(args: argparse.Namespace) -> int:
    """Upload FILE; with --wait, follow it to its final state. Exit 0 when scored, 1 when rejected or failed."""
    require_file(args.file, option="FILE")
    server = args.server.rstrip("/")
    answer = _post_file(f"{server}/api/submissions", path=args.file, name=args.name)
    print(f"drivebench board: submitted {args.file.name}: {server}/submissions/{answer['id']}", file=sys.stderr)
    if args.wait:
        answer = _wait(f"{server}/api/submissions/{answer['id']}")
    if args.json:
        print(json.dumps(answer))
    else:
        print(_summary(answer))
    return EXIT_FAILED if answer["state"] in ("rejected", "error") else EXIT_OK


def _summary(answer: dict[str, Any]) -> str:
    if answer["state"] == "scored":
        progress = answer["scores"]["hidden"]["progress_iqm"]
        return f"scored: IQM progress {progress['estimate']:.2f} [{progress['low']:.2f}, {progress['high']:.2f}]"
    if answer["state"] == "rejected":
        return f"rejected: {answer['reason']}: {answer['detail']}"
    return f"{answer['state']}" + (f": {answer['detail']}" if answer.get("detail") else "")


def _wait(url: str) -> dict[str, Any]:
    while True:
        answer = _request(urllib.request.Request(url))
        if answer["final"]:
            return answer
        time.sleep(WAIT_POLL_S)  # polling a server's state: the wait is the point, not a guess at a duration


def _post_file(url: str, *, path: Path, name: str) -> dict[str, Any]:
    boundary = uuid.uuid4().hex
    body = b"".join(
        [
            f'--{boundary}\r\nContent-Disposition: form-data; name="name"\r\n\r\n{name}\r\n'.encode(),
            f'--{boundary}\r\nContent-Disposition: form-data; name="file"; filename="{path.name}"\r\n'.encode(),
            b"Content-Type: application/octet-stream\r\n\r\n",
            path.read_bytes(),
            f"\r\n--{boundary}--\r\n".encode(),
        ]
    )
    headers = {"Content-Type": f"multipart/form-data; boundary={boundary}"}
    return _request(urllib.request.Request(url, data=body, headers=headers, method="POST"))


def _request(request: urllib.request.Request) -> dict[str, Any]:
    try:
        with urllib.request.urlopen(request, timeout=60) as response:
            return json.loads(response.read())
    except urllib.error.HTTPError as error:
        reason = _error_text(error)
        if 400 <= error.code < 500:
            raise UsageError(f"the server refused it: {reason}") from None
        raise CommandFailed(f"the server answered {error.code}: {reason}") from None
    except (urllib.error.URLError, OSError) as error:
        raise CommandFailed(f"cannot reach {request.full_url}: {getattr(error, 'reason', error)}") from None


def _error_text(error: urllib.error.HTTPError) -> str:
    try:
        return str(json.loads(error.read()).get("error", error.reason))
    except (ValueError, AttributeError):
        return str(error.reason)
