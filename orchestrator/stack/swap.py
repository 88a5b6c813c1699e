"""``drivebench swap``: replace the driving brain of a running stack, live, without losing a step.

    drivebench swap BRAIN [--weights CKPT] [--brain-option K=V] [--name NAME] [--run RUN_ID] [--router EP]
                          [--runs-dir runs] [--keep-old] [--timeout S]
                          [--brain-cert PEM --brain-key KEY | --brain-user U --brain-password-file F]

How (:func:`swap_brain`): ask the simulator's status for the active brain and the running episode; start the new
brain host as a detached process (it outlives this command, and is not tied to it as the stack's children are to
the stack); wait for its liveliness token and for its first command answering a frame of the running episode; send
"switch" to the simulator (its command for the next frame drives; in lock-step no step is lost); then ask the old
brain to stop (its control key), unless ``--keep-old``. Without an episode running there is nothing to switch: the
new brain is left running for the next episode to name it, and the old one is kept.

Names: a new brain's name is reserved on the bus (a liveliness token under ``keys.name_claims``) before its host
starts, so two swaps at once start two differently named brains (:func:`_claim_name`).

On a secure stack (TLS, access control: ``docs/security.md``) the swap itself runs with the orchestrator's identity
(only it may switch brains and stop them), and the brain host it starts gets a brain's identity of its own
(:class:`BrainIdentity`), never the swap's: a brain host with the orchestrator's rights could start runs and switch
to itself, and the orchestrator's identity may not declare a brain's token or put commands.

Finding the stack: ``drivebench run`` writes ``<run folder>/stack.json`` ({"router", "run_id", "pid"}) while it runs.
Without ``--router``, the newest such file under ``--runs-dir`` whose process is alive (with ``--run``: that run's)
gives the router and the run id; ``--router EP --run RUN_ID`` reach any stack (compose, another machine).
"""

from __future__ import annotations

import json
import logging
import os
import random
import subprocess
import tempfile
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

from brains.registry import UnknownBrainError, bus_name, require_brain
from orchestrator.stack import processes
from protocol import codec, environment, keys
from protocol.bus import (
    ANSWER_TIMEOUT_S,
    PASSWORD_ENV,
    TLS_CERT_ENV,
    TLS_KEY_ENV,
    USER_ENV,
    Bus,
    BusConfig,
    BusError,
    resolve_bus,
)
from protocol.deploy.runtime import UsageError
from protocol.messages import Command, ControlReply, ControlRequest, ServerState

# The stack-side messages keep the launcher's logger: they are what a closing stack does.
log = logging.getLogger("drivebench.launcher")

DEFAULT_TIMEOUT_S = 60.0
STATUS_ATTEMPTS_S = 5.0  # a fresh session may need a moment (more on a loaded machine) to reach the simulator
STOP_WAIT_S = 5.0  # how long to wait for the old brain's token to go after it accepted "stop"
ORPHAN_TIMEOUT_S = 10.0  # a swapped-in brain exits when the run has had no simulator this long (its stack is gone)
STACK_FILE = "stack.json"  # in the run folder while ``drivebench run`` runs: how ``drivebench swap`` finds the stack
FOREIGN_BRAIN_STOP_S = 3.0  # how long a closing stack waits for the brains swapped into it to go
# A name claim reaches every other session of the run well within this; of two claims on one name, the later claimant
# then always sees the earlier one (see _claim_name).
CLAIM_SETTLE_S = 1.0


class SwapError(RuntimeError):
    """The swap could not be done (no stack, the new brain died or never answered, the switch was refused)."""


@dataclass(frozen=True, kw_only=True)
class BrainIdentity:
    """Who the new brain host is to a secure router: a certificate and its key (mutual TLS) and/or a user name and a
    file holding its password. The brain host gets this instead of the swap's own identity."""

    tls_cert: Path | None = None
    tls_key: Path | None = None
    user: str = ""
    password_file: Path | None = None

    def __post_init__(self) -> None:
        for path, option in (
            (self.tls_cert, "--brain-cert"),
            (self.tls_key, "--brain-key"),
            (self.password_file, "--brain-password-file"),
        ):
            if path is not None and not path.is_file():
                raise UsageError(f"{option}: no such file {path}")
        if (self.tls_cert is None) != (self.tls_key is None):
            raise UsageError("--brain-cert and --brain-key go together (the brain host's certificate and its key)")
        if bool(self.user) != (self.password_file is not None):
            raise UsageError("--brain-user and --brain-password-file go together")
        if self.tls_cert is None and not self.user:
            raise UsageError("a brain identity needs --brain-cert and --brain-key, or --brain-user")

    def overrides(self) -> list[str]:
        """The brain host's ``--set`` arguments (a config wins over the environment)."""
        settings = []
        if self.tls_cert is not None and self.tls_key is not None:
            settings += [f"bus.tls_cert={json.dumps(str(self.tls_cert.resolve()))}"]
            settings += [f"bus.tls_key={json.dumps(str(self.tls_key.resolve()))}"]
        if self.user and self.password_file is not None:
            settings += [f"bus.user={json.dumps(self.user)}"]
            settings += [f"bus.password_file={json.dumps(str(self.password_file.resolve()))}"]
        return [arg for setting in settings for arg in ("--set", setting)]


@dataclass(frozen=True)
class StackInfo:
    """Where a running stack is: its router endpoint, run id and, when known, its run folder."""

    router: str
    run_id: str
    run_dir: Path | None = None


@dataclass(frozen=True)
class SwapResult:
    """What a swap did.

    name: the new brain's bus name (``brain`` is its registered brain). old_brain: the brain active before ("" if
    unknown). switched: the new brain drives now (False: no episode was running). old_stopped: the old brain
    accepted "stop". episode: the episode switched in, -1 if none. process: the detached brain host.
    """

    run_id: str
    brain: str
    name: str
    old_brain: str
    switched: bool
    old_stopped: bool
    episode: int
    log_path: Path
    process: subprocess.Popen = field(compare=False, repr=False)

    @property
    def pid(self) -> int:
        return self.process.pid

    def summary(self) -> str:
        """One line for the user."""
        if not self.switched:
            return (
                f"drivebench: run {self.run_id}: no episode is running; brain {self.name} ({self.brain}, pid "
                f"{self.pid}) is up for the next episode, {self.old_brain or 'the old brain'} kept; log "
                f"{self.log_path}"
            )
        old = ("stopped" if self.old_stopped else "kept running") if self.old_brain else "unknown"
        return (
            f"drivebench: run {self.run_id}: {self.name} ({self.brain}, pid {self.pid}) drives episode "
            f"{self.episode} in place of {self.old_brain} ({old}); log {self.log_path}"
        )


# -- the swap ----------------------------------------------------------------------------------------------------------


def swap_brain(
    *,
    router: str,
    run_id: str,
    brain: str,
    name: str | None,
    options: tuple[str, ...],
    log_path: Path | None,
    timeout_s: float = DEFAULT_TIMEOUT_S,
    keep_old: bool = False,
    identity: BrainIdentity | None = None,
) -> SwapResult:
    """Start brain ``brain`` as ``name`` on the stack at ``router`` / ``run_id`` and make it the driving brain.

    options: constructor options as ``key=value`` YAML overrides (``weights="/abs/ckpt"`` for neural brains).
    name: its bus name; None = the brain's name, or ``<brain>-2``, ``-3``... when taken.
    log_path: the new brain host's log file, or a folder to write ``brain-<name>.log`` in (a run folder's ``logs``;
    None: the temporary folder). timeout_s: for it to come up and to answer its first frame. keep_old: leave the
    old brain running (it answers frames, driving nothing; not a shadow, so the score does not list it). identity:
    the new brain host's on a secure stack (required when this process has an identity of its own there, i.e. the
    orchestrator's).
    Raises :class:`UsageError` or :class:`SwapError` with a one-line reason; on failure the new brain is stopped.
    """
    _check_brain(brain)
    _check_name(run_id, what="run id")
    if name:
        _check_name(name, what="brain name")
    # The mode comes from the environment: a peer on a plain stack, a client of a secure router (DRIVEBENCH_TLS_*).
    check_identity(identity)
    with Bus(BusConfig(connect=[router]), name=f"swap-{run_id}") as bus:
        _wait_for_simulator_token(bus, run_id, router=router)
        status = _sim_status(bus, run_id, router=router)
        name = _claim_name(
            bus, run_id, brain=brain, name=name, driving=status.active_brain, deadline=time.monotonic() + timeout_s
        )
        if log_path is None:
            log_path = Path(tempfile.gettempdir()) / f"drivebench-{run_id}-brain-{name}.log"
        elif log_path.is_dir():
            log_path = log_path / f"brain-{name}.log"
        process = _start_brain(
            router=router,
            run_id=run_id,
            brain=brain,
            name=name,
            options=options,
            log_path=log_path,
            identity=identity,
        )
        try:
            return _take_over(
                bus,
                status,
                run_id=run_id,
                brain=brain,
                name=name,
                process=process,
                log_path=log_path,
                timeout_s=timeout_s,
                keep_old=keep_old,
            )
        except BaseException:
            _terminate(process)
            raise


def _take_over(
    bus: Bus,
    status: ControlReply,
    *,
    run_id: str,
    brain: str,
    name: str,
    process: subprocess.Popen,
    log_path: Path,
    timeout_s: float,
    keep_old: bool,
) -> SwapResult:
    """Wait until the new brain is up and answering, switch to it, stop the old one."""
    deadline = time.monotonic() + timeout_s
    _wait_alive(bus, run_id, name, process=process, log_path=log_path, deadline=deadline)
    episode = status.episode if status.state == ServerState.RUNNING else -1
    if episode >= 0 and not _wait_first_answer(
        bus, run_id, name, episode, process=process, log_path=log_path, deadline=deadline
    ):
        episode = -1  # it ended meanwhile
    old = _sim_status(bus, run_id).active_brain if episode >= 0 else status.active_brain
    result = SwapResult(
        run_id=run_id,
        brain=brain,
        name=name,
        old_brain=old,
        switched=False,
        old_stopped=False,
        episode=episode,
        log_path=log_path,
        process=process,
    )
    if episode < 0:
        return result
    reply = _request(bus, keys.sim_control(run_id), ControlRequest(action="switch", brain=name))
    if reply is None:
        # A secure router drops the switch of any identity but the orchestrator's without a word.
        raise SwapError(
            f"the simulator did not answer the switch to {name} (on a secure stack, run swap with the "
            f"orchestrator's identity: {TLS_CERT_ENV}/{TLS_KEY_ENV} or {USER_ENV})"
        )
    if not reply.ok:
        raise SwapError(f"the simulator refused the switch to {name} ({reply.code}): {reply.detail}")
    stopped = not keep_old and bool(old) and _stop_brain(bus, run_id, old)
    return SwapResult(
        run_id=run_id,
        brain=brain,
        name=name,
        old_brain=old,
        switched=True,
        old_stopped=stopped,
        episode=episode,
        log_path=log_path,
        process=process,
    )


def _check_brain(brain: str) -> None:
    try:
        require_brain(brain)
    except UnknownBrainError as error:
        raise UsageError(str(error)) from None


def _check_name(name: str, *, what: str) -> str:
    try:
        return keys.check_name(name, what=what)
    except ValueError as error:
        raise UsageError(str(error)) from None


def _request(
    bus: Bus, key: str, request: ControlRequest, *, timeout_s: float = ANSWER_TIMEOUT_S
) -> ControlReply | None:
    payload = bus.request(key, codec.encode(request), timeout_s=timeout_s)
    return codec.decode(payload, ControlReply) if payload is not None else None


def check_identity(identity: BrainIdentity | None) -> None:
    """On a secure stack, this process's identity (the orchestrator's: it switches and stops brains) must not pass to
    the brain host, which needs a brain's: refuse before anything starts when none is given."""
    try:
        resolved = resolve_bus(BusConfig())  # the swap's bus: its identity comes from the environment
    except BusError:
        return  # opening the bus says what is wrong, in its own words
    if identity is None and (resolved.tls_cert or resolved.user):
        raise UsageError(
            "on a secure stack swap runs with the orchestrator's identity and the new brain host needs a brain's: "
            "give --brain-cert and --brain-key (or --brain-user and --brain-password-file)"
        )


def _sim_status(bus: Bus, run_id: str, *, router: str = "") -> ControlReply:
    """The simulator's status, from its read-only key (any identity of a secure stack may read it); retried briefly
    while a fresh session learns of its queryable."""
    deadline = time.monotonic() + STATUS_ATTEMPTS_S
    while True:
        reply = _request(bus, keys.sim_status(run_id), ControlRequest(action="status"))
        if reply is not None:
            return reply
        if time.monotonic() > deadline:
            where = f" via {router}" if router else ""
            raise SwapError(f"no running simulator answers on run {run_id}{where}")
        time.sleep(0.1)


def _wait_for_simulator_token(bus: Bus, run_id: str, *, router: str) -> None:
    """Until the run's liveliness tokens reach this fresh session (a query right after ``open`` finds none yet):
    seeing the simulator's says they have, so the brain names alive are known too."""
    deadline = time.monotonic() + STATUS_ATTEMPTS_S
    while time.monotonic() < deadline:
        if any(keys.parse_alive(key)[1] == "simulator" for key in bus.alive_now(keys.alive_all(run_id))):
            return
        time.sleep(0.05)
    raise SwapError(f"no running simulator on run {run_id} via {router}")


BRAINS_QUERY_S = 3.0  # how long to ask again for the brains' tokens until the driving brain's is among them


def _alive_brains(bus: Bus, run_id: str, *, driving: str) -> set[str]:
    """The bus names of the run's live brains. A liveliness query from a session just opened sometimes answers
    before its routes are up and misses tokens (a swap then picked the driving brain's own name), so it is asked
    again until the driving brain, alive for sure, is in the answer; the driving brain's name is taken either way."""
    deadline = time.monotonic() + BRAINS_QUERY_S
    while True:
        tokens = (keys.parse_alive(key) for key in bus.alive_now(keys.alive_all(run_id)))
        names = {name for _, role, name in tokens if role == "brain"}
        if not driving or driving in names or time.monotonic() >= deadline:
            return names | ({driving} if driving else set())
        time.sleep(0.1)


def _claimed_names(bus: Bus, run_id: str, *, besides: str) -> set[str]:
    """The brain names other swaps (all claimants but ``besides``) have claimed on the run."""
    claims = (keys.parse_name_claim(key) for key in bus.alive_now(keys.name_claims(run_id)))
    return {name for name, claimant in claims if claimant != besides}


def _claim_name(bus: Bus, run_id: str, *, brain: str, name: str | None, driving: str, deadline: float) -> str:
    """Pick the new brain's name (:func:`_pick_name`) and reserve it with a liveliness token kept until this swap's
    bus closes (by then the brain's own token is up), so two swaps at once never pick the same name.

    Picking and checking are not atomic, so: declare the claim, wait :data:`CLAIM_SETTLE_S`, look again. Of two
    claims on one name the later claimant always sees the earlier, so it never keeps the name; the earlier keeps it
    unless it saw the later too, and then both withdraw and try again after a random pause (one soon goes first)."""
    claimant = uuid.uuid4().hex[:12]
    while True:
        taken = _alive_brains(bus, run_id, driving=driving) | _claimed_names(bus, run_id, besides=claimant)
        picked = _pick_name(brain, name, taken, run_id=run_id)
        withdraw = bus.declare_alive(keys.name_claim(run_id, picked, claimant))
        time.sleep(CLAIM_SETTLE_S)
        rivals = _claimed_names(bus, run_id, besides=claimant)
        if picked not in rivals:
            return picked
        withdraw()
        if time.monotonic() > deadline:
            raise SwapError(f"could not claim the name {picked!r} on run {run_id}: other swaps keep claiming it")
        time.sleep(random.uniform(0.0, CLAIM_SETTLE_S))


def _pick_name(brain: str, name: str | None, alive: set[str], *, run_id: str) -> str:
    """``name`` if free; by default the brain's name, else ``<brain>-2``, ``<brain>-3``, ... ``alive``: the names of
    live brains and those other swaps claimed."""
    if name:
        _check_name(name, what="brain name")
        if name in alive:
            raise UsageError(f"a brain named {name!r} is already alive (or being started) on run {run_id}")
        return name
    base = bus_name(brain)
    candidates = (base if n == 1 else f"{base}-{n}" for n in range(1, len(alive) + 2))
    return next(candidate for candidate in candidates if candidate not in alive)


def _start_brain(
    *,
    router: str,
    run_id: str,
    brain: str,
    name: str,
    options: tuple[str, ...],
    log_path: Path,
    identity: BrainIdentity | None,
) -> subprocess.Popen:
    """The brain host, detached: its own session, and no parent watch (DRIVEBENCH_PARENT_PID), so that it lives on
    after this command; the stack stops it (over its control key) when the stack closes. With ``identity`` it joins
    as that brain identity, and none of this process's own identity is passed on."""
    argv = [
        *processes.python_module("brains"),
        "--router",
        router,
        "--run-id",
        run_id,
        "--brain",
        brain,
        "--name",
        name,
        "--set",
        f"orphan_timeout_s={ORPHAN_TIMEOUT_S}",
    ]  # it watches no parent: it ends when its stack does
    for option in options:
        argv += ["--set", f"options.{option}"]
    dropped = {environment.PARENT_PID.name}
    if identity is not None:
        argv += identity.overrides()
        dropped |= {TLS_CERT_ENV, TLS_KEY_ENV, USER_ENV, PASSWORD_ENV}
    env = {key: value for key, value in os.environ.items() if key not in dropped}
    return processes.spawn(argv, log_path=log_path, env=env)


def _died(process: subprocess.Popen, name: str, log_path: Path) -> str | None:
    """Why the new brain host is gone (exit code and last log line), or None while it runs."""
    return processes.exit_reason(process, what=f"brain {name!r}", log_path=log_path)


def _wait_alive(
    bus: Bus, run_id: str, name: str, *, process: subprocess.Popen, log_path: Path, deadline: float
) -> None:
    watch = bus.watch_alive(keys.alive(run_id, "brain", name))
    try:
        missing = watch.wait_for(
            {keys.alive(run_id, "brain", name)},
            timeout_s=max(0.0, deadline - time.monotonic()),
            abort=lambda: _died(process, name, log_path),
        )
    finally:
        watch.close()
    if (dead := _died(process, name, log_path)) is not None:
        raise SwapError(dead)
    if missing:
        raise SwapError(f"brain {name!r} not alive on run {run_id} in time (log {log_path})")


def _wait_first_answer(
    bus: Bus, run_id: str, name: str, episode: int, *, process: subprocess.Popen, log_path: Path, deadline: float
) -> bool:
    """Wait for the new brain's first command of ``episode``: True, or False if the episode ended meanwhile."""
    commands = bus.subscribe(keys.command(run_id, name), Command)
    try:
        next_status = time.monotonic() + 1.0
        while True:
            received = commands.recv(timeout_s=0.1)
            if received is not None and received.message.header.episode == episode:
                return True
            if (dead := _died(process, name, log_path)) is not None:
                raise SwapError(dead)
            if time.monotonic() > deadline:
                raise SwapError(f"brain {name!r} answered no frame of episode {episode} in time (log {log_path})")
            if time.monotonic() > next_status:
                status = _sim_status(bus, run_id)
                if status.state != ServerState.RUNNING or status.episode != episode:
                    return False
                next_status = time.monotonic() + 1.0
    finally:
        commands.close()


def _stop_brain(bus: Bus, run_id: str, name: str) -> bool:
    """Ask brain ``name`` to stop; True once it accepted and its token is gone (or the wait ran out)."""
    reply = _request(bus, keys.brain_control(run_id, name), ControlRequest(action="stop"))
    if reply is None or not reply.ok:
        return False
    token = keys.alive(run_id, "brain", name)
    deadline = time.monotonic() + STOP_WAIT_S
    while token in bus.alive_now(keys.alive_all(run_id)) and time.monotonic() < deadline:
        time.sleep(0.1)
    return True


def _terminate(process: subprocess.Popen) -> None:
    processes.stop([process], grace_s=10.0, names=["the new brain host"])


# -- finding the stack -------------------------------------------------------------------------------------------------


def _pid_alive(pid: object) -> bool:
    if not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def running_stacks(runs_dir: Path) -> list[StackInfo]:
    """Stacks whose ``stack.json`` lies in ``runs_dir`` or one of its folders and whose process is alive, newest
    first."""
    found = []
    for path in [runs_dir / STACK_FILE, *runs_dir.glob(f"*/{STACK_FILE}")]:
        try:
            info = json.loads(path.read_text())
            mtime = path.stat().st_mtime
        except (OSError, ValueError):
            continue
        if (
            isinstance(info, dict)
            and _pid_alive(info.get("pid"))
            and isinstance(info.get("router"), str)
            and isinstance(info.get("run_id"), str)
        ):
            found.append((mtime, StackInfo(router=info["router"], run_id=info["run_id"], run_dir=path.parent)))
    return [info for _, info in sorted(found, key=lambda item: item[0], reverse=True)]


def locate_stack(*, runs_dir: Path, run_id: str | None, router: str | None) -> StackInfo:
    """The stack to swap on: ``--router`` and ``--run`` when both given, else from the running stacks' files."""
    stacks = [s for s in running_stacks(runs_dir) if run_id is None or s.run_id == run_id]
    if router and run_id:
        return StackInfo(router=router, run_id=run_id, run_dir=stacks[0].run_dir if stacks else None)
    if not stacks:
        which = f"run {run_id}" if run_id else "stack"
        raise SwapError(
            f"no running {which} found under {runs_dir} (start one with drivebench run, or pass "
            f"--router EP --run RUN_ID)"
        )
    return StackInfo(router=router or stacks[0].router, run_id=stacks[0].run_id, run_dir=stacks[0].run_dir)


# -- the running stack's side: how swap finds it, and the swapped-in brains it stops when it closes --


def write_stack_file(run_dir: Path, *, router: str, run_id: str) -> Path:
    """Write ``<run_dir>/stack.json`` ({"router", "run_id", "pid"}): how ``drivebench swap`` finds a running stack
    (:func:`running_stacks`)."""
    path = run_dir / STACK_FILE
    path.write_text(json.dumps({"router": router, "run_id": run_id, "pid": os.getpid()}) + "\n")
    return path


def remove_stack_file(run_dir: Path) -> None:
    """Remove ``<run_dir>/stack.json`` if this process wrote it."""
    path = run_dir / STACK_FILE
    try:
        if json.loads(path.read_text()).get("pid") == os.getpid():
            path.unlink()
    except (OSError, ValueError, AttributeError):
        pass  # none, or not ours


def stop_foreign_brains(bus: Bus, *, run_id: str, ours: set[str], timeout_s: float = FOREIGN_BRAIN_STOP_S) -> None:
    """Ask every brain alive on run ``run_id`` whose bus name is not in ``ours`` (swapped in by ``drivebench swap``)
    to stop, and wait until its token is gone: a swapped-in brain must not outlive the stack."""
    try:
        foreign = {
            name
            for _, role, name in map(keys.parse_alive, bus.alive_now(keys.alive_all(run_id)))
            if role == "brain" and name not in ours
        }
        for name in sorted(foreign):
            log.info("stopping brain %s (not started by this stack)", name)
            bus.request(keys.brain_control(run_id, name), codec.encode(ControlRequest(action="stop")), timeout_s=2.0)
    except (BusError, ValueError) as error:
        log.warning("could not stop the brains this stack did not start: %s", error)
        return
    deadline = time.monotonic() + timeout_s
    gone = {keys.alive(run_id, "brain", name) for name in foreign}
    while gone and gone & bus.alive_now(keys.alive_all(run_id)) and time.monotonic() < deadline:
        time.sleep(0.1)
