"""``drivebench swap BRAIN``: make another brain drive a running stack, live (``orchestrator.stack.swap`` does it)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from brains.registry import brain_names
from orchestrator.cli.errors import EXIT_OK, CommandFailed, UsageError
from orchestrator.stack.launcher import BrainLaunch, preflight_launches
from orchestrator.stack.swap import (
    DEFAULT_TIMEOUT_S,
    BrainIdentity,
    SwapError,
    check_identity,
    locate_stack,
    swap_brain,
)
from protocol.bus import BusError


def add(commands: argparse._SubParsersAction) -> None:
    swap = commands.add_parser("swap", help="make another brain drive a running stack, live (lock-step: no step lost)")
    swap.add_argument("brain", help=f"brain to start ({', '.join(brain_names())})")
    swap.add_argument("--weights", type=Path, metavar="CKPT", help="checkpoint (or .onnx) of a neural brain")
    swap.add_argument(
        "--brain-option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="brain constructor option, e.g. --brain-option speed_mps=2 (repeatable)",
    )
    swap.add_argument("--name", help="its name on the bus (default: the brain's name, or BRAIN-2, -3... if taken)")
    swap.add_argument("--run", dest="swap_run", metavar="RUN_ID", help="run id (default: the newest running stack)")
    swap.add_argument(
        "--router",
        dest="swap_router",
        metavar="EP",
        help="router endpoint, e.g. tcp/127.0.0.1:7447 (default: from the run's stack.json)",
    )
    swap.add_argument(
        "--runs-dir", type=Path, default=Path("runs"), help="where drivebench run keeps its run folders (default: runs)"
    )
    swap.add_argument("--keep-old", action="store_true", help="leave the old brain running (not a shadow)")
    swap.add_argument(
        "--timeout",
        type=float,
        default=DEFAULT_TIMEOUT_S,
        metavar="SECONDS",
        help=f"for the new brain to come up and answer a frame (default: {DEFAULT_TIMEOUT_S:.0f})",
    )
    secure = swap.add_argument_group(
        "secure stack",
        "swap runs with the orchestrator's identity (DRIVEBENCH_TLS_CERT/KEY or DRIVEBENCH_USER: only it may switch "
        "and stop brains); the brain host it starts gets a brain's identity, given here (docs/security.md)",
    )
    secure.add_argument("--brain-cert", type=Path, metavar="PEM", help="the new brain host's certificate")
    secure.add_argument("--brain-key", type=Path, metavar="KEY", help="its private key")
    secure.add_argument("--brain-user", default="", metavar="USER", help="the new brain host's user name")
    secure.add_argument("--brain-password-file", type=Path, metavar="FILE", help="its password (first line)")
    swap.set_defaults(func=run_swap_command)


def brain_options(brain_option: list[str], weights: Path | None) -> tuple[str, ...]:
    """``--brain-option`` and ``--weights`` as the brain host's option overrides."""
    for option in brain_option:
        if "=" not in option or not option.split("=", 1)[0]:
            raise UsageError(f"--brain-option must look like KEY=VALUE, got {option!r}")
    options = tuple(brain_option)
    if weights is not None:
        if not weights.is_file():
            raise UsageError(f"--weights: no such file {weights}")
        options += (f"weights={json.dumps(str(weights.resolve()))}",)
    return options


def brain_identity(args: argparse.Namespace) -> BrainIdentity | None:
    """The new brain host's identity on a secure stack, None when no ``--brain-*`` option is given."""
    if args.brain_cert is None and args.brain_key is None and not args.brain_user and args.brain_password_file is None:
        return None
    return BrainIdentity(
        tls_cert=args.brain_cert,
        tls_key=args.brain_key,
        user=args.brain_user,
        password_file=args.brain_password_file,
    )


def run_swap_command(args: argparse.Namespace) -> int:
    """``drivebench swap``: one line on stdout when done, one line on stderr when not (exit 2 usage, 1 stack)."""
    options = brain_options(args.brain_option, args.weights)
    identity = brain_identity(args)
    check_identity(identity)
    try:
        preflight_launches([BrainLaunch(args.brain, options=options)])
    except ValueError as error:
        raise UsageError(str(error)) from None
    try:
        stack = locate_stack(runs_dir=args.runs_dir, run_id=args.swap_run, router=args.swap_router)
        logs = stack.run_dir / "logs" if stack.run_dir is not None else None
        result = swap_brain(
            router=stack.router,
            run_id=stack.run_id,
            brain=args.brain,
            name=args.name or None,
            options=options,
            log_path=logs if logs is not None and logs.is_dir() else None,
            timeout_s=args.timeout,
            keep_old=args.keep_old,
            identity=identity,
        )
    except (SwapError, BusError) as error:
        raise CommandFailed(f"swap failed: {error}") from None
    print(result.summary())
    return EXIT_OK
