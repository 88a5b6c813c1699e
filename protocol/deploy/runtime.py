"""What every service ``__main__`` does the same way: arguments, config, logging, signals, clean exit.

A service is ``main(argv) -> int``: parse ``--config FILE --set key=value --router EP --run-id ID``, load and
log its config, turn SIGTERM into a normal exit (Python as PID 1 ignores SIGTERM otherwise, and a Zenoh session
must be closed for the process to exit at all), run, and turn user mistakes into one line on stderr.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol, TypeVar

import msgspec

from protocol import environment
from protocol.bus import Bus, BusConfig, BusError, resolve_bus
from protocol.deploy.config import ConfigError, dump_config, load_config  # noqa: F401 (re-exported)

T = TypeVar("T")


class ServiceConfig(Protocol):
    """What ``service_main`` needs of a service's config type: how to join the bus, and its name on it."""

    @property
    def bus(self) -> BusConfig: ...

    @property
    def name(self) -> str: ...


C = TypeVar("C", bound=ServiceConfig)

log = logging.getLogger("drivebench")

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")
RUN_ID_ENV = environment.RUN_ID.name  # the run id of a service started without --run-id (compose sets it for all)


class UserError(Exception):
    """A mistake the user can fix (bad name, bad file, unreachable router): one line, no traceback."""


class UsageError(UserError):
    """A mistake on a command line or in a file it names: one line; ``drivebench`` exits 2 (orchestrator.cli.errors).
    Raised by the command modules and by the library functions they call with the user's values."""


def setup_logging(name: str, *, level: str | None = None) -> None:
    """Log to stderr at ``level``, else $DRIVEBENCH_LOG, else INFO; UsageError names a level logging does not know
    (logging's own error is a traceback from deep inside basicConfig)."""
    source = "level" if level else environment.LOG.name
    level = (level or environment.LOG.value() or "INFO").strip().upper()
    if level not in LOG_LEVELS:
        raise UsageError(f"{source} must be one of {', '.join(LOG_LEVELS)}, got {level!r}")
    logging.basicConfig(
        level=level,
        stream=sys.stderr,
        format=f"%(asctime)s {name} %(levelname)s %(message)s",
        datefmt="%H:%M:%S",
    )


def exit_on_sigterm() -> None:
    """SIGTERM raises SystemExit in the main thread, so ``with`` blocks close sessions and files.

    For command-line tools (``drivebench run``: its stack stops as on Ctrl-C). Services use :func:`stop_on_signals`
    instead: an exception raised at an arbitrary point could cut a write in half.
    """

    def handler(signum, frame):
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, handler)


_stop_signal: list[int] = []  # the signal that asked this service to stop, if one did
_stopping = threading.Event()


def stop_on_signals() -> None:
    """SIGTERM and SIGINT only set a flag (:func:`stop_requested`): every service loop checks it at least every
    half second, finishes what it is doing (an episode ends ``stopped``, a frame is answered, a write completes)
    and returns, so sessions and files close in order. Outside the main thread no handler can be installed."""
    if threading.current_thread() is not threading.main_thread():
        return

    def handler(signum, frame):
        _stop_signal.append(signum)
        _stopping.set()

    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, handler)


def stop_requested() -> bool:
    """Whether this process was asked to stop (SIGTERM or SIGINT, or its launcher died): loops return when true."""
    return _stopping.is_set()


def stop_exit_code() -> int:
    """The exit code of a service that returned: 128 + the signal that stopped it (143, 130), else 0."""
    return 128 + _stop_signal[0] if _stop_signal else 0


def service_parser(description: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--config", help="YAML config file")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override one config field, e.g. --set bus.lease_ms=2000 (repeatable)",
    )
    parser.add_argument("--router", help="router endpoint to connect to, e.g. tcp/127.0.0.1:7447")
    parser.add_argument("--run-id", help=f"run id (every key of the run carries it; default: ${RUN_ID_ENV})")
    return parser


def load_service_config(config_type: type[T], args: argparse.Namespace, *, extra: dict[str, Any] | None = None) -> T:
    # Command-line values are strings: quote them, or YAML would read a run id like 0123 as a number.
    overrides = list(args.set)
    if getattr(args, "router", None):
        overrides.append(f"bus.connect=[{json.dumps(args.router)}]")
    run_id = getattr(args, "run_id", None) or environment.RUN_ID.value()
    if run_id:
        overrides.append(f"run_id={json.dumps(run_id)}")
    for key, value in (extra or {}).items():
        if value is not None:
            overrides.append(f"{key}={json.dumps(value)}")
    return load_config(config_type, path=args.config, overrides=overrides)


def exit_with_parent() -> None:
    """Stop (SIGTERM to ourselves, i.e. :func:`stop_requested`) when the launcher that started us dies, even by
    SIGKILL: no orphans.

    The launcher passes its pid in ``DRIVEBENCH_PARENT_PID``; a re-parented process sees another ``getppid()``.
    """
    parent = environment.PARENT_PID.value()
    if not parent or not parent.isdigit():
        return

    def watch() -> None:
        while os.getppid() == int(parent):
            time.sleep(0.5)
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def run_service(name: str, main: Callable[[], int | None]) -> int:
    """Run ``main`` with the process conventions; return the exit code."""
    try:
        setup_logging(name)  # in the try: a bad $DRIVEBENCH_LOG is the user's one-line mistake
        stop_on_signals()
        exit_with_parent()
        return int(main() or 0) or stop_exit_code()
    except (UserError, ConfigError, BusError) as error:
        print(f"{name}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


def log_config(config: Any) -> None:
    """Log the config as the process runs with it: a ``bus`` section as the process joins the bus (the environment
    and the defaults applied: mode, endpoints, certificates), not the empty fields that stand for them."""
    settings = msgspec.to_builtins(config)
    if isinstance(bus := getattr(config, "bus", None), BusConfig):
        settings["bus"] = resolve_bus(bus).settings()  # a bad value fails here, as one line, as it would on opening
    log.info("resolved config:\n%s", dump_config(settings).rstrip())


class Service(Protocol):
    def serve_forever(self) -> None: ...


def service_main(
    role: str,
    description: str,
    config_type: type[C],
    make_service: Callable[[C, Bus], Service],
    argv: list[str] | None = None,
) -> int:
    """The whole ``main`` of a service: parse, load and log the config, open the bus, serve until stopped.

    ``config_type`` needs ``bus`` and ``name`` fields. A service with a ``close()`` method has it called on exit.
    """
    args = service_parser(description).parse_args(argv)

    def run() -> int:
        config = load_service_config(config_type, args)
        log_config(config)
        with Bus(config.bus, name=f"{role}-{config.name}") as bus:
            service = make_service(config, bus)
            try:
                service.serve_forever()
            finally:
                if hasattr(service, "close"):
                    service.close()
        return 0

    return run_service(role, run)
