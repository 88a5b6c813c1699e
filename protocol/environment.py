"""Every ``DRIVEBENCH_*`` environment variable: its name, the kind of value, what an unset one means, and what it
does. The only module that reads them: the others ask :meth:`Variable.value`, so that a name, a default or a meaning
lives in one place and the docs' table (``docs/environment.md``) is made from this one::

    python -m protocol.environment           # check: exit 1 when docs/environment.md differs from the table
    python -m protocol.environment --write   # rewrite it

It imports nothing outside the standard library but :mod:`circuits.variables` (the record type, and the circuit
library's own variable, which live on the ground floor so that circuits/ never imports upward), so a process with
no optional extra imports it.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Mapping
from pathlib import Path

from circuits.variables import CIRCUITS_DIR, Variable

# The default renderer of each command that takes --renderer, when neither --renderer nor $DRIVEBENCH_RENDERER
# says: `run` keeps the reference renderer, the long runs take the faster one where its parity is measured
# (docs/guides/renderers.md).
RENDERER_BY_COMMAND = {"run": "pybullet", "matrix": "auto", "dataset collect": "auto"}

ROUTER = Variable(
    name="DRIVEBENCH_ROUTER",
    kind="endpoints, comma separated (e.g. tcp/10.0.0.5:7447, tls/HOST:7447)",
    default="none: a process listens for peers; `run --attach`, `view`, `replay` ask for --router; "
    "`health`: tcp/127.0.0.1:7447",
    meaning="the router every process connects to (the config's bus.connect wins)",
    read_by="every process; `drivebench run --attach`, `view`, `health`, `replay`",
)
MODE = Variable(
    name="DRIVEBENCH_MODE",
    kind="peer or client",
    default="peer, or client when TLS or credentials are set (scorer and recorder are always clients)",
    meaning="how a process joins the bus (bus.mode wins): client (everything through the router) for a process "
    "on another machine than the router",
    read_by="every process",
)
LISTEN = Variable(
    name="DRIVEBENCH_LISTEN",
    kind="endpoints, comma separated",
    default="a peer takes a free port on every interface, or on loopback when its router is on loopback; the "
    "router tcp/[::]:7447, compose's router tcp/127.0.0.1:7447",
    meaning="where a peer or the router listens (bus.listen wins); clients never listen",
    read_by="every process; compose's router",
)
TLS_ROOT_CA = Variable(
    name="DRIVEBENCH_TLS_ROOT_CA",
    kind="path to a PEM file",
    default="none: no TLS",
    meaning="the CA that signed the router's (and, mutual TLS, the clients') certificates (bus.tls_root_ca wins)",
    read_by="every process",
)
TLS_CERT = Variable(
    name="DRIVEBENCH_TLS_CERT",
    kind="path to a PEM file",
    default="none",
    meaning="this process's own certificate, with DRIVEBENCH_TLS_KEY (bus.tls_cert wins)",
    read_by="every process; `drivebench swap` (the orchestrator's identity)",
)
TLS_KEY = Variable(
    name="DRIVEBENCH_TLS_KEY",
    kind="path to a PEM file",
    default="none",
    meaning="the private key of DRIVEBENCH_TLS_CERT (bus.tls_key wins)",
    read_by="every process",
)
USER = Variable(
    name="DRIVEBENCH_USER",
    kind="text",
    default="none: no user/password authentication",
    meaning="user name for the router's user/password authentication, an identity for its roles (bus.user wins)",
    read_by="every process; `drivebench swap`",
)
PASSWORD = Variable(
    name="DRIVEBENCH_PASSWORD",
    kind="text",
    default="none",
    meaning="the password of DRIVEBENCH_USER (or bus.password_file: never in a config, which is logged and recorded)",
    read_by="every process",
)
RUN_ID = Variable(
    name="DRIVEBENCH_RUN_ID",
    kind="text",
    default="a service's config run_id; `run --attach` and `view`: the only run alive on the router; `health`: default",
    meaning="the run a service started without --run-id serves, or a command attaches to",
    read_by="every service; `drivebench run --attach`, `view`, `health`",
)
LOG = Variable(
    name="DRIVEBENCH_LOG",
    kind="DEBUG, INFO, WARNING, ERROR or CRITICAL (any case)",
    default="INFO",
    meaning="the log level of every service (on stderr)",
    read_by="every service",
)
RENDERER = Variable(
    name="DRIVEBENCH_RENDERER",
    kind="pybullet, gl or auto",
    default="the command's: "
    + ", ".join(f"`{command}` {name}" for command, name in RENDERER_BY_COMMAND.items())
    + " (auto: gl where EGL works, else pybullet)",
    meaning="the camera renderer where --renderer (or a matrix's `renderer:`) does not say",
    read_by="`drivebench run`, `matrix`, `dataset collect` (compose passes it to the orchestrator)",
)
TRACE_DIR = Variable(
    name="DRIVEBENCH_TRACE_DIR",
    kind="path to a folder",
    default="none: no trace",
    meaning="each bus session writes a timestamp per message there (put, sent, received: benchmarks/closed_loop.py)",
    read_by="every process",
)
PARENT_PID = Variable(
    name="DRIVEBENCH_PARENT_PID",
    kind="process id",
    default="none: the process outlives whoever started it",
    meaning="set by the launcher for its children: a child stops by itself when that process dies (no orphans)",
    read_by="every service (set by the launcher, not by users)",
)
UID = Variable(
    name="DRIVEBENCH_UID",
    kind="user id",
    default="1000",
    meaning="the user the compose services run as, so that ./results stays yours",
    read_by="docker compose",
)
GID = Variable(
    name="DRIVEBENCH_GID",
    kind="group id",
    default="1000",
    meaning="the group the compose services run as",
    read_by="docker compose",
)
TORCH_VERSION = Variable(
    name="DRIVEBENCH_TORCH_VERSION",
    kind="a torch version",
    default="the version scripts/setup.sh pins",
    meaning="the torch that scripts/setup.sh installs",
    read_by="scripts/setup.sh",
)
REQUIRE_MCAP_VALIDATOR = Variable(
    name="DRIVEBENCH_REQUIRE_MCAP_VALIDATOR",
    kind="1 or empty",
    default="empty: the tests skip the MCAP validator's checks where it is not installed",
    meaning="a missing MCAP validator fails the tests instead of skipping (scripts/test.sh sets it where node is)",
    read_by="the tests",
)
BOARD_RAY = Variable(
    name="DRIVEBENCH_BOARD_RAY",
    kind="a Ray address (auto, HOST:PORT)",
    default="none: a challenge's evaluations run on the server's machine",
    meaning="the Ray cluster a challenge's evaluations run their episodes on",
    read_by="a challenge's evaluations (set by `drivebench board serve --ray`, not by users)",
)
DOCKER_CHECK_BOARD = Variable(
    name="DRIVEBENCH_BOARD",
    kind="1 or empty",
    default="empty: the check drives the simulation stack",
    meaning="scripts/docker-check.sh checks the challenge server's image and service (profile board) instead",
    read_by="scripts/docker-check.sh",
)
BM_ROOT = Variable(
    name="DRIVEBENCH_BM_ROOT",
    kind="path to a folder",
    default="none: a Behavior Metrics brain file that imports BM's own modules is refused",
    meaning="a BehaviorMetrics checkout (or its behavior_metrics folder): Behavior Metrics brain files import "
    "`brains.gazebo...` and `utils...` from it (the brain option bm_root wins)",
    read_by="brain hosts of Behavior Metrics brain files; `drivebench run`, `matrix`, `brains check` (their preflight)",
)

VARIABLES = (
    ROUTER,
    MODE,
    LISTEN,
    TLS_ROOT_CA,
    TLS_CERT,
    TLS_KEY,
    USER,
    PASSWORD,
    RUN_ID,
    LOG,
    RENDERER,
    CIRCUITS_DIR,
    TRACE_DIR,
    PARENT_PID,
    UID,
    GID,
    TORCH_VERSION,
    REQUIRE_MCAP_VALIDATOR,
    BOARD_RAY,
    DOCKER_CHECK_BOARD,
    BM_ROOT,
)
# How a process joins the bus; a local stack's children get none of them (they are meant for a standing stack).
BUS = (ROUTER, MODE, LISTEN, TLS_ROOT_CA, TLS_CERT, TLS_KEY, USER, PASSWORD)


def bus_settings() -> Mapping[str, str]:
    """The bus variables set in this process's environment, by name (what ``protocol.bus_config`` resolves)."""
    return {variable.name: variable.value() for variable in BUS if variable.name in os.environ}


# -- the docs' table -------------------------------------------------------------------------------------------------

DOC_PATH = Path(__file__).resolve().parent.parent / "docs" / "environment.md"


def markdown() -> str:
    """docs/environment.md: one row per variable, in the order of :data:`VARIABLES`."""
    lines = [
        "# Environment variables",
        "",
        "Generated from `protocol/environment.py` by `python -m protocol.environment --write`: edit that file, not "
        "this one.",
        "A value in a config file or on the command line wins over the variable; an empty variable counts as unset.",
        "",
        "| variable | value | unset or empty | what it sets | read by |",
        "|---|---|---|---|---|",
    ]
    for variable in VARIABLES:
        cells = (f"`{variable.name}`", variable.kind, variable.default, variable.meaning, variable.read_by)
        lines.append("| " + " | ".join(cell.replace("|", "\\|") for cell in cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m protocol.environment", description=__doc__.split("\n")[0])
    parser.add_argument("--write", action="store_true", help=f"rewrite {DOC_PATH.name} from the table")
    args = parser.parse_args(argv)
    if args.write:
        DOC_PATH.write_text(markdown())
        return 0
    if not DOC_PATH.is_file() or DOC_PATH.read_text() != markdown():
        print(f"{DOC_PATH} differs from protocol/environment.py: run python -m protocol.environment --write")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
