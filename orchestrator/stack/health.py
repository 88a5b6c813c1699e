"""Is this process of a running stack up? (compose healthchecks, scripts).

The router is healthy when its TCP port accepts connections; any other role when its liveliness token is on the
bus (``drivebench/alive/<run>/<role>/<name>``), which it declares only once it is ready to serve. Exit code 0 when
healthy, 1 otherwise, with one line saying why.
"""

from __future__ import annotations

from protocol import keys
from protocol.bus import Bus, BusConfig, BusError, probe_router
from protocol.deploy import graph

ROLES = graph.health_roles()  # "driver": the orchestrator driving an episode
CONNECT_TIMEOUT_S = 2.0


def check_health(role: str, *, endpoint: str, run_id: str, name: str | None = None) -> str | None:
    """None when healthy, else why not (one line)."""
    try:
        probe_router(endpoint.split(",")[0], timeout_s=CONNECT_TIMEOUT_S)
    except BusError as error:
        return str(error)
    if role == "router":
        return None
    try:
        with Bus(BusConfig(mode="client", connect=endpoint.split(",")), name=f"health-{role}") as bus:
            alive = [keys.parse_alive(key) for key in bus.alive_now(keys.alive_all(run_id))]
    except BusError as error:
        return str(error)
    names = sorted(n for _, r, n in alive if r == role)
    if name is not None and role == "brain":
        from brains.registry import bus_name

        name = bus_name(name)  # compose passes the BRAIN it started, which may be a module path or a file
    if (name is None and names) or name in names:
        return None
    return (
        f"no {role}{f' {name!r}' if name else ''} alive on run {run_id!r} (alive: "
        f"{', '.join(f'{r}/{n}' for _, r, n in alive) or 'nothing'})"
    )
