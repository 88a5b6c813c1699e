"""``drivebench matrix FILE``: run a test matrix into a folder of results and a report; ``drivebench report DIR``
writes that report again from the folder (``orchestrator.report.matrix`` writes it).

    drivebench matrix experiments/generalization.yaml -o runs/gen --workers 2 [--record] [--resume] [--plan]

Exit codes: 0 every episode ran; 3 the matrix ran but the stack failed some episodes (listed in the report);
2 a usage mistake (bad matrix file: one line naming the line); 1 the stack could not run at all; 130 interrupted
(finished episodes are kept; ``--resume`` runs the rest).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from orchestrator.cli.errors import EXIT_INTERRUPTED, EXIT_OK, EXIT_SOME_FAILED, UsageError
from orchestrator.cli.ray import add_ray_options, ray_options_from
from orchestrator.cli.run import add_scene_options

if TYPE_CHECKING:
    from orchestrator.matrix.plan import PlannedEpisode
    from orchestrator.matrix.results import EpisodeResult
    from orchestrator.matrix.runner import MatrixProgress
    from protocol.messages import LiveMetrics

MATRIX_EXAMPLES = """examples:
  drivebench matrix experiments/smoke.yaml -o runs/smoke                  eight short episodes, then the report
  drivebench matrix experiments/generalization.yaml --plan --json         the planned episodes; nothing starts
  drivebench matrix study.yaml --plan --power runs/pilot                  what difference the study can detect
  drivebench matrix experiments/generalization.yaml --workers 2 -o runs/gen --record
  drivebench matrix experiments/generalization.yaml -o runs/gen --resume  after Ctrl-C, SIGKILL or a crash
  drivebench matrix experiments/generalization.yaml --ray auto -o runs/gen --artifacts /shared/gen
"""


def add(commands: argparse._SubParsersAction) -> None:
    matrix = commands.add_parser(
        "matrix",
        help="run a test matrix (brains x circuits x variations x perturbations x repetitions) and report",
        description="Run every episode of a matrix file, each on its own stack, results into DIR/results.sqlite "
        "as each episode ends, then write DIR/report.html and report.md.",
        epilog=MATRIX_EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    matrix.add_argument("file", type=Path, help="matrix file (YAML)")
    add_run_options(matrix, default_out="runs/matrix-<name>-<time>", default_workers=1)
    matrix.add_argument("--no-report", action="store_true", help="do not write the report at the end")
    matrix.add_argument(
        "--smoke",
        action="store_true",
        help="a seconds-long form: every brain, the first 2 conditions of every part, repetition 0, "
        "4 s of simulated time each on a 160x120 camera (Behavior Metrics brain files keep theirs: BM's brains crop "
        "fixed rows); brains that never moved are named (what CI runs)",
    )
    add_ray_options(matrix)
    matrix.set_defaults(func=run_matrix_command)
    _add_report(commands)


def add_run_options(parser: argparse.ArgumentParser, *, default_out: str, default_workers: int) -> None:
    """The options every command that runs a matrix file takes (drivebench matrix, drivebench paper)."""
    parser.add_argument("-o", "--out", type=Path, help=f"output folder (default: {default_out})")
    parser.add_argument(
        "--workers",
        type=int,
        default=default_workers,
        metavar="N",
        help=f"episodes run at the same time, each on its own stack (default: {default_workers}; about a core each)",
    )
    parser.add_argument("--record", action="store_true", help="record every episode to MCAP in its folder")
    parser.add_argument(
        "--fresh-stacks",
        action="store_true",
        help="start a new stack for every episode (default: each worker keeps its stack warm across episodes; "
        "see docs/warm-stacks.md)",
    )
    parser.add_argument(
        "--record-images",
        choices=("raw", "jpeg"),
        default="jpeg",
        help="camera images in recordings (default: jpeg, ~10x smaller than raw)",
    )
    parser.add_argument(
        "--resume",
        action="store_true",
        help="run only the episodes DIR's results do not hold yet (after a crash or Ctrl-C)",
    )
    parser.add_argument(
        "--retry-failed", action="store_true", help="with --resume: also run again the episodes the stack failed"
    )
    parser.add_argument("--plan", action="store_true", help="print the planned episodes and exit")
    parser.add_argument(
        "--json", action="store_true", help="with --plan: the planned episodes as one JSON array (index, key, spec)"
    )
    power = parser.add_argument_group("power before driving (with --plan; docs/statistics.md)")
    power.add_argument(
        "--power",
        type=Path,
        metavar="PILOT_DIR",
        help="with --plan: the difference in lap success rate this design (its training runs x conditions) detects "
        "with 80%% power, simulated from the run-to-run spread of a pilot's results folder",
    )
    power.add_argument(
        "--run-spread",
        type=float,
        metavar="SD",
        help="with --plan: the same from a given standard deviation of a run's success rate over training runs",
    )
    power.add_argument(
        "--runs",
        type=int,
        metavar="N",
        help="with --power or --run-spread: the training runs per brain the study will have (default: the runs its "
        "weights name now), to size a study before its seeds are trained",
    )
    power.add_argument(
        "--base-rate",
        type=float,
        default=0.5,
        metavar="P",
        help="with --run-spread: the success rate the difference is measured from (default 0.5)",
    )
    # camera and variations come from the matrix file; the renderer may be overridden for every episode
    add_scene_options(
        parser,
        renderer_default="the file's `renderer:`, else $DRIVEBENCH_RENDERER, else auto",
        camera=False,
        variation=False,
    )


def load_matrix_file(path: Path):
    """The parsed matrix file; its mistakes as a usage error (one line)."""
    from orchestrator.matrix.load import MatrixError, load_matrix

    try:
        return load_matrix(path)
    except MatrixError as error:
        raise UsageError(str(error)) from None


def run_matrix_command(args: argparse.Namespace) -> int:
    from orchestrator.matrix.load import smoke_form

    matrix = load_matrix_file(args.file)
    if args.smoke:
        matrix = smoke_form(matrix)
    return run_matrix_args(
        matrix,
        args,
        what="matrix",
        default_folder=f"matrix-{matrix.name}",
        command=f"drivebench matrix {args.file}" + (" --smoke" if args.smoke else ""),
        report=not args.no_report,
    )


def run_matrix_args(
    matrix,
    args: argparse.Namespace,
    *,
    what: str,
    default_folder: str,
    command: str,
    report: bool = True,
    facts: dict | None = None,
) -> int:
    """``--plan``, or run ``matrix`` as the options of :func:`add_run_options` say, with progress on stderr, then
    write its report (unless ``report`` is False); the exit code.

    what: the kind of run in messages ("matrix", "paper"); default_folder: ``runs/<default_folder>-<time>`` without
    ``-o``; command: the command line that ran it, less ``-o`` (printed with ``--resume`` after an interruption);
    facts: extra results-database facts (``drivebench paper`` marks its runs).
    """
    from orchestrator.matrix.executor import RunOptions
    from orchestrator.matrix.pipeline import MatrixRun, RunRefused
    from orchestrator.matrix.plan import plan_json, plan_table
    from orchestrator.matrix.runner import never_moved

    sizing = getattr(args, "power", None) is not None or getattr(args, "run_spread", None) is not None
    if sizing and not args.plan:
        raise UsageError("--power and --run-spread go with --plan (they size a study before it runs)")
    if getattr(args, "runs", None) is not None and not sizing:
        raise UsageError("--runs goes with --power or --run-spread (the runs a study's sizing assumes)")
    if args.plan:
        print(plan_json(matrix) if args.json else plan_table(matrix))
        if sizing:
            print(_power_of_design(matrix, args))
        return EXIT_OK
    if args.json:
        raise UsageError("--json goes with --plan (a matrix's results are in DIR/results.sqlite and episodes.csv)")
    _check_run_options(args, what=what)
    ray_options = _ray_options(args)
    out_dir = args.out or Path("runs") / f"{default_folder}-{time.strftime('%Y%m%d-%H%M%S')}"
    options = RunOptions(
        workers=args.workers,
        record=args.record,
        record_images=args.record_images,
        resume=args.resume,
        retry_failed=args.retry_failed,
        facts=dict(facts or {}),
        fresh_stacks=args.fresh_stacks,
    )
    run = MatrixRun(
        matrix,
        out_dir=out_dir,
        options=options,
        ray_options=ray_options,
        renderer=getattr(args, "renderer", None),
        notify=lambda line: print(f"drivebench: {line}", file=sys.stderr),
    )
    try:
        matrix = run.prepare()
    except RunRefused as error:
        raise UsageError(str(error)) from None
    logging.basicConfig(
        filename=out_dir / "matrix.log",
        level=logging.INFO,
        format="%(asctime)s %(threadName)s %(name)s %(levelname)s %(message)s",
    )
    where = f"{args.workers} worker(s)" if ray_options is None else f"Ray cluster {ray_options.address}"
    print(
        f"drivebench: {what} {matrix.name}: {len(matrix.episodes)} episode(s), {where}; output {out_dir}",
        file=sys.stderr,
    )
    progress = _run_to_the_end(run, out_dir=out_dir, command=command)
    if progress is None:
        return EXIT_INTERRUPTED
    print(summary_line(progress, out_dir), file=sys.stderr)
    if getattr(args, "smoke", False):
        for line in never_moved(progress):
            print(f"drivebench: smoke: {line}", file=sys.stderr)
    if report:
        _write_report(out_dir)
    return EXIT_SOME_FAILED if progress.failed else EXIT_OK


def _power_of_design(matrix, args: argparse.Namespace) -> str:
    """``--power`` / ``--run-spread``: what difference the matrix's design detects (lines for stdout)."""
    from collections import Counter

    from orchestrator.report.power import PowerError, power_curve, power_report, spread_given, spread_of_results

    if args.power is not None and args.run_spread is not None:
        raise UsageError("give --power PILOT_DIR or --run-spread SD, not both")
    runs_by_brain = Counter(brain.compared_as for brain in matrix.brains)
    runs = args.runs if args.runs is not None else min(runs_by_brain.values(), default=0)
    first = matrix.brains[0].label if matrix.brains else None
    conditions = sum(episode.brain.label == first for episode in matrix.episodes)
    try:
        if args.power is not None:
            spread = spread_of_results(args.power)
        else:
            spread = spread_given(run_spread=args.run_spread, base_rate=args.base_rate)
        curve = power_curve(spread, runs=runs, conditions=conditions)
    except PowerError as error:
        raise UsageError(f"{matrix.name}: {error}") from None
    return power_report(spread, runs=runs, conditions=conditions, curve=curve)


def _check_run_options(args: argparse.Namespace, *, what: str) -> None:
    """The options of :func:`add_run_options` that only make sense together, checked before anything runs."""
    if args.workers < 1:
        raise UsageError(f"--workers must be >= 1, got {args.workers}")
    if args.resume and args.out is None:
        raise UsageError(f"--resume needs -o DIR, the folder of the {what} run to resume")
    if args.retry_failed and not args.resume:
        raise UsageError("--retry-failed goes with --resume")


def _run_to_the_end(run, *, out_dir: Path, command: str):
    """``run.run()``'s progress, shown on stderr, or None after Ctrl-C (with the command that resumes it on stderr);
    a results database that does not fit is a usage error."""
    from orchestrator.matrix.results import ResultsError

    display = ProgressDisplay()
    try:
        return run.run(on_change=display.update)
    except ResultsError as error:
        raise UsageError(str(error)) from None
    except KeyboardInterrupt:
        display.close()
        print(
            f"drivebench: interrupted; finished episodes are in {out_dir / 'results.sqlite'}; "
            f"`{command} -o {out_dir} --resume` runs the rest",
            file=sys.stderr,
        )
        return None
    finally:
        display.close()


def _ray_options(args: argparse.Namespace):
    """``--ray`` and its companions (None: a local run), checked before anything starts."""
    from orchestrator.matrix.ray_options import import_ray

    try:
        ray_options = ray_options_from(args)
    except ValueError as error:
        raise UsageError(str(error)) from None
    if ray_options is not None:
        import_ray()  # without Ray installed: how to install it, in one line
    return ray_options


def _write_report(out_dir: Path) -> None:
    from orchestrator.report.matrix import write_report

    files = write_report(out_dir)
    print(f"report: {files.html} and {files.markdown}", file=sys.stderr)
    if files.paper is not None:
        print(f"paper tables: {files.paper}", file=sys.stderr)


# -- the progress on stderr --


class ProgressDisplay:
    """Progress on stderr: one line per finished episode, and on a terminal live bars: episodes done / running /
    failed with an ETA, and each worker's lap progress.

    The bars are made on the first update, when the number of episodes a resume skips is known (the ETA counts
    only the episodes run in this session).
    """

    def __init__(self, *, enabled: bool = True):
        self._enabled = enabled
        self._tty = sys.stderr.isatty()
        self._main: Any = None  # a tqdm bar, made at the first update
        self._lanes: list = []
        self._reported = 0

    def _make(self, progress: MatrixProgress) -> None:
        from tqdm import tqdm

        bars = self._enabled and self._tty
        self._main = tqdm(
            total=progress.total,
            initial=progress.skipped,
            unit="episode",
            file=sys.stderr,
            disable=not bars,
            dynamic_ncols=True,
            smoothing=0.0,
            desc="matrix",
        )
        self._lanes = [
            tqdm(
                total=100,
                file=sys.stderr,
                position=i + 1,
                leave=False,
                dynamic_ncols=True,
                disable=not bars,
                bar_format="  {desc} {percentage:3.0f}%|{bar}|",
            )
            for i in range(len(progress.workers))
        ]

    def update(self, progress: MatrixProgress) -> None:
        if self._main is None:
            self._make(progress)
        with progress.lock:
            finished = progress.skipped + progress.done + progress.failed
            new_results = progress.finished[self._reported :]
            self._reported = len(progress.finished)
            lanes = [(worker.episode, worker.live) for worker in progress.workers]
            counts = f"done {progress.done}, running {progress.running}, failed {progress.failed}" + (
                f", resumed past {progress.skipped}" if progress.skipped else ""
            )
        for number, result in enumerate(new_results, start=finished - len(new_results) + 1):
            if self._enabled:
                self._main.write(f"[{number}/{progress.total}] {_result_line(result)}", file=sys.stderr)
        self._main.update(finished - self._main.n)
        self._main.set_postfix_str(counts, refresh=False)
        self._main.refresh()
        for lane, (episode, live) in zip(self._lanes, lanes):
            lane.n = 0 if episode is None else self._lap_percent(live)
            lane.set_description_str("idle" if episode is None else self._lane_text(episode, live), refresh=False)
            lane.refresh()

    @staticmethod
    def _lap_percent(live: LiveMetrics | None) -> int:
        if live is None:
            return 0
        return min(100, round(100 * live.progress_laps / max(1, live.laps_target)))

    @staticmethod
    def _lane_text(episode: PlannedEpisode, live: LiveMetrics | None) -> str:
        status = f"sim {live.sim_time_s:5.1f} s" if live is not None else "starting"
        return f"{episode.key[:60]:<60} {status}"

    def close(self) -> None:
        for lane in self._lanes:
            lane.close()
        if self._main is not None:
            self._main.close()


def _result_line(result: EpisodeResult) -> str:
    """``explicit/simple/default/none/r0: laps_completed, BM lap 57.20 s (21.3 s wall)`` or the failure: the lap
    time the report's tables give (BM lap seconds; the arc-length lap when BM counts no lap), named as there."""
    wall = f"({result.wall_s:.1f} s wall)"
    if result.status == "failed":
        return f"{result.key}: FAILED {result.failure} {wall}"
    assert result.score is not None  # a done episode was scored
    metrics = result.score.metrics
    if metrics.bm_lap_seconds is not None:
        lap = f", BM lap {metrics.bm_lap_seconds:.2f} s"
    else:
        lap = f", lap (arc length) {metrics.lap_times_s[0]:.2f} s" if metrics.lap_times_s else ""
    return (
        f"{result.key}: {result.reason}{lap}, {metrics.percentage_completed:.0f} % of a lap in "
        f"{metrics.sim_time_s:.1f} s sim {wall}"
    )


def summary_line(progress: MatrixProgress, out_dir: Path) -> str:
    ran = progress.done + progress.failed
    return (
        f"{ran} episode(s) run ({progress.done} done, {progress.failed} failed)"
        + (f", {progress.skipped} already in the results" if progress.skipped else "")
        + f"; results in {out_dir / 'results.sqlite'}"
    )


def _add_report(commands: argparse._SubParsersAction) -> None:
    """``drivebench report DIR [-o FOLDER]``."""
    parser = commands.add_parser(
        "report",
        help="tables and plots of a matrix's results (HTML, Markdown, CSV)",
        description="Read DIR/results.sqlite (written by `drivebench matrix`) and write report.html (self-contained), "
        "report.md, episodes.csv and plots/*.png: the paper's main table per brain and circuit, "
        "generalisation and robustness grids, internal metrics, failures, trajectories on the circuit.",
    )
    parser.add_argument("dir", type=Path, metavar="DIR", help="the matrix's output folder")
    parser.add_argument("-o", "--output", type=Path, metavar="FOLDER", help="write the report here instead of into DIR")
    parser.set_defaults(func=run_report)


def run_report(args: argparse.Namespace) -> int:
    """Run ``drivebench report``: 0 with the written paths on stderr; 2 with one error line on stderr."""
    from orchestrator.matrix.results import ResultsError
    from orchestrator.report.data import ReportError
    from orchestrator.report.matrix import write_report

    try:
        files = write_report(args.dir, output=getattr(args, "output", None))
    except (ReportError, ResultsError) as error:
        raise UsageError(str(error)) from None
    written = [files.html, files.markdown, files.csv, *([files.parquet] if files.parquet else [])]
    for path in written:
        print(f"wrote {path}", file=sys.stderr)
    if files.plots:
        print(f"wrote {len(files.plots)} plot(s) in {files.plots[0].parent}", file=sys.stderr)
    return EXIT_OK
