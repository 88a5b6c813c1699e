"""``drivebench brains list | check | schema``: what brains there are, whether one meets the contract, and the wire
contract's JSON Schemas for brains written in other languages."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import importlib.util
import json
import os
import sys
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from orchestrator.cli.errors import EXIT_INTERRUPTED, UsageError
from protocol.deploy.config import ConfigError, parse_override

SCHEMA_DIR = Path(__file__).resolve().parents[2] / "docs" / "protocol"


def add(commands: argparse._SubParsersAction) -> None:
    brains = commands.add_parser(
        "brains", help="list brains, check one against the brain contract, write the wire contract's JSON Schemas"
    )
    sub = brains.add_subparsers(dest="brains_command", required=True)
    listing = sub.add_parser(
        "list", help="every brain known by name, and where it comes from (built-in or which package)"
    )
    listing.add_argument("--json", action="store_true", help="one JSON array on stdout instead of the table")
    check = sub.add_parser(
        "check",
        help="run the brain contract on a brain, one line per check with the fix for "
        "each failure (exit 1 if any fails)",
    )
    check.add_argument("brain", help="name, installed brain, package.module:Class, or a Behavior Metrics brain file")
    check.add_argument(
        "--json", action="store_true", help="one JSON array of the checks on stdout (name, status, detail, fix)"
    )
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
    check.add_argument(
        "--brain-timeout",
        type=float,
        default=10.0,
        metavar="SECONDS",
        help="lock-step timeout of the runs it is for (run --brain-timeout; default 10): answers slower than this "
        "fail the answer-time check, which stops the checks early once it has clearly failed",
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
        return _list(as_json=args.json)
    if args.brains_command == "check":
        return _check(args)
    return _schema(args.output)


def _list(*, as_json: bool) -> int:
    """Every brain by name, where it comes from, what it needs beyond the core install (the demo's .venv has no
    torch: a network brain there says so before a run does) and what makes it."""
    from brains.registry import brain_sources, needs

    sources = brain_sources()
    extras = {source.name: needs(source) for source in sources}
    if as_json:
        listed = [
            {
                "name": source.name,
                "origin": source.origin,
                "target": source.target,
                "needs": None if (pair := extras[source.name]) is None else pair[1],
                "extra": None if pair is None else pair[0],
            }
            for source in sources
        ]
        print(json.dumps(listed, indent=2))
        return 0
    rows = [("name", "from", "needs", "made by")]
    rows += [(s.name, s.origin, _needs_words(extras[s.name]), s.target) for s in sources]
    widths = [max(len(row[column]) for row in rows) for column in range(3)]
    for row in rows:
        print("  ".join(f"{cell:<{width}}" for cell, width in zip(row[:3], widths, strict=True)) + f"  {row[3]}")
    print("\nalso: --brain package.module:Class, or a Behavior Metrics brain file path/to/brain.py", file=sys.stderr)
    for extra, module in sorted({pair for pair in extras.values() if pair is not None}):
        if importlib.util.find_spec(module) is None:
            print(f"{module} is not installed here: pip install 'drivebench[{extra}]'", file=sys.stderr)
    return 0


def _needs_words(pair: tuple[str, str] | None) -> str:
    return "-" if pair is None else f"{pair[1]} ({pair[0]})"


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
    """The report on stdout, one line per check as each is known; progress on stderr; whatever the brain prints
    to stdout is kept out of the report (it could bury or imitate it) and summed up on stderr at the end."""
    from brains.checker import iter_checks, passed

    options = brain_option_dict(args.brain_option, args.weights)
    if args.memory_steps < 2:
        raise UsageError("--memory-steps must be at least 2")
    if not args.brain_timeout > 0:
        raise UsageError(f"--brain-timeout must be positive, got {args.brain_timeout}")
    print(f"checking brain {args.brain!r} on rendered frames of simple ...", file=sys.stderr)
    _import_pybullet_quietly()
    results = []
    stage = ["make"]

    def progress(text: str) -> None:
        stage[0] = text
        print(f"  ... {text}", file=sys.stderr, flush=True)

    with _brain_stdout_captured() as report:
        try:
            for result in iter_checks(
                args.brain,
                options=options,
                memory_steps=args.memory_steps,
                brain_timeout_s=args.brain_timeout,
                progress=progress,
            ):
                results.append(result)
                if not args.json:
                    report(result.line())
        except KeyboardInterrupt:
            print(
                f"{args.brain}: interrupted during {stage[0]}; {len(results)} check(s) done, above "
                f"({sum(r.status == 'fail' for r in results)} failed)",
                file=sys.stderr,
            )
            return EXIT_INTERRUPTED
    if args.json:
        print(json.dumps([dataclasses.asdict(result) for result in results], indent=2))
    failures = sum(result.status == "fail" for result in results)
    print(
        f"{args.brain}: " + (f"{failures} check(s) failed" if failures else "meets the brain contract"), file=sys.stderr
    )
    return 0 if passed(results) else 1


def _import_pybullet_quietly() -> None:
    """PyBullet's C code writes its build time to file descriptor 2 when first imported; the checker renders frames
    with it, so import it here, with fd 2 on /dev/null, and the report's stderr holds only our lines."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
            try:
                import pybullet  # noqa: F401
            except ImportError:  # no simulator installed: the checker says so itself
                pass
    finally:
        os.dup2(saved, 2)
        os.close(saved)


BRAIN_OUTPUT_SHOWN = 5  # lines of what the brain printed, shown on stderr after the report


@contextlib.contextmanager
def _brain_stdout_captured() -> Iterator[Callable[[str], None]]:
    """Point file descriptor 1 (Python's prints and C libraries' writes alike) at a temporary file while the brain
    runs; yield a function that writes a report line to the real stdout. Afterwards, say on stderr what the brain
    printed, marked as its own."""
    sys.stdout.flush()
    real = os.dup(1)
    with tempfile.TemporaryFile() as captured:
        os.dup2(captured.fileno(), 1)

        def report(line: str) -> None:
            os.write(real, (line + "\n").encode())

        try:
            yield report
        finally:
            sys.stdout.flush()
            os.dup2(real, 1)
            os.close(real)
            captured.seek(0)
            lines = captured.read().decode(errors="replace").splitlines()
        if lines:
            print(
                f"the brain printed {len(lines)} line(s) to stdout (not part of the report); the last:", file=sys.stderr
            )
            for line in lines[-BRAIN_OUTPUT_SHOWN:]:
                print(f"  brain| {line}", file=sys.stderr)


def _schema(folder: Path) -> int:
    from protocol.schema import write_schemas

    for path in write_schemas(folder):
        print(path)
    return 0
