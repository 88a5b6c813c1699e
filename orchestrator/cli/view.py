"""``drivebench view``: serve a running run to Foxglove (WebSocket) from this machine, until Ctrl-C or SIGTERM.

    drivebench view [--run RUN] [--router EP] [--host 127.0.0.1] [--port 8765] [--backlog 120] [--max-viewers 4]
                    [--backlog-bytes 4000000]

The router comes from ``--router`` or ``DRIVEBENCH_ROUTER``; the run from ``--run``, ``DRIVEBENCH_RUN_ID``, or else the
only run with a process alive on that router (from the liveliness tokens). Mistakes and an unreachable router are
one line on stderr: exit 2 for a usage mistake, 1 when there is nothing to view.

"""

from __future__ import annotations

import argparse
import os
import sys

from orchestrator.cli.errors import EXIT_OK, CommandFailed, UsageError
from protocol import environment, keys
from protocol.bus import ROUTER_ENV, Bus, BusConfig, BusError, probe_router
from protocol.deploy.runtime import RUN_ID_ENV as RUN_ENV
from protocol.deploy.runtime import UserError, setup_logging, stop_on_signals
from protocol.episodes import running_runs
from services.viz.service import DEFAULT_PORT, VizConfig, VizService, viewer_url

ROUTER_PROBE_S = 3.0
CONNECT_TIMEOUT_MS = 10_000


def add(commands: argparse._SubParsersAction) -> None:
    """Add ``view`` to the ``drivebench`` subcommands (``commands`` from ``parser.add_subparsers``)."""
    view = commands.add_parser(
        "view",
        help="live view of a running run in Foxglove (WebSocket): camera, car on the circuit, commands, metrics",
        description="Serve a running run to Foxglove: Open connection -> Foxglove WebSocket -> the ws:// address "
        "printed on start. Runs until Ctrl-C.",
    )
    view.add_argument(
        "--run",
        dest="view_run",
        metavar="RUN_ID",
        help=f"run to view (default: ${RUN_ENV}, else the only run alive on the router)",
    )
    view.add_argument(
        "--router",
        dest="view_router",
        metavar="EP",
        help=f"router endpoint, e.g. tcp/127.0.0.1:7447 (default: ${ROUTER_ENV})",
    )
    view.add_argument(
        "--host",
        dest="view_host",
        default="127.0.0.1",
        help="address to serve on (default: 127.0.0.1; 0.0.0.0 for other machines)",
    )
    view.add_argument(
        "--port",
        dest="view_port",
        type=int,
        default=DEFAULT_PORT,
        help=f"TCP port to serve on (default: {DEFAULT_PORT})",
    )
    view.add_argument(
        "--backlog",
        dest="view_backlog",
        type=int,
        default=VizConfig().backlog,
        help="messages queued per viewer before the oldest are dropped (default: %(default)s)",
    )
    view.add_argument(
        "--max-viewers",
        dest="view_max_viewers",
        type=int,
        default=VizConfig().max_viewers,
        help="viewers served at once; more are refused (default: %(default)s)",
    )
    view.add_argument(
        "--backlog-bytes",
        dest="view_backlog_bytes",
        type=int,
        default=VizConfig().backlog_bytes,
        help="bytes queued per viewer before messages are dropped (default: %(default)s)",
    )
    view.set_defaults(func=run_view_command)


def run_view_command(args: argparse.Namespace) -> int:
    """``drivebench view``: serves until Ctrl-C / SIGTERM (exit 0); one line on stderr when it cannot."""
    setup_logging("view")
    try:
        router = args.view_router or environment.ROUTER.value().split(",")[0].strip()
        if not router:
            raise UsageError(
                f"no router: give --router EP (e.g. tcp/127.0.0.1:7447) or set {ROUTER_ENV} (a "
                f"running `drivebench run` writes its router to <run folder>/stack.json)"
            )
        wanted = args.view_run or environment.RUN_ID.value() or None
        try:
            if wanted is not None:
                keys.check_name(wanted, what="run id")
            limits = {
                "backlog": args.view_backlog,
                "max_viewers": args.view_max_viewers,
                "backlog_bytes": args.view_backlog_bytes,
            }
            VizConfig(host=args.view_host, port=args.view_port, **limits)  # checks the values
            # TLS and credentials come from the environment as for every process (protocol.bus.BusConfig); a
            # router that accepts TCP but never completes Zenoh's handshake ends in an error line, not a hang.
            bus_config = BusConfig(mode="client", connect=[router], connect_timeout_ms=CONNECT_TIMEOUT_MS)
        except ValueError as error:
            raise UsageError(str(error)) from None
        probe_router(router, timeout_s=ROUTER_PROBE_S)
        stop_on_signals()  # Ctrl-C or SIGTERM: the view's loop returns and the session closes in order
        with Bus(bus_config, name=f"view-{os.getpid()}") as bus:
            run_id = _choose_run(bus, router, wanted)
            config = VizConfig(
                bus=bus.config,
                run_id=run_id,
                name=f"view-{os.getpid()}",
                host=args.view_host,
                port=args.view_port,
                **limits,
            )
            service = VizService(config, bus)
            try:
                print(
                    f"drivebench view: run {run_id} via {router}: in Foxglove, Open connection -> Foxglove "
                    f"WebSocket -> {viewer_url(args.view_host, service.port)}  (Ctrl-C to stop)",
                    file=sys.stderr,
                    flush=True,
                )
                service.serve_forever()
            except (KeyboardInterrupt, SystemExit):
                pass  # Ctrl-C or SIGTERM: the normal end of a view
            finally:
                service.close()
    except UsageError:
        raise
    except (UserError, BusError) as error:
        raise CommandFailed(f"view failed: {error}") from None
    except (KeyboardInterrupt, SystemExit):
        pass  # stopped before it served
    return EXIT_OK


def _choose_run(bus: Bus, router: str, wanted: str | None) -> str:
    """The run to view: ``wanted`` when given, else the only run with a simulator alive."""
    runs = running_runs(bus, timeout_s=2.0)
    if wanted is not None:
        if wanted not in runs:
            print(
                f"drivebench view: no process of run {wanted} is alive on {router} yet; waiting for it", file=sys.stderr
            )
        return wanted
    if not runs:
        raise UserError(f"no run is alive on the router at {router} (start one, or name it with --run RUN_ID)")
    if len(runs) > 1:
        raise UserError(f"{len(runs)} runs are alive on {router}: {', '.join(sorted(runs))}; pick one with --run")
    return next(iter(runs))
