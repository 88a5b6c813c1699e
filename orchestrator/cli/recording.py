"""``drivebench recorder ...``, ``drivebench replay`` and ``drivebench dataset ...``: recordings from the command line.

drivebench recorder info FILE.mcap          what a recording holds (channels, counts, episodes)
drivebench recorder repair FILE [-o OUT]    recover a recording left by a killed recorder
drivebench recorder merge A B -o AB.mcap    compare runs: each under its own namespace (recorder.merge)
drivebench recorder export FILE --ros2 -o DIR  a rosbag2 folder of standard ROS 2 messages (recorder.ros2bag)
drivebench replay FILE.mcap [--rate R | --max-speed] [--run-id NEW] [--keys GLOB] [--router EP]
drivebench dataset build RECORDINGS... -o DIR [--size 100x50] [--crop 0.5:1] [--history 3 --stride 1] ...
drivebench dataset collect --circuits simple,many_curves --laps 1 -o DIR [build options]
"""

from __future__ import annotations

import argparse
import dataclasses
import fnmatch
import functools
import json
import sys
from collections.abc import Callable
from pathlib import Path

from orchestrator.cli.errors import EXIT_OK, UsageError
from orchestrator.cli.run import add_scene_options
from protocol import environment
from protocol.bus import ROUTER_ENV, Bus, BusConfig
from recorder.dataset.build import DatasetError
from recorder.reading import RecordingError, recording_info


def add(commands: argparse._SubParsersAction) -> None:
    """``recorder info|repair``, ``replay`` and ``dataset build|collect``."""
    _add_recording_commands(commands)
    _add_dataset_commands(commands)


def _usage_errors(command: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """``command`` with a bad recording, dataset or value turned into a usage error (one line, exit 2)."""

    @functools.wraps(command)
    def run(args: argparse.Namespace) -> int:
        try:
            return command(args)
        except (RecordingError, DatasetError, ValueError) as error:  # ValueError: CollectError
            raise UsageError(str(error)) from None

    return run


def _add_recording_commands(commands: argparse._SubParsersAction) -> None:
    recorder = commands.add_parser("recorder", help="inspect and repair MCAP recordings")
    recorder_commands = recorder.add_subparsers(dest="recorder_command", required=True)
    info = recorder_commands.add_parser("info", help="channels, message counts, episodes of a recording")
    info.add_argument("file", type=Path)
    info.add_argument(
        "--json", action="store_true", help="one JSON object on stdout: messages, duration, channels, metadata"
    )
    info.set_defaults(func=_usage_errors(_info))
    repair = recorder_commands.add_parser("repair", help="recover everything readable from a killed recorder's file")
    repair.add_argument("file", type=Path, help="a .mcap.part file, or a truncated .mcap")
    repair.add_argument(
        "-o", "--output", type=Path, help="output file (default: x.mcap.part -> x.mcap, x.mcap -> x.repaired.mcap)"
    )
    repair.add_argument("--overwrite", action="store_true", help="replace the output file if it exists")
    repair.set_defaults(func=_usage_errors(_repair))
    merge = recorder_commands.add_parser(
        "merge", help="several recordings in one file, each run under its own namespace (compare runs in Foxglove)"
    )
    merge.add_argument("files", nargs="+", type=Path, metavar="FILE.mcap")
    merge.add_argument("-o", "--output", type=Path, required=True, help="the merged .mcap to write")
    merge.add_argument("--names", help="namespaces, comma-separated, one per file (default runA,runB,...)")
    merge.add_argument("--overwrite", action="store_true", help="replace the output file if it exists")
    merge.set_defaults(func=_usage_errors(_merge))
    _add_export_command(recorder_commands)

    replay = commands.add_parser("replay", help="publish a recording back onto the bus")
    replay.add_argument("file", type=Path)
    pace = replay.add_mutually_exclusive_group()
    pace.add_argument("--rate", type=float, default=1.0, help="playback speed (default 1.0 = recorded pace)")
    pace.add_argument("--max-speed", action="store_true", help="as fast as the bus takes it")
    replay.add_argument("--run-id", help="publish under this run id instead of the recorded one")
    replay.add_argument("--keys", help="only keys matching this glob, e.g. '*/sim/*'")
    replay.add_argument("--router", help=f"router endpoint (default: ${ROUTER_ENV})")
    replay.set_defaults(func=_usage_errors(_replay))


def _add_export_command(recorder_commands: argparse._SubParsersAction) -> None:
    export = recorder_commands.add_parser(
        "export", help="write a recording in another tool's format: --ros2, a rosbag2 folder (ros2 bag play, RViz)"
    )
    export.add_argument("file", type=Path, metavar="FILE.mcap")
    target = export.add_mutually_exclusive_group(required=True)
    target.add_argument(
        "--ros2",
        action="store_true",
        help="a rosbag2 folder (metadata.yaml and MCAP, ros2msg schemas, CDR): sensor_msgs/Image, "
        "geometry_msgs/Twist, nav_msgs/Odometry, tf2_msgs/TFMessage, rosgraph_msgs/Clock, events as std_msgs/String",
    )
    export.add_argument("-o", "--output", type=Path, required=True, help="the bag folder to write")
    export.add_argument("--overwrite", action="store_true", help="replace the bag in the output folder if it exists")
    export.set_defaults(func=_usage_errors(_export))


def _add_dataset_commands(commands: argparse._SubParsersAction) -> None:
    dataset = commands.add_parser("dataset", help="training datasets from recordings")
    dataset_commands = dataset.add_subparsers(dest="dataset_command", required=True)
    build = dataset_commands.add_parser("build", help="pair recorded frames with the commands that answered them")
    build.add_argument("recordings", nargs="+", type=Path, help="MCAP recordings (drivebench run --record)")
    _add_build_options(build)
    build.set_defaults(func=_usage_errors(_build))
    collect = dataset_commands.add_parser(
        "collect", help="drive the explicit brain on each circuit with recording on, then build the dataset"
    )
    collect.add_argument("--circuits", required=True, help="comma-separated circuit names")
    collect.add_argument(
        "--direction",
        choices=("forward", "reverse", "both"),
        default="forward",
        help="drive each circuit forward (its own direction: clockwise for the built-ins), reverse, "
        "or both, one episode each (default: forward)",
    )
    collect.add_argument("--laps", type=int, default=1, help="laps per circuit (default 1)")
    collect.add_argument("--brain", default="explicit", help="the brain whose driving is recorded (default explicit)")
    add_scene_options(collect, renderer_default="$DRIVEBENCH_RENDERER, else auto")
    collect.add_argument(
        "--randomise",
        action="store_true",
        help="domain randomisation: each episode draws its own line, road, walls, lighting, camera "
        "mount and camera noise from its seed (use with a brain that does not look, e.g. "
        "--brain expert, which drives on ground truth); --variation pins what it names, e.g. "
        "line=none,walls=off, and the rest is still drawn",
    )
    collect.add_argument(
        "--looks",
        type=_looks,
        metavar="LOOK,LOOK",
        help="with --randomise: the looks each episode draws from, e.g. flat,gazebo (default flat; gazebo needs "
        "the gl renderer)",
    )
    collect.add_argument("--max-sim-seconds", type=float, default=600.0, help="limit per circuit (default 600)")
    collect.add_argument(
        "--recovery-noise",
        type=float,
        default=0.0,
        metavar="RADPS",
        help="drive with bursts of extra yaw rate up to RADPS (the noisy brain) while --brain, "
        "undisturbed, labels every frame: recovery data (DART); default 0 = off",
    )
    _add_build_options(collect)
    collect.set_defaults(func=_usage_errors(_collect))


def _looks(text: str) -> tuple[str, ...]:
    from protocol.episode_spec import LOOKS

    looks = tuple(dict.fromkeys(item.strip() for item in text.split(",") if item.strip()))
    unknown = [look for look in looks if look not in LOOKS]
    if not looks or unknown:
        raise argparse.ArgumentTypeError(f"unknown look {', '.join(unknown) or text!r} (looks: {', '.join(LOOKS)})")
    return looks


def _add_build_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-o", "--output", type=Path, required=True, help="dataset folder to create")
    parser.add_argument(
        "--size",
        default="100x50",
        metavar="WxH",
        help="image size of the samples (default 100x50; PilotNet uses 200x66)",
    )
    parser.add_argument(
        "--crop",
        default="0:1",
        metavar="TOP:BOTTOM",
        help="rows kept before resizing, as fractions of the height (default 0:1; DeepestLSTMTinyPilotNet uses 0.5:1)",
    )
    history = parser.add_mutually_exclusive_group()
    history.add_argument(
        "--history", type=int, default=1, help="frames per sample: the current one and N-1 earlier ones (default 1)"
    )
    history.add_argument(
        "--offsets",
        help="explicit frame offsets, e.g. --offsets=-9,-5,0 (the paper's memory "
        "models; write the = because the value starts with -)",
    )
    parser.add_argument(
        "--stride", type=int, help="frames between the frames of --history (default 1; --offsets says it itself)"
    )
    parser.add_argument(
        "--camera-key",
        choices=("perturbed", "truth"),
        default="perturbed",
        help="pair the frames the brain saw (default) or the simulator's ground truth",
    )
    parser.add_argument("--label-brain", help="label with this brain's commands (default: the active brain)")
    parser.add_argument(
        "--split",
        default="episode:0.2",
        help="episode:FRACTION, circuit:NAME,NAME or none (default episode:0.2); never by frame",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the episode split (default 0)")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder")


def dataset_options(args: argparse.Namespace):
    from recorder.dataset.build import DatasetOptions

    width, sep, height = args.size.lower().partition("x")
    top, colon, bottom = args.crop.partition(":")
    try:
        size = (int(width), int(height)) if sep else None
        crop = (float(top), float(bottom)) if colon else None
    except ValueError:
        size = crop = None
    if size is None:
        raise UsageError(f"--size must look like 100x50, got {args.size!r}")
    if crop is None:
        raise UsageError(f"--crop must look like 0.5:1, got {args.crop!r}")
    if args.seed < 0:
        raise UsageError(f"--seed must be >= 0, got {args.seed}")
    return DatasetOptions(
        width_px=size[0],
        height_px=size[1],
        crop_top_fraction=crop[0],
        crop_bottom_fraction=crop[1],
        camera=args.camera_key,
        brain=args.label_brain,
        offsets_frames=_offsets(args),
        split=args.split,
        seed=args.seed,
    )


def _offsets(args: argparse.Namespace) -> tuple[int, ...]:
    """--offsets, or --history frames --stride apart."""
    if args.offsets and args.stride is not None:  # argparse would otherwise drop it without a word
        raise UsageError(f"--stride {args.stride} applies to --history; with --offsets put the spacing in the offsets")
    stride = 1 if args.stride is None else args.stride
    if args.history < 1 or stride < 1:
        raise UsageError(f"--history and --stride must be >= 1, got {args.history} and {stride}")
    if not args.offsets:
        return tuple(-k * stride for k in range(args.history - 1, -1, -1))
    try:
        return tuple(int(v) for v in args.offsets.split(","))
    except ValueError:
        raise UsageError(f"--offsets must be comma-separated integers ending in 0, got {args.offsets!r}") from None


def _build(args: argparse.Namespace) -> int:
    from orchestrator.collect import build_from_recordings

    return build_from_recordings(
        args.recordings, output=args.output, options=dataset_options(args), overwrite=args.overwrite
    )


def _collect(args: argparse.Namespace) -> int:
    from orchestrator.collect import collect

    return collect(args, dataset_options(args))


def _merge(args: argparse.Namespace) -> int:
    """Raises MergeError (a RecordingError: a usage error here) on a mistake."""
    from recorder.merge import merge

    names = [n.strip() for n in args.names.split(",")] if args.names else None
    report = merge(args.files, output=args.output, names=names, overwrite=args.overwrite)
    runs = ", ".join(f"/{ns} <- {source}" for ns, source in report.namespaces.items())
    print(
        f"merged {report.messages} messages -> {report.output} ({runs}); open it in Foxglove with "
        f"docs/foxglove/drivebench-compare-layout.json",
        file=sys.stderr,
    )
    return EXIT_OK


def _export(args: argparse.Namespace) -> int:
    """Raises RecordingError (a usage error here) for a bad recording or an output that holds a bag."""
    from recorder.ros2bag import export_ros2

    report = export_ros2(args.file, output=args.output, overwrite=args.overwrite)
    print(
        f"exported {report.messages} ROS 2 messages on {len(report.counts)} topics -> {report.folder} "
        f"(ros2 bag info {report.folder})",
        file=sys.stderr,
    )
    return EXIT_OK


def _info(args: argparse.Namespace) -> int:
    info = recording_info(args.file)
    if args.json:
        print(
            json.dumps(
                {
                    "path": str(info.path),
                    "messages": info.messages,
                    "duration_s": info.duration_s,
                    "channels": [dataclasses.asdict(channel) for channel in info.channels],
                    "metadata": info.metadata,
                },
                indent=2,
            )
        )
        return EXIT_OK
    print(f"{info.path}: {info.messages} messages over {info.duration_s:.1f} s of recording time")
    width = max((len(c.topic) for c in info.channels), default=10)
    for channel in sorted(info.channels, key=lambda c: c.topic):
        kind = "bus  " if channel.bus_key else "view " if channel.view else "other"  # other: not drivebench's
        key = f"  <- {channel.key}" if channel.key and channel.key != channel.topic else ""  # stable topics
        print(
            f"  {kind} {channel.topic:<{width}}  {channel.messages:>7}  "
            f"{channel.schema} ({channel.message_encoding}){key}"
        )
    for name, data in info.metadata.items():
        # A merged file (recorder merge) keeps each run's metadata under its namespace: "runA/episode:0".
        namespace, _, base = name.rpartition("/")
        run = f"/{namespace} " if namespace else ""
        missing = json.loads(data.get("missing", "{}")) if base == "drivebench.recording" else {}
        if any(missing.values()):
            print(f"  WARNING: {run}messages that never reached the recorder (sequence gaps): {missing}")
        if base.startswith("episode:"):
            spec = json.loads(data.get("spec", "{}"))
            print(
                f"  {run}{base}: run {data.get('run_id')}, circuit {spec.get('circuit')}, "
                f"brain {spec.get('active_brain')}, seed {spec.get('seed')}"
            )
    return EXIT_OK


def _repair(args: argparse.Namespace) -> int:
    from recorder.repair import repair

    report = repair(args.file, output=args.output, overwrite=args.overwrite)
    tail = f"; stopped at a damaged or torn record ({report.stopped_at})" if report.stopped_at else ""
    print(f"recovered {report.messages} messages -> {report.output}{tail}", file=sys.stderr)
    return EXIT_OK


def _replay(args: argparse.Namespace) -> int:
    from recorder.replay import replay

    router = args.router or environment.ROUTER.value()
    if not router:
        raise UsageError(f"replay needs a router to publish to: --router tcp/HOST:7447 or ${ROUTER_ENV}")
    if not args.max_speed and not args.rate > 0:
        raise UsageError(f"--rate must be > 0, got {args.rate}")
    _check_one_run(args)  # a bad file fails here, before a bus session is opened
    # No shared memory: a large put through it lives in a buffer of this process, which a subscriber still behind
    # (a recorder on a loaded machine) could no longer map once the replay exited: its last camera frames were lost.
    # Without it the bytes travel in the transport, which the session's close flushes onto the wire.
    with Bus(BusConfig(connect=[router], shared_memory=False), name="replay") as bus:
        report = replay(
            args.file,
            bus,
            rate=None if args.max_speed else args.rate,
            run_id=args.run_id,
            keys_glob=args.keys,
            progress=sys.stderr.isatty(),
        )
    print(
        f"replayed {report.messages} messages on {len(report.counts)} keys "
        f"({report.span_s:.1f} s of recording in {report.wall_s:.1f} s)",
        file=sys.stderr,
    )
    return EXIT_OK


def _check_one_run(args: argparse.Namespace) -> None:
    """--run-id on a file of several runs (a merged file) would fold their episodes into one run: refused."""
    info = recording_info(args.file)
    runs = sorted(
        {
            c.run_id
            for c in info.channels
            if c.bus_key and c.run_id and (args.keys is None or fnmatch.fnmatchcase(c.key, args.keys))
        }
    )
    if args.run_id is not None and len(runs) > 1:
        raise UsageError(
            f"{args.file} holds {len(runs)} runs ({', '.join(runs)}): --run-id {args.run_id} would fold them into "
            f"one; replay one at a time, e.g. --keys 'drivebench/run/{runs[0]}/*'"
        )
