"""The report of a whole matrix: the paper's tables, plots and a per-episode CSV, from an output folder's results.

    drivebench report OUT [-o OTHER_FOLDER]

reads ``OUT/results.sqlite`` (:mod:`orchestrator.matrix.results`) and writes, into ``OUT`` (or ``-o``):

    report.html      one self-contained file: inline CSS, plots embedded as base64 PNG, no external reference
    report.md        the same tables; the plots as relative links into plots/
    episodes.csv     one row per episode: its conditions, status, and every scalar of EpisodeMetrics
    episodes.parquet the same, only when pyarrow is installed
    plots/*.png      trajectories on the circuit (coloured by speed, and by cross-track error), lap-time and
                     position-deviation box plots per brain, lap progress over simulated time

Tables (Markdown and HTML carry the same ones):

1. the matrix: name, episodes done / failed / total, wall time, date;
2. the paper's main table for the *baseline* condition (no perturbation, the first value of every variation
   axis): per brain and circuit, mean ± sample std over repetitions of each metric column with a main-table header
   (:data:`orchestrator.report.columns.MAIN_COLUMNS`: BM lap seconds of the episodes that completed the lap, BM
   position deviation (mean of 1000^d, not metres), cross-track error mean and max (m), average speed, BM
   percentage completed), laps completed, and what ended the others;
3. generalisation: brain x world variation (no perturbation): the mean lap time when every repetition reached its
   lap target, else ``✗ <most common reason> k/n``;
4. robustness: brain x camera perturbation (baseline variation), the same cell plus the mean BM percentage;
5. internal metrics of trained brains, from their checkpoints (validation MAE / MSE), when torch is installed;
6. brain switches and shadow brains, when scores carry them;
7. stack failures (with their log folders) and episodes that ended before their lap target.

Everything is pure (no bus): it can run on a copy of an output folder on any machine.

The report's parts have modules of their own: the document model and its Markdown / HTML rendering
(:mod:`orchestrator.report.document`), the cells' statistics and formatting (:mod:`orchestrator.report.cells`), the
one table of metric columns the main table, an episode's table and the CSV are made from
(:mod:`orchestrator.report.columns`), the results and facts read from the folder (:mod:`orchestrator.report.data`),
trajectory files and circuit drawings (:mod:`orchestrator.report.trajectories`) and the plots
(:mod:`orchestrator.report.plots`). This module keeps the report's tables and the command that writes the files.
"""

from __future__ import annotations

import functools
import importlib.util
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from orchestrator.matrix.results import DATABASE_NAME, EpisodeResult
from orchestrator.report.cells import (
    brief,
    date_text,
    duration_text,
    failure_summary,
    grid_cell,
    mean_std,
    metrics_of,
    optional_number,
    outcome,
    reached_target,
    scored_only,
)
from orchestrator.report.columns import MAIN_COLUMNS
from orchestrator.report.comparison import comparison_section
from orchestrator.report.data import NO_PERTURBATION, PAPER_FACT, PLOTS_DIR, ReportData, ReportError
from orchestrator.report.document import FAIL_MARK, Section, Table, render_html, render_markdown
from orchestrator.report.export import episode_rows, write_csv, write_parquet
from orchestrator.report.plots import plot_sections

__all__ = [
    "CSV_FILE",
    "HTML_FILE",
    "MARKDOWN_FILE",
    "PAPER_FACT",
    "PAPER_MARKDOWN",
    "PARQUET_FILE",
    "PLOTS_DIR",
    "MatrixReport",
    "ReportError",
    "ReportFiles",
    "write_report",
]

HTML_FILE, MARKDOWN_FILE, CSV_FILE, PARQUET_FILE = ("report.html", "report.md", "episodes.csv", "episodes.parquet")

COMBINED_COLUMNS = 8  # grids with at most this many circuit x condition columns become one table
MAX_EARLY_ROWS = 200  # rows of the "ended early" list
PAPER_MARKDOWN = "paper.md"  # drivebench paper's tables alone


@dataclass(frozen=True)
class ReportFiles:
    """What :func:`write_report` wrote."""

    html: Path
    markdown: Path
    csv: Path
    plots: tuple[Path, ...]
    parquet: Path | None = None
    paper: Path | None = None  # paper.md, for a drivebench paper run


# -- the report -----------------------------------------------------------------------------------------------------


class MatrixReport:
    """The report's sections, from one :class:`~orchestrator.report.data.ReportData` (the plots take the same)."""

    def __init__(self, data: ReportData):
        self.data = data

    # -- sections --

    @functools.cached_property
    def paper_sections(self) -> list[Section]:
        """The paper's six tables, ours beside its figures, when ``drivebench paper`` ran this folder (built once:
        they read every checkpoint)."""
        if not self.data.is_paper:
            return []
        from orchestrator.report.paper import paper_sections

        return paper_sections(self.data.results, self.data.folder)

    def header(self) -> Section:
        done = sum(r.status == "done" for r in self.data.results)
        failed = sum(r.status == "failed" for r in self.data.results)
        reached = sum(reached_target(r) for r in self.data.results)
        start = min(r.started_at for r in self.data.results)
        end = max(r.ended_at for r in self.data.results)
        episode_wall = sum(max(0.0, r.wall_s) for r in self.data.results)
        baseline, created = self.data.baseline_variation, date_text(self.data.created_at) or date_text(start)
        rows = [
            ["matrix", self.data.name],
            [
                "episodes",
                f"{len(self.data.results)} recorded: {done} done, {failed} failed (stack); "
                f"{reached} reached their lap target",
            ],
            ["brains", ", ".join(self.data.brains)],
            ["circuits", ", ".join(self.data.circuits)],
            [
                "variations",
                ", ".join(self.data.variations)
                + (
                    f" (axes: {', '.join(map(str, self.data.variation_keys))}; baseline `{baseline}`)"
                    if self.data.variation_keys
                    else f" (baseline `{baseline}`)"
                ),
            ],
            ["perturbations", ", ".join(self.data.perturbations)],
            [
                "wall time",
                f"{duration_text(end - start)} from first start to last end "
                f"({duration_text(episode_wall)} of episodes)",
            ],
            [
                "date",
                f"{created} (matrix created); ran {date_text(start)} – {date_text(end)}",
            ],
            ["report", f"{time.strftime('%Y-%m-%d %H:%M:%S')} from `{self.data.folder / DATABASE_NAME}`"],
        ]
        return Section(f"Matrix {self.data.name}", [Table(["", ""], rows)])

    def main_table(self) -> Section:
        episodes, sentence = self.data.baseline()
        columns = ["Brain", "Circuit", "Episodes", *(c.main or c.field for c in MAIN_COLUMNS), "Laps", "Did not finish"]
        rows = []
        for brain in self.data.brains:
            for circuit in self.data.circuits:
                group = [r for r in episodes if r.brain == brain and r.circuit == circuit]
                if not group:
                    continue
                scored = scored_only(group)
                metrics = [metrics_of(r) for r in scored]
                laps_done = sum(min(m.completed_laps, r.spec.laps) for r, m in zip(scored, metrics))
                figures = [
                    mean_std([v for v in (c.main_figure(m) for m in metrics) if v is not None], c.main_digits)
                    for c in MAIN_COLUMNS
                ]
                laps = f"{laps_done}/{sum(r.spec.laps for r in group)}"
                rows.append([brain, circuit, str(len(group)), *figures, laps, failure_summary(group)])
        legend = (
            "Each figure is mean ± sample standard deviation over the repetitions (the mean alone for one). "
            "Lap (s): BM lap seconds (first lap: Behavior Metrics' own lap time, from its 5 m checkpoints, the one "
            "the paper's tables use), over the episodes that completed it only. `drivebench run` also prints "
            "'lap times (arc length)', timed at full resolution from the progress along the centre line: the two "
            "differ by about 1 % (57.93 s and 57.20 s for the explicit brain on simple). Position deviation: "
            "Behavior Metrics' `position_deviation_mae`, the mean of 1000^d over the circuit's checkpoints, d being "
            "a checkpoint's distance in metres to the car's path (1: on it, 2: 0.1 m off, 31.6: 0.5 m off, 1000: "
            "1 m off); not metres. Cross-track: |distance| of the car to the centre line, in metres. Completed: BM "
            "percentage completed (above 100 = lap completed). Laps: laps completed / laps targeted, summed over "
            "the episodes. Did not finish: how the episodes that fell short of their lap target ended (end reason, "
            "or the stack failure's kind); stack failures are "
            "left out of every figure."
        )
        return Section(
            "Main table (baseline condition)",
            [
                sentence,
                Table(columns, rows, numeric=[False, False] + [True] * (len(MAIN_COLUMNS) + 2) + [False]),
                legend,
            ],
        )

    def _grid(
        self, episodes: Sequence[EpisodeResult], conditions: Sequence[str], attribute: str, *, with_completion: bool
    ) -> list[Table]:
        circuits = [c for c in self.data.circuits if any(r.circuit == c for r in episodes)]
        present = [v for v in conditions if any(getattr(r, attribute) == v for r in episodes)]

        def cell(brain: str, circuit: str, condition: str) -> str:
            return grid_cell(
                [
                    r
                    for r in episodes
                    if r.brain == brain and r.circuit == circuit and getattr(r, attribute) == condition
                ],
                with_completion=with_completion,
            )

        if len(circuits) * len(present) <= COMBINED_COLUMNS or len(circuits) == 1:
            if len(circuits) == 1:
                columns = ["Brain", *present]
            else:
                columns = ["Brain", *(f"{c} · {v}" for c in circuits for v in present)]
            rows = [[brain, *(cell(brain, c, v) for c in circuits for v in present)] for brain in self.data.brains]
            caption = f"circuit {circuits[0]}" if len(circuits) == 1 else ""
            return [Table(columns, rows, numeric=[False] + [True] * (len(columns) - 1), caption=caption)]
        return [
            Table(
                ["Brain", *present],
                [[brain, *(cell(brain, c, v) for v in present)] for brain in self.data.brains],
                numeric=[False] + [True] * len(present),
                caption=f"circuit {c}",
            )
            for c in circuits
        ]

    def generalisation(self) -> Section:
        section = Section("Generalisation (world variations)")
        if len(self.data.variations) < 2:
            section.blocks.append(f"One world variation only (`{self.data.variations[0]}`): see the main table.")
            return section
        episodes = [r for r in self.data.results if r.perturbation == NO_PERTURBATION]
        if episodes:
            section.blocks.append(f"Episodes without camera perturbation (`{NO_PERTURBATION}`), per world variation.")
        else:
            episodes = list(self.data.results)
            section.blocks.append("The matrix has no unperturbed episode: every perturbation is pooled.")
        section.blocks.extend(self._grid(episodes, self.data.variations, "variation", with_completion=False))
        section.blocks.append(_CELL_LEGEND)
        return section

    def robustness(self) -> Section:
        section = Section("Robustness (camera perturbations)")
        if len(self.data.perturbations) < 2:
            section.blocks.append(f"One perturbation only (`{self.data.perturbations[0]}`): see the main table.")
            return section
        episodes = [r for r in self.data.results if r.variation == self.data.baseline_variation]
        section.blocks.append(
            f"Episodes in the baseline variation (`{self.data.baseline_variation}`), per perturbation."
        )
        section.blocks.extend(self._grid(episodes, self.data.perturbations, "perturbation", with_completion=True))
        section.blocks.append(_CELL_LEGEND + " After the dot: mean BM percentage completed of the scored episodes.")
        return section

    def internal_metrics(self) -> Section | None:
        entries: dict[str, Path] = {}
        for r in self.data.results:
            if r.brain_entry.weights is not None and r.brain not in entries:
                entries[r.brain] = r.brain_entry.weights
        if not entries:
            return None
        section = Section("Internal metrics (offline, from training)")
        if importlib.util.find_spec("torch") is None:
            section.blocks.append(
                "torch is not installed: the checkpoints' training metrics are not read (`pip install drivebench[ml]`)."
            )
            return section
        from brains.neural.checkpoint import CheckpointError, read_checkpoint

        rows, notes = [], []
        for brain, weights in entries.items():
            path = self._weights_path(str(weights))
            try:
                checkpoint = read_checkpoint(path)
            except CheckpointError as error:
                notes.append(f"{brain}: skipped: {error}")
                continue
            except Exception as error:  # never let one unreadable file stop the report
                notes.append(f"{brain}: skipped: {path}: {type(error).__name__}: {error}")
                continue
            metrics = checkpoint.get("metrics") or {}
            split = "val" if isinstance(metrics.get("val"), dict) else "train"
            figures = metrics.get(split) if isinstance(metrics.get(split), dict) else {}
            train: dict = metrics["train"] if isinstance(metrics.get("train"), dict) else {}
            if not figures:
                notes.append(f"{brain}: {path}: the checkpoint carries no MAE/MSE metrics")
                continue
            rows.append(
                [
                    brain,
                    str(checkpoint.get("model", "?")),
                    f"`{path.name}`",
                    split,
                    optional_number(figures.get("mae_speed_mps"), 3),
                    optional_number(figures.get("mae_yaw_rate_radps"), 3),
                    optional_number(figures.get("mse_normalised"), 4),
                    optional_number(train.get("mse_normalised"), 4),
                    str(metrics.get("best_epoch", "–")),
                ]
            )
        if rows:
            section.blocks.append(
                Table(
                    [
                        "Brain",
                        "Model",
                        "Checkpoint",
                        "Split",
                        "MAE v (m/s)",
                        "MAE w (rad/s)",
                        "MSE (normalised)",
                        "Train MSE (normalised)",
                        "Best epoch",
                    ],
                    rows,
                    numeric=[False, False, False, False, True, True, True, True, True],
                )
            )
            section.blocks.append(
                "The paper's internal metrics on the held-out split (the training subset when the "
                "dataset had no validation split): mean absolute error of speed and yaw rate in "
                "physical units, and mean squared error of the normalised outputs."
            )
        section.blocks.extend(notes)
        return section

    def _weights_path(self, weights: str) -> Path:
        path = Path(weights).expanduser()
        if not path.is_absolute() and not path.is_file() and (self.data.folder / path).is_file():
            return self.data.folder / path
        return path

    def switches(self) -> Section | None:
        rows = []
        for r in self.data.results:
            if r.score is None:
                continue
            switches = list(getattr(r.score, "switches", None) or [])
            shadows = list(getattr(r.score, "shadows", None) or [])
            if switches or shadows:
                rows.append([r.key, r.brain, str(len(switches)), brief(switches), str(len(shadows)), brief(shadows)])
        if not rows:
            return None
        return Section(
            "Brain switches and shadow brains",
            [
                Table(
                    ["Episode", "Brain", "Switches", "Switch details", "Shadows", "Shadow details"],
                    rows,
                    numeric=[False, False, True, False, True, False],
                )
            ],
        )

    def failures(self) -> Section:
        section = Section("Failures")
        failed = [r for r in self.data.results if r.status == "failed"]
        if failed:
            section.blocks.append(
                f"{len(failed)} episode(s) failed because of the stack, not the brain (they are "
                "run again by `--resume`)."
            )
            section.blocks.append(
                Table(
                    ["Episode", "Brain", "Circuit", "Condition", "Failure", "Logs"],
                    [
                        [
                            r.key,
                            r.brain,
                            r.circuit,
                            f"{r.variation} / {r.perturbation}",
                            str(r.failure or "–"),
                            f"`{r.logs}`" if r.logs else "–",
                        ]
                        for r in failed
                    ],
                )
            )
        else:
            section.blocks.append("No stack failure.")
        early = [r for r in self.data.results if r.status == "done" and not reached_target(r)]
        if early:
            shown = early[:MAX_EARLY_ROWS]
            section.blocks.append(
                f"{len(early)} episode(s) ended before their lap target"
                + (f" (the first {len(shown)} listed)" if len(shown) < len(early) else "")
                + ":"
            )
            section.blocks.append(
                Table(
                    ["Episode", "Brain", "Circuit", "Condition", "Ended by", "Completed (%)", "Sim time (s)"],
                    [
                        [
                            r.key,
                            r.brain,
                            r.circuit,
                            f"{r.variation} / {r.perturbation}",
                            outcome(r),
                            optional_number(r.score.metrics.percentage_completed if r.score else None, 1),
                            optional_number(r.score.metrics.sim_time_s if r.score else None, 1),
                        ]
                        for r in shown
                    ],
                    numeric=[False, False, False, False, False, True, True],
                )
            )
        return section

    def comparison(self) -> Section:
        section, plot = comparison_section(self.data.results, plots_dir=self.data.plots_dir)
        if plot is not None:
            self.data.plots.append(plot)
        return section

    # -- assembling --

    def sections(self) -> list[Section]:
        sections = [self.header(), *self.paper_sections, self.main_table(), self.comparison()]
        sections += [self.generalisation(), self.robustness()]
        for optional in (self.internal_metrics(), self.switches()):
            if optional is not None:
                sections.append(optional)
        sections.append(self.failures())
        sections.extend(plot_sections(self.data))
        if self.data.notes:
            sections.append(Section("Notes", list(self.data.notes)))
        return sections


_CELL_LEGEND = (
    f"A cell: the mean first-lap time (s, BM lap seconds, as in every table here) when every repetition reached its "
    f"lap target; otherwise "
    f"{FAIL_MARK} with the most common way the others ended (end reason, or the stack failure's kind) and "
    "how many of the cell's episodes ended that way."
)


def write_report(folder: Path, *, output: Path | None = None) -> ReportFiles:
    """Read ``folder/results.sqlite`` and write the report into ``output`` (default: ``folder``).

    Raises :class:`ReportError` (no folder, no database, no episode) or :class:`ResultsError` (a damaged
    database), one line each naming the path.
    """
    folder = Path(folder)
    output = Path(output) if output is not None else folder
    report = MatrixReport(ReportData.load(folder, output=output))
    output.mkdir(parents=True, exist_ok=True)
    sections = report.sections()
    markdown_path, html_path, csv_path = output / MARKDOWN_FILE, output / HTML_FILE, output / CSV_FILE
    markdown_path.write_text(render_markdown(sections, output), encoding="utf-8")
    html_path.write_text(render_html(sections, f"drivebench report: {report.data.name}"), encoding="utf-8")
    rows = episode_rows(report.data.results)
    write_csv(rows, csv_path)
    parquet = write_parquet(rows, output / PARQUET_FILE)
    paper = output / PAPER_MARKDOWN if report.data.is_paper else None
    if paper is not None:
        paper.write_text(render_markdown(report.paper_sections, output), encoding="utf-8")
    return ReportFiles(
        html=html_path,
        markdown=markdown_path,
        csv=csv_path,
        plots=tuple(report.data.plots),
        parquet=parquet,
        paper=paper,
    )
