"""How a stack drives its recorder process: the recorder's command line, and a control request (open a file, close
it) sent and then followed until the recorder reports it done. A stack that records one file per episode (a warm
matrix lane) opens and closes through these; ``orchestrator.stack.launcher`` starts and stops the process."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

from orchestrator.stack.failures import FailureKind, StackFailure
from protocol import codec, keys
from protocol.bus import ANSWER_TIMEOUT_S, Bus
from protocol.messages import ControlReply, ControlRequest

RECORDER_STOP_GRACE_S = 30.0  # finishing a recording (drain, summary, fsync) must not be cut short


def argv(record: Path, *, run_dir: Path, options: tuple[str, ...], attach: tuple[Path, ...] | None) -> list[str]:
    """The recorder's arguments: record into ``record``, attaching ``attach`` (None: the run's config.yaml when
    there is one), with the recorder config overrides ``options``."""
    args = ["--set", f"output={json.dumps(str(Path(record).resolve()))}"]
    config = run_dir / "config.yaml"
    files = attach if attach is not None else ((config,) if config.is_file() else ())
    if files:
        args += ["--set", f"attach=[{', '.join(json.dumps(str(Path(f).resolve())) for f in files)}]"]
    for option in options:
        args += ["--set", option]
    return args


def send(
    bus: Bus,
    *,
    run_id: str,
    request: ControlRequest,
    done: Callable[[ControlReply], bool],
    dead: Callable[[], str | None],
) -> None:
    """Send ``request`` to run ``run_id``'s recorder, then ask its status until ``done(reply)``: StackFailure
    (``recorder_died``) when it refuses, when ``dead()`` names a process of the stack that died, or when it is not
    done within :data:`RECORDER_STOP_GRACE_S`."""
    key = keys.recorder_control(run_id)
    payload = bus.request(key, codec.encode(request), timeout_s=ANSWER_TIMEOUT_S)
    reply = None if payload is None else codec.decode(payload, ControlReply)
    if reply is None or not reply.ok:
        why = "no answer" if reply is None else reply.detail
        raise StackFailure(FailureKind.RECORDER_DIED, f"the recorder did not take {request.action!r} on {key}: {why}")
    deadline = time.monotonic() + RECORDER_STOP_GRACE_S
    status = codec.encode(ControlRequest(action="status"))
    while time.monotonic() < deadline:
        payload = bus.request(key, status, timeout_s=ANSWER_TIMEOUT_S)
        if payload is not None and done(codec.decode(payload, ControlReply)):
            return
        if (reason := dead()) is not None:
            raise StackFailure(FailureKind.RECORDER_DIED, reason)
        time.sleep(0.02)
    raise StackFailure(
        FailureKind.RECORDER_DIED, f"the recorder did not {request.action} a file within {RECORDER_STOP_GRACE_S:.0f} s"
    )
