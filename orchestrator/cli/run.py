"""``drivebench run``: one episode.

    drivebench run [--circuit simple] [--brain explicit] [--laps 1] [--camera 320x240] [--record F.mcap] [--json] ...
    drivebench run --attach [--router EP]

``run`` starts a local stack (embedded router, simulator, brain, scorer: one process each), drives one episode,
prints its metrics (or one JSON object with ``--json``) and leaves a run folder with the resolved config, the score
and every process's log. Exit code 0 when the episode ran, whatever the brain did; 2 for a usage mistake; 1 when
the stack could not run, with a one-line reason on stderr.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import logging
import sys
import time
import uuid
from pathlib import Path

import msgspec

from brains.registry import UnknownBrainError, bus_name, is_behavior_metrics_brain, require_brain, resolve
from circuits import CircuitError, load_circuit
from orchestrator.cli.errors import EXIT_OK, UsageError, require_file
from orchestrator.report.episode import episode_words, metrics_table
from orchestrator.stack import run_folder
from orchestrator.stack.attached import AttachedRun, only_running_run, wait_for_router
from orchestrator.stack.launcher import BrainLaunch, preflight_launches
from orchestrator.stack.local_run import LocalRun
from orchestrator.stack.progress import EpisodeProgress
from orchestrator.stack.sandbox import (
    LIMIT_KEYS,
    Sandbox,
    SandboxUnavailable,
    limits_in_force,
    parse_limits,
    require_bubblewrap,
)
from protocol import codec, environment
from protocol.episode_spec import RENDERERS, CameraSpec, EpisodeSpec, FieldError
from protocol.messages import EpisodeScore
from protocol.variations import apply_variation, check_look, noise_stage
from services.simulator.renderers import choose_renderer


def parse_camera(text: str) -> tuple[int, int]:
    width, sep, height = text.lower().partition("x")
    if not sep or not width.isdigit() or not height.isdigit():
        raise argparse.ArgumentTypeError(f"camera size must look like 320x240, got {text!r}")
    return int(width), int(height)


def add_scene_options(
    parser: argparse._ActionsContainer,
    *,
    renderer_default: str,
    camera: bool = True,
    variation: bool = True,
    camera_default: str = "320x240; Behavior Metrics uses 640x480",
) -> None:
    """``--camera``, ``--renderer`` and ``--variation`` with one help text for every command that takes them (run,
    dataset collect, matrix), so they cannot drift apart; only the default, which differs by command, is stated per
    command (``renderer_default``). ``camera``/``variation``: False where the command takes them from a file."""
    if camera:
        parser.add_argument(
            "--camera",
            type=parse_camera,
            default=(320, 240),
            metavar="WxH",
            help=f"simulator camera resolution in pixels (default: {camera_default})",
        )
    parser.add_argument(
        "--renderer",
        choices=RENDERERS,
        help="camera renderer: pybullet (TinyRenderer, the reference), gl (OpenGL on headless EGL, same scene, "
        f"~10x faster) or auto (gl where EGL works, else pybullet); default: {renderer_default} "
        "(look=gazebo: auto)",
    )
    if variation:
        parser.add_argument(
            "--variation",
            action="append",
            default=[],
            metavar="KEY=VALUE,...",
            help="world and camera variation, applied in order (repeatable), e.g. line=white,road=white,walls=off,"
            "lighting=no_sun,camera=left (presets: left, right, rotate_down, rotate_up), camera_yaw_rad=0.1, "
            "direction=reverse, start_m=120 or look=gazebo (textured, shaded, shadowed, as Behavior Metrics' Gazebo "
            "worlds; gl renderer only, and run's default renderer becomes auto)",
        )


RUN_EXAMPLES = """examples:
  drivebench run                                              the explicit brain, one lap of simple
  drivebench run --circuit montmelo --camera 640x480 --laps 2
  drivebench run --start-m 150 --direction reverse            one lap of simple from 150 m along, driven in reverse
  drivebench run --brain my_module:MyBrain --brain-option speed_mps=4
  drivebench run --brain deepest_lstm_tiny_pilotnet --variation line=white --noise salt_pepper=0.2
  drivebench run --record runs/simple.mcap --json              record everything; the score as JSON on stdout
  drivebench run --config runs/20261202-101500-ab12cd34/config.yaml    run a run again, as it was
  drivebench run --attach --router tcp/10.0.0.5:7447           drive on a stack that is already running

exit codes: 0 the episode ran (whatever the brain did), 1 the stack could not run, 2 a usage mistake
"""


def add(commands: argparse._SubParsersAction) -> None:
    run = commands.add_parser(
        "run",
        help="drive one episode on a local stack and print its metrics",
        description="Drive one episode on a local stack (every component its own process) and print its metrics.\n"
        "The run folder keeps the resolved config, the score and every process's log.",
        epilog=RUN_EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    world = run.add_argument_group("world", "the circuit, what the world looks like and what the brain's camera sees")
    world.add_argument("--circuit", default="simple", help="circuit name (default: simple; drivebench circuits list)")
    world.add_argument(
        "--direction",
        choices=("forward", "reverse"),
        default="forward",
        help="forward: the circuit's own direction (clockwise for the built-ins); reverse: the other "
        "way round (default: forward; or --variation direction=reverse, not both with other values)",
    )
    world.add_argument(
        "--start-m",
        type=float,
        default=0.0,
        metavar="METRES",
        help="start the car this far along the circuit from its start line, in the driving direction, on the "
        "centre line facing along it; progress, laps and lap times count from there (default: 0, the start line; "
        "below the circuit's length, drivebench circuits list; or --variation start_m=120, not both with other values)",
    )
    add_scene_options(
        world,
        renderer_default="$DRIVEBENCH_RENDERER, else pybullet",
        camera_default="320x240; 640x480, Behavior Metrics' camera, for a Behavior Metrics brain file",
    )
    run.set_defaults(camera=None)  # None: camera_of chooses, by the brain
    _add_noise_option(world)
    brain = run.add_argument_group("brain", "who drives, and who watches")
    _add_brain_options(brain)
    episode = run.add_argument_group("episode", "limits, seed and pacing")
    _add_episode_options(episode)
    record_given(action for group in (world, brain, episode) for action in group._group_actions)
    output = run.add_argument_group("output", "the run folder, what is printed and recorded")
    _add_run_folder_options(output)
    _add_output_options(output)
    _add_ros2_options(run.add_argument_group("ROS 2", "the run on rmw_zenoh's keys (docs/guides/ros2.md)"))
    _add_attach_options(run.add_argument_group("attach", "drive on a stack that is already running"))
    run.set_defaults(func=command_run)


class _Given:
    """An action that also notes the option as typed in ``args.config_replaced``: ``--config`` replaces these, and
    one typed with its default's value (``--seed 0``) would be ignored as silently as another."""

    def __call__(self, parser, namespace, values, option_string=None):
        namespace.config_replaced = [*getattr(namespace, "config_replaced", []), option_string]
        super().__call__(parser, namespace, values, option_string)


def record_given(actions) -> None:
    """Make each of ``actions`` (but ``--config``'s) note itself when typed (:class:`_Given`)."""
    for action in actions:
        if action.dest != "config":
            action.__class__ = type(f"Given{type(action).__name__}", (_Given, type(action)), {})


def refuse_replaced_options(args: argparse.Namespace) -> None:
    """``--config`` drives the file's episode and brains as they are: an option it replaces is refused, not
    dropped (``--seed 5`` beside it once drove seed 0 without a word)."""
    typed = list(dict.fromkeys(getattr(args, "config_replaced", [])))
    if args.config is not None and typed:
        raise UsageError(
            f"--config {args.config} runs the file as it is: {', '.join(typed)} would be ignored; edit the file "
            "(its episode and brains), or run without --config"
        )


def _add_brain_options(run: argparse._ActionsContainer) -> None:
    """The driving brain, its weights and options, and shadow brains."""
    run.add_argument(
        "--brain",
        help="brain to drive (default: explicit; with --attach: the bus name of a running "
        "brain, by default the only one alive)",
    )
    run.add_argument(
        "--weights",
        type=Path,
        metavar="CKPT",
        help="checkpoint (or exported .onnx) of a neural brain (drivebench train makes them)",
    )
    run.add_argument(
        "--brain-option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="brain constructor option, e.g. --brain-option speed_mps=2 (repeatable)",
    )
    run.add_argument(
        "--shadow",
        action="append",
        default=[],
        metavar="BRAIN[=CKPT]",
        help="a shadow brain: sees the same frames, drives nothing; the score says how far its commands "
        "were from the driver's (repeatable; bus name BRAIN, or BRAIN-shadowN when taken)",
    )
    run.add_argument(
        "--sandbox",
        action="store_true",
        help="run every brain host inside bubblewrap, as a challenge server does: no network but the bus over a "
        "Unix socket, a read-only file system but its scratch (RUN_FOLDER/scratch/NAME), resource limits "
        "(docs/guides/sandbox.md); needs bubblewrap",
    )
    run.add_argument(
        "--sandbox-limit",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="with --sandbox: one of its limits, e.g. memory_bytes=268435456 "
        f"(repeatable; keys: {', '.join(LIMIT_KEYS)})",
    )


def _add_episode_options(run: argparse._ActionsContainer) -> None:
    """What the episode is: limits, seed, pacing; or all of it from a run folder's config.yaml."""
    run.add_argument(
        "--config",
        type=Path,
        metavar="RUN/config.yaml",
        help="run the episode and brains of an earlier run again, exactly (its config.yaml); the options of the "
        "world, brain and episode groups are refused beside it (edit the file instead)",
    )
    run.add_argument("--laps", type=int, default=1, help="lap target (default: 1)")
    run.add_argument("--max-sim-seconds", type=float, default=300.0, help="simulated-time limit (default: 300)")
    run.add_argument("--seed", type=int, default=0, help="seed of every random generator (default: 0)")
    run.add_argument(
        "--realtime",
        action="store_true",
        help="free-running at wall-clock rate with the latest command (default: lock-step)",
    )
    run.add_argument(
        "--brain-timeout",
        type=float,
        default=10.0,
        metavar="SECONDS",
        help="lock-step: wall seconds to wait for the brain's answer to a frame (default: 10)",
    )


def _add_noise_option(run: argparse._ActionsContainer) -> None:
    run.add_argument(
        "--noise",
        action="append",
        default=[],
        metavar="MODEL[=VALUE]",
        help="camera perturbation, applied in order (repeatable): salt_pepper=0.2, gaussian=10, "
        "blur=5, brightness=-0.3, occlusion:patches=2,size_fraction=0.3, jpeg=40, delay=2, "
        "drop=0.1",
    )


def _add_run_folder_options(run: argparse._ActionsContainer) -> None:
    """The run id and where the run folder goes."""
    run.add_argument(
        "--run-id",
        help="run id used in every key (default: random; with --attach: "
        "$DRIVEBENCH_RUN_ID, else the only run alive on the router)",
    )
    run.add_argument("--out", type=Path, help="run folder (default: RUNS_DIR/<time>-<run id>)")
    run.add_argument("--runs-dir", type=Path, default=Path("runs"), help="where run folders go (default: runs)")


def _add_attach_options(run: argparse._ActionsContainer) -> None:
    """Driving on a stack that is already running instead of starting one."""
    run.add_argument(
        "--attach",
        action="store_true",
        help="drive an episode on a stack that is already running (docker compose, other machines) "
        "instead of starting one: nothing is started or stopped",
    )
    run.add_argument(
        "--router",
        metavar="ENDPOINT",
        help="with --attach: the router of that stack, e.g. tcp/10.0.0.5:7447 (default: $DRIVEBENCH_ROUTER)",
    )
    run.add_argument(
        "--wait",
        type=float,
        default=120.0,
        metavar="SECONDS",
        help="with --attach: how long to wait for the stack's processes to be alive (default: 120)",
    )


def _add_ros2_options(run: argparse._ActionsContainer) -> None:
    """The ROS 2 bridge: its domain and topics."""
    run.add_argument(
        "--ros2",
        action="store_true",
        help="start a ROS 2 bridge: ROS 2 tools (RMW_IMPLEMENTATION=rmw_zenoh_cpp) on this run's router see its "
        "camera, odometry, clock and commands; --brain ros2 lets a ROS 2 node drive",
    )
    run.add_argument(
        "--ros-domain-id",
        type=int,
        metavar="N",
        help="ROS 2 domain of the bridge and of the ros2 brain (default: $ROS_DOMAIN_ID, else 0)",
    )
    run.add_argument(
        "--ros2-option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="ROS 2 bridge option, e.g. camera_topic=/front/image_raw, odom_topic, clock_topic, "
        "command_topic=/brain/{brain}/cmd_vel, node (repeatable)",
    )


def ros2_domain_id(args: argparse.Namespace) -> int:
    """The ROS 2 domain: ``--ros-domain-id``, else ``ROS_DOMAIN_ID``, else 0 (one line naming a bad value)."""
    from protocol.ros2.rmw_zenoh import check_domain_id, domain_id_from_env

    try:
        if args.ros_domain_id is not None:
            return check_domain_id(args.ros_domain_id, where=f"--ros-domain-id {args.ros_domain_id}")
        return domain_id_from_env()
    except ValueError as error:
        raise UsageError(str(error)) from None


def ros2_bridge_options(args: argparse.Namespace) -> tuple[str, ...] | None:
    """The ROS 2 bridge's config overrides (None: no bridge); ``--ros2-option`` without ``--ros2`` is refused."""
    if not args.ros2:
        if args.ros2_option:
            raise UsageError("--ros2-option needs --ros2 (it configures the ROS 2 bridge)")
        return None
    from protocol.deploy.config import ConfigError, load_config
    from services.ros2_bridge.service import Ros2BridgeConfig

    options = (f"domain_id={ros2_domain_id(args)}", *args.ros2_option)
    try:  # the bridge's own config check, now: a typo'd option is one line, not a bridge dead after start-up
        load_config(Ros2BridgeConfig, overrides=options)
    except (ConfigError, ValueError) as error:
        raise UsageError(f"--ros2-option: {error}") from None
    return options


def _add_output_options(run: argparse._ActionsContainer) -> None:
    """What the run prints and records."""
    run.add_argument("--json", action="store_true", help="print the final score as one JSON object on stdout")
    run.add_argument("--record", type=Path, metavar="FILE.mcap", help="record the whole run to this MCAP file")
    run.add_argument(
        "--record-images",
        choices=("raw", "jpeg"),
        default="raw",
        help="camera images in the recording: raw (lossless, default) or jpeg (~10x smaller)",
    )


@contextlib.contextmanager
def flag(text: str):
    """A mistake in one option's value as one line that starts with the option as the user typed it
    (``--camera 0x0: width_px must be within 8..4096, got 0``)."""
    try:
        yield
    except (ValueError, CircuitError, UnknownBrainError) as error:  # VariationError, the specs' own checks
        raise UsageError(f"{text}: {error}") from None


SPEC_FLAGS = {
    "laps": "laps",
    "max_sim_seconds": "max_sim_seconds",
    "brain_timeout_s": "brain_timeout",
    "start_m": "start_m",
}


@contextlib.contextmanager
def spec_flags(args: argparse.Namespace):
    """EpisodeSpec's own checks raise a FieldError that carries the field (``laps must be >= 1, got 0``): name the
    option that set it instead."""
    try:
        yield
    except ValueError as error:
        dest = SPEC_FLAGS.get(error.field) if isinstance(error, FieldError) else None
        where = f"--{dest.replace('_', '-')} {getattr(args, dest)}" if dest else "drivebench run"
        raise UsageError(f"{where}: {error}") from None


DEFAULT_CAMERA_WH = (320, 240)
BM_CAMERA_WH = (640, 480)  # Behavior Metrics' F1 camera: its brains crop fixed rows of a 480-row image


def camera_of(args: argparse.Namespace) -> tuple[int, int]:
    """``--camera``, else BM's 640x480 for a BM brain file, else 320x240. Which camera a BM brain file gets is said
    once, under the run's first line (``args.camera_note``): its fixed crops see another part of a smaller image and
    it drives differently (issue 40: explicit 367.7 m at 320x240 against 165.6 m at 640x480)."""
    bm = not getattr(args, "attach", False) and is_behavior_metrics_brain(args.brain)
    if args.camera is None:
        if bm:
            args.camera_note = (
                "drivebench run: camera 640x480, Behavior Metrics' F1 camera, for a Behavior Metrics brain file "
                "(--camera WxH to choose another)"
            )
            return BM_CAMERA_WH
        return DEFAULT_CAMERA_WH
    if bm and tuple(args.camera) != BM_CAMERA_WH:
        args.camera_note = (
            f"drivebench run: camera {args.camera[0]}x{args.camera[1]} (--camera) for a Behavior Metrics brain file: "
            "Behavior Metrics drives it at 640x480, and a brain that crops fixed rows drives differently"
        )
    return tuple(args.camera)


def refuse_disagreement(args: argparse.Namespace, spec: EpisodeSpec, *, variation: str) -> None:
    """A typed ``--start-m`` or ``--direction`` that ``variation`` overrode with another value: two answers to one
    question, refused (the variation used to win without a word)."""
    typed = getattr(args, "config_replaced", [])
    for option, typed_value, value in (
        ("--start-m", args.start_m, spec.start_m),
        ("--direction", args.direction, spec.direction),
    ):
        if option in typed and value != typed_value:
            shown = f"{typed_value:g}" if isinstance(typed_value, float) else typed_value
            raise UsageError(
                f"{option} {shown} and --variation {variation} disagree: say the {option.removeprefix('--')} once"
            )


def episode_spec(args: argparse.Namespace) -> EpisodeSpec:
    with flag(f"--circuit {args.circuit}"):
        load_circuit(args.circuit)
    width, height = camera_of(args)
    with flag(f"--camera {width}x{height}"):
        camera = CameraSpec(width_px=width, height_px=height)
    noise = []
    for item in args.noise:
        with flag(f"--noise {item}"):
            noise.append(noise_stage(item))
    with flag(f"--brain {args.brain}"):
        brain = args.brain if args.attach else bus_name(args.brain)
    with spec_flags(args):
        spec = EpisodeSpec(
            circuit=args.circuit,
            laps=args.laps,
            max_sim_seconds=args.max_sim_seconds,
            seed=args.seed,
            realtime=args.realtime,
            camera=camera,
            active_brain=brain,
            brain_timeout_s=args.brain_timeout,
            noise=noise,
            direction=args.direction,
            start_m=args.start_m,
        )
    for variation in args.variation:
        with flag(f"--variation {variation}"):
            spec = apply_variation(spec, variation)
        refuse_disagreement(args, spec, variation=variation)
    # After the variations: they may turn the circuit round or move the start.
    with flag(f"--start-m {args.start_m:g}" if spec.start_m == args.start_m else "--variation start_m"):
        load_circuit(spec.circuit, direction=spec.direction).check_start_m(spec.start_m)
    # Only gl draws the gazebo look: there the default is auto (gl where EGL works), not run's pybullet.
    fallback = "auto" if spec.world.look != "flat" else environment.RENDERER_BY_COMMAND["run"]
    try:
        spec = msgspec.structs.replace(
            spec,
            renderer=choose_renderer(args.renderer, fallback=fallback, local=not args.attach, look=spec.world.look),
        )
        check_look(spec)
    except ValueError as error:  # VariationError: a look this renderer cannot draw
        raise UsageError(str(error)) from None
    from services.noise.models import require_extras

    with flag("--noise"):
        require_extras(spec.noise)  # BM's perturbations without albumentations: one line now, not a dead injector
    return spec


def command_run(args: argparse.Namespace) -> int:
    if args.attach:
        return command_run_attached(args)
    if args.router is not None:
        raise UsageError("--router needs --attach (without it, drivebench run starts its own router)")
    refuse_replaced_options(args)
    ros2_options = ros2_bridge_options(args)  # a bad --ros2-option or domain: one line before anything starts
    spec, brains = run_from_config(args.config) if args.config else run_from_options(args)
    run_id = args.run_id or uuid.uuid4().hex[:8]
    run_dir = args.out or args.runs_dir / f"{time.strftime('%Y%m%d-%H%M%S')}-{run_id}"
    brains = sandboxed(brains, args, run_dir=run_dir)
    try:
        preflight_launches(brains)  # bad weights or options: one line now, not a dead brain after start-up
    except ValueError as error:
        raise UsageError(str(error)) from None
    run_dir.mkdir(parents=True, exist_ok=True)
    logging.basicConfig(
        filename=run_dir / "launcher.log", level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s"
    )
    run = LocalRun(
        run_id=run_id,
        run_dir=run_dir,
        spec=spec,
        brains=brains,
        record=args.record,
        record_images=args.record_images,
        ros2=ros2_options,
    )
    run.write_config()
    print(
        f"drivebench: run {run_id}: {episode_words(spec, brain=spec.active_brain)}, "
        f"camera {spec.camera.width_px}x{spec.camera.height_px} ({spec.renderer}), "
        f"{'real-time' if spec.realtime else 'lock-step'}; run folder {run_dir}",
        file=sys.stderr,
    )
    if note := getattr(args, "camera_note", ""):
        print(note, file=sys.stderr)
    if args.record is not None and args.record.suffix != ".mcap":
        raise UsageError(f"--record needs a .mcap file name, got {args.record}")
    progress = EpisodeProgress(spec.laps, enabled=sys.stderr.isatty())
    try:
        outcome = run.drive(on_live=progress.update, on_failure_record=print_record if args.json else None)
    finally:
        progress.close()
    if outcome.brain_died is not None:
        print(f"drivebench: brain_died: {outcome.brain_died}", file=sys.stderr)
    report(outcome.score, run_dir, as_json=args.json)
    if outcome.recording_failure is not None:
        print(f"drivebench: the recording is incomplete: {outcome.recording_failure}", file=sys.stderr)
    elif args.record is not None:
        print(f"recording: {args.record}", file=sys.stderr)
    return EXIT_OK


def sandboxed(brains: list[BrainLaunch], args: argparse.Namespace, *, run_dir: Path) -> list[BrainLaunch]:
    """``brains`` each in its own sandbox with ``--sandbox`` (its limits from ``--sandbox-limit``), else as they
    are. UsageError (one line) without bubblewrap, or for a bad limit."""
    if not args.sandbox:
        if args.sandbox_limit:
            raise UsageError("--sandbox-limit needs --sandbox")
        return brains
    try:
        require_bubblewrap()
    except SandboxUnavailable as error:
        raise UsageError(f"--sandbox: {error}") from None
    try:
        limits = parse_limits(args.sandbox_limit)
    except ValueError as error:
        raise UsageError(f"--sandbox-limit {error}") from None
    try:
        boxes = [
            dataclasses.replace(Sandbox.default(scratch_dir=run_dir / "scratch" / launch.bus_name), **limits)
            for launch in brains
        ]
    except ValueError as error:
        raise UsageError(f"--sandbox-limit: {error}") from None
    print(f"drivebench: sandbox limits: {limits_in_force(boxes[0])}", file=sys.stderr)
    return [dataclasses.replace(launch, sandbox=box) for launch, box in zip(brains, boxes, strict=True)]


def run_from_options(args: argparse.Namespace) -> tuple[EpisodeSpec, list[BrainLaunch]]:
    args.brain = args.brain or "explicit"
    with flag(f"--brain {args.brain}"):
        # A brain to sandbox is not imported out here: its module's code may be anything.
        (resolve if args.sandbox else require_brain)(args.brain)
    spec = episode_spec(args)
    options = tuple(args.brain_option)
    if args.weights is not None:
        require_file(args.weights, option="--weights")
        options += (f"weights={json.dumps(str(args.weights.resolve()))}",)
    if args.brain == "ros2" and not any(option.startswith("domain_id=") for option in options):
        options += (f"domain_id={ros2_domain_id(args)}",)  # the node joins the bridge's domain
    brains = [BrainLaunch(args.brain, options=options)]
    brains += shadow_launches(args.shadow, taken={bus_name(args.brain)})
    return spec, brains


def run_from_config(path: Path) -> tuple[EpisodeSpec, list[BrainLaunch]]:
    """The episode and brains of an earlier run (``--config RUN/config.yaml``), checked as the options would be:
    every mistake of the file at once, one line each with its line number."""
    require_file(path, option="--config")
    config = run_folder.read_run_config(path)
    return config.episode, [entry.launch() for entry in config.brains]


def print_record(record: dict) -> None:
    """``--json``: the failure's record on stdout (the one-line message still goes to stderr)."""
    print(json.dumps(record))


def command_run_attached(args: argparse.Namespace) -> int:
    """``drivebench run --attach``: one episode on a running stack (compose, several machines); nothing spawned."""
    if args.sandbox:
        raise UsageError("--sandbox starts its own stack: it cannot be used with --attach")
    for flag, given in (
        ("--weights", args.weights),
        ("--brain-option", args.brain_option),
        ("--shadow", args.shadow),
        ("--record", args.record),
        ("--ros2", args.ros2),
    ):
        if given:
            raise UsageError(
                f"{flag} cannot be used with --attach: the running stack's processes are already "
                f"configured (record with the compose profile 'record' or `python -m recorder`)"
            )
    router = args.router or environment.ROUTER.value()
    if not router:
        raise UsageError(f"no router to attach to: give --router ENDPOINT or set {environment.ROUTER.name}")
    wait_for_router(router, wait_s=args.wait)
    run_id = args.run_id or environment.RUN_ID.value() or only_running_run(args.router, wait_s=args.wait)
    run_dir = args.out or args.runs_dir / f"{time.strftime('%Y%m%d-%H%M%S')}-{run_id}"
    run_dir.mkdir(parents=True, exist_ok=True)
    logging.basicConfig(
        filename=run_dir / "driver.log", level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s"
    )
    with AttachedRun(
        run_id=run_id, run_dir=run_dir, router_endpoint=args.router, brain_name=args.brain, wait_s=args.wait
    ) as run:
        args.brain = run.brain_name
        spec = episode_spec(args)
        print(
            f"drivebench: attached to run {run_id} on {run.endpoint}: {spec.active_brain} on {spec.circuit}, "
            f"{spec.laps} lap(s); run folder {run_dir}",
            file=sys.stderr,
        )
        progress = EpisodeProgress(spec.laps, enabled=sys.stderr.isatty())
        try:
            score = run.drive(spec, on_live=progress.update, on_failure_record=print_record if args.json else None)
        finally:
            progress.close()
    report(score, run_dir, as_json=args.json)
    return EXIT_OK


def shadow_launches(shadows: list[str], *, taken: set[str]) -> list[BrainLaunch]:
    """``--shadow BRAIN[=CKPT]`` as brain launches; a name already taken becomes ``BRAIN-shadowN``."""
    launches = []
    taken = set(taken)
    for item in shadows:
        brain, _, weights = item.partition("=")
        try:
            require_brain(brain)
        except UnknownBrainError as error:
            raise UsageError(f"--shadow: {error}") from None
        options: tuple[str, ...] = ()
        if weights:
            if not Path(weights).is_file():
                raise UsageError(f"--shadow {brain}: no such weights file {weights}")
            options = (f"weights={json.dumps(str(Path(weights).resolve()))}",)
        base = bus_name(brain)
        name = (
            base
            if base not in taken
            else next(f"{base}-shadow{n}" for n in range(1, len(taken) + 2) if f"{base}-shadow{n}" not in taken)
        )
        taken.add(name)
        launches.append(BrainLaunch(brain, name=name, options=options, host=("shadow=true",)))
    return launches


def report(score: EpisodeScore, run_dir: Path, *, as_json: bool) -> None:
    if as_json:
        print(codec.to_json(score))
        return
    print(metrics_table(score))
    print(f"\nscore: {run_dir / 'score.json'}", file=sys.stderr)
