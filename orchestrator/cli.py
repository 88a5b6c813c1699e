"""The ``drivebench`` command.

    drivebench run [--circuit simple] [--brain explicit] [--laps 1] [--camera 320x240] [--json] ...

``run`` starts a local stack (embedded router, simulator, brain, scorer: one process each), drives one episode,
prints its metrics (or one JSON object with ``--json``) and leaves a run folder with the resolved config, the score
and every process's log. Exit code 0 when the episode ran, whatever the brain did; 2 for a usage mistake; 1 when
the stack could not run, with a one-line reason on stderr.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
import uuid
from pathlib import Path

import msgspec
import yaml

from brains.registry import brain_names
from orchestrator.launcher import BrainLaunch, LocalStack, StackError
from orchestrator.report import metrics_table
from protocol import codec
from protocol.bus import BusError
from protocol.runtime import exit_on_sigterm
from protocol.messages import CameraSpec, EpisodeScore, EpisodeSpec, LiveMetrics
from services.circuits import circuit_names

EXIT_OK, EXIT_STACK, EXIT_USAGE = 0, 1, 2


class UsageError(Exception):
    pass


def parse_camera(text: str) -> tuple[int, int]:
    width, sep, height = text.lower().partition("x")
    if not sep or not width.isdigit() or not height.isdigit():
        raise argparse.ArgumentTypeError(f"camera size must look like 320x240, got {text!r}")
    return int(width), int(height)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="drivebench", description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    run = commands.add_parser("run", help="drive one episode on a local stack and print its metrics")
    run.add_argument("--circuit", default="simple", help="circuit name (default: simple)")
    run.add_argument("--brain", default="explicit", help="brain to drive (default: explicit)")
    run.add_argument("--brain-option", action="append", default=[], metavar="KEY=VALUE",
                     help="brain constructor option, e.g. --brain-option speed_mps=2 (repeatable)")
    run.add_argument("--laps", type=int, default=1, help="lap target (default: 1)")
    run.add_argument("--max-sim-seconds", type=float, default=300.0, help="simulated-time limit (default: 300)")
    run.add_argument("--camera", type=parse_camera, default=(320, 240), metavar="WxH",
                     help="camera resolution (default: 320x240; Behavior Metrics uses 640x480)")
    run.add_argument("--seed", type=int, default=0, help="seed of every random generator (default: 0)")
    run.add_argument("--realtime", action="store_true",
                     help="free-running at wall-clock rate with the latest command (default: lock-step)")
    run.add_argument("--brain-timeout", type=float, default=10.0, metavar="SECONDS",
                     help="lock-step: wall seconds to wait for the brain's answer to a frame (default: 10)")
    run.add_argument("--run-id", help="run id used in every key (default: random)")
    run.add_argument("--out", type=Path, help="run folder (default: runs/<time>-<run id>)")
    run.add_argument("--json", action="store_true", help="print the final score as one JSON object on stdout")
    return parser


def episode_spec(args: argparse.Namespace) -> EpisodeSpec:
    if args.circuit not in circuit_names():
        raise UsageError(f"unknown circuit {args.circuit!r} (known: {', '.join(circuit_names())})")
    if args.brain not in brain_names():
        raise UsageError(f"unknown brain {args.brain!r} (known: {', '.join(brain_names())})")
    width, height = args.camera
    try:
        return EpisodeSpec(circuit=args.circuit, laps=args.laps, max_sim_seconds=args.max_sim_seconds, seed=args.seed,
                           realtime=args.realtime, camera=CameraSpec(width_px=width, height_px=height),
                           active_brain=args.brain, brain_timeout_s=args.brain_timeout)
    except ValueError as error:
        raise UsageError(str(error)) from None


class Progress:
    """Lap progress, sim time and real-time factor on stderr while an episode runs."""

    def __init__(self, laps: int, *, enabled: bool):
        from tqdm import tqdm

        self._bar = tqdm(total=100 * laps, unit="%", file=sys.stderr, disable=not enabled, dynamic_ncols=True,
                         bar_format="lap progress {percentage:3.0f}%|{bar}| {desc}")

    def update(self, live: LiveMetrics) -> None:
        self._bar.n = min(self._bar.total, round(100 * live.progress_laps, 1))
        self._bar.set_description_str(f"lap {min(live.completed_laps + 1, live.laps_target)}/{live.laps_target}  "
                                  f"sim {live.sim_time_s:6.1f} s  RTF {live.real_time_factor:4.1f}x  "
                                  f"|xte| {live.cross_track_m:4.2f} m", refresh=True)

    def close(self) -> None:
        self._bar.close()


def command_run(args: argparse.Namespace) -> int:
    spec = episode_spec(args)
    run_id = args.run_id or uuid.uuid4().hex[:8]
    run_dir = args.out or Path("runs") / f"{time.strftime('%Y%m%d-%H%M%S')}-{run_id}"
    run_dir.mkdir(parents=True, exist_ok=True)
    logging.basicConfig(filename=run_dir / "launcher.log", level=logging.INFO,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    brain = BrainLaunch(args.brain, options=tuple(args.brain_option))
    (run_dir / "config.yaml").write_text(yaml.safe_dump({
        "run_id": run_id, "episode": msgspec.to_builtins(spec),
        "brains": [{"brain": brain.brain, "name": brain.bus_name, "options": list(brain.options)}],
    }, sort_keys=False))
    print(f"drivebench: run {run_id}: {spec.active_brain} on {spec.circuit}, {spec.laps} lap(s), "
          f"camera {spec.camera.width_px}x{spec.camera.height_px}, "
          f"{'real-time' if spec.realtime else 'lock-step'}; run folder {run_dir}", file=sys.stderr)
    progress = Progress(spec.laps, enabled=sys.stderr.isatty())
    try:
        with LocalStack(run_id=run_id, run_dir=run_dir, brains=[brain]) as stack:
            score = stack.run_episode(spec, on_live=progress.update)
    finally:
        progress.close()
    (run_dir / "score.json").write_text(codec.to_json(score, indent=2) + "\n")
    report(score, run_dir, as_json=args.json)
    return EXIT_OK


def report(score: EpisodeScore, run_dir: Path, *, as_json: bool) -> None:
    if as_json:
        print(codec.to_json(score))
        return
    print(metrics_table(score))
    print(f"\nscore: {run_dir / 'score.json'}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    exit_on_sigterm()  # SIGTERM stops the stack as cleanly as Ctrl-C does
    try:
        if args.command == "run":
            return command_run(args)
    except UsageError as error:
        print(f"drivebench: error: {error}", file=sys.stderr)
        return EXIT_USAGE
    except (StackError, BusError) as error:
        print(f"drivebench: the stack could not run: {error}", file=sys.stderr)
        return EXIT_STACK
    except KeyboardInterrupt:
        print("drivebench: interrupted; every process stopped", file=sys.stderr)
        return 130
    except SystemExit as stop:
        if isinstance(stop.code, int) and stop.code > 128:  # our SIGTERM handler: the stack is already stopped
            print("drivebench: terminated; every process stopped", file=sys.stderr)
        raise
    return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
