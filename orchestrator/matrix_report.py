"""The report of a whole matrix: the paper's tables, plots and a per-episode CSV, from an output folder's results.

    drivebench report OUT [-o OTHER_FOLDER]

reads ``OUT/results.sqlite`` (:mod:`orchestrator.results`) and writes, into ``OUT`` (or ``-o``):

    report.html      one self-contained file: inline CSS, plots embedded as base64 PNG, no external reference
    report.md        the same tables; the plots as relative links into plots/
    episodes.csv     one row per episode: its conditions, status, and every scalar of EpisodeMetrics
    episodes.parquet the same, only when pyarrow is installed
    plots/*.png      trajectories on the circuit (coloured by speed, and by cross-track error), lap-time and
                     position-deviation box plots per brain, lap progress over simulated time

Tables (Markdown and HTML carry the same ones):

1. the matrix: name, episodes done / failed / total, wall time, date;
2. the paper's main table for the *baseline* condition (no perturbation, the first value of every variation
   axis): per brain and circuit, mean ± sample std over repetitions of the BM lap seconds (episodes that completed
   the lap only), BM position deviation (mean of 1000^d, not metres), cross-track error mean and max (m), average
   speed, BM percentage completed, laps completed, and what ended the others;
3. generalisation: brain x world variation (no perturbation): the mean lap time when every repetition reached its
   lap target, else ``✗ <most common reason> k/n``;
4. robustness: brain x camera perturbation (baseline variation), the same cell plus the mean BM percentage;
5. internal metrics of trained brains, from their checkpoints (validation MAE / MSE), when torch is installed;
6. brain switches and shadow brains, when scores carry them;
7. stack failures (with their log folders) and episodes that ended before their lap target.

Everything is pure (no bus): it can run on a copy of an output folder on any machine.
"""

from __future__ import annotations

import argparse
import base64
import csv
import functools
import html
import importlib.util
import math
import re
import statistics
import sys
import time
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from orchestrator.results import DATABASE_NAME, EpisodeResult, ResultsError, ResultStore
from protocol.messages import EpisodeMetrics

HTML_FILE, MARKDOWN_FILE, CSV_FILE, PARQUET_FILE, PLOTS_DIR = (
    "report.html", "report.md", "episodes.csv", "episodes.parquet", "plots")

NO_PERTURBATION = "none"
DEFAULT_VARIATION = "default"
MAX_SUBPLOTS = 24  # trajectory subplots per figure (one figure per circuit and colouring)
MAX_PLOT_POINTS = 1200  # poses drawn per episode (decimated beyond: ~0.4 m apart on a 450 m lap)
MAX_BOX_CIRCUITS = 8  # circuits (columns) in the box-plot figure
MAX_PROGRESS_CIRCUITS = 12  # circuits (subplots) in the progress figure
COMBINED_COLUMNS = 8  # grids with at most this many circuit x condition columns become one table
MAX_EARLY_ROWS = 200  # rows of the "ended early" list
FAIL_MARK = "✗"
PAPER_MARKDOWN = "paper.md"  # drivebench paper's tables alone
BASELINE_FACT = "baseline_variation"  # results-database fact: the variation label of the matrix's first episode
PAPER_FACT = "paper"  # results-database fact set by drivebench paper: the report then carries the paper's tables
STALE_PLOTS = ("trajectories_*.png", "boxplots.png", "progress.png")  # what the report writes into plots/

# Order of the EpisodeMetrics scalars in the CSV (the struct's own order; lap_times_s joined with ';').
METRIC_FIELDS: tuple[str, ...] = EpisodeMetrics.__struct_fields__


class ReportError(RuntimeError):
    """The report cannot be made (no results database, an empty one, ...); one line that names the path."""


@dataclass(frozen=True)
class ReportFiles:
    """What :func:`write_report` wrote."""

    html: Path
    markdown: Path
    csv: Path
    plots: tuple[Path, ...]
    parquet: Path | None = None
    paper: Path | None = None  # paper.md, for a drivebench paper run


# -- document model: the same blocks render to Markdown and to HTML ---------------------------------------------------


@dataclass
class Table:
    columns: list[str]
    rows: list[list[str]]
    numeric: list[bool] | None = None  # right-aligned columns
    caption: str = ""


@dataclass
class Plot:
    path: Path
    caption: str


@dataclass
class Section:
    title: str
    blocks: list[Table | Plot | str] = field(default_factory=list)  # str: a paragraph (may hold `code`)


# -- small helpers --------------------------------------------------------------------------------------------------


def _ordered(values: Iterable[str]) -> list[str]:
    """Distinct values in order of first appearance."""
    return list(dict.fromkeys(values))


def _fmt_number(value: float, digits: int) -> str:
    if not math.isfinite(value):
        return str(value)
    if abs(value) >= 10_000:  # BM position deviation explodes off the road (1000^d): no decimals there
        return f"{value:,.0f}"
    return f"{value:.{digits}f}"


def mean_std(values: Sequence[float], digits: int = 2) -> str:
    """``"mean ± std"`` (sample standard deviation, ddof 1) over repetitions; just the mean for one value; "–" for
    none."""
    values = [float(v) for v in values if v is not None]
    if not values:
        return "–"
    mean = statistics.fmean(values)
    if len(values) == 1:
        return _fmt_number(mean, digits)
    return f"{_fmt_number(mean, digits)} ± {_fmt_number(statistics.stdev(values), digits)}"


def lap_seconds(result: EpisodeResult) -> float | None:
    """The episode's first-lap time: BM's ``bm_lap_seconds`` when BM counts the lap, else the first timed lap;
    None when the episode completed no lap (or was not scored)."""
    if result.score is None:
        return None
    metrics = result.score.metrics
    if metrics.bm_lap_seconds is not None:
        return float(metrics.bm_lap_seconds)
    return float(metrics.lap_times_s[0]) if metrics.lap_times_s else None


def reached_target(result: EpisodeResult) -> bool:
    """Ran and was scored, and completed its lap target."""
    return (result.status == "done" and result.score is not None
            and result.score.metrics.completed_laps >= result.spec.laps)


def outcome(result: EpisodeResult) -> str:
    """A short word for how an episode ended: the failure kind of a stack failure, else the episode's end reason."""
    if result.status == "failed":
        return result.failure_kind or "failed"
    if result.reason:
        return str(result.reason)
    return str(result.score.reason) if result.score is not None else "not_scored"


def _scored(results: Iterable[EpisodeResult]) -> list[EpisodeResult]:
    """Episodes the brain is judged on: ran and scored (stack failures are not the brain's doing)."""
    return [r for r in results if r.status == "done" and r.score is not None]


def _failure_summary(results: Sequence[EpisodeResult]) -> str:
    counts = Counter(outcome(r) for r in results if not reached_target(r))
    if not counts:
        return "–"
    return ", ".join(f"{name} {count}" for name, count in counts.most_common())


def grid_cell(results: Sequence[EpisodeResult], *, with_completion: bool = False) -> str:
    """One cell of the generalisation / robustness grids.

    Every episode reached its lap target: the mean first-lap time (``"74.3 s"``). Otherwise a failure mark with the
    most common way the others ended and its count over all episodes of the cell (``"✗ crash 2/3"``,
    ``"✗ brain_died 1/2"`` for a stack failure). ``with_completion`` adds the mean BM percentage completed of the
    scored episodes (``" · 63 %"``).
    """
    if not results:
        return "–"
    missed = [r for r in results if not reached_target(r)]
    if not missed:
        laps = [t for t in (lap_seconds(r) for r in results) if t is not None]
        text = f"{statistics.fmean(laps):.1f} s" if laps else "✓"
    else:
        counts = Counter(outcome(r) for r in missed)
        name, count = counts.most_common(1)[0]
        text = f"{FAIL_MARK} {name} {count}/{len(results)}"
    if with_completion:
        scored = _scored(results)
        if scored:
            text += f" · {statistics.fmean(r.score.metrics.percentage_completed for r in scored):.0f} %"
    return text


def baseline_variation(results: Sequence[EpisodeResult], planned: str | None = None) -> str | None:
    """The variation label of the baseline condition: ``"default"`` when present, else ``planned`` (the first planned
    episode's variation, the first value of every axis, which the runner stores as the ``baseline_variation`` fact)
    when some episode has it, else the variation of the first stored episode in matrix order."""
    labels = _ordered(r.variation for r in sorted(results, key=lambda r: r.index))
    if not labels:
        return None
    if DEFAULT_VARIATION in labels:
        return DEFAULT_VARIATION
    return planned if planned in labels else labels[0]


# -- trajectories and circuits ----------------------------------------------------------------------------------------


TRAJECTORY_ARRAYS = ("stamp_s", "x_m", "y_m", "yaw_rad", "speed_mps", "live_sim_time_s", "live_progress_laps",
                     "live_cross_track_m")


def load_trajectory(folder: Path, relative: str | None) -> dict[str, np.ndarray] | None:
    """The episode's trajectory arrays (every name of :data:`TRAJECTORY_ARRAYS`, empty when absent), or None when
    there is no file or it cannot be read."""
    if not relative:
        return None
    path = folder / relative
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: np.asarray(data[name], dtype=float).ravel() if name in data.files else np.zeros(0)
                      for name in TRAJECTORY_ARRAYS}
    except Exception:  # a damaged file (BadZipFile, ValueError, OSError...) only loses its plot
        return None
    n = min(len(arrays["x_m"]), len(arrays["y_m"]))
    arrays["x_m"], arrays["y_m"] = arrays["x_m"][:n], arrays["y_m"][:n]
    return arrays


class _Track:
    """A circuit's drawing: its points, road edges and extent (cross-track colours come from its centreline)."""

    def __init__(self, circuit):
        self.circuit = circuit
        self.points = circuit.centreline.points_m
        normals = circuit.centreline.left_normals()
        half = circuit.road_half_width_m
        self.left_edge = self.points + half * normals
        self.right_edge = self.points - half * normals
        self.half_width_m = half
        margin = half + 3.0
        self.extent = (float(self.points[:, 0].min() - margin), float(self.points[:, 0].max() + margin),
                       float(self.points[:, 1].min() - margin), float(self.points[:, 1].max() + margin))

    def lateral_m(self, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        """Signed distance (+ left) of each point to the centreline, for colouring a plot."""
        return self.circuit.centreline.lateral_offsets_m(x_m, y_m)


def _speeds(trajectory: dict[str, np.ndarray]) -> np.ndarray:
    """Speed at each pose: the recorded one, else from successive positions and stamps."""
    x, y = trajectory["x_m"], trajectory["y_m"]
    speed = trajectory["speed_mps"]
    if len(speed) == len(x):
        return speed
    stamps = trajectory["stamp_s"]
    if len(stamps) == len(x) and len(x) >= 2:
        dt = np.diff(stamps)
        step = np.hypot(np.diff(x), np.diff(y)) / np.where(dt > 0, dt, np.nan)
        return np.nan_to_num(np.concatenate([[step[0]], step]))
    return np.zeros(len(x))


# -- the report -----------------------------------------------------------------------------------------------------


class _Report:
    def __init__(self, folder: Path, output: Path):
        self.folder = folder
        self.output = output
        self.plots_dir = output / PLOTS_DIR
        database = folder / DATABASE_NAME
        if not folder.is_dir():
            raise ReportError(f"{folder}: no such folder")
        if not database.is_file():
            raise ReportError(f"{database}: no results database (run `drivebench matrix FILE -o {folder}` first)")
        store = ResultStore(folder, create=False)
        try:
            self.results = store.results()
            self.name = store.fact("name") or folder.resolve().name
            self.source_text = store.fact("source_text")
            self.planned_baseline = store.fact(BASELINE_FACT)
            self.variation_keys = store.fact("variation_keys") or []
            self.created_at = store.fact("created_at")
            self.is_paper = bool(store.fact(PAPER_FACT))
        finally:
            store.close()
        if not self.results:
            raise ReportError(f"{database}: no episodes recorded yet (an empty matrix, or one that has not run)")
        self.brains = _ordered(r.brain for r in self.results)
        self.circuits = _ordered(r.circuit for r in self.results)
        self.variations = _ordered(r.variation for r in self.results)
        perturbations = _ordered(r.perturbation for r in self.results)
        self.perturbations = ([NO_PERTURBATION] if NO_PERTURBATION in perturbations else []) + [
            p for p in perturbations if p != NO_PERTURBATION]
        self.baseline_variation = baseline_variation(self.results, self.planned_baseline)
        self.notes: list[str] = []  # problems met while drawing (missing trajectories, unknown circuits)
        self._tracks: dict[str, _Track | None] = {}
        self._trajectories: dict[str, dict[str, np.ndarray] | None] = {}
        self.plots: list[Path] = []

    # -- data access --

    def track(self, circuit: str) -> _Track | None:
        if circuit not in self._tracks:
            from circuits import CircuitError, load_circuit

            try:
                self._tracks[circuit] = _Track(load_circuit(circuit))
            except (CircuitError, ValueError, OSError) as error:
                self.notes.append(f"circuit {circuit!r} not drawn: {error}")
                self._tracks[circuit] = None
        return self._tracks[circuit]

    def trajectory(self, result: EpisodeResult) -> dict[str, np.ndarray] | None:
        if result.key not in self._trajectories:
            self._trajectories[result.key] = load_trajectory(self.folder, result.trajectory)
        return self._trajectories[result.key]

    def baseline(self) -> tuple[list[EpisodeResult], str]:
        """Episodes of the baseline condition and a sentence saying what it is."""
        chosen = [r for r in self.results
                  if r.perturbation == NO_PERTURBATION and r.variation == self.baseline_variation]
        if chosen:
            return chosen, (f"Baseline condition: variation `{self.baseline_variation}`, perturbation "
                            f"`{NO_PERTURBATION}`.")
        return list(self.results), ("The matrix has no episode in the baseline condition (first variation, no "
                                    "perturbation): every episode is pooled.")

    # -- sections --

    @functools.cached_property
    def paper_sections(self) -> list[Section]:
        """The paper's six tables, ours beside its figures, when ``drivebench paper`` ran this folder (built once:
        they read every checkpoint)."""
        if not self.is_paper:
            return []
        from orchestrator.paper import paper_sections

        return paper_sections(self.results, self.folder)

    def header(self) -> Section:
        done = sum(r.status == "done" for r in self.results)
        failed = sum(r.status == "failed" for r in self.results)
        reached = sum(reached_target(r) for r in self.results)
        start = min(r.started_at for r in self.results)
        end = max(r.ended_at for r in self.results)
        episode_wall = sum(max(0.0, r.wall_s) for r in self.results)
        rows = [
            ["matrix", self.name],
            ["episodes", f"{len(self.results)} recorded: {done} done, {failed} failed (stack); "
                         f"{reached} reached their lap target"],
            ["brains", ", ".join(self.brains)],
            ["circuits", ", ".join(self.circuits)],
            ["variations", ", ".join(self.variations)
             + (f" (axes: {', '.join(map(str, self.variation_keys))}; baseline `{self.baseline_variation}`)"
                if self.variation_keys else f" (baseline `{self.baseline_variation}`)")],
            ["perturbations", ", ".join(self.perturbations)],
            ["wall time", f"{_duration(end - start)} from first start to last end "
                          f"({_duration(episode_wall)} of episodes)"],
            ["date", f"{_date(self.created_at) or _date(start)} (matrix created); ran "
                     f"{_date(start)} – {_date(end)}"],
            ["report", f"{time.strftime('%Y-%m-%d %H:%M:%S')} from `{self.folder / DATABASE_NAME}`"],
        ]
        return Section(f"Matrix {self.name}", [Table(["", ""], rows)])

    def main_table(self) -> Section:
        episodes, sentence = self.baseline()
        columns = ["Brain", "Circuit", "Episodes", "Lap (s)", "Position deviation (BM)", "Cross-track mean (m)",
                   "Cross-track max (m)", "Avg speed (m/s)", "Completed (%)", "Laps", "Did not finish"]
        rows = []
        for brain in self.brains:
            for circuit in self.circuits:
                group = [r for r in episodes if r.brain == brain and r.circuit == circuit]
                if not group:
                    continue
                scored = _scored(group)
                metrics = [r.score.metrics for r in scored]
                laps_done = sum(min(m.completed_laps, r.spec.laps) for r, m in zip(scored, metrics))
                rows.append([
                    brain, circuit, str(len(group)),
                    mean_std([t for t in (lap_seconds(r) for r in scored) if t is not None], 2),
                    mean_std([m.position_deviation_mae for m in metrics], 2),
                    mean_std([m.cross_track_mean_m for m in metrics], 3),
                    mean_std([m.cross_track_max_m for m in metrics], 3),
                    mean_std([m.average_speed_mps for m in metrics], 2),
                    mean_std([m.percentage_completed for m in metrics], 1),
                    f"{laps_done}/{sum(r.spec.laps for r in group)}",
                    _failure_summary(group),
                ])
        legend = (
            "Each figure is mean ± sample standard deviation over the repetitions (the mean alone for one). "
            "Lap (s): BM lap seconds (first lap), over the episodes that completed it only. Position deviation: "
            "Behavior Metrics' `position_deviation_mae`, the mean of 1000^d over the circuit's checkpoints, d being "
            "a checkpoint's distance in metres to the car's path (1: on it, 2: 0.1 m off, 31.6: 0.5 m off, 1000: "
            "1 m off); not metres. Cross-track: |distance| of the car to the centre line, in metres. Completed: BM "
            "percentage completed (above 100 = lap completed). Laps: laps completed / laps targeted, summed over "
            "the episodes. Did not finish: how the episodes that fell short of their lap target ended (end reason, "
            "or the stack failure's kind); stack failures are "
            "left out of every figure.")
        return Section("Main table (baseline condition)",
                       [sentence, Table(columns, rows, numeric=[False, False] + [True] * 8 + [False]), legend])

    def _grid(self, episodes: Sequence[EpisodeResult], conditions: Sequence[str], attribute: str, *,
              with_completion: bool) -> list[Table]:
        circuits = [c for c in self.circuits if any(r.circuit == c for r in episodes)]
        present = [v for v in conditions if any(getattr(r, attribute) == v for r in episodes)]

        def cell(brain: str, circuit: str, condition: str) -> str:
            return grid_cell([r for r in episodes if r.brain == brain and r.circuit == circuit
                              and getattr(r, attribute) == condition], with_completion=with_completion)

        if len(circuits) * len(present) <= COMBINED_COLUMNS or len(circuits) == 1:
            if len(circuits) == 1:
                columns = ["Brain", *present]
            else:
                columns = ["Brain", *(f"{c} · {v}" for c in circuits for v in present)]
            rows = [[brain, *(cell(brain, c, v) for c in circuits for v in present)] for brain in self.brains]
            caption = f"circuit {circuits[0]}" if len(circuits) == 1 else ""
            return [Table(columns, rows, numeric=[False] + [True] * (len(columns) - 1), caption=caption)]
        return [Table(["Brain", *present], [[brain, *(cell(brain, c, v) for v in present)] for brain in self.brains],
                      numeric=[False] + [True] * len(present), caption=f"circuit {c}") for c in circuits]

    def generalisation(self) -> Section:
        section = Section("Generalisation (world variations)")
        if len(self.variations) < 2:
            section.blocks.append(f"One world variation only (`{self.variations[0]}`): see the main table.")
            return section
        episodes = [r for r in self.results if r.perturbation == NO_PERTURBATION]
        if episodes:
            section.blocks.append(f"Episodes without camera perturbation (`{NO_PERTURBATION}`), per world variation.")
        else:
            episodes = list(self.results)
            section.blocks.append("The matrix has no unperturbed episode: every perturbation is pooled.")
        section.blocks.extend(self._grid(episodes, self.variations, "variation", with_completion=False))
        section.blocks.append(_CELL_LEGEND)
        return section

    def robustness(self) -> Section:
        section = Section("Robustness (camera perturbations)")
        if len(self.perturbations) < 2:
            section.blocks.append(f"One perturbation only (`{self.perturbations[0]}`): see the main table.")
            return section
        episodes = [r for r in self.results if r.variation == self.baseline_variation]
        section.blocks.append(f"Episodes in the baseline variation (`{self.baseline_variation}`), per perturbation.")
        section.blocks.extend(self._grid(episodes, self.perturbations, "perturbation", with_completion=True))
        section.blocks.append(_CELL_LEGEND + " After the dot: mean BM percentage completed of the scored episodes.")
        return section

    def internal_metrics(self) -> Section | None:
        entries: dict[str, dict[str, Any]] = {}
        for r in self.results:
            if r.brain_entry.get("weights") and r.brain not in entries:
                entries[r.brain] = r.brain_entry
        if not entries:
            return None
        section = Section("Internal metrics (offline, from training)")
        if importlib.util.find_spec("torch") is None:
            section.blocks.append("torch is not installed: the checkpoints' training metrics are not read "
                                  "(`pip install drivebench[ml]`).")
            return section
        from brains.neural.checkpoint import CheckpointError, read_checkpoint

        rows, notes = [], []
        for brain, entry in entries.items():
            path = self._weights_path(str(entry["weights"]))
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
            train = metrics.get("train") if isinstance(metrics.get("train"), dict) else {}
            if not figures:
                notes.append(f"{brain}: {path}: the checkpoint carries no MAE/MSE metrics")
                continue
            rows.append([brain, str(checkpoint.get("model", "?")), f"`{path.name}`", split,
                         _opt(figures.get("mae_speed_mps"), 3), _opt(figures.get("mae_yaw_rate_radps"), 3),
                         _opt(figures.get("mse_normalised"), 4), _opt(train.get("mse_normalised"), 4),
                         str(metrics.get("best_epoch", "–"))])
        if rows:
            section.blocks.append(Table(
                ["Brain", "Model", "Checkpoint", "Split", "MAE v (m/s)", "MAE w (rad/s)", "MSE (normalised)",
                 "Train MSE (normalised)", "Best epoch"], rows,
                numeric=[False, False, False, False, True, True, True, True, True]))
            section.blocks.append("The paper's internal metrics on the held-out split (the training subset when the "
                                  "dataset had no validation split): mean absolute error of speed and yaw rate in "
                                  "physical units, and mean squared error of the normalised outputs.")
        section.blocks.extend(notes)
        return section

    def _weights_path(self, weights: str) -> Path:
        path = Path(weights).expanduser()
        if not path.is_absolute() and not path.is_file() and (self.folder / path).is_file():
            return self.folder / path
        return path

    def switches(self) -> Section | None:
        rows = []
        for r in self.results:
            if r.score is None:
                continue
            switches = list(getattr(r.score, "switches", None) or [])
            shadows = list(getattr(r.score, "shadows", None) or [])
            if switches or shadows:
                rows.append([r.key, r.brain, str(len(switches)), _brief(switches), str(len(shadows)),
                             _brief(shadows)])
        if not rows:
            return None
        return Section("Brain switches and shadow brains", [Table(
            ["Episode", "Brain", "Switches", "Switch details", "Shadows", "Shadow details"], rows,
            numeric=[False, False, True, False, True, False])])

    def failures(self) -> Section:
        section = Section("Failures")
        failed = [r for r in self.results if r.status == "failed"]
        if failed:
            section.blocks.append(f"{len(failed)} episode(s) failed because of the stack, not the brain (they are "
                                  "run again by `--resume`).")
            section.blocks.append(Table(
                ["Episode", "Brain", "Circuit", "Condition", "Failure", "Logs"],
                [[r.key, r.brain, r.circuit, f"{r.variation} / {r.perturbation}", r.failure or "–",
                  f"`{r.logs}`" if r.logs else "–"] for r in failed]))
        else:
            section.blocks.append("No stack failure.")
        early = [r for r in self.results if r.status == "done" and not reached_target(r)]
        if early:
            shown = early[:MAX_EARLY_ROWS]
            section.blocks.append(f"{len(early)} episode(s) ended before their lap target"
                                  + (f" (the first {len(shown)} listed)" if len(shown) < len(early) else "") + ":")
            section.blocks.append(Table(
                ["Episode", "Brain", "Circuit", "Condition", "Ended by", "Completed (%)", "Sim time (s)"],
                [[r.key, r.brain, r.circuit, f"{r.variation} / {r.perturbation}", outcome(r),
                  _opt(r.score.metrics.percentage_completed if r.score else None, 1),
                  _opt(r.score.metrics.sim_time_s if r.score else None, 1)] for r in shown],
                numeric=[False, False, False, False, False, True, True]))
        return section

    # -- plots --

    def plot_sections(self) -> list[Section]:
        import matplotlib

        matplotlib.use("Agg", force=True)
        self.plots_dir.mkdir(parents=True, exist_ok=True)
        for pattern in STALE_PLOTS:  # a previous report's plots (a circuit since dropped) would mislead
            for stale in self.plots_dir.glob(pattern):
                stale.unlink(missing_ok=True)
        sections = []
        trajectories = Section("Trajectories", [
            "Every episode's path over the road (grey: road edges, dashed: centre line, ○ and arrow: start and "
            "driving direction), one panel per brain and condition with the repetitions overlaid; ✕ where an "
            "episode ended short of its lap target; (k/n finished): episodes of the panel that reached their lap "
            "target. Colours: "
            "speed from the poses, and |cross-track error| from projecting every pose onto the centre line."])
        for circuit in self.circuits:
            for plot in self._trajectory_figures(circuit):
                trajectories.blocks.append(plot)
        if not any(isinstance(b, Plot) for b in trajectories.blocks):
            trajectories.blocks.append("No trajectory file could be read.")
        sections.append(trajectories)
        distributions = Section("Distributions")
        for plot in (self._box_plots(), self._progress_plot()):
            if plot is not None:
                distributions.blocks.append(plot)
        if distributions.blocks:
            sections.append(distributions)
        return sections

    def _save(self, fig, name: str) -> Path:
        import matplotlib.pyplot as plt

        path = self.plots_dir / name
        fig.savefig(path, dpi=110)
        plt.close(fig)
        self.plots.append(path)
        return path

    def _trajectory_figures(self, circuit: str) -> list[Plot]:
        import matplotlib.pyplot as plt
        from matplotlib.collections import LineCollection
        from matplotlib.colors import Normalize
        from matplotlib.ticker import MaxNLocator

        episodes = [r for r in self.results if r.circuit == circuit]
        loaded = [(r, self.trajectory(r)) for r in episodes]
        unreadable = [r for r, t in loaded if r.trajectory and (t is None or len(t["x_m"]) < 2)]
        unrecorded = [r for r in episodes if r.status == "done" and not r.trajectory]
        if unreadable:
            self.notes.append(f"{circuit}: {len(unreadable)} episode(s) have no readable trajectory file (missing, "
                              f"damaged or empty), e.g. `{unreadable[0].trajectory}`")
        if unrecorded:
            self.notes.append(f"{circuit}: {len(unrecorded)} episode(s) ran without a trajectory file")
        loaded = [(r, t) for r, t in loaded if t is not None and len(t["x_m"]) >= 2]
        if not loaded:
            return []
        track = self.track(circuit)
        # One panel per brain and condition; when that makes too many panels, coarser groups (conditions overlaid).
        for fields in (("brain", "variation", "perturbation"), ("brain", "variation"), ("brain",)):
            def group_of(r: EpisodeResult, fields=fields) -> tuple[str, ...]:
                return tuple(getattr(r, name) for name in fields)

            if len({group_of(r) for r, _ in loaded}) <= MAX_SUBPLOTS:
                break
        totals = Counter(group_of(r) for r in episodes)
        finished = Counter(group_of(r) for r in episodes if reached_target(r))
        groups: dict[tuple[str, ...], list[tuple[EpisodeResult, dict]]] = {}
        for r, t in loaded:
            groups.setdefault(group_of(r), []).append((r, t))
        keys = list(groups)
        if len(fields) < 3:
            self.notes.append(f"{circuit}: trajectories drawn per {', '.join(fields)} (every other condition "
                              f"overlaid), to keep to {MAX_SUBPLOTS} panels")
        if len(keys) > MAX_SUBPLOTS:
            self.notes.append(f"{circuit}: trajectories of {len(keys) - MAX_SUBPLOTS} of {len(keys)} brains not "
                              f"drawn (at most {MAX_SUBPLOTS} panels per figure)")
            keys = keys[:MAX_SUBPLOTS]

        # Colour data per episode (decimated): speed, and |cross-track error| from the circuit's centreline.
        data = {}
        for key in keys:
            for r, t in groups[key]:
                step = max(1, math.ceil(len(t["x_m"]) / MAX_PLOT_POINTS))
                x, y = t["x_m"][::step], t["y_m"][::step]
                speed = _speeds(t)[::step]
                xte = np.abs(track.lateral_m(x, y)) if track is not None else None
                data[r.key] = (x, y, speed, xte)
        all_xy = np.concatenate([np.column_stack(d[:2]) for d in data.values()])
        if track is not None:
            x0, x1, y0, y1 = track.extent
            x0, x1 = min(x0, all_xy[:, 0].min()), max(x1, all_xy[:, 0].max())
            y0, y1 = min(y0, all_xy[:, 1].min()), max(y1, all_xy[:, 1].max())
        else:
            pad = 5.0
            x0, x1 = all_xy[:, 0].min() - pad, all_xy[:, 0].max() + pad
            y0, y1 = all_xy[:, 1].min() - pad, all_xy[:, 1].max() + pad
        ratio = (y1 - y0) / max(x1 - x0, 1e-9)
        n = len(keys)
        ncols = min(n, 3 if n <= 9 else 4 if n <= 16 else 6)
        nrows = math.ceil(n / ncols)
        panel_w = 4.2 if ncols <= 3 else 3.4  # inches of one map
        map_h = min(max(panel_w * ratio, 1.2), 1.6 * panel_w)
        # A manual grid (shared axes, colour bar in its own column): constrained layout costs seconds per figure.
        left, right, top, bottom, wgap, hgap, bar_gap, bar_w = 0.65, 0.9, 0.85, 0.5, 0.25, 0.65, 0.3, 0.18
        fig_w = left + ncols * panel_w + (ncols - 1) * wgap + bar_gap + bar_w + right
        fig_h = top + nrows * map_h + (nrows - 1) * hgap + bottom

        plots = []
        for colour_by in ("speed", "xte"):
            if colour_by == "xte" and track is None:
                continue
            values = np.concatenate([d[2] if colour_by == "speed" else d[3] for d in data.values()])
            values = values[np.isfinite(values)]
            top_value = float(np.percentile(values, 99)) if len(values) else 1.0
            if colour_by == "xte":
                norm = Normalize(0.0, max(top_value, track.half_width_m))
                cmap, label = "magma_r", "|cross-track error| (m)"
            else:
                norm, cmap, label = Normalize(0.0, max(top_value, 1e-3)), "viridis", "speed (m/s)"
            fig = plt.figure(figsize=(fig_w, fig_h))
            grid = fig.add_gridspec(nrows, ncols, left=left / fig_w,
                                    right=(left + ncols * panel_w + (ncols - 1) * wgap) / fig_w,
                                    bottom=bottom / fig_h, top=1 - top / fig_h, wspace=wgap / panel_w,
                                    hspace=hgap / map_h)
            axes = grid.subplots(sharex=True, sharey=True, squeeze=False)
            for ax, key in zip(axes.flat, keys):
                if track is not None:
                    for edge in (track.left_edge, track.right_edge):
                        closed = np.vstack([edge, edge[:1]])
                        ax.plot(closed[:, 0], closed[:, 1], color="0.55", lw=0.8, zorder=1)
                    centre = np.vstack([track.points, track.points[:1]])
                    ax.plot(centre[:, 0], centre[:, 1], color="0.75", lw=0.6, ls=(0, (4, 3)), zorder=1)
                    sx, sy, heading = track.circuit.centreline.pose_at(0.0)
                    arrow = 0.06 * max(x1 - x0, y1 - y0)  # the driving direction at the start
                    ax.annotate("", xy=(sx + arrow * math.cos(heading), sy + arrow * math.sin(heading)),
                                xytext=(sx, sy), zorder=4,
                                arrowprops={"arrowstyle": "-|>", "color": "0.3", "lw": 1.0, "shrinkA": 0,
                                            "shrinkB": 0})
                    ax.plot([sx], [sy], marker="o", ms=5, mfc="white", mec="0.3", zorder=4)
                for r, _ in groups[key]:
                    x, y, speed, xte = data[r.key]
                    colours = speed if colour_by == "speed" else xte
                    points = np.column_stack([x, y]).reshape(-1, 1, 2)
                    segments = np.concatenate([points[:-1], points[1:]], axis=1)
                    lines = LineCollection(segments, cmap=cmap, norm=norm, linewidths=1.6, zorder=2)
                    lines.set_array(colours[1:])
                    ax.add_collection(lines)
                    if not reached_target(r):
                        ax.plot([x[-1]], [y[-1]], marker="X", ms=8, color="crimson", mec="white", mew=0.8, zorder=5)
                condition = " · ".join(key[1:]) or "all conditions"
                ax.set_title(f"{key[0]}\n{condition} ({finished[key]}/{totals[key]} finished)", fontsize=8.5)
                ax.set_xlim(x0, x1)
                ax.set_ylim(y0, y1)
                ax.set_aspect("equal", adjustable="box")
                ax.tick_params(labelsize=7)
                ax.xaxis.set_major_locator(MaxNLocator(5))
                ax.yaxis.set_major_locator(MaxNLocator(5))
                ax.grid(True, color="0.93", lw=0.5)
            for index, ax in enumerate(axes.flat):
                if index >= n:
                    ax.set_visible(False)
                    continue
                ax.tick_params(labelleft=index % ncols == 0, labelbottom=index + ncols >= n)
                if index % ncols == 0:
                    ax.set_ylabel("y (m)", fontsize=8)
                if index + ncols >= n:
                    ax.set_xlabel("x (m)", fontsize=8)
            bar_left = (fig_w - right - bar_w) / fig_w
            bar_height = min(0.8, 4.0 / fig_h)
            colour_axis = fig.add_axes((bar_left, 0.5 - bar_height / 2, bar_w / fig_w, bar_height))
            fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap=cmap), cax=colour_axis, label=label)
            title = "speed" if colour_by == "speed" else "cross-track error"
            fig.suptitle(f"{circuit}: trajectories coloured by {title}", fontsize=11, y=1 - 0.12 / fig_h,
                         va="top")
            path = self._save(fig, f"trajectories_{colour_by}_{_slug(circuit)}.png")
            plots.append(Plot(path, f"{circuit}, coloured by {title}."))
        return plots

    def _box_plots(self) -> Plot | None:
        import matplotlib.pyplot as plt

        episodes, _ = self.baseline()
        scored = _scored(episodes)
        circuits = [c for c in self.circuits if any(r.circuit == c for r in scored)]
        if not circuits:
            return None
        if len(circuits) > MAX_BOX_CIRCUITS:
            self.notes.append(f"box plots: {len(circuits) - MAX_BOX_CIRCUITS} circuit(s) left out")
            circuits = circuits[:MAX_BOX_CIRCUITS]
        colours = _brain_colours(self.brains)
        fig, axes = plt.subplots(2, len(circuits), figsize=(max(3.8, 0.75 * len(self.brains) + 1.8) * len(circuits),
                                                            7.0), squeeze=False, layout="constrained")
        rng = np.random.default_rng(0)
        for column, circuit in enumerate(circuits):
            for row, (metric, label) in enumerate(((lap_seconds, "lap time (s)"),
                                                   (lambda r: r.score.metrics.position_deviation_mae,
                                                    "position deviation (BM, mean 1000^d)"))):
                ax = axes[row][column]
                series = [[v for v in (metric(r) for r in scored if r.brain == b and r.circuit == circuit)
                           if v is not None] for b in self.brains]
                positions = [i + 1 for i, s in enumerate(series) if s]
                if positions:
                    box = ax.boxplot([s for s in series if s], positions=positions, widths=0.55,
                                     patch_artist=True, showfliers=False, medianprops={"color": "black"})
                    for patch, position in zip(box["boxes"], positions):
                        patch.set_facecolor(colours[self.brains[position - 1]])
                        patch.set_alpha(0.35)
                    for position in positions:
                        values = series[position - 1]
                        jitter = rng.uniform(-0.12, 0.12, len(values))
                        ax.scatter(np.full(len(values), position) + jitter, values, s=16, zorder=3,
                                   color=colours[self.brains[position - 1]], edgecolor="white", linewidth=0.5)
                    flat = [v for s in series for v in s]
                    if row == 1 and min(flat) > 0 and max(flat) / min(flat) > 100:
                        ax.set_yscale("log")
                for i, s in enumerate(series):
                    if not s:
                        ax.text(i + 1, 0.5, "no lap" if row == 0 else "–", transform=ax.get_xaxis_transform(),
                                ha="center", va="center", color="0.5", fontsize=8)
                ax.set_xticks(range(1, len(self.brains) + 1), self.brains, rotation=20 if len(self.brains) > 3 else 0,
                              ha="right" if len(self.brains) > 3 else "center", fontsize=8)
                ax.set_xlim(0.4, len(self.brains) + 0.6)
                ax.set_ylabel(label, fontsize=8.5)
                ax.tick_params(axis="y", labelsize=8)
                ax.grid(True, axis="y", color="0.92")
                if row == 0:
                    ax.set_title(circuit, fontsize=10)
        fig.suptitle("Baseline condition, per brain: lap time (episodes that completed the lap) and BM position "
                     "deviation", fontsize=10.5)
        path = self._save(fig, "boxplots.png")
        return Plot(path, "Box plots over the repetitions of the baseline condition (dots: single episodes). "
                          "Position deviation is BM's mean of 1000^d, not metres (1 = on the reference path).")

    def _progress_plot(self) -> Plot | None:
        import matplotlib.pyplot as plt
        from matplotlib.lines import Line2D

        curves: dict[str, list[tuple[EpisodeResult, np.ndarray, np.ndarray]]] = {}
        for r in self.results:
            t = self.trajectory(r)
            if t is None:
                continue
            time_s, progress = t["live_sim_time_s"], t["live_progress_laps"]
            if len(time_s) != len(progress) or len(time_s) < 2:
                time_s, progress = self._progress_from_poses(r, t)
            if len(time_s) >= 2:
                curves.setdefault(r.circuit, []).append((r, time_s, progress))
        circuits = [c for c in self.circuits if c in curves]
        if not circuits:
            return None
        if len(circuits) > MAX_PROGRESS_CIRCUITS:
            self.notes.append(f"progress plot: {len(circuits) - MAX_PROGRESS_CIRCUITS} circuit(s) left out")
            circuits = circuits[:MAX_PROGRESS_CIRCUITS]
        colours = _brain_colours(self.brains)
        ncols = min(len(circuits), 3)
        nrows = math.ceil(len(circuits) / ncols)
        fig, axes = plt.subplots(nrows, ncols, figsize=(5.2 * ncols, 3.6 * nrows + 0.6), squeeze=False,
                                 layout="constrained")
        alpha = 0.85 if max(len(v) for v in curves.values()) <= 20 else 0.45
        for ax, circuit in zip(axes.flat, circuits):
            targets = set()
            for r, time_s, progress in curves[circuit]:
                ax.plot(time_s, progress, color=colours[r.brain], lw=1.2, alpha=alpha)
                targets.add(r.spec.laps)
                if not reached_target(r):
                    ax.plot([time_s[-1]], [progress[-1]], marker="X", ms=7, color=colours[r.brain], mec="black",
                            mew=0.6, zorder=4)
            for target in targets:
                ax.axhline(target, color="0.6", lw=0.8, ls="--")
            ax.set_title(circuit, fontsize=10)
            ax.set_xlabel("simulated time (s)", fontsize=8.5)
            ax.set_ylabel("progress (laps)", fontsize=8.5)
            ax.set_xlim(left=0)
            ax.grid(True, color="0.92")
            ax.tick_params(labelsize=8)
        for ax in list(axes.flat)[len(circuits):]:
            ax.set_visible(False)
        handles = [Line2D([], [], color=colours[b], lw=2, label=b) for b in self.brains]
        handles.append(Line2D([], [], color="0.4", marker="X", ls="", label="ended short of its target"))
        fig.legend(handles=handles, loc="outside lower center", ncols=min(len(handles), 6), fontsize=8.5,
                   frameon=False)
        fig.suptitle("Lap progress over simulated time, one line per episode", fontsize=10.5)
        path = self._save(fig, "progress.png")
        return Plot(path, "Arc-length progress in laps (live scorer samples) against simulated time; dashed: the lap "
                          "target; ✕: an episode that ended before it.")

    def _progress_from_poses(self, r: EpisodeResult, t: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Progress from the poses when the live samples are missing: unwrapped centreline arc length."""
        track = self.track(r.circuit)
        stamps = t["stamp_s"]
        if track is None or len(stamps) != len(t["x_m"]) or len(stamps) < 2:
            return np.zeros(0), np.zeros(0)
        _, nearest = track._tree.query(np.column_stack([t["x_m"], t["y_m"]]))
        centreline = track.circuit.centreline
        s = centreline.s_m[nearest]
        ds = centreline.wrap_ds(np.diff(s))
        progress = np.concatenate([[0.0], np.cumsum(ds)]) / centreline.length_m
        return stamps - stamps[0], progress

    # -- assembling --

    def sections(self) -> list[Section]:
        sections = [self.header(), *self.paper_sections, self.main_table(), self.generalisation(), self.robustness()]
        for optional in (self.internal_metrics(), self.switches()):
            if optional is not None:
                sections.append(optional)
        sections.append(self.failures())
        sections.extend(self.plot_sections())
        if self.notes:
            sections.append(Section("Notes", list(self.notes)))
        return sections


_CELL_LEGEND = (f"A cell: the mean first-lap time (s) when every repetition reached its lap target; otherwise "
                f"{FAIL_MARK} with the most common way the others ended (end reason, or the stack failure's kind) and "
                "how many of the cell's episodes ended that way.")


def _opt(value: Any, digits: int) -> str:
    if value is None:
        return "–"
    try:
        return _fmt_number(float(value), digits)
    except (TypeError, ValueError):
        return str(value)


def _brief(items: Sequence[Any], limit: int = 160) -> str:
    import msgspec

    parts = []
    for item in items:
        if isinstance(item, msgspec.Struct):
            item = msgspec.to_builtins(item)
        if isinstance(item, dict):
            parts.append(" ".join(f"{k}={_short(v)}" for k, v in item.items() if k != "type"))
        else:
            parts.append(_short(item))
    text = "; ".join(parts)
    return text if len(text) <= limit else text[:limit - 1] + "…"


def _short(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.3g}"
    return str(value)


def _duration(seconds: float) -> str:
    seconds = max(0.0, float(seconds))
    if seconds < 60:
        return f"{seconds:.1f} s"
    minutes, secs = divmod(round(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d} min"


def _date(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, (int, float)):
        return datetime.fromtimestamp(float(value)).strftime("%Y-%m-%d %H:%M:%S")
    return str(value)


def _slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("_") or "circuit"


def _brain_colours(brains: Sequence[str]) -> dict[str, Any]:
    import matplotlib

    palette = matplotlib.colormaps["tab10" if len(brains) <= 10 else "tab20"]
    return {brain: palette(i % palette.N) for i, brain in enumerate(brains)}


# -- rendering --------------------------------------------------------------------------------------------------------


def _md_cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def render_markdown(sections: Sequence[Section], output: Path) -> str:
    lines: list[str] = []
    for level, section in enumerate(sections):
        lines += [f"{'#' if level == 0 else '##'} {section.title}", ""]
        for block in section.blocks:
            if isinstance(block, Table):
                if block.caption:
                    lines += [f"*{block.caption}*", ""]
                align = block.numeric or [False] * len(block.columns)
                lines.append("| " + " | ".join(_md_cell(c) for c in block.columns) + " |")
                lines.append("|" + "|".join("---:" if a else ":---" for a in align) + "|")
                lines += ["| " + " | ".join(_md_cell(c) for c in row) + " |" for row in block.rows]
                lines.append("")
            elif isinstance(block, Plot):
                relative = block.path.relative_to(output).as_posix()
                lines += [f"![{block.path.stem}]({relative})", "", f"*{block.caption}*", ""]
            else:
                lines += [block, ""]
    return "\n".join(lines)


_CSS = """
body { font-family: -apple-system, "Segoe UI", Roboto, "Helvetica Neue", Arial, sans-serif; color: #222;
       max-width: 1400px; margin: 24px auto; padding: 0 20px; line-height: 1.45; font-size: 14px; }
h1 { font-size: 22px; border-bottom: 2px solid #345; padding-bottom: 6px; }
h2 { font-size: 17px; margin-top: 32px; color: #234; border-bottom: 1px solid #ccd; padding-bottom: 3px; }
table { border-collapse: collapse; margin: 10px 0 6px; font-size: 13px; }
th, td { border: 1px solid #d4d8de; padding: 4px 9px; vertical-align: top; }
th { background: #eef1f5; text-align: left; font-weight: 600; }
tr:nth-child(even) td { background: #f8f9fb; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
td.fail { color: #b3261e; font-weight: 600; }
caption { caption-side: top; text-align: left; font-style: italic; color: #555; padding-bottom: 3px; }
table.facts th { display: none; }
table.facts td:first-child { font-weight: 600; background: #eef1f5; }
p.note { color: #555; font-size: 12.5px; max-width: 1000px; }
code { background: #f1f3f5; padding: 0 3px; border-radius: 3px; font-size: 12px; }
figure { margin: 14px 0 22px; }
figure img { max-width: 100%; border: 1px solid #e1e4e8; }
figcaption { color: #555; font-size: 12.5px; max-width: 1000px; }
"""


def _inline(text: str) -> str:
    """Escape, then turn `code` spans into <code>."""
    return re.sub(r"`([^`]*)`", r"<code>\1</code>", html.escape(text))


def render_html(sections: Sequence[Section], title: str) -> str:
    out = ["<!DOCTYPE html>", '<html lang="en">', "<head>", '<meta charset="utf-8">',
           f"<title>{html.escape(title)}</title>", f"<style>{_CSS}</style>", "</head>", "<body>"]
    for level, section in enumerate(sections):
        tag = "h1" if level == 0 else "h2"
        out.append(f"<{tag}>{html.escape(section.title)}</{tag}>")
        for block in section.blocks:
            if isinstance(block, Table):
                facts = all(not c for c in block.columns)
                out.append('<table class="facts">' if facts else "<table>")
                if block.caption:
                    out.append(f"<caption>{html.escape(block.caption)}</caption>")
                if not facts:
                    out.append("<thead><tr>" + "".join(f"<th>{html.escape(c)}</th>" for c in block.columns)
                               + "</tr></thead>")
                out.append("<tbody>")
                numeric = block.numeric or [False] * len(block.columns)
                for row in block.rows:
                    cells = []
                    for value, is_number in zip(row, numeric):
                        classes = (["num"] if is_number else []) + (["fail"] if value.startswith(FAIL_MARK) else [])
                        attribute = f' class="{" ".join(classes)}"' if classes else ""
                        cells.append(f"<td{attribute}>{_inline(value)}</td>")
                    out.append("<tr>" + "".join(cells) + "</tr>")
                out.append("</tbody></table>")
            elif isinstance(block, Plot):
                encoded = base64.b64encode(block.path.read_bytes()).decode("ascii")
                out.append(f'<figure><img alt="{html.escape(block.path.name)}" '
                           f'src="data:image/png;base64,{encoded}">'
                           f"<figcaption>{_inline(block.caption)}</figcaption></figure>")
            else:
                out.append(f'<p class="note">{_inline(block)}</p>')
    out += ["</body>", "</html>"]
    return "\n".join(out)


def episode_rows(results: Sequence[EpisodeResult]) -> list[dict[str, Any]]:
    """One flat dict per episode: conditions, status, timings, every scalar of EpisodeMetrics, files."""
    rows = []
    for r in results:
        row: dict[str, Any] = {
            "key": r.key, "brain": r.brain, "circuit": r.circuit, "variation": r.variation,
            "perturbation": r.perturbation, "repetition": r.repetition, "seed": r.spec.seed,
            "laps_target": r.spec.laps, "status": r.status, "reason": r.reason or "", "failure": r.failure or "",
            "wall_s": round(r.wall_s, 3),
        }
        metrics = r.score.metrics if r.score is not None else None
        for name in METRIC_FIELDS:
            value = getattr(metrics, name) if metrics is not None else None
            if name == "lap_times_s":
                value = ";".join(repr(float(v)) for v in value) if value else ""
            row[name] = "" if value is None else value
        row.update({"recording": r.recording or "", "trajectory": r.trajectory or "", "logs": r.logs or ""})
        rows.append(row)
    return rows


def _write_csv(rows: list[dict[str, Any]], path: Path) -> None:
    with open(path, "w", newline="", encoding="utf-8") as file:
        writer = csv.DictWriter(file, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def _write_parquet(rows: list[dict[str, Any]], path: Path) -> Path | None:
    if importlib.util.find_spec("pyarrow") is None:
        return None
    import pyarrow as pa
    import pyarrow.parquet as pq

    # Empty strings of unscored episodes become nulls, so numeric columns keep a numeric type.
    columns = {name: [None if row[name] == "" else row[name] for row in rows] for name in rows[0]}
    pq.write_table(pa.table(columns), path)
    return path


def write_report(folder: Path, *, output: Path | None = None) -> ReportFiles:
    """Read ``folder/results.sqlite`` and write the report into ``output`` (default: ``folder``).

    Raises :class:`ReportError` (no folder, no database, no episode) or :class:`ResultsError` (a damaged
    database), one line each naming the path.
    """
    folder = Path(folder)
    output = Path(output) if output is not None else folder
    report = _Report(folder, output)
    output.mkdir(parents=True, exist_ok=True)
    sections = report.sections()
    markdown_path, html_path, csv_path = output / MARKDOWN_FILE, output / HTML_FILE, output / CSV_FILE
    markdown_path.write_text(render_markdown(sections, output), encoding="utf-8")
    html_path.write_text(render_html(sections, f"drivebench report: {report.name}"), encoding="utf-8")
    rows = episode_rows(report.results)
    _write_csv(rows, csv_path)
    parquet = _write_parquet(rows, output / PARQUET_FILE)
    paper = output / PAPER_MARKDOWN if report.is_paper else None
    if paper is not None:
        paper.write_text(render_markdown(report.paper_sections, output), encoding="utf-8")
    return ReportFiles(html=html_path, markdown=markdown_path, csv=csv_path, plots=tuple(report.plots),
                       parquet=parquet, paper=paper)


# -- command line -----------------------------------------------------------------------------------------------------


def add_report_command(commands: argparse._SubParsersAction) -> None:
    """``drivebench report DIR [-o FOLDER]``."""
    parser = commands.add_parser(
        "report", help="tables and plots of a matrix's results (HTML, Markdown, CSV)",
        description="Read DIR/results.sqlite (written by `drivebench matrix`) and write report.html (self-contained), "
                    "report.md, episodes.csv and plots/*.png: the paper's main table per brain and circuit, "
                    "generalisation and robustness grids, internal metrics, failures, trajectories on the circuit.")
    parser.add_argument("dir", type=Path, metavar="DIR", help="the matrix's output folder")
    parser.add_argument("-o", "--output", type=Path, metavar="FOLDER",
                        help="write the report here instead of into DIR")


def run_report(args: argparse.Namespace) -> int:
    """Run ``drivebench report``: 0 with the written paths on stderr; 2 with one error line on stderr."""
    try:
        files = write_report(args.dir, output=getattr(args, "output", None))
    except (ReportError, ResultsError) as error:
        print(f"drivebench: error: {error}", file=sys.stderr)
        return 2
    written = [files.html, files.markdown, files.csv, *([files.parquet] if files.parquet else [])]
    for path in written:
        print(f"wrote {path}", file=sys.stderr)
    if files.plots:
        print(f"wrote {len(files.plots)} plot(s) in {files.plots[0].parent}", file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m orchestrator.matrix_report DIR [-o FOLDER]``: the same as ``drivebench report``."""
    parser = argparse.ArgumentParser(prog="drivebench")
    add_report_command(parser.add_subparsers(dest="command", required=True))
    argv = list(sys.argv[1:] if argv is None else argv)
    return run_report(parser.parse_args(argv if argv[:1] == ["report"] else ["report", *argv]))


if __name__ == "__main__":
    sys.exit(main())
