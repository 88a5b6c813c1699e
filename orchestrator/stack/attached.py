"""A stack that someone else started (``drivebench run --attach``, ``docker compose``, other machines): joined, never
spawned or stopped here; its episodes run through the simulator's control queryable as a :class:`LocalStack`'s do."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from orchestrator.stack import run_folder
from orchestrator.stack.failures import StackError
from orchestrator.stack.launcher import LocalStack
from orchestrator.stack.run_folder import RunConfig
from protocol import environment, keys
from protocol.bus import Bus, BusConfig, BusError, probe_router, router_address
from protocol.deploy import graph
from protocol.deploy.runtime import UsageError
from protocol.episode_spec import EpisodeSpec
from protocol.messages import EpisodeScore, LiveMetrics

log = logging.getLogger("drivebench.launcher")


@dataclass
class AttachedStack(LocalStack):
    """A stack that someone else started (``docker compose``, other machines): nothing is spawned or stopped here.

    It joins the router at ``router_endpoint`` (None: the ``DRIVEBENCH_ROUTER`` environment variable) as a client,
    waits until the simulator, the noise injector, the scorer and the brain are alive, and runs episodes through the
    simulator's control queryable like :class:`LocalStack`. ``brain_name`` is the bus name of the brain to drive;
    None takes the only brain alive on the run (an error when there are several).
    """

    brain_name: str | None = None

    def __post_init__(self) -> None:
        keys.check_name(self.run_id, what="run id")
        self.endpoint = self.router_endpoint or environment.ROUTER.value()
        self._init_state(busy_wait_s=self.startup_timeout_s)  # --attach waits for a running episode up to --wait

    def start(self) -> None:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        if not self.endpoint:
            raise StackError(f"no router to attach to: give --router ENDPOINT or set {environment.ROUTER.name}")
        watch = self._join_run(client=f"driver-{self.run_id}")
        self.brain_name = self._wait_for_brain(watch)
        log.info("attached to run %s on %s, driving with brain %s", self.run_id, self.endpoint, self.brain_name)

    def _join_run(self, *, client: str):
        """Join the router as ``client`` and wait until the run's simulator, noise injector and scorer are alive;
        the alive watch it returns keeps following the run's tokens."""
        self.bus = Bus(BusConfig(mode="client", connect=[e.strip() for e in self.endpoint.split(",")]), name=client)
        watch = self._watch = self.bus.watch_alive(keys.alive_all(self.run_id))
        self._required = {row.token_key(self.run_id) for row in graph.local_stack_roles()}
        missing = watch.wait_for(self._required, timeout_s=self.startup_timeout_s)
        if missing:
            names = ", ".join(sorted("/".join(keys.parse_alive(k)[1:]) for k in missing))
            raise StackError(
                f"run {self.run_id!r} on {self.endpoint}: not alive after {self.startup_timeout_s:.0f} s: {names}"
            )
        return watch

    def _wait_for_brain(self, watch) -> str:
        deadline = time.monotonic() + self.startup_timeout_s
        while True:
            brains = sorted(name for _, role, name in map(keys.parse_alive, watch.alive()) if role == "brain")
            if self.brain_name is not None and self.brain_name in brains:
                return self.brain_name
            if self.brain_name is None and len(brains) == 1:
                return brains[0]
            if self.brain_name is None and len(brains) > 1:
                raise StackError(
                    f"run {self.run_id!r} has several brains alive ({', '.join(brains)}): choose one with --brain"
                )
            if time.monotonic() > deadline:
                wanted = f"brain {self.brain_name!r}" if self.brain_name else "a brain"
                raise StackError(
                    f"run {self.run_id!r}: {wanted} not alive after {self.startup_timeout_s:.0f} s"
                    + (f" (alive: {', '.join(brains)})" if brains else "")
                )
            time.sleep(0.1)

    def close(self) -> None:
        if self.bus is not None:
            self.bus.close()
            self.bus = None


@dataclass(kw_only=True)
class AttachedRun:
    """One ``drivebench run --attach`` episode on a stack someone else started, into ``run_dir``: the pipeline the
    CLI hands its parsed options to, as :class:`~orchestrator.stack.local_run.LocalRun` is for a stack of its own.

    Entering joins the run ``run_id`` on the router at ``router_endpoint`` (None: ``DRIVEBENCH_ROUTER``), waiting
    up to ``wait_s`` for its processes and for the brain ``brain_name`` (None: the only brain alive), which
    :attr:`brain_name` then names; :meth:`drive` runs one episode there. Leaving closes the bus session only: the
    stack's processes are not ours to stop."""

    run_id: str
    run_dir: Path
    router_endpoint: str | None = None
    brain_name: str | None = None
    wait_s: float
    _stack: AttachedStack | None = field(default=None, init=False, repr=False)

    def __enter__(self) -> AttachedRun:
        stack = AttachedStack(
            run_id=self.run_id,
            run_dir=self.run_dir,
            router_endpoint=self.router_endpoint,
            brain_name=self.brain_name,
            startup_timeout_s=self.wait_s,
        )
        stack.__enter__()
        self._stack = stack
        self.brain_name = stack.brain_name
        return self

    def __exit__(self, *exc_info: object) -> None:
        if self._stack is not None:
            self._stack.__exit__(*exc_info)
            self._stack = None

    @property
    def endpoint(self) -> str:
        """The router joined."""
        assert self._stack is not None, "enter the AttachedRun first"
        return self._stack.endpoint

    def drive(
        self,
        spec: EpisodeSpec,
        *,
        on_live: Callable[[LiveMetrics], None] | None = None,
        on_failure_record: Callable[[dict], None] | None = None,
    ) -> EpisodeScore:
        """The run's ``config.yaml`` (attached: the router, no brain launched), the episode ``spec``, and its
        ``score.json``. A failed episode leaves ``failure.json`` (also handed to ``on_failure_record``) and raises
        its StackFailure."""
        assert self._stack is not None, "enter the AttachedRun first"
        config = RunConfig(run_id=self.run_id, router=self.endpoint, attached=True, episode=spec)
        run_folder.write_run_config(self.run_dir, config)
        with run_folder.recorded_failure(self.run_dir, run_id=self.run_id, on_record=on_failure_record):
            score = self._stack.run_episode(spec, on_live=on_live)
        run_folder.write_score(self.run_dir, score)
        return score


def wait_for_router(endpoint: str, *, wait_s: float) -> None:
    """Until the router's port answers (a Zenoh client would wait for an absent router forever, silently)."""
    first = endpoint.split(",")[0].strip()
    try:
        router_address(first)  # an endpoint without a port is refused at once: no wait makes it one
    except ValueError as error:
        raise StackError(str(error)) from None
    deadline = time.monotonic() + wait_s
    while True:
        try:
            return probe_router(first)
        except BusError as error:
            if time.monotonic() > deadline:
                raise StackError(f"{error} (waited {wait_s:.0f} s)") from None
            time.sleep(0.5)


def only_running_run(router: str | None, *, wait_s: float) -> str:
    """The run id of the only run with a simulator alive on the router (waiting up to ``wait_s`` for one)."""
    from protocol.episodes import running_runs

    endpoint = router or environment.ROUTER.value()
    if not endpoint:
        raise UsageError(f"no router to attach to: give --router ENDPOINT or set {environment.ROUTER.name}")
    with Bus(BusConfig(mode="client", connect=endpoint.split(",")), name="driver-discovery") as bus:
        deadline = time.monotonic() + wait_s
        while not (runs := running_runs(bus)) and time.monotonic() < deadline:
            time.sleep(0.5)
    if len(runs) != 1:
        found = f"runs {', '.join(sorted(runs))}" if runs else "no run"
        raise UsageError(f"{found} alive on {endpoint}: choose one with --run-id or {environment.RUN_ID.name}")
    return runs.pop()
