"""``drivebench brains list | check | schema``: what brains there are, whether one meets the contract, and the wire
contract's JSON Schemas for brains written in other languages."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from orchestrator.cli.errors import UsageError
from protocol.config import ConfigError, parse_override

SCHEMA_DIR = Path(__file__).resolve().parents[2] / "docs" / "protocol"


def add(commands: argparse._SubParsersAction) -> None:
    brains = commands.add_parser(
        "brains", help="list brains, check one against the brain contract, write the wire contract's JSON Schemas"
    )
    sub = brains.add_subparsers(dest="brains_command", required=True)
    sub.add_parser("list", help="every brain known by name, and where it comes from (built-in or which package)")
    check = sub.add_parser(
        "check",
        help="run the brain contract on a brain, one line per check with the fix for "
        "each failure (exit 1 if any fails)",
    )
    check.add_argument("brain", help="name, installed brain, package.module:Class, or a Behavior Metrics brain file")
    check.add_argument("--weights", type=Path, metavar="CKPT", help="checkpoint of a neural brain")
    check.add_argument(
        "--brain-option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="constructor option, value as YAML (repeatable)",
    )
    check.add_argument(
        "--memory-steps", type=int, default=300, metavar="N", help="frames of the memory-growth check (default 300)"
    )
    schema = sub.add_parser("schema", help="write the JSON Schema of every message a brain process exchanges")
    schema.add_argument(
        "-o",
        "--output",
        type=Path,
        default=SCHEMA_DIR,
        help=f"folder (default: {SCHEMA_DIR.relative_to(SCHEMA_DIR.parent.parent)})",
    )
    brains.set_defaults(func=run_brains_command)


def run_brains_command(args: argparse.Namespace) -> int:
    if args.brains_command == "list":
        return _list()
    if args.brains_command == "check":
        return _check(args)
    return _schema(args.output)


def _list() -> int:
    from brains.registry import brain_sources

    sources = brain_sources()
    width = max(len(source.name) for source in sources)
    for source in sources:
        print(f"{source.name:<{width}}  {source.origin:<40} {source.target}")
    print("\nalso: --brain package.module:Class, or a Behavior Metrics brain file path/to/brain.py", file=sys.stderr)
    return 0


def brain_option_dict(items: list[str], weights: Path | None) -> dict[str, Any]:
    """``--brain-option KEY=VALUE`` (YAML values) and ``--weights`` as constructor keyword options."""
    options: dict[str, Any] = {}
    for item in items:
        try:
            keys, value = parse_override(item)
        except ConfigError as error:
            raise UsageError(f"--brain-option: {error}") from None
        if len(keys) != 1:
            raise UsageError(f"--brain-option {item!r}: one key, no dots")
        options[keys[0]] = value
    if weights is not None:
        if not weights.is_file():
            raise UsageError(f"--weights: no such file {weights}")
        options["weights"] = str(weights.resolve())
    return options


def _check(args: argparse.Namespace) -> int:
    from brains.checker import check_brain, passed

    options = brain_option_dict(args.brain_option, args.weights)
    if args.memory_steps < 2:
        raise UsageError("--memory-steps must be at least 2")
    print(f"checking brain {args.brain!r} on rendered frames of simple ...", file=sys.stderr)
    results = check_brain(args.brain, options=options, memory_steps=args.memory_steps)
    for result in results:
        print(result.line())
    failures = sum(result.status == "fail" for result in results)
    print(
        f"{args.brain}: " + (f"{failures} check(s) failed" if failures else "meets the brain contract"), file=sys.stderr
    )
    return 0 if passed(results) else 1


def _schema(folder: Path) -> int:
    from protocol.schema import write_schemas

    for path in write_schemas(folder):
        print(path)
    return 0
