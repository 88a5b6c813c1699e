"""The local launcher: a whole stack on this machine, each service its own process, one run folder.

``LocalStack`` embeds the Zenoh router in the calling process (on a free loopback port), starts the simulator,
the noise injector, the brain host(s) and the scorer as child processes with a log file each, waits for their
liveliness tokens, runs episodes through the simulator's control queryable, and on exit stops every child (SIGTERM,
then SIGKILL).
Children also stop by themselves when this process dies (they watch their parent), so nothing is orphaned.

Beside it in ``orchestrator/stack``: its errors (``failures``), a sandboxed brain's router and spawn (``sandbox``),
the recorder's control (``recorder_control``), the stack file and swapped-in brains of ``drivebench swap``
(``swap``), and a stack someone else started (``attached``).
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
import subprocess
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from brains.registry import bus_name
from orchestrator.stack import processes, recorder_control, sandbox
from orchestrator.stack.failures import EpisodeAborted, FailureKind, StackError, StackFailure
from orchestrator.stack.recorder_control import RECORDER_STOP_GRACE_S
from orchestrator.stack.sandbox import Sandbox, SandboxedProcess
from orchestrator.stack.swap import remove_stack_file, stop_foreign_brains, write_stack_file
from protocol import codec, environment, keys
from protocol.bus import (
    ANSWER_TIMEOUT_S,
    BUS_ENV,
    Bus,
    BusConfig,
    BusError,
    Inbox,
    LivelinessWatch,
    Subscription,
    probe_router,
)
from protocol.deploy import graph
from protocol.episode_spec import EpisodeSpec
from protocol.messages import ControlReply, ControlRequest, EndReason, EpisodeScore, LiveMetrics, ReplyCode

log = logging.getLogger("drivebench.launcher")

STOP_GRACE_S = 5.0


LOCAL_ENV: dict[str, str] = {}  # the environment a local stack's own sessions read their bus settings from: none

# How long a start refused because the simulator has not yet seen the brain's token is retried.
START_RETRY_S = 5.0
# After a brain dies, the simulator ends the episode (brain_lost) and the scorer still scores it: wait this long.
SCORE_AFTER_DEATH_S = 1.5
# An episode's wall-clock guard, the one rule for ``drivebench run``, a matrix and a Ray task (which adds its own
# watchdog slack on top): wall seconds per simulated second plus a fixed slack for the first frame (renderer and
# brain warm-up, a checkpoint's first forward pass). Lock-step runs 2-5x faster than real time here, so 20x slower
# than real time means a stuck stack, not a slow one. It is the looser of the two rules it replaces (run: 20x + 60 s,
# matrix: 10x + 120 s) because a guard that fires on a slow but moving stack loses a real result, while one that
# fires late only costs time on a stack already stuck, and exits and liveliness catch most failures long before.
WALL_SECONDS_PER_SIM_SECOND = 20.0
WALL_SLACK_S = 120.0


def wall_guard_s(*, max_sim_seconds: float) -> float:
    """Wall seconds an episode of ``max_sim_seconds`` may take before its stack counts as stuck (the rule above)."""
    return max_sim_seconds * WALL_SECONDS_PER_SIM_SECOND + WALL_SLACK_S


def free_loopback_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@dataclass(frozen=True)
class BrainLaunch:
    """A brain host to start: registered brain, its bus name, constructor options as ``key=value`` YAML overrides,
    and overrides of the host's own config (``brains.host.BrainHostConfig``, e.g. ``("camera=perturbed",)``).
    ``sandbox``: run this host inside bubblewrap with these limits (``orchestrator.stack.sandbox``), joined to the
    stack's router only through a Unix socket; None: an ordinary child process."""

    brain: str
    name: str = ""
    options: tuple[str, ...] = ()
    host: tuple[str, ...] = ()
    sandbox: Sandbox | None = None

    @property
    def bus_name(self) -> str:
        return self.name or bus_name(self.brain)


def preflight_launches(launches: list[BrainLaunch]) -> None:
    """Check every brain launch before anything starts (``brains.registry.preflight``): UnknownBrainError or
    BrainOptionsError, one line, naming the brain and what is wrong. A sandboxed brain's code is not imported here,
    outside its sandbox: only its name is resolved."""
    from brains.registry import preflight, resolve
    from protocol.deploy.config import ConfigError, apply_overrides

    for launch in launches:
        try:
            options = apply_overrides({}, launch.options)
        except ConfigError as error:
            raise ConfigError(f"brain {launch.brain!r}: {error}") from None
        if launch.sandbox is not None:
            resolve(launch.brain)
        else:
            preflight(launch.brain, options)


@dataclass
class Child:
    role: str
    name: str
    process: subprocess.Popen
    log_path: Path
    sandboxed: SandboxedProcess | None = None

    def last_log_line(self) -> str:
        return processes.last_log_line(self.log_path)


# Our own simulator publishes an episode's END (and so our score comes) a moment before it is idle again: a start
# right after a score may find it "busy" with the episode that just ended (seen under load, back-to-back episodes).
OWN_SIMULATOR_BUSY_WAIT_S = 5.0


# Mesa's: how many threads llvmpipe (the CPU OpenGL) rasterises with. Named here, not imported from
# services.simulator.gl_scene (which sets 1 where nobody chose): that import costs every command 0.4 s (circuits).
LLVMPIPE_THREADS = "LP_NUM_THREADS"


def render_threads_for(*, stacks: int) -> int:
    """The llvmpipe threads each of ``stacks`` stacks running side by side on this machine gets: its share of the
    cores this process may use, at least 1. 8 at most: a 640x480 frame is 80 of llvmpipe's 64x64-pixel tiles, and
    only 1 and 2 threads were measured (benchmarks/looks.py)."""
    cores = len(os.sched_getaffinity(0))
    return max(1, min(8, cores // max(1, stacks)))


@dataclass
class LocalStack:
    """A stack on this machine. Use as a context manager; ``run_episode`` as often as needed inside."""

    run_id: str
    run_dir: Path
    brains: list[BrainLaunch] = field(default_factory=lambda: [BrainLaunch("explicit")])
    startup_timeout_s: float = 60.0
    embed_router: bool = True  # False: the router is a child process too (``python -m services.router``)
    router_endpoint: str | None = None  # join this running router instead (a matrix's workers share one)
    record: Path | None = None  # an MCAP file: a recorder process records the whole run to it
    record_options: tuple[str, ...] = ()  # recorder config overrides, e.g. ("image_format=jpeg",)
    # ROS 2 bridge config overrides, e.g. ("domain_id=3",): a bridge process publishes the run on rmw_zenoh's keys
    # (services.ros2_bridge); None: no bridge.
    ros2: tuple[str, ...] | None = None
    # True: every child joins one new process group (``process_group``, the first child's pid) instead of a session
    # each, so that its owner can kill the whole stack, grandchildren included, with one killpg (a Ray task does).
    one_group: bool = False
    # llvmpipe's rendering threads in the simulator (Mesa's LP_NUM_THREADS; a value the user exported wins). One
    # by default; a stack alone on the machine gets its cores (render_threads_for): in lock-step the other
    # processes wait for the frame, so the frame may use every core.
    render_threads: int = 1
    children: list[Child] = field(default_factory=list)

    def __post_init__(self) -> None:
        keys.check_name(self.run_id, what="run id")
        self.endpoint = self.router_endpoint or f"tcp/127.0.0.1:{free_loopback_port()}"
        if self.sandboxed and self.router_endpoint is not None:
            # A sandboxed brain's stack has its own router, whose access control is made for that brain: a shared
            # router (a matrix's) would let it publish on every other stack's keys.
            log.info("run %s has a sandboxed brain: its own router, not the shared %s", self.run_id, self.endpoint)
            self.endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
        self.process_group: int | None = None  # with one_group, once the first child is started
        self._init_state(busy_wait_s=OWN_SIMULATOR_BUSY_WAIT_S)

    def _init_state(self, *, busy_wait_s: float) -> None:
        """What a stack knows about itself before it starts (shared with :class:`AttachedStack`)."""
        self.bus: Bus | None = None
        self._watch: LivelinessWatch | None = None
        self._driver_name = ""  # our driver liveliness token (declared at the first start)
        self.busy_wait_s = busy_wait_s  # how long a start waits for a simulator busy with another episode
        self._tolerated: set[tuple[str, str]] = set()  # (role, name) of children whose death no longer fails
        self.recording_failure: StackFailure | None = None  # the recorder died: the recording is incomplete
        self.last_episode: int | None = None  # the simulator's number of the episode run last (a warm stack runs many)
        self._last_episode_scored = False  # its score came: what it published is complete, so worth waiting for
        self._recording_open = False  # the recorder writes a file that finish_recording has not finished
        self._required: set[str] = set()  # tokens that must stay alive while an episode runs (not the brains':
        # the simulator itself ends the episode with brain_lost when the active brain's token goes)
        self._bus_socket: Path | None = None  # the router's Unix socket, the only way in of sandboxed brains
        self._sandboxed_names: frozenset[str] = frozenset()  # the brains the router lets publish over it
        self._start_deadlines: dict[str, float] = {}  # a sandboxed brain's token: when its start timeout ends

    @property
    def sandboxed(self) -> bool:
        """Whether a brain of this stack runs in a sandbox (the stack then has its own router, always)."""
        return any(launch.sandbox is not None for launch in self.brains)

    def __enter__(self) -> LocalStack:
        try:
            self.start()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    # -- start / stop --

    def start(self) -> None:
        (self.run_dir / "logs").mkdir(parents=True, exist_ok=True)
        # A local stack is configured by its own arguments alone (LOCAL_ENV): bus variables meant for a stack spread
        # over machines (router, mode, TLS, credentials) must not leak into it.
        if self.sandboxed:
            self._open_sandboxed_router()
        elif self.router_endpoint is not None:
            self.bus = Bus(
                BusConfig(mode="peer", connect=[self.endpoint]), name=f"launcher-{self.run_id}", env=LOCAL_ENV
            )
        elif self.embed_router:
            self.bus = Bus(BusConfig(mode="router", listen=[self.endpoint]), name="launcher", env=LOCAL_ENV)
        else:
            self._spawn("router", "router", "services.router", ["--listen", self.endpoint], connect=False)
            self._wait_for_router()
            self.bus = Bus(BusConfig(mode="peer", connect=[self.endpoint]), name="launcher", env=LOCAL_ENV)
        assert self.bus is not None, "every branch above opens the stack's bus"
        self._watch = self.bus.watch_alive(keys.alive_all(self.run_id))
        wanted: set[str] = set()
        if self.record is not None:
            # First, so that its subscription is in place before anything is published.
            wanted.add(self._spawn_role(graph.role("recorder"), self._recorder_argv()))
            self._recording_open = True
        for row in graph.local_stack_roles():
            wanted.add(self._spawn_role(row, []))
        if self.ros2 is not None:
            wanted.add(self._spawn_role(graph.role("ros2_bridge"), [a for o in self.ros2 for a in ("--set", o)]))
        wanted |= {self._spawn_brain(launch) for launch in self.brains}
        self._wait_alive(wanted)
        self._required = {key for key in wanted if keys.parse_alive(key)[1] != "brain"}
        log.info("stack up on %s: %s", self.endpoint, ", ".join(f"{c.role}/{c.name}" for c in self.children))

    def _open_sandboxed_router(self) -> None:
        """The stack's own router, listening on its TCP endpoint and on a Unix socket for the sandboxed brains
        (embedded, whatever ``embed_router`` and ``router_endpoint`` say): :func:`sandbox.open_router`."""
        self._sandboxed_names = frozenset(launch.bus_name for launch in self.brains if launch.sandbox is not None)
        try:
            self.bus, self._bus_socket = sandbox.open_router(
                run_id=self.run_id, endpoint=self.endpoint, brain_names=self._sandboxed_names, env=LOCAL_ENV
            )
        except sandbox.SandboxUnavailable as error:
            raise StackError(str(error)) from None

    def _spawn_brain(self, launch: BrainLaunch) -> str:
        argv = ["--brain", launch.brain, "--name", launch.bus_name]
        for option in launch.options:
            argv += ["--set", f"options.{option}"]
        for setting in launch.host:
            argv += ["--set", setting]
        if launch.sandbox is not None:
            return self._spawn_sandboxed(launch, argv)
        return self._spawn_role(graph.role("brain"), argv, name=launch.bus_name)

    def _spawn_sandboxed(self, launch: BrainLaunch, argv: list[str]) -> str:
        """Start one brain host inside its sandbox, a client of the router through the Unix socket only."""
        assert launch.sandbox is not None
        if self._bus_socket is None or launch.bus_name not in self._sandboxed_names:
            raise StackError(f"brain {launch.bus_name!r}: a sandboxed brain is started with its stack, not added later")
        log_path = self.run_dir / "logs" / f"brain-{launch.bus_name}.log"
        confined_process = sandbox.spawn_brain(
            launch.sandbox,
            brain=launch.brain,
            options=launch.options,
            host_argv=argv,
            run_id=self.run_id,
            socket_path=self._bus_socket,
            log_path=log_path,
        )
        child = Child(
            role="brain",
            name=launch.bus_name,
            process=confined_process.process,
            log_path=log_path,
            sandboxed=confined_process,
        )
        self.children.append(child)
        token = graph.role("brain").token_key(self.run_id, launch.bus_name)
        self._start_deadlines[token] = time.monotonic() + launch.sandbox.start_timeout_s
        return token

    def _wait_alive(self, wanted: set[str]) -> None:
        """Until every liveliness key in ``wanted`` is alive; StackError (one line) when a child dies or time is up
        (a typed StackFailure for a sandboxed brain: how it died, or ``brain_start_timeout``)."""
        assert self._watch is not None
        confined = {token for token in wanted if token in self._start_deadlines}
        missing = self._watch.wait_for(
            wanted - confined, timeout_s=self.startup_timeout_s, abort=self._dead_child_reason
        )
        self._raise_if_dead()
        if missing:
            names = ", ".join(sorted("/".join(keys.parse_alive(k)[1:]) for k in missing))
            raise StackError(
                f"not alive after {self.startup_timeout_s:.0f} s: {names} (logs in {self.run_dir / 'logs'})"
            )
        for token in sorted(confined):
            left_s = max(0.0, self._start_deadlines[token] - time.monotonic())
            missing = self._watch.wait_for({token}, timeout_s=left_s, abort=self._dead_child_reason)
            self._raise_if_dead()
            if missing:
                name = keys.parse_alive(token)[2]
                raise StackFailure(
                    FailureKind.BRAIN_START_TIMEOUT,
                    f"sandboxed brain {name!r} not alive within its start timeout "
                    f"({self.child('brain', name).sandboxed.sandbox.start_timeout_s:.0f} s)",  # type: ignore[union-attr]
                )

    def _raise_if_dead(self) -> None:
        """StackError for a child that died while the stack came up; a sandboxed brain's death is typed."""
        if (dead := self._dead_child_reason()) is None:
            return
        child = self._dead_child()
        if child is not None and child.sandboxed is not None:
            raise self._sandboxed_failure(child)
        raise StackError(dead)

    def _sandboxed_failure(self, child: Child) -> StackFailure:
        """A dead sandboxed brain's failure: the sandbox's reason (a limit, a refused operation), else its death."""
        assert child.sandboxed is not None
        reason = processes.exit_reason(child.process, what=f"brain {child.name!r}", log_path=child.log_path)
        typed = child.sandboxed.failure()
        if typed is None:
            return StackFailure(FailureKind.BRAIN_DIED, reason or f"brain {child.name!r} exited")
        kind, detail = typed
        return StackFailure(kind, f"sandboxed brain {child.name!r}: {detail} ({reason})")

    # -- a warm stack: what changes from one episode to the next (orchestrator.matrix.executor) --

    def set_brains(self, launches: list[BrainLaunch]) -> tuple[int, int]:
        """Make ``launches`` this running stack's brain hosts: a host started with the same launch (brain, bus name,
        options including weights, host settings) stays, and its brain is reset with each episode's seed; the others
        stop, and missing ones start and are waited for. Returns (kept, started)."""
        assert self._watch is not None, "start the stack first"
        retired = [launch for launch in self.brains if launch not in launches]
        for launch in retired:
            self._retire_child("brain", launch.bus_name)
        started = [launch for launch in launches if launch not in self.brains]
        self.brains = list(launches)
        self._wait_alive({self._spawn_brain(launch) for launch in started})
        return len(launches) - len(started), len(started)

    def _retire_child(self, role: str, name: str) -> None:
        """Stop one child on purpose (SIGTERM, its grace, then SIGKILL) and forget it; wait until its liveliness
        token is gone, so that a successor of the same name is never taken for dead when the old token's removal
        arrives late."""
        child = self.child(role, name)
        self.children.remove(child)
        token = graph.role(role).token_key(self.run_id, name)
        self._required.discard(token)
        grace_s = RECORDER_STOP_GRACE_S if role == "recorder" else STOP_GRACE_S
        self._stop([child], grace_s=grace_s)
        deadline = time.monotonic() + STOP_GRACE_S
        while self._watch is not None and token in self._watch.alive() and time.monotonic() < deadline:
            time.sleep(0.05)

    def record_episode(self, output: Path, *, attach: tuple[Path, ...] = ()) -> None:
        """Record what this running stack publishes from now on into ``output`` (one episode's file): the first
        time, a recorder is started into it; later, the running recorder is asked to open it. Returns once the
        recorder writes there; StackFailure (``recorder_died``) when it does not within its grace period."""
        if not any(child.role == "recorder" for child in self.children):
            self.record = output
            key = self._spawn_role(graph.role("recorder"), self._recorder_argv(attach=attach))
            self._wait_alive({key})
            self._required.add(key)
            self._recording_open = True
            return
        path = str(Path(output).resolve())
        request = ControlRequest(action="open", output=path, attach=[str(Path(f).resolve()) for f in attach])
        self._recorder_request(request, done=lambda reply: reply.output == path)
        self._recording_open = True

    def finish_recording(self) -> None:
        """Have the recorder finish its file (what is on its way, then summary and index) and wait until it has:
        the episode's recording is complete before the next episode starts."""
        self._recording_open = False  # finished, or failed trying: a second attempt would not do better
        self._recorder_request(ControlRequest(action="close"), done=lambda reply: reply.output == "")

    def _recorder_request(self, request: ControlRequest, *, done: Callable[[ControlReply], bool]) -> None:
        assert self.bus is not None
        recorder_control.send(self.bus, run_id=self.run_id, request=request, done=done, dead=self._dead_child_reason)

    def stop_recorder(self) -> None:
        """Stop this stack's recorder: it drains what is still on its way, then writes a complete, indexed file."""
        for child in [c for c in self.children if c.role == "recorder"]:
            self._retire_child("recorder", child.name)
        self.record = None
        self._recording_open = False

    def failure_now(self) -> StackFailure | None:
        """A process of this stack that has died, or a required token gone, as a typed failure (None: healthy)."""
        return self._failure()

    def _recorder_argv(self, *, attach: tuple[Path, ...] | None = None) -> list[str]:
        assert self.record is not None, "a recorder is started for a recording"
        return recorder_control.argv(self.record, run_dir=self.run_dir, options=self.record_options, attach=attach)

    def _wait_for_router(self) -> None:
        """Until the router child accepts TCP connections (a peer would otherwise wait for it forever)."""
        host, port = self.endpoint.removeprefix("tcp/").rsplit(":", 1)
        deadline = time.monotonic() + self.startup_timeout_s
        while time.monotonic() < deadline:
            if (dead := self._dead_child_reason()) is not None:
                raise StackError(dead)
            try:
                socket.create_connection((host, int(port)), timeout=0.5).close()
                return
            except OSError:
                time.sleep(0.1)
        raise StackError(f"the router did not listen on {self.endpoint} within {self.startup_timeout_s:.0f} s")

    def _spawn_role(self, row: graph.Role, argv: list[str], *, name: str = "") -> str:
        """Start one process of a graph role; the liveliness key it declares once ready."""
        self._spawn(row.token_role, row.token or name, row.module, argv)
        return row.token_key(self.run_id, name)

    def _spawn(self, role: str, name: str, module: str, argv: list[str], *, connect: bool = True) -> Child:
        log_path = self.run_dir / "logs" / (f"{role}-{name}.log" if role == "brain" else f"{role}.log")
        env = {k: v for k, v in os.environ.items() if k not in BUS_ENV and k != environment.RUN_ID.name}
        env[environment.PARENT_PID.name] = str(os.getpid())  # children stop by themselves when this process dies
        if role == "simulator":
            env.setdefault(LLVMPIPE_THREADS, str(self.render_threads))
        joins = ["--router", self.endpoint, "--run-id", self.run_id] if connect else []
        # Ctrl-C reaches only us (we stop the children in order): a session each, or one process group of their own.
        group = (self.process_group or 0) if self.one_group else None
        process = processes.spawn(
            [*processes.python_module(module), *joins, *argv], log_path=log_path, env=env, process_group=group
        )
        if self.one_group and self.process_group is None:
            self.process_group = process.pid
        child = Child(role=role, name=name, process=process, log_path=log_path)
        self.children.append(child)
        return child

    def _dead_child(self) -> Child | None:
        for child in self.children:
            code = child.process.poll()
            if code == 0 and child.role == "brain":
                continue  # stopped on request (a live swap retired it): not a failure
            if code is not None and (child.role, child.name) not in self._tolerated:
                return child
        return None

    def _dead_child_reason(self) -> str | None:
        if (child := self._dead_child()) is None:
            return None
        return processes.exit_reason(child.process, what=f"{child.role} {child.name!r}", log_path=child.log_path)

    def dead_child_reason(self, *, wait_s: float = 0.0) -> str | None:
        """Which process of this stack has exited, with its exit code and last log line (None: all running after
        ``wait_s``). A brain whose code raised closes its bus session (its token goes, the episode ends brain_lost)
        before Python writes the traceback and exits: waiting a moment gets the error line instead of nothing."""
        deadline = time.monotonic() + wait_s
        while (reason := self._dead_child_reason()) is None and time.monotonic() < deadline:
            time.sleep(0.05)
        return reason

    def _failure(self) -> StackFailure | None:
        """A process of this stack that died, or a required liveliness token that vanished, as a typed failure."""
        if (dead := self._dead_child()) is not None:
            if dead.sandboxed is not None:
                return self._sandboxed_failure(dead)
            reason = processes.exit_reason(dead.process, what=f"{dead.role} {dead.name!r}", log_path=dead.log_path)
            return StackFailure(FailureKind.died(dead.role), reason or f"{dead.role} {dead.name!r} exited")
        if self._watch is not None and (gone := self._required - self._watch.alive()):
            if self._router_gone():
                return StackFailure(
                    FailureKind.ROUTER_DIED,
                    f"the router at {self.endpoint} stopped answering (every "
                    f"process lost its link: {len(gone)} liveliness token(s) gone)",
                )
            if len(gone) > 1 and gone == self._required:
                # A router killed and started again at once answers the probe, but every link through it broke.
                return StackFailure(
                    FailureKind.ROUTER_DIED,
                    f"every process lost its liveliness token at once ({len(gone)} "
                    f"tokens): the link through the router at {self.endpoint} broke "
                    f"(the router restarted?)",
                )
            _, role, name = keys.parse_alive(sorted(gone)[0])
            return StackFailure(FailureKind.died(role), f"{role} {name!r} lost its liveliness token")
        return None

    def _router_gone(self) -> bool:
        """Whether the router no longer takes connections (a vanished token then means the router, not its
        process)."""
        try:
            probe_router(self.endpoint.split(",")[0], timeout_s=0.5)
            return False
        except (BusError, ValueError):
            return True

    def child(self, role: str, name: str) -> Child:
        for child in self.children:
            if (child.role, child.name) == (role, name):
                return child
        raise KeyError(f"{role}/{name}")

    def close(self) -> None:
        """Finish the recording of a scored episode, then stop every process (the recorder last) and close the
        bus; the stop happens whatever the finishing does (a second Ctrl-C included)."""
        try:
            self._finish_scored_recording()
        finally:
            self._stop_all()

    def _stop_all(self) -> None:
        if self.bus is not None:
            stop_foreign_brains(self.bus, run_id=self.run_id, ours={c.name for c in self.children if c.role == "brain"})
        # The recorder stops last, so it still records whatever the others publish while stopping.
        self._stop([c for c in self.children if c.role != "recorder"], grace_s=STOP_GRACE_S)
        self._stop([c for c in self.children if c.role == "recorder"], grace_s=RECORDER_STOP_GRACE_S)
        if self.bus is not None:
            self.bus.close()
            self.bus = None
        if self._bus_socket is not None:
            shutil.rmtree(self._bus_socket.parent, ignore_errors=True)  # our own folder of the router's socket
            self._bus_socket = None
        remove_stack_file(self.run_dir)

    def _finish_scored_recording(self) -> None:
        """Finish the open recording of a scored episode while every process still runs. Stopping them first
        could lose the episode's last frames: a noise injector behind on a loaded machine (nothing waits for it
        when the brain drives from the simulator's frames) forwards its backlog only when stopped, and frames
        published just before its bus session closed never reached the recorder (a CI run's dataset lost an
        episode's last 6 perturbed frames). After an interrupted episode, or with a process dead (a brain_lost
        episode's brain, the recorder itself), the recorder only drains at its stop, as before."""
        healthy = self.recording_failure is None and self._dead_child() is None
        if not (self._recording_open and self._last_episode_scored and self.bus is not None and healthy):
            return
        try:
            self.finish_recording()
        except StackFailure as failure:
            log.warning("the recording of run %s was not finished before the stop: %s", self.run_id, failure)
            self.recording_failure = self.recording_failure or failure

    @staticmethod
    def _stop(children: list[Child], *, grace_s: float) -> None:
        processes.stop([c.process for c in children], grace_s=grace_s, names=[f"{c.role} {c.name}" for c in children])

    def write_stack_file(self) -> Path:
        """Write ``<run_dir>/stack.json`` so that ``drivebench swap`` finds this running stack; :meth:`close`
        removes it."""
        return write_stack_file(self.run_dir, router=self.endpoint, run_id=self.run_id)

    # -- episodes --

    def run_episode(
        self,
        spec: EpisodeSpec,
        *,
        on_live: Callable[[LiveMetrics], None] | None = None,
        wall_timeout_s: float | None = None,
        abort: Callable[[], bool] | None = None,
    ) -> EpisodeScore:
        """Start one episode and wait for its score.

        ``wall_timeout_s`` guards against a stack that stops moving. ``abort`` is polled a few times a second: when
        it returns True the episode is stopped and :class:`EpisodeAborted` raised. A process that dies, or a
        required liveliness token that vanishes, raises :class:`StackFailure` within a second. A dead brain is
        different: the simulator ends its episode with ``brain_lost`` and the scorer scores it, so the score is
        returned; only when no score comes within ``SCORE_AFTER_DEATH_S`` does it raise (kind ``brain_died``).
        """
        assert self.bus is not None, "start the stack first"
        inbox = Inbox()
        subscriptions: list[Subscription] = [
            self.bus.subscribe(keys.score(self.run_id), EpisodeScore, inbox=inbox),
            self.bus.subscribe(keys.live_metrics(self.run_id), LiveMetrics, inbox=inbox),
        ]
        try:
            return self._await_score(spec, inbox, on_live=on_live, wall_timeout_s=wall_timeout_s, abort=abort)
        finally:
            for subscription in subscriptions:
                subscription.close()

    def _await_score(self, spec: EpisodeSpec, inbox: Inbox, *, on_live, wall_timeout_s, abort) -> EpisodeScore:
        self.last_episode = None
        self._last_episode_scored = False
        reply = self._start(spec)
        if not reply.ok:
            raise StackFailure(FailureKind.START_FAILED, f"the simulator refused the episode: {reply.detail}")
        episode = self.last_episode = reply.episode
        guard = wall_timeout_s or wall_guard_s(max_sim_seconds=spec.max_sim_seconds)
        deadline = time.monotonic() + guard
        failure: StackFailure | None = None
        failure_deadline = 0.0
        while True:
            if failure is None and (failure := self._failure()) is not None:
                if failure.kind == FailureKind.RECORDER_DIED:  # the driving is fine: score it, flag the recording
                    self._tolerate_recorder(failure)
                    failure = None
                    continue
                if failure.kind != FailureKind.BRAIN_DIED:
                    raise failure
                failure_deadline = time.monotonic() + SCORE_AFTER_DEATH_S
            if failure is not None and time.monotonic() > failure_deadline:
                raise failure
            if abort is not None and abort():
                self._control(ControlRequest(action="stop"), attempts=1)
                raise EpisodeAborted(f"episode {episode} abandoned")
            if time.monotonic() > deadline:
                self._control(ControlRequest(action="stop"), attempts=1)
                raise StackFailure(
                    FailureKind.WALL_TIMEOUT, f"episode {episode} not scored after {guard:.0f} s of wall time"
                )
            received = inbox.recv(timeout_s=0.2)
            if received is None:
                continue
            message = received.message
            if message.header.episode != episode:
                continue
            if isinstance(message, EpisodeScore):
                if message.reason == EndReason.BRAIN_LOST and (typed := self._sandbox_ended(message)) is not None:
                    raise typed
                self._last_episode_scored = True
                return message  # a dead brain's episode is still a scored episode: it ends with brain_lost
            if on_live is not None:
                on_live(message)

    def _sandbox_ended(self, score: EpisodeScore) -> StackFailure | None:
        """A brain_lost episode whose sandboxed brain its sandbox stopped: that failure, with the score (the score
        may come before the process is reaped: wait a moment for it)."""
        deadline = time.monotonic() + SCORE_AFTER_DEATH_S
        while True:
            for child in self.children:
                if child.sandboxed is not None and child.process.poll() is not None:
                    failure = self._sandboxed_failure(child)
                    if failure.kind != FailureKind.BRAIN_DIED:
                        failure.score = score
                        return failure
            if time.monotonic() > deadline or not any(c.sandboxed is not None for c in self.children):
                return None
            time.sleep(0.05)

    def _tolerate_recorder(self, failure: StackFailure) -> None:
        log.warning("the recorder died; the episode goes on: %s", failure)
        self.recording_failure = failure
        self._tolerated |= {(c.role, c.name) for c in self.children if c.role == "recorder"}
        self._required = {key for key in self._required if keys.parse_alive(key)[1] != "recorder"}

    def _start(self, spec: EpisodeSpec) -> ControlReply:
        """Ask the simulator to start ``spec``, as this stack's driver (the simulator ends the episode when our
        driver token goes: nobody would collect its score). A refusal because the brain is not alive is retried
        for a moment: the brain's liveliness token reaches the simulator on its own route, which may be slower than
        ours (a brain on another machine, seen here through the router). A busy simulator (someone else's
        episode) is waited for up to ``busy_wait_s``."""
        started = time.monotonic()
        request = ControlRequest(action="start", spec=spec, driver=self._driver_token())
        while True:
            reply = self._control(request)
            waited = time.monotonic() - started
            retry = (reply.code == ReplyCode.NOT_ALIVE and waited < START_RETRY_S) or (
                reply.code == ReplyCode.BUSY and waited < self.busy_wait_s
            )
            if reply.ok or not retry:
                return reply
            time.sleep(0.2)

    def _driver_token(self) -> str:
        """The name of this stack's driver liveliness token, declared on first use."""
        if not self._driver_name:
            self._driver_name = f"driver-{os.getpid()}-{uuid.uuid4().hex[:6]}"
            assert self.bus is not None, "start the stack first"
            self.bus.declare_alive(keys.alive(self.run_id, "driver", self._driver_name))
        return self._driver_name

    def _control(self, request: ControlRequest, *, attempts: int = 10) -> ControlReply:
        """A control query to the simulator; retried while its queryable is not yet reachable."""
        assert self.bus is not None
        for _ in range(attempts):
            payload = self.bus.request(keys.sim_control(self.run_id), codec.encode(request), timeout_s=ANSWER_TIMEOUT_S)
            if payload is not None:
                return codec.decode(payload, ControlReply)
            time.sleep(0.2)
        hint = (
            " (under the router's access control, only an orchestrator identity may start, stop or switch runs)"
            if self.bus.resolved.secure
            else ""
        )
        raise StackFailure(
            FailureKind.SIMULATOR_DIED,
            f"the simulator did not answer {request.action!r} on {keys.sim_control(self.run_id)}{hint}",
        )
