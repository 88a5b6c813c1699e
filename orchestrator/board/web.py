"""The page and the submission API (Starlette; ``drivebench board serve`` runs it on uvicorn).

    GET  /                          the leaderboard, the public conditions, the upload form
    GET  /submissions/ID            one submission: state (live), public cells, its own brain's log, its reason
    POST /upload                    the form's upload (redirects to the submission's page)
    GET  /api/leaderboard           the ranking as JSON
    POST /api/submissions           multipart ``file`` and ``name``: 201 with the submission, or 400/413 and a reason
    GET  /api/submissions/ID        the submission as JSON (its state, scores with intervals, or its typed reason)
    GET  /api/submissions/ID/log    its own brain's log (the contract check and the public conditions' episodes)

Nothing here reads the secret seed or the hidden conditions: the scores hold the hidden part's aggregates only, a
log is shown only from the check (rendered on a public circuit) and the public episodes, and every text a
submitter sees passes the :class:`~orchestrator.board.challenge.Redactor` as a last guard.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import JSONResponse, PlainTextResponse, RedirectResponse, Response
from starlette.routing import Route
from starlette.templating import Jinja2Templates

from orchestrator.board.challenge import PUBLIC, Challenge, Redactor
from orchestrator.board.intake import MAX_UPLOAD_BYTES, Refused, unpack
from orchestrator.board.scoring import ranks
from orchestrator.board.store import BoardStore, State, Submission, new_id
from orchestrator.board.worker import Folders
from orchestrator.matrix.results import ResultStore

TEMPLATES = Path(__file__).resolve().parent / "templates"
MAX_NAME_CHARS = 80
LOG_TAIL_LINES = 200
_FORM_OVERHEAD_BYTES = 64 * 1024  # multipart boundaries and the name field beside the file


@dataclass(frozen=True)
class Board:
    """What the app serves from: the store, the challenge, the data folder's layout, and whether brains run
    sandboxed (the page says when they do not)."""

    store: BoardStore
    challenge: Challenge
    folders: Folders
    redact: Redactor
    sandboxed: bool


def public_view(submission: Submission, *, redact: Redactor) -> dict[str, Any]:
    """A submission as anyone may see it."""
    return {
        "id": submission.id,
        "name": submission.name,
        "kind": submission.kind,
        "filename": submission.filename,
        "state": str(submission.state),
        "final": submission.state in (State.SCORED, State.REJECTED, State.ERROR),
        "reason": submission.reason,
        "detail": redact(submission.detail) if submission.detail else None,
        "scores": submission.scores,
        "config_sha256": submission.config_sha256,
        "created_at": submission.created_at,
        "updated_at": submission.updated_at,
    }


def leaderboard(store: BoardStore) -> list[dict[str, Any]]:
    """Scored submissions by IQM progress, each with its rank (entries whose intervals overlap share one)."""
    scored = [s for s in store.all() if s.state is State.SCORED and s.scores]
    rows = [(s, s.scores["hidden"]["progress_iqm"]) for s in scored]  # type: ignore[index]
    rows.sort(key=lambda row: (-row[1]["estimate"], row[0].seq))
    places = ranks([(p["estimate"], p["low"], p["high"]) for _, p in rows])
    return [
        {"rank": place, "id": s.id, "name": s.name, "progress_iqm": p, **_hidden_counts(s)}
        for place, (s, p) in zip(places, rows)
    ]


def _hidden_counts(submission: Submission) -> dict[str, Any]:
    hidden = (submission.scores or {})["hidden"]
    return {"success": hidden["success"], "conditions": hidden["conditions"]}


def brain_log(board: Board, submission: Submission) -> str:
    """The brain's own output: the contract check's, then each public episode's brain log (tails)."""
    folder = board.folders.evaluation(submission)
    parts = []
    if (folder / "check.log").is_file():
        parts.append(("brain contract check", folder / "check.log"))
    matrix = folder / "matrix"
    if (matrix / "results.sqlite").is_file():
        with ResultStore(matrix, create=False) as results:
            for result in results.results():
                if result.key.partition(":")[0] == PUBLIC and result.logs:
                    for path in sorted((matrix / result.logs).glob("brain-*.log")):
                        parts.append((f"episode {result.circuit} {result.variation}", path))
    text = "\n".join(f"== {title} ==\n{_tail(path)}" for title, path in parts)
    return board.redact(text)


def _tail(path: Path) -> str:
    return "\n".join(path.read_text(errors="replace").splitlines()[-LOG_TAIL_LINES:])


def submit(board: Board, *, name: str, filename: str, content: bytes) -> Submission:
    """Queue an upload: :class:`Refused` (one line) when it is not something the server evaluates."""
    name = " ".join(name.split())[:MAX_NAME_CHARS]
    if not name:
        raise Refused("a submission needs a name")
    filename = Path(filename or "upload").name
    submission_id = new_id()
    folder = board.folders.submission(submission_id)
    brain = unpack(folder=folder, filename=filename, content=content)  # classifies it first: Refused
    (folder / "brain.json").write_text(json.dumps({"kind": brain.kind, "entry": brain.entry}))
    return board.store.add(submission_id=submission_id, name=name, kind=brain.kind, filename=filename)


async def _upload(request: Request) -> tuple[str, str, bytes]:
    """(name, filename, content) of a multipart upload; :class:`Refused` for one too big or without a file."""
    length = request.headers.get("content-length")
    if length and length.isdigit() and int(length) > MAX_UPLOAD_BYTES + _FORM_OVERHEAD_BYTES:
        raise Refused(f"upload of {length} bytes, over the limit of {MAX_UPLOAD_BYTES} bytes")
    async with request.form(max_files=1, max_fields=4) as form:
        upload, name = form.get("file"), form.get("name")
        if upload is None or isinstance(upload, str):
            raise Refused("the upload has no file (a multipart field named file)")
        content = await upload.read(MAX_UPLOAD_BYTES + 1)
        return str(name or ""), upload.filename or "upload", content


def make_app(board: Board) -> Starlette:
    templates = Jinja2Templates(directory=str(TEMPLATES))

    def page(request: Request, template: str, status_code: int = 200, **context: Any) -> Response:
        context.update(sandboxed=board.sandboxed)
        return templates.TemplateResponse(request, template, context, status_code=status_code)

    async def index(request: Request, error: str = "", status_code: int = 200) -> Response:
        recent = [public_view(s, redact=board.redact) for s in reversed(board.store.all())]
        return page(
            request,
            "index.html",
            status_code,
            ranking=leaderboard(board.store),
            recent=recent,
            conditions=board.challenge.public_text(),
            error=error,
            max_upload_bytes=MAX_UPLOAD_BYTES,
        )

    async def submission_page(request: Request) -> Response:
        submission = board.store.get(request.path_params["id"])
        if submission is None:
            return PlainTextResponse("no such submission", status_code=404)
        view = public_view(submission, redact=board.redact)
        return page(request, "submission.html", submission=view, log=brain_log(board, submission))

    async def upload_form(request: Request) -> Response:
        try:
            name, filename, content = await _upload(request)
            submission = submit(board, name=name, filename=filename, content=content)
        except Refused as refused:
            return await index(request, error=str(refused), status_code=400)
        return RedirectResponse(f"/submissions/{submission.id}", status_code=303)

    async def api_submit(request: Request) -> Response:
        try:
            name, filename, content = await _upload(request)
            submission = submit(board, name=name, filename=filename, content=content)
        except Refused as refused:
            too_big = "over the limit" in str(refused)
            return JSONResponse({"error": str(refused)}, status_code=413 if too_big else 400)
        return JSONResponse(public_view(submission, redact=board.redact), status_code=201)

    async def api_submission(request: Request) -> Response:
        submission = board.store.get(request.path_params["id"])
        if submission is None:
            return JSONResponse({"error": "no such submission"}, status_code=404)
        return JSONResponse(public_view(submission, redact=board.redact))

    async def api_log(request: Request) -> Response:
        submission = board.store.get(request.path_params["id"])
        if submission is None:
            return PlainTextResponse("no such submission", status_code=404)
        return PlainTextResponse(brain_log(board, submission))

    async def api_leaderboard(request: Request) -> Response:
        return JSONResponse(leaderboard(board.store))

    return Starlette(
        routes=[
            Route("/", index),
            Route("/submissions/{id}", submission_page),
            Route("/upload", upload_form, methods=["POST"]),
            Route("/api/leaderboard", api_leaderboard),
            Route("/api/submissions", api_submit, methods=["POST"]),
            Route("/api/submissions/{id}", api_submission),
            Route("/api/submissions/{id}/log", api_log),
        ]
    )
