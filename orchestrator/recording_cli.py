"""``drivebench recorder ...``, ``drivebench replay`` and ``drivebench dataset ...``: recordings from the command line.

    drivebench recorder info FILE.mcap          what a recording holds (channels, counts, episodes)
    drivebench recorder repair FILE [-o OUT]    recover a recording left by a killed recorder
    drivebench replay FILE.mcap [--rate R | --max-speed] [--run-id NEW] [--keys GLOB] [--router EP]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from protocol.bus import ROUTER_ENV, Bus, BusConfig
from recorder.reading import RecordingError, recording_info


class RecordingUsageError(Exception):
    """A mistake on the command line (one line)."""


def add_commands(commands: argparse._SubParsersAction) -> None:
    recorder = commands.add_parser("recorder", help="inspect and repair MCAP recordings")
    recorder_commands = recorder.add_subparsers(dest="recorder_command", required=True)
    info = recorder_commands.add_parser("info", help="channels, message counts, episodes of a recording")
    info.add_argument("file", type=Path)
    repair = recorder_commands.add_parser("repair", help="recover everything readable from a killed recorder's file")
    repair.add_argument("file", type=Path, help="a .mcap.part file, or a truncated .mcap")
    repair.add_argument("-o", "--output", type=Path, help="output file (default: x.mcap.part -> x.mcap, "
                                                          "x.mcap -> x.repaired.mcap)")
    repair.add_argument("--overwrite", action="store_true", help="replace the output file if it exists")

    replay = commands.add_parser("replay", help="publish a recording back onto the bus")
    replay.add_argument("file", type=Path)
    pace = replay.add_mutually_exclusive_group()
    pace.add_argument("--rate", type=float, default=1.0, help="playback speed (default 1.0 = recorded pace)")
    pace.add_argument("--max-speed", action="store_true", help="as fast as the bus takes it")
    replay.add_argument("--run-id", help="publish under this run id instead of the recorded one")
    replay.add_argument("--keys", help="only keys matching this glob, e.g. '*/sim/*'")
    replay.add_argument("--router", help=f"router endpoint (default: ${ROUTER_ENV})")


def run_command(args: argparse.Namespace) -> int:
    try:
        if args.command == "recorder" and args.recorder_command == "info":
            return _info(args)
        if args.command == "recorder" and args.recorder_command == "repair":
            return _repair(args)
        if args.command == "replay":
            return _replay(args)
    except RecordingError as error:
        raise RecordingUsageError(str(error)) from None
    raise RecordingUsageError(f"unknown command {args.command!r}")


def _info(args: argparse.Namespace) -> int:
    info = recording_info(args.file)
    print(f"{info.path}: {info.messages} messages over {info.duration_s:.1f} s of recording time")
    width = max((len(c.topic) for c in info.channels), default=10)
    for channel in sorted(info.channels, key=lambda c: c.topic):
        kind = "bus " if channel.bus_key else "view"
        print(f"  {kind} {channel.topic:<{width}}  {channel.messages:>7}  {channel.schema} ({channel.message_encoding})")
    for name, data in info.metadata.items():
        if name.startswith("episode:"):
            spec = json.loads(data.get("spec", "{}"))
            print(f"  {name}: circuit {spec.get('circuit')}, brain {spec.get('active_brain')}, seed {spec.get('seed')}")
    return 0


def _repair(args: argparse.Namespace) -> int:
    from recorder.repair import repair

    report = repair(args.file, output=args.output, overwrite=args.overwrite)
    tail = f"; stopped at a damaged or torn record ({report.stopped_at})" if report.stopped_at else ""
    print(f"recovered {report.messages} messages -> {report.output}{tail}", file=sys.stderr)
    return 0


def _replay(args: argparse.Namespace) -> int:
    from recorder.replay import replay

    router = args.router or os.environ.get(ROUTER_ENV)
    if not router:
        raise RecordingUsageError(f"replay needs a router to publish to: --router tcp/HOST:7447 or ${ROUTER_ENV}")
    if not args.max_speed and not args.rate > 0:
        raise RecordingUsageError(f"--rate must be > 0, got {args.rate}")
    recording_info(args.file)  # a bad file fails here, before a bus session is opened
    with Bus(BusConfig(connect=[router]), name="replay") as bus:
        report = replay(args.file, bus, rate=None if args.max_speed else args.rate, run_id=args.run_id,
                        keys_glob=args.keys, progress=sys.stderr.isatty())
    print(f"replayed {report.messages} messages on {len(report.counts)} keys "
          f"({report.span_s:.1f} s of recording in {report.wall_s:.1f} s)", file=sys.stderr)
    return 0
