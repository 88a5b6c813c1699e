"""The report's plots (matplotlib, drawn into ``plots/*.png``): trajectories on the circuit coloured by speed and by
cross-track error, lap-time and position-deviation box plots per brain, lap progress over simulated time.

Separate from the report's tables (:mod:`orchestrator.report.matrix`) because drawing is most of the code and the only
part that needs matplotlib (imported inside the functions, so that reading this module costs nothing). The plots are
functions of one :class:`~orchestrator.report.data.ReportData`: they read its results and cached trajectories, and
append the files they write to its ``plots`` and what they could not draw to its ``notes``.
"""

from __future__ import annotations

import math
import textwrap
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from orchestrator.matrix.results import EpisodeResult
from orchestrator.report.cells import lap_seconds, reached_target, scored_only, slug
from orchestrator.report.data import ReportData
from orchestrator.report.document import Plot, Section
from orchestrator.report.trajectories import speeds_mps

MAX_SUBPLOTS = 24  # trajectory subplots per figure (one figure per circuit and colouring)
MAX_PLOT_POINTS = 1200  # poses drawn per episode (decimated beyond: ~0.4 m apart on a 450 m lap)
MAX_BOX_CIRCUITS = 8  # circuits (columns) in the box-plot figure
MAX_PROGRESS_CIRCUITS = 12  # circuits (subplots) in the progress figure
STALE_PLOTS = ("trajectories_*.png", "boxplots.png", "progress.png")  # what the report writes into plots/


def plot_sections(report: ReportData) -> list[Section]:
    import matplotlib

    matplotlib.use("Agg", force=True)
    report.plots_dir.mkdir(parents=True, exist_ok=True)
    for pattern in STALE_PLOTS:  # a previous report's plots (a circuit since dropped) would mislead
        for stale in report.plots_dir.glob(pattern):
            stale.unlink(missing_ok=True)
    sections = []
    trajectories = Section(
        "Trajectories",
        [
            "Every episode's path over the road (grey: road edges, dashed: centre line, ○ and arrow: start line "
            "and driving direction, small ○: where an episode started along the circuit), one panel per brain "
            "and condition with the repetitions overlaid; ✕ where an "
            "episode ended short of its lap target; (k/n finished): episodes of the panel that reached their lap "
            "target. Colours: "
            "speed from the poses, and |cross-track error| from projecting every pose onto the centre line."
        ],
    )
    for circuit in report.circuits:
        for plot in _trajectory_figures(report, circuit):
            trajectories.blocks.append(plot)
    if not any(isinstance(b, Plot) for b in trajectories.blocks):
        trajectories.blocks.append("No trajectory file could be read.")
    sections.append(trajectories)
    distributions = Section("Distributions")
    for figure in (_box_plots(report), _progress_plot(report)):
        if figure is not None:
            distributions.blocks.append(figure)
    if distributions.blocks:
        sections.append(distributions)
    return sections


def _save(report: ReportData, fig, name: str) -> Path:
    import matplotlib.pyplot as plt

    path = report.plots_dir / name
    fig.savefig(path, dpi=130)  # figures flow side by side across the page (document.py), at their own size
    plt.close(fig)
    report.plots.append(path)
    return path


def _trajectory_figures(report: ReportData, circuit: str) -> list[Plot]:
    episodes = [r for r in report.results if r.circuit == circuit]
    loaded = _readable_trajectories(report, circuit, episodes)
    if not loaded:
        return []
    track = report.track(circuit)
    panels = _trajectory_panels(report, circuit, episodes, loaded)
    data = _colour_data(panels, track)
    layout = _map_layout(data, track, panels=len(panels.keys))
    plots = []
    for colour_by in ("speed", "xte"):
        if colour_by == "xte" and track is None:
            continue
        plots.append(
            _trajectory_figure(report, circuit, colour_by, panels=panels, data=data, track=track, layout=layout)
        )
    return plots


def _readable_trajectories(
    report: ReportData, circuit: str, episodes: list[EpisodeResult]
) -> list[tuple[EpisodeResult, dict[str, np.ndarray]]]:
    """The episodes of ``circuit`` whose trajectory file reads with two poses or more; the others in the notes."""
    loaded = [(r, report.trajectory(r)) for r in episodes]
    unreadable = [r for r, t in loaded if r.trajectory and (t is None or len(t["x_m"]) < 2)]
    unrecorded = [r for r in episodes if r.status == "done" and not r.trajectory]
    if unreadable:
        report.notes.append(
            f"{circuit}: {len(unreadable)} episode(s) have no readable trajectory file (missing, "
            f"damaged or empty), e.g. `{unreadable[0].trajectory}`"
        )
    if unrecorded:
        report.notes.append(f"{circuit}: {len(unrecorded)} episode(s) ran without a trajectory file")
    return [(r, t) for r, t in loaded if t is not None and len(t["x_m"]) >= 2]


def _trajectory_panels(
    report: ReportData, circuit: str, episodes: list[EpisodeResult], loaded: list[tuple[EpisodeResult, dict]]
) -> _Panels:
    """The episodes grouped into panels, at most ``MAX_SUBPLOTS`` (what had to be merged or left out: notes)."""
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
        report.notes.append(
            f"{circuit}: trajectories drawn per {', '.join(fields)} (every other condition "
            f"overlaid), to keep to {MAX_SUBPLOTS} panels"
        )
    if len(keys) > MAX_SUBPLOTS:
        report.notes.append(
            f"{circuit}: trajectories of {len(keys) - MAX_SUBPLOTS} of {len(keys)} brains not "
            f"drawn (at most {MAX_SUBPLOTS} panels per figure)"
        )
        keys = keys[:MAX_SUBPLOTS]
    return _Panels(keys=keys, groups=groups, totals=totals, finished=finished)


def _trajectory_figure(
    report: ReportData, circuit: str, colour_by: str, *, panels: _Panels, data: dict, track, layout: _MapLayout
) -> Plot:
    """One figure of ``circuit``'s panels, coloured by speed or by |cross-track error| ("xte")."""
    import matplotlib.pyplot as plt

    norm, cmap, label = _colour_scale(colour_by, data=data)
    fig = plt.figure(figsize=(layout.fig_w, layout.fig_h))
    grid = fig.add_gridspec(
        layout.nrows,
        layout.ncols,
        left=layout.left / layout.fig_w,
        right=(layout.left + layout.ncols * layout.panel_w + (layout.ncols - 1) * layout.wgap) / layout.fig_w,
        bottom=layout.bottom / layout.fig_h,
        top=1 - layout.top / layout.fig_h,
        wspace=layout.wgap / layout.panel_w,
        hspace=layout.hgap / layout.map_h,
    )
    axes = grid.subplots(sharex=True, sharey=True, squeeze=False)
    for ax, key in zip(axes.flat, panels.keys):
        if track is not None:
            directions = sorted({r.spec.direction for r, _ in panels.groups[key]})
            _draw_track(ax, track, layout=layout, directions=directions or ["forward"])
        for r, _ in panels.groups[key]:
            _draw_episode(ax, r, data[r.key], colour_by=colour_by, cmap=cmap, norm=norm)
        condition = " · ".join(key[1:]) or "all conditions"
        ax.set_title(f"{key[0]}\n{condition} ({panels.finished[key]}/{panels.totals[key]} finished)", fontsize=8.5)
        _frame_map(ax, layout)
    _label_axes(axes, panels=len(panels.keys), ncols=layout.ncols)
    bar_left = (layout.fig_w - layout.right - layout.bar_w) / layout.fig_w
    bar_height = min(0.8, 4.0 / layout.fig_h)
    colour_axis = fig.add_axes((bar_left, 0.5 - bar_height / 2, layout.bar_w / layout.fig_w, bar_height))
    fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap=cmap), cax=colour_axis, label=label)
    title = "speed" if colour_by == "speed" else "cross-track error"
    fig.suptitle(f"{circuit}: trajectories coloured by {title}", fontsize=11, y=1 - 0.12 / layout.fig_h, va="top")
    path = _save(report, fig, f"trajectories_{colour_by}_{slug(circuit)}.png")
    return Plot(path, f"{circuit}, coloured by {title}.")


def _box_plots(report: ReportData) -> Plot | None:
    import matplotlib.pyplot as plt

    episodes, _ = report.baseline()
    scored = scored_only(episodes)
    circuits = [c for c in report.circuits if any(r.circuit == c for r in scored)]
    if not circuits:
        return None
    circuits = _at_most(report, circuits, MAX_BOX_CIRCUITS, what="box plots")
    colours = _brain_colours(report.brains)
    fig, axes = plt.subplots(
        2,
        len(circuits),
        figsize=(max(3.8, 0.75 * len(report.brains) + 1.8) * len(circuits), 7.0),
        squeeze=False,
        layout="constrained",
    )
    rng = np.random.default_rng(0)
    for column, circuit in enumerate(circuits):
        for row, (metric, label) in enumerate(
            (
                (lap_seconds, "BM lap seconds (s)"),
                (lambda r: r.score.metrics.position_deviation_mae, "position deviation (BM, mean 1000^d)"),
            )
        ):
            ax = axes[row][column]
            series = [
                [v for v in (metric(r) for r in scored if r.brain == b and r.circuit == circuit) if v is not None]
                for b in report.brains
            ]
            _draw_boxes(ax, series, brains=report.brains, colours=colours, rng=rng, log_scale=row == 1)
            _label_boxes(ax, series, brains=report.brains, empty="no lap" if row == 0 else "–")
            ax.set_ylabel(label, fontsize=8.5)
            if row == 0:
                ax.set_title(circuit, fontsize=10)
    title = "Baseline condition, per brain: BM lap seconds (episodes that completed the lap) and BM position deviation"
    # Wrapped to the figure's width (about 11 characters an inch at 10.5 pt): one circuit's figure is narrow.
    fig.suptitle(textwrap.fill(title, width=int(fig.get_figwidth() * 11)), fontsize=10.5)
    path = _save(report, fig, "boxplots.png")
    return Plot(
        path,
        "Box plots over the repetitions of the baseline condition (dots: single episodes). "
        "Position deviation is BM's mean of 1000^d, not metres (1 = on the reference path).",
    )


def _progress_plot(report: ReportData) -> Plot | None:
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    curves: dict[str, list[tuple[EpisodeResult, np.ndarray, np.ndarray]]] = {}
    for r in report.results:
        t = report.trajectory(r)
        if t is None:
            continue
        time_s, progress = t["live_sim_time_s"], t["live_progress_laps"]
        if len(time_s) != len(progress) or len(time_s) < 2:
            time_s, progress = _progress_from_poses(report, r, t)
        if len(time_s) >= 2:
            curves.setdefault(r.circuit, []).append((r, *_to_the_finish(r, time_s, progress)))
    circuits = [c for c in report.circuits if c in curves]
    if not circuits:
        return None
    circuits = _at_most(report, circuits, MAX_PROGRESS_CIRCUITS, what="progress plot")
    colours = _brain_colours(report.brains)
    ncols = min(len(circuits), 3)
    nrows = math.ceil(len(circuits) / ncols)
    fig, axes = plt.subplots(
        nrows, ncols, figsize=(5.2 * ncols, 3.6 * nrows + 0.6), squeeze=False, layout="constrained"
    )
    alpha = 0.85 if max(len(v) for v in curves.values()) <= 20 else 0.45
    for ax, circuit in zip(axes.flat, circuits):
        targets = set()
        for r, time_s, progress in curves[circuit]:
            ax.plot(time_s, progress, color=colours[r.brain], lw=1.2, alpha=alpha)
            targets.add(r.spec.laps)
            if not reached_target(r):
                ax.plot(
                    [time_s[-1]],
                    [progress[-1]],
                    marker="X",
                    ms=7,
                    color=colours[r.brain],
                    mec="black",
                    mew=0.6,
                    zorder=4,
                )
        for target in targets:
            ax.axhline(target, color="0.6", lw=0.8, ls="--")
        ax.set_title(circuit, fontsize=10)
        ax.set_xlabel("simulated time (s)", fontsize=8.5)
        ax.set_ylabel("progress (laps)", fontsize=8.5)
        ax.set_xlim(left=0)
        ax.grid(True, color="0.92")
        ax.tick_params(labelsize=8)
    for ax in list(axes.flat)[len(circuits) :]:
        ax.set_visible(False)
    handles = [Line2D([], [], color=colours[b], lw=2, label=b) for b in report.brains]
    handles.append(Line2D([], [], color="0.4", marker="X", ls="", label="ended short of its target"))
    fig.legend(handles=handles, loc="outside lower center", ncols=min(len(handles), 6), fontsize=8.5, frameon=False)
    fig.suptitle("Lap progress over simulated time, one line per episode", fontsize=10.5)
    path = _save(report, fig, "progress.png")
    return Plot(
        path,
        "Arc-length progress in laps (live scorer samples) against simulated time; dashed: the lap "
        "target; ✕: an episode that ended before it.",
    )


def _at_most(report: ReportData, circuits: list[str], limit: int, *, what: str) -> list[str]:
    """The first ``limit`` circuits; a note in the report says how many a figure left out."""
    if len(circuits) > limit:
        report.notes.append(f"{what}: {len(circuits) - limit} circuit(s) left out")
    return circuits[:limit]


def _progress_from_poses(
    report: ReportData, r: EpisodeResult, t: dict[str, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Progress from the poses when the live samples are missing: unwrapped centreline arc length."""
    track = report.track(r.circuit)
    stamps = t["stamp_s"]
    if track is None or len(stamps) != len(t["x_m"]) or len(stamps) < 2:
        return np.zeros(0), np.zeros(0)
    centreline = track.circuit.centreline
    s, _ = centreline.project_many(t["x_m"], t["y_m"])
    ds = centreline.wrap_ds(np.diff(s))
    progress = np.concatenate([[0.0], np.cumsum(ds)]) / centreline.length_m
    return stamps - stamps[0], progress


def _to_the_finish(r: EpisodeResult, time_s: np.ndarray, progress: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The curve with its last point at the lap target when the episode reached it: the live samples come a few
    times a second, so the last one falls short of the line (0.95-0.97 laps) although the lap was completed; the
    finish is at the sum of the timed laps."""
    if not reached_target(r) or r.score is None:
        return time_s, progress
    laps = list(r.score.metrics.lap_times_s)[: r.spec.laps]
    if len(laps) < r.spec.laps:
        return time_s, progress
    finish_s = float(sum(laps))
    keep = time_s < finish_s
    return np.append(time_s[keep], finish_s), np.append(progress[keep], float(r.spec.laps))


def _brain_colours(brains: Sequence[str]) -> dict[str, Any]:
    import matplotlib

    palette = matplotlib.colormaps["tab10" if len(brains) <= 10 else "tab20"]
    return {brain: palette(i % palette.N) for i, brain in enumerate(brains)}


@dataclass(frozen=True)
class _Panels:
    """A circuit's trajectory panels: their keys (brain, then the condition fields grouped on), the episodes of
    each with their trajectories, and per key how many episodes there were and how many reached their target."""

    keys: list[tuple[str, ...]]
    groups: dict[tuple[str, ...], list[tuple[EpisodeResult, dict]]]
    totals: Counter
    finished: Counter


@dataclass(frozen=True)
class _MapLayout:
    """A trajectory figure's geometry: the map's extent (m) and the grid of panels (inches)."""

    x0: float
    x1: float
    y0: float
    y1: float
    ncols: int
    nrows: int
    panel_w: float
    map_h: float
    left: float
    right: float
    top: float
    bottom: float
    wgap: float
    hgap: float
    bar_gap: float
    bar_w: float
    fig_w: float
    fig_h: float


def _colour_data(panels: _Panels, track) -> dict:
    """Colour data per episode (decimated): x, y, speed, and |cross-track error| from the circuit's centreline."""
    data = {}
    for key in panels.keys:
        for r, t in panels.groups[key]:
            step = max(1, math.ceil(len(t["x_m"]) / MAX_PLOT_POINTS))
            x, y = t["x_m"][::step], t["y_m"][::step]
            speed = speeds_mps(t)[::step]
            xte = np.abs(track.lateral_m(x, y)) if track is not None else None
            data[r.key] = (x, y, speed, xte)
    return data


def _map_layout(data: dict, track, *, panels: int) -> _MapLayout:
    """The extent (the road and every path) and a grid of ``panels`` maps with a colour bar column."""
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
    n = panels
    ncols = min(n, 3 if n <= 9 else 4 if n <= 16 else 6)
    nrows = math.ceil(n / ncols)
    panel_w = 4.2 if ncols <= 3 else 3.4  # inches of one map
    map_h = min(max(panel_w * ratio, 1.2), 1.6 * panel_w)
    # A manual grid (shared axes, colour bar in its own column): constrained layout costs seconds per figure.
    left, right, top, bottom, wgap, hgap, bar_gap, bar_w = 0.65, 0.9, 0.85, 0.5, 0.25, 0.65, 0.3, 0.18
    return _MapLayout(
        x0=x0,
        x1=x1,
        y0=y0,
        y1=y1,
        ncols=ncols,
        nrows=nrows,
        panel_w=panel_w,
        map_h=map_h,
        left=left,
        right=right,
        top=top,
        bottom=bottom,
        wgap=wgap,
        hgap=hgap,
        bar_gap=bar_gap,
        bar_w=bar_w,
        fig_w=left + ncols * panel_w + (ncols - 1) * wgap + bar_gap + bar_w + right,
        fig_h=top + nrows * map_h + (nrows - 1) * hgap + bottom,
    )


MIN_XTE_SCALE_M = 0.01  # a colour bar of at least 1 cm: paths that never leave the line are not a range of zero


def _colour_scale(colour_by: str, *, data: dict):
    """Norm, colour map and label of one colouring, up to the 99th percentile (one outlier does not wash it out)."""
    from matplotlib.colors import Normalize

    values = np.concatenate([d[2] if colour_by == "speed" else d[3] for d in data.values()])
    values = values[np.isfinite(values)]
    top_value = float(np.percentile(values, 99)) if len(values) else 1.0
    if colour_by == "xte":  # the errors' own range (cm for a good brain), not the road's half width (1.5 m)
        return Normalize(0.0, max(top_value, MIN_XTE_SCALE_M)), "magma_r", "|cross-track error| (m, to the 99th pct)"
    return Normalize(0.0, max(top_value, 1e-3)), "viridis", "speed (m/s)"


def _draw_track(ax, track, *, layout: _MapLayout, directions: Sequence[str] = ("forward",)) -> None:
    """Road edges, the dashed centre line, and the start with an arrow in each driving direction of the panel's
    episodes (``EpisodeSpec.direction``: a reverse episode leaves the same start line the other way round)."""
    for edge in (track.left_edge, track.right_edge):
        closed = np.vstack([edge, edge[:1]])
        ax.plot(closed[:, 0], closed[:, 1], color="0.55", lw=0.8, zorder=1)
    centre = np.vstack([track.points, track.points[:1]])
    ax.plot(centre[:, 0], centre[:, 1], color="0.75", lw=0.6, ls=(0, (4, 3)), zorder=1)
    arrow = 0.06 * max(layout.x1 - layout.x0, layout.y1 - layout.y0)
    for direction in dict.fromkeys(directions):
        circuit = track.circuit.reversed() if direction == "reverse" else track.circuit
        sx, sy, heading = circuit.centreline.pose_at(0.0)  # the reverse circuit's own start pose faces its way
        ax.annotate(
            "",
            xy=(sx + arrow * math.cos(heading), sy + arrow * math.sin(heading)),
            xytext=(sx, sy),
            zorder=4,
            arrowprops={"arrowstyle": "-|>", "color": "0.3", "lw": 1.0, "shrinkA": 0, "shrinkB": 0},
        )
    sx, sy, _ = track.circuit.centreline.pose_at(0.0)
    ax.plot([sx], [sy], marker="o", ms=5, mfc="white", mec="0.3", zorder=4)


def _draw_episode(ax, r: EpisodeResult, episode_data: tuple, *, colour_by: str, cmap: str, norm) -> None:
    """One episode's path coloured segment by segment, with ✕ where it ended short of its lap target and a small ○
    where it started when that was not the start line (``EpisodeSpec.start_m``)."""
    from matplotlib.collections import LineCollection

    x, y, speed, xte = episode_data
    colours = speed if colour_by == "speed" else xte
    points = np.column_stack([x, y]).reshape(-1, 1, 2)
    segments = np.concatenate([points[:-1], points[1:]], axis=1)
    lines = LineCollection(list(segments), cmap=cmap, norm=norm, linewidths=1.6, zorder=2)
    lines.set_array(colours[1:])
    ax.add_collection(lines)
    if r.spec.start_m > 0 and len(x):  # started along the circuit, not at the track's start (the arrow)
        ax.plot([x[0]], [y[0]], marker="o", ms=4, mfc="white", mec="0.3", zorder=4)
    if not reached_target(r):
        ax.plot([x[-1]], [y[-1]], marker="X", ms=8, color="crimson", mec="white", mew=0.8, zorder=5)


def _frame_map(ax, layout: _MapLayout) -> None:
    """A map panel's extent, equal aspect, ticks and grid."""
    from matplotlib.ticker import MaxNLocator

    ax.set_xlim(layout.x0, layout.x1)
    ax.set_ylim(layout.y0, layout.y1)
    ax.set_aspect("equal", adjustable="box")
    ax.tick_params(labelsize=7)
    ax.xaxis.set_major_locator(MaxNLocator(5))
    ax.yaxis.set_major_locator(MaxNLocator(5))
    ax.grid(True, color="0.93", lw=0.5)


def _label_axes(axes, *, panels: int, ncols: int) -> None:
    """Tick labels and axis titles on the outer panels only; the grid's unused panels hidden."""
    n = panels
    for index, ax in enumerate(axes.flat):
        if index >= n:
            ax.set_visible(False)
            continue
        ax.tick_params(labelleft=index % ncols == 0, labelbottom=index + ncols >= n)
        if index % ncols == 0:
            ax.set_ylabel("y (m)", fontsize=8)
        if index + ncols >= n:
            ax.set_xlabel("x (m)", fontsize=8)


def _draw_boxes(ax, series: list[list[float]], *, brains: Sequence[str], colours, rng, log_scale: bool) -> None:
    """A box per brain with values, its episodes as jittered dots over it; a log scale when ``log_scale`` allows
    and the values span more than 100x (position deviation is exponential in the distance)."""
    positions = [i + 1 for i, s in enumerate(series) if s]
    if not positions:
        return
    box = ax.boxplot(
        [s for s in series if s],
        positions=positions,
        widths=0.55,
        patch_artist=True,
        showfliers=False,
        medianprops={"color": "black"},
    )
    for patch, position in zip(box["boxes"], positions):
        patch.set_facecolor(colours[brains[position - 1]])
        patch.set_alpha(0.35)
    for position in positions:
        values = series[position - 1]
        jitter = rng.uniform(-0.12, 0.12, len(values))
        ax.scatter(
            np.full(len(values), position) + jitter,
            values,
            s=16,
            zorder=3,
            color=colours[brains[position - 1]],
            edgecolor="white",
            linewidth=0.5,
        )
    flat = [v for s in series for v in s]
    if log_scale and min(flat) > 0 and max(flat) / min(flat) > 100:
        ax.set_yscale("log")


def _label_boxes(ax, series: list[list[float]], *, brains: Sequence[str], empty: str) -> None:
    """``empty`` where a brain has no value, the brains as ticks (slanted when more than 3), the y grid."""
    for i, s in enumerate(series):
        if not s:
            ax.text(
                i + 1,
                0.5,
                empty,
                transform=ax.get_xaxis_transform(),
                ha="center",
                va="center",
                color="0.5",
                fontsize=8,
            )
    ax.set_xticks(
        range(1, len(brains) + 1),
        brains,
        rotation=20 if len(brains) > 3 else 0,
        ha="right" if len(brains) > 3 else "center",
        fontsize=8,
    )
    ax.set_xlim(0.4, len(brains) + 0.6)
    ax.tick_params(axis="y", labelsize=8)
    ax.grid(True, axis="y", color="0.92")
