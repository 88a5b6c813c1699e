"""The recorder process: every message of one run to an MCAP file (``python -m recorder``).

It subscribes to ``drivebench/run/<id>/**`` into an unbounded queue (the Zenoh callback only decodes and queues,
so a burst never makes Zenoh drop frames for us), and one thread writes. SIGTERM / SIGINT finish a complete,
indexed file; SIGKILL leaves ``<file>.part`` with everything up to the last flush (~1 s), which the next recorder
started on the same folder repairs, as does ``drivebench recorder repair``.
"""

from __future__ import annotations

import json
import logging
import queue
import subprocess
import time
from pathlib import Path

import msgspec

from protocol import codec, keys
from protocol.bus import OBSERVER_BUS, Bus, BusConfig, Inbox
from protocol.deploy.runtime import UserError, stop_on_signals, stop_requested
from protocol.episodes import running_spec, start_event
from protocol.mapping.recording import (
    FORMAT_VERSION,
    RecordFormatError,
    check_image_format,
    check_recordable,
)
from protocol.messages import (
    AnyRunMessage,
    BrainEvent,
    CameraFrame,
    ControlReply,
    ControlRequest,
    EpisodeEvent,
    EventKind,
    Pose,
    ReplyCode,
    RunMessage,
    ServerState,
)
from recorder.repair import repair_leftovers
from recorder.writer import RecordingWriter

log = logging.getLogger("drivebench.recorder")

STARTED_AT = time.strftime("%Y%m%d-%H%M%S")  # the {time} of output file names: one value for the whole process
STOP_QUIET_S = 0.2  # on a stop, record until nothing has arrived for this long ...
STOP_DRAIN_MAX_S = 3.0  # ... but no longer than this: a publisher that never pauses must not keep it open
STOP_COMPLETE_MAX_S = 10.0  # and, for a lock-step episode that ended, until its last frames and pose are in


class RecorderConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Config of the recorder process.

    output: the MCAP file to write; ``{run_id}`` is replaced by the run id and ``{time}`` by the recorder's start time
        (``YYYYmmdd-HHMMSS``, so a restarted recorder never overwrites). Written as ``<output>.part`` until done.
    image_format: "raw" (lossless ``foxglove.RawImage``: training data, exact replay) or "jpeg"
        (``foxglove.CompressedImage``, ~10x smaller, lossy).
    jpeg_quality: 1-100, for image_format "jpeg".
    views: also write the Foxglove car pose, transform and track channels (for the 3D panel).
    flush_interval_s: the most a SIGKILL can lose, in wall time and in simulated time (of what was written).
    attach: text files (e.g. the run's resolved config) stored in the file's metadata, one entry each.
    """

    bus: BusConfig = OBSERVER_BUS  # a Zenoh client by default: see protocol.bus.OBSERVER_BUS
    run_id: str = "default"
    name: str = "recorder"
    output: str = "recordings/{run_id}.mcap"
    image_format: str = "raw"
    jpeg_quality: int = 90
    views: bool = True
    flush_interval_s: float = 1.0
    attach: list[str] = []

    def __post_init__(self) -> None:
        check_image_format(self.image_format)
        if not 1 <= self.jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality must be 1-100, got {self.jpeg_quality}")
        if not self.flush_interval_s > 0:
            raise ValueError(f"flush_interval_s must be > 0, got {self.flush_interval_s}")

    @property
    def output_path(self) -> Path:
        return Path(self.output.replace("{run_id}", self.run_id).replace("{time}", STARTED_AT))


class RecorderService:
    def __init__(self, config: RecorderConfig, bus: Bus):
        self.config = config
        self._bus = bus
        self.writer: RecordingWriter | None = None
        self._open(config.output_path, attach=config.attach)
        self._inbox = Inbox()
        # Control requests ("open", "close"), carried out by the writing thread: the writer is not thread-safe.
        self._requests: queue.Queue[ControlRequest] = queue.Queue()
        self._closed_through = -1  # episodes up to this one went into closed files: their stragglers are dropped
        # Everything of the run, the brains' copy of the episode events too (BrainEvent): it decodes, and is not
        # written (the recorded sim/events hold all of it, and a replay publishes the brains' copy from them again).
        self._subscription = bus.subscribe(keys.run_all(config.run_id), AnyRunMessage, inbox=self._inbox)
        bus.serve(keys.recorder_control(config.run_id), self._on_control)
        bus.declare_alive(keys.alive(config.run_id, "recorder", config.name))

    def _open(self, path: Path, *, attach: list[str]) -> None:
        """Start writing into ``path`` (repairing what a killed recorder left in its folder)."""
        if path.suffix != ".mcap":
            raise UserError(f"recorder output must end in .mcap, got {path}")
        for report in repair_leftovers(path.parent):
            log.warning(
                "repaired a recording left by a killed recorder: %s (%d messages)", report.output, report.messages
            )
        self.writer = RecordingWriter(
            path,
            image_format=self.config.image_format,
            jpeg_quality=self.config.jpeg_quality,
            views=self.config.views,
            flush_interval_s=self.config.flush_interval_s,
        )
        self.writer.add_metadata("drivebench.run", _run_metadata(self.config))
        for name in attach:
            self._attach(Path(name))
        self._started: set[int] = set()  # episodes whose START is written
        self._asked: set[int] = set()  # episodes whose missing START we asked the simulator for
        self._ends = EpisodeEnds()

    def _attach(self, path: Path) -> None:
        assert self.writer is not None
        try:
            text = path.read_text()
        except OSError as error:
            raise UserError(f"recorder attach: cannot read {path}: {error.strerror}") from None
        self.writer.add_metadata(f"file:{path.name}", {"path": str(path), "text": text})

    def serve_forever(self) -> None:
        """Record until SIGTERM or SIGINT (:func:`~protocol.deploy.runtime.stop_requested`), then return after the
        current write (the process exits 143 or 130).

        The signals only set a flag: raised at an arbitrary point, an exception could interrupt the MCAP writer in
        the middle of a chunk, and ``close()`` would then write the rest after a half-written record (a CI run lost
        8 steps to a corrupted chunk that way, which is why every service now stops on the flag).
        """
        log.info("recording run %s to %s", self.config.run_id, self.config.output_path)
        stop_on_signals()  # also when embedded in another main (a service's main installs it already)
        while not stop_requested():
            self.record_pending(timeout_s=0.2)
            self._carry_out_requests()
        self._drain()

    def _drain(self) -> None:
        """Record what is still on its way (a burst the recorder lags behind): until nothing has arrived for
        STOP_QUIET_S, for at most STOP_DRAIN_MAX_S; then, while a lock-step episode that ended lacks its last frames
        or pose, for at most STOP_COMPLETE_MAX_S more. A quiet pause alone is not proof: on a loaded machine a
        collection lost the last 42 of 80 frames that were still in transit when the recorder went quiet."""
        deadline = time.monotonic() + STOP_DRAIN_MAX_S
        while self.record_pending(timeout_s=STOP_QUIET_S) and time.monotonic() < deadline:
            pass
        deadline = time.monotonic() + STOP_COMPLETE_MAX_S
        while (missing := self._ends.missing()) and time.monotonic() < deadline:
            self.record_pending(timeout_s=0.05)
        if missing := self._ends.missing():
            log.warning("finishing without what never came: %s", missing)
        self._ends = EpisodeEnds()

    # -- control: one file per episode on a warm stack (the writing thread carries requests out) --

    def _on_control(self, payload: bytes) -> bytes:
        """The control queryable (Zenoh's callback thread: never block): "status" at once; "open" and "close" are
        queued for the writing thread, and "status" says when they are done."""
        request = codec.decode(payload, ControlRequest)
        if request.action in ("open", "close"):
            if request.action == "open" and not request.output.endswith(".mcap"):
                return self._reply(ok=False, code=ReplyCode.BAD_REQUEST, detail="open needs an output ending in .mcap")
            self._requests.put(request)
        elif request.action != "status":
            return self._reply(ok=False, code=ReplyCode.UNKNOWN_ACTION, detail=f"unknown action {request.action!r}")
        return self._reply(ok=True)

    def _reply(self, *, ok: bool, code: ReplyCode = ReplyCode.OK, detail: str = "") -> bytes:
        writer = self.writer
        state = ServerState.IDLE if writer is None else ServerState.SERVING
        output = "" if writer is None else str(writer.path)
        return codec.encode(ControlReply(ok=ok, code=code, detail=detail, state=state, output=output))

    def _carry_out_requests(self) -> None:
        while True:
            try:
                request = self._requests.get_nowait()
            except queue.Empty:
                return
            self._close_file()
            if request.action == "open":
                try:
                    self._open(Path(request.output), attach=list(request.attach))
                except (UserError, OSError) as error:
                    log.error("cannot open %s: %s", request.output, error)

    def _close_file(self) -> None:
        """Finish the file being written (what is still on its way first); record nothing until the next open."""
        if self.writer is None:
            return
        self._drain()
        self._closed_through = max([self._closed_through, *self._started, *self._asked])
        self.writer.close()
        log.info("finished %s", self.writer.path)
        self.writer = None

    def record_pending(self, *, timeout_s: float) -> int:
        """Write what has arrived (waiting up to ``timeout_s`` for the first); flush when due."""
        written = 0
        received = self._inbox.recv(timeout_s)
        while received is not None:
            if self.writer is None:  # between two files: not recorded
                self._inbox.drain()
                return written
            self._write(received.key, received.message)
            written += 1
            if self.writer.flush_if_due():
                break  # keep the flush period even under a steady stream
            received = self._inbox.try_recv()
        if self.writer is not None:
            self.writer.flush_if_due()
        return written

    def _write(self, key: str, message: AnyRunMessage) -> None:
        if isinstance(message, BrainEvent):
            return
        try:
            check_recordable(message)
        except RecordFormatError as error:
            # Decoded, but no file can hold it (a client's frame of width -1): dropped and counted like any bad
            # message, so the rest of the run is still recorded.
            self._bus.rejects.reject(key, error)
            return
        assert self.writer is not None
        start_spec = message.spec if isinstance(message, EpisodeEvent) and message.kind == EventKind.START else None
        episode = message.header.episode
        if episode <= self._closed_through:
            return  # a straggler of an episode whose file is finished
        if start_spec is not None and episode in self._started:
            return  # recovered from the simulator before it arrived: the same message, already written
        if start_spec is None and episode not in self._started | self._asked:
            self._recover_start(episode)
        self.writer.write(key, message)
        self._ends.note(key, message)
        if start_spec is not None:
            self._started.add(episode)
            self.writer.add_metadata(
                f"episode:{episode}", {"run_id": message.header.run_id, "spec": codec.to_json(start_spec)}
            )

    def _recover_start(self, episode: int) -> None:
        """An episode's messages arrive without its START: we joined late, or the simulator published START before
        our subscription reached it. START holds nothing but the spec, so ask the simulator for the running
        episode's spec and write the very message it published (a recording without START cannot be replayed or
        turned into a dataset)."""
        self._asked.add(episode)  # once per episode
        spec = running_spec(self._bus, self.config.run_id, episode)
        if spec is not None:
            self._write(keys.events(self.config.run_id), start_event(self.config.run_id, episode, spec))

    def close(self) -> None:
        self._subscription.close()
        if self.writer is not None:
            for received in self._inbox.drain():  # what arrived while we were stopping is still recorded
                self._write(received.key, received.message)
            self.writer.close()
        if self._bus.rejects.total:
            log.warning("dropped %d malformed messages: %s", self._bus.rejects.total, dict(self._bus.rejects.counts))


class EpisodeEnds:
    """What a recording still lacks of its lock-step episodes that ended: END says the last pose's seq N; every pose
    up to N and every camera frame up to N - 1 is published in lock-step (the simulator waits for each), so a stream
    seen in the episode that has not reached that seq has messages still on their way. Realtime episodes drop frames
    by design; only their poses are awaited."""

    def __init__(self) -> None:
        self._lockstep: set[int] = set()
        self._last_pose_seq: dict[int, int] = {}  # ended episodes
        self._highest: dict[tuple[int, str], tuple[bool, int]] = {}  # (episode, key) -> (is a frame, highest seq)

    def note(self, key: str, message: RunMessage) -> None:
        if isinstance(message, EpisodeEvent):
            episode = message.header.episode
            if message.kind == EventKind.START and message.spec is not None and not message.spec.realtime:
                self._lockstep.add(episode)
            elif message.kind == EventKind.END and message.last_pose_seq >= 0:
                self._last_pose_seq[episode] = message.last_pose_seq
        elif isinstance(message, (CameraFrame, Pose)):
            episode, is_frame = message.header.episode, isinstance(message, CameraFrame)
            _, seq = self._highest.get((episode, key), (is_frame, -1))
            self._highest[(episode, key)] = (is_frame, max(seq, message.header.seq))

    def missing(self) -> list[str]:
        """``episode E: KEY up to seq S`` for each stream of an ended episode still short of its end."""
        short = []
        for (episode, key), (is_frame, seq) in self._highest.items():
            last = self._last_pose_seq.get(episode)
            if last is None or (is_frame and episode not in self._lockstep):
                continue
            wanted = last - 1 if is_frame else last
            if seq < wanted:
                short.append(f"episode {episode}: {key} up to seq {wanted} (have {seq})")
        return short


def _run_metadata(config: RecorderConfig) -> dict[str, str]:
    return {
        "run_id": config.run_id,
        "format": FORMAT_VERSION,
        "git_sha": _git_sha(),
        "started_unix_s": f"{time.time():.3f}",
        "recorder_config": json.dumps(msgspec.to_builtins(config)),
    }


def _git_sha() -> str:
    try:
        result = subprocess.run(
            ["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5, cwd=Path(__file__).resolve().parent
        )
    except (OSError, subprocess.SubprocessError):
        return ""
    return result.stdout.strip() if result.returncode == 0 else ""


def main(argv: list[str] | None = None) -> int:
    from protocol.deploy.runtime import service_main

    return service_main(
        "recorder",
        "drivebench recorder: every message of one run to an MCAP file",
        RecorderConfig,
        RecorderService,
        argv,
    )
