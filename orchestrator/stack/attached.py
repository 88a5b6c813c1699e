"""A stack that someone else started (``drivebench run --attach``, ``docker compose``, other machines): joined, never
spawned or stopped here; its episodes run through the simulator's control queryable as a :class:`LocalStack`'s do."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

from orchestrator.stack.failures import StackError
from orchestrator.stack.launcher import LocalStack
from protocol import environment, keys
from protocol.bus import Bus, BusConfig, BusError, probe_router, router_address
from protocol.deploy import graph
from protocol.deploy.runtime import UsageError

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
