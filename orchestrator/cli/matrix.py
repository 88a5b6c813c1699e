"""``drivebench matrix FILE``: run a test matrix into a folder of results and a report.

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

from orchestrator.cli.errors import EXIT_INTERRUPTED, EXIT_OK, EXIT_SOME_FAILED, UsageError
from orchestrator.cli.ray import add_ray_options, ray_options_from
from orchestrator.cli.run import add_scene_options

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


def _preflight(matrix) -> None:
    """Every brain of the matrix checked before the first episode (weights load and fit, options are taken)."""
    from orchestrator.matrix.runner import brain_launch
    from orchestrator.stack.launcher import preflight_launches
    from services.noise.models import MissingExtra, require_extras

    try:
        require_extras([stage for episode in matrix.episodes for stage in episode.spec.noise])
    except MissingExtra as error:
        raise UsageError(f"{matrix.name}: {error}") from None
    for entry in matrix.brains + matrix.shadows:
        try:
            preflight_launches([brain_launch(entry)])
        except ValueError as error:
            raise UsageError(f"{matrix.name}: brain {entry.label!r}: {error}") from None


def _resolve_renderers(matrix, requested: str | None, *, here: bool = True):
    """Every episode's renderer: ``requested`` (--renderer) over the file's, with "auto" resolved here, where the
    matrix's stacks run (one notice on stderr when it falls back), and "gl" checked before the first episode."""
    from orchestrator.matrix.load import with_renderer
    from services.simulator.renderers import choose_renderer

    chosen: dict[str, str] = {}

    def choose(renderer: str) -> str:
        wanted = requested or renderer
        if not here and wanted == "auto":
            return wanted
        if wanted not in chosen:
            try:
                chosen[wanted] = choose_renderer(wanted)
            except ValueError as error:
                raise UsageError(f"{matrix.name}: {error}") from None
        return chosen[wanted]

    matrix = with_renderer(matrix, choose)
    _check_looks(matrix)
    return matrix


def _check_looks(matrix) -> None:
    """Every episode's look drawable by its renderer, before the first episode (one line naming the choices)."""
    from protocol.variations import VariationError, check_look

    for episode in matrix.episodes:
        try:
            check_look(episode.spec)
        except VariationError as error:
            raise UsageError(f"{matrix.name}: {error}") from None


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
    from orchestrator.matrix.runner import (
        MatrixRunner,
        ProgressDisplay,
        RunOptions,
        never_moved,
        plan_json,
        plan_table,
        summary_line,
    )

    sizing = getattr(args, "power", None) is not None or getattr(args, "run_spread", None) is not None
    if sizing and not args.plan:
        raise UsageError("--power and --run-spread go with --plan (they size a study before it runs)")
    if args.plan:
        print(plan_json(matrix) if args.json else plan_table(matrix))
        if sizing:
            print(_power_of_design(matrix, args))
        return EXIT_OK
    if args.json:
        raise UsageError("--json goes with --plan (a matrix's results are in DIR/results.sqlite and episodes.csv)")
    _check_run_options(args, what=what)
    ray_options = _ray_options(args)
    # On a cluster, "auto" is resolved by each node's simulator: this machine's EGL says nothing about theirs.
    matrix = _resolve_renderers(matrix, getattr(args, "renderer", None), here=ray_options is None)
    _preflight(matrix)
    matrix, out_dir = _prepare_out_dir(matrix, args, default_folder=default_folder)
    options = RunOptions(
        workers=args.workers,
        record=args.record,
        record_images=args.record_images,
        resume=args.resume,
        retry_failed=args.retry_failed,
        facts=dict(facts or {}),
        fresh_stacks=args.fresh_stacks,
    )
    where = f"{args.workers} worker(s)" if ray_options is None else f"Ray cluster {ray_options.address}"
    print(
        f"drivebench: {what} {matrix.name}: {len(matrix.episodes)} episode(s), {where}; output {out_dir}",
        file=sys.stderr,
    )
    display = ProgressDisplay()
    if ray_options is None:
        runner = MatrixRunner(matrix, out_dir, options, on_change=display.update)
    else:
        from orchestrator.matrix.ray_runner import RayMatrixRunner

        runner = RayMatrixRunner(matrix, out_dir, options, ray_options=ray_options, on_change=display.update)
    progress = _run_to_the_end(runner, display, out_dir=out_dir, command=command)
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
    runs = min(runs_by_brain.values(), default=0)
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


def _prepare_out_dir(matrix, args: argparse.Namespace, *, default_folder: str):
    """The output folder, made, with the log going there; ``matrix`` fitted to its results with ``--resume``, and a
    folder that already holds results refused without it (never mix two runs' results)."""
    out_dir = args.out or Path("runs") / f"{default_folder}-{time.strftime('%Y%m%d-%H%M%S')}"
    if not args.resume and (out_dir / "results.sqlite").exists():
        raise UsageError(
            f"{out_dir} already holds matrix results: add --resume to finish that run, or choose another -o folder"
        )
    if args.resume:
        matrix = _fit_to_results(matrix, out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    logging.basicConfig(
        filename=out_dir / "matrix.log",
        level=logging.INFO,
        format="%(asctime)s %(threadName)s %(name)s %(levelname)s %(message)s",
    )
    return matrix, out_dir


def _run_to_the_end(runner, display, *, out_dir: Path, command: str):
    """``runner.run()``'s progress, or None after Ctrl-C (with the command that resumes it on stderr); a results
    database that does not fit is a usage error."""
    from orchestrator.matrix.results import ResultsError

    try:
        return runner.run()
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


def _fit_to_results(matrix, out_dir: Path):
    """``--resume``: ``matrix`` fitted to the folder's results; refused in one line when it changed what they ran,
    said on stderr when it adds episodes to them."""
    from orchestrator.matrix.results import DATABASE_NAME, ResultsError, ResultStore
    from orchestrator.matrix.resume import resume_matrix

    if not (out_dir / DATABASE_NAME).is_file():
        return matrix
    try:
        with ResultStore(out_dir, create=False) as store:
            resumed = resume_matrix(matrix, store)
    except ResultsError as error:
        raise UsageError(str(error)) from None
    if (note := resumed.note()) is not None:
        print(f"drivebench: resume: {note}", file=sys.stderr)
    return resumed.matrix


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
