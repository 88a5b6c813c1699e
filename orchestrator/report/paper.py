"""``drivebench paper``: the six tables of "Memory based neural networks for end-to-end autonomous driving", ours
beside the paper's.

    drivebench paper [-o DIR] [--workers N] [--resume] [--smoke]

``experiments/paper.yaml`` is a matrix file with one part per closed-loop table; its brain labels name the paper's
rows. This module knows the paper's figures and puts each finished episode in its cell:

    table 1  internal metrics (MAE, MSE in the paper's normalisation), from each brain's checkpoint
    table 2  parameters and input shape, from each brain's checkpoint
    table 3  part ``montmelo``: lap seconds, BM position deviation, average speed (mean over repetitions)
    table 4  part ``generalisation``: lap seconds or a failure mark per world (line / road / walls, and direction)
    table 5  part ``camera``: the moved and rotated camera worlds, lap seconds and BM position deviation
    table 6  part ``noise``: salt and pepper noise on the camera, lap seconds

A brain whose label is not one of the paper's rows gets its own row with "–" for the paper. The run itself is an
ordinary matrix run (results.sqlite, --resume, the full report); the results database remembers that it is the
paper's, so ``drivebench report DIR`` writes these tables again.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import statistics
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import msgspec

from orchestrator.matrix.results import EpisodeResult
from orchestrator.report.cells import lap_seconds, metrics_of, outcome, reached_target
from orchestrator.report.document import FAIL_MARK, Section, Table

# orchestrator/experiments links to the top-level experiments/ in a checkout and holds the files in a wheel.
PAPER_FILE = Path(__file__).resolve().parents[1] / "experiments" / "paper.yaml"
PAPER_ONLY = "–"  # no figure in the paper for this cell (a brain or a world the paper did not run)

# The paper's rows, by brain label in experiments/paper.yaml, and how the paper names them.
PAPER_BRAINS: dict[str, str] = {
    "explicit": "Explicit brain (PID)",
    "pilotnet": "PilotNet",
    "deepest_lstm_tiny_pilotnet": "DeepestLSTMTinyPilotNet",
    "pilotnet_x3": "PilotNet x3",
    "memdccp": "memDCCP",
}
FAIL = "fail"

# Table 1: MAE train, MAE validation, MSE train, MSE validation (normalised outputs).
TABLE1: dict[str, tuple[float, float, float, float]] = {
    "pilotnet": (0.0044, 0.00546, 0.00016, 0.00064),
    "deepest_lstm_tiny_pilotnet": (0.018, 0.016, 0.00416, 0.00382),
    "pilotnet_x3": (0.0044, 0.0048, 0.00018, 0.00032),
    "memdccp": (0.019, 0.018, 0.0039, 0.0035),
}
# Table 2: parameters (as the paper writes them) and input size (width x height).
TABLE2: dict[str, tuple[str, str]] = {
    "pilotnet": ("17M", "200x66"),
    "deepest_lstm_tiny_pilotnet": ("62k", "100x50"),
    "pilotnet_x3": ("15.9M", "100x50"),
    "memdccp": ("910k", "100x50"),
}
# Table 3, Montmeló (3 repetitions averaged): lap s, position deviation (BM's mean 1000^d), average speed m/s.
TABLE3: dict[str, tuple[float, float, float]] = {
    "explicit": (78, 3.01, 9.34),
    "pilotnet": (77, 2.73, 9.43),
    "deepest_lstm_tiny_pilotnet": (77, 4.76, 9.17),
    "pilotnet_x3": (97.3, 5.40, 7.52),
    "memdccp": (80, 4.93, 9.17),
}
# Table 4, simple: lap s or FAIL per world (line, road, walls); the paper drove every world forward only.
TABLE4_WORLDS: tuple[tuple[str, str, bool], ...] = (
    ("red", "grey", True),
    ("red", "white", True),
    ("white", "grey", True),
    ("none", "grey", True),
    ("none", "white", True),
    ("none", "grey", False),
)
TABLE4: dict[str, tuple[Any, ...]] = {
    "explicit": ("50-61", 50, FAIL, FAIL, FAIL, FAIL),
    "pilotnet": (50, 55, 50, FAIL, FAIL, FAIL),
    "deepest_lstm_tiny_pilotnet": (46, 53, FAIL, FAIL, FAIL, FAIL),
    "pilotnet_x3": (54.5, 60, FAIL, FAIL, FAIL, FAIL),
    "memdccp": (56, 61, 62.6, 72, 61, FAIL),
}
# Table 5, a held-out circuit: lap s (and, where the paper gives it, position deviation) per camera preset.
TABLE5_CAMERAS = ("left", "right", "rotate_down")
TABLE5: dict[str, tuple[Any, ...]] = {
    "explicit": ((123, 5.2), (115, 17.2), FAIL),
    "pilotnet": (140, 142, FAIL),
    "deepest_lstm_tiny_pilotnet": (160, 159, 160),
    "pilotnet_x3": (145, 144, FAIL),
    "memdccp": (160, 160, 162),
}
# Table 6, the same held-out circuit: lap s per salt-and-pepper probability.
TABLE6_LEVELS = (0.2, 0.4, 0.6)
TABLE6: dict[str, tuple[Any, ...]] = {
    "explicit": (117, 132, FAIL),
    "pilotnet": (FAIL, FAIL, FAIL),
    "deepest_lstm_tiny_pilotnet": (FAIL, FAIL, FAIL),
    "pilotnet_x3": (FAIL, FAIL, FAIL),
    "memdccp": (155, 158, FAIL),
}
PARTS = {"montmelo": 3, "generalisation": 4, "camera": 5, "noise": 6}
CIRCUITS_PART = "circuits"  # beyond the paper: one lap of many circuits (experiments/randomised.yaml)

# --smoke: a few seconds of two brains in the first cells of every part, small camera.
SMOKE_BRAINS = ("explicit", "deepest_lstm_tiny_pilotnet")
SMOKE_CELLS_PER_PART = 2
SMOKE_SIM_SECONDS = 4.0
SMOKE_CAMERA = (160, 120)


# -- cells -----------------------------------------------------------------------------------------------------------


def paper_text(value: Any, unit: str = "") -> str:
    """The paper's figure as a cell shows it: ``"50 s"``, ``"✗"`` for a failure, ``"–"`` when the paper has none."""
    if value is None:
        return PAPER_ONLY
    if value == FAIL:
        return FAIL_MARK
    if isinstance(value, tuple):  # (lap s, position deviation)
        return f"{paper_text(value[0], unit)}, {value[1]:g}"
    return f"{value:g}{unit}" if isinstance(value, (int, float)) else f"{value}{unit}"


def our_lap_cell(results: Sequence[EpisodeResult], *, with_deviation: bool = False) -> str:
    """Our side of a closed-loop cell: the mean first-lap time when every episode lapped, else ✗ and how the
    others ended (``"✗ crash 1/1"``); ``"–"`` when the cell has no episode (yet)."""
    if not results:
        return PAPER_ONLY
    missed = [r for r in results if not reached_target(r)]
    if missed:
        kinds = statistics.multimode(outcome(r) for r in missed)
        return f"{FAIL_MARK} {kinds[0]} {len(missed)}/{len(results)}"
    laps = [t for t in (lap_seconds(r) for r in results) if t is not None]
    text = f"{statistics.fmean(laps):.1f} s" if laps else "✓"
    if with_deviation:
        text += f", {statistics.fmean(metrics_of(r).position_deviation_mae for r in results):.2f}"
    return text


def cell(ours: str, paper: str) -> str:
    """One cell, ours then the paper's: ``"57.2 s / 50 s"``."""
    return f"{ours} / {paper}"


# -- the tables ------------------------------------------------------------------------------------------------------


def _brains(results: Sequence[EpisodeResult]) -> list[str]:
    """The paper's rows first (in the paper's order), then every other brain in the order it ran."""
    present = list(dict.fromkeys(r.brain for r in results))
    return [b for b in PAPER_BRAINS if b in present] + [b for b in present if b not in PAPER_BRAINS]


def _name(brain: str) -> str:
    return PAPER_BRAINS.get(brain, brain)


def _in_part(results: Sequence[EpisodeResult], part: str) -> list[EpisodeResult]:
    from orchestrator.matrix.load import part_of

    return [r for r in results if part_of(r.key) == part]


def table3(results: Sequence[EpisodeResult]) -> Table:
    """Montmeló: lap, position deviation and average speed, mean over the episodes that lapped, beside the paper."""
    rows = []
    for brain in _brains(results):
        group = [r for r in results if r.brain == brain]
        lapped = [r for r in group if reached_target(r)]
        paper = TABLE3.get(brain, (None, None, None))
        if lapped:
            metrics = [metrics_of(r) for r in lapped]
            ours = [
                f"{statistics.fmean(t for t in map(lap_seconds, lapped) if t is not None):.1f}",
                f"{statistics.fmean(m.position_deviation_mae for m in metrics):.2f}",
                f"{statistics.fmean(m.average_speed_mps for m in metrics):.2f}",
            ]
        else:
            ours = [our_lap_cell(group), PAPER_ONLY, PAPER_ONLY]
        laps = f"{len(lapped)}/{len(group)}"
        rows.append([_name(brain), laps, *(item for pair in zip(ours, map(paper_text, paper)) for item in pair)])
    columns = ["Brain", "Lapped", "Lap (s)", "paper", "Position deviation", "paper", "Avg speed (m/s)", "paper"]
    return Table(
        columns, rows, numeric=[False] + [True] * 7, caption="Table 3: Montmeló, mean over the repetitions that lapped"
    )


def table4(results: Sequence[EpisodeResult]) -> Table:
    """Generalisation on simple: one column per world in the part, the paper's six worlds first."""
    worlds = list(dict.fromkeys(r.variation for r in results))
    by_world = {w: next(r.spec for r in results if r.variation == w) for w in worlds}

    def paper_index(world: str) -> int | None:
        spec = by_world[world]
        default_mount = msgspec.structs.replace(
            type(spec.camera)(), width_px=spec.camera.width_px, height_px=spec.camera.height_px
        )
        if spec.direction != "forward" or spec.camera != default_mount or spec.world.lighting != "sun":
            return None  # a world the paper did not drive
        key = (spec.world.line, spec.world.road, spec.world.walls)
        return TABLE4_WORLDS.index(key) if key in TABLE4_WORLDS else None

    worlds.sort(key=lambda w: (paper_index(w) is None, paper_index(w) or 0))
    rows = []
    for brain in _brains(results):
        paper = TABLE4.get(brain)
        row = [_name(brain)]
        for world in worlds:
            index = paper_index(world)
            theirs = paper[index] if paper is not None and index is not None else None
            ours = our_lap_cell([r for r in results if r.brain == brain and r.variation == world])
            row.append(cell(ours, paper_text(theirs, " s")))
        rows.append(row)
    return Table(
        ["Brain", *(_world_title(by_world[w]) for w in worlds)],
        rows,
        numeric=[False] + [True] * len(worlds),
        caption="Table 4: simple, lap time or ✗ per world (line / road / walls), ours / paper",
    )


def _world_title(spec) -> str:
    title = f"{spec.world.line} / {spec.world.road} / {'walls' if spec.world.walls else 'no walls'}"
    return title + (" / reverse" if spec.direction == "reverse" else "")


def _perturbation_table(
    results: Sequence[EpisodeResult],
    *,
    paper: dict[str, tuple[Any, ...]],
    labels: Sequence[str],
    titles: Sequence[str],
    with_deviation: bool,
    caption: str,
) -> Table:
    present = list(dict.fromkeys(r.perturbation for r in results))
    columns = [p for p in labels if p in present] + [p for p in present if p not in labels]
    rows = []
    for brain in _brains(results):
        row = [_name(brain)]
        for label in columns:
            theirs = paper[brain][labels.index(label)] if brain in paper and label in labels else None
            ours = our_lap_cell(
                [r for r in results if r.brain == brain and r.perturbation == label], with_deviation=with_deviation
            )
            row.append(cell(ours, paper_text(theirs, " s")))
        rows.append(row)
    header = [titles[labels.index(c)] if c in labels else c for c in columns]
    return Table(["Brain", *header], rows, numeric=[False] + [True] * len(columns), caption=caption)


def table5(results: Sequence[EpisodeResult]) -> Table:
    circuit = results[0].circuit if results else "?"
    return _perturbation_table(
        results,
        paper=TABLE5,
        labels=[f"camera={c}" for c in TABLE5_CAMERAS],
        titles=["camera moved left", "camera moved right", "camera rotated down"],
        with_deviation=True,
        caption=f"Table 5: {circuit}, moved cameras: lap time, position deviation; ours / paper (their held-out "
        "circuit)",
    )


def table6(results: Sequence[EpisodeResult]) -> Table:
    circuit = results[0].circuit if results else "?"
    return _perturbation_table(
        results,
        paper=TABLE6,
        labels=[f"salt_pepper={p:g}" for p in TABLE6_LEVELS],
        titles=[f"salt and pepper {p:g}" for p in TABLE6_LEVELS],
        with_deviation=False,
        caption=f"Table 6: {circuit}, salt and pepper noise on the brain's camera: lap time; ours / paper (their "
        "held-out circuit)",
    )


# -- tables 1 and 2: from the checkpoints ----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class CheckpointFacts:
    """What tables 1 and 2 need of one brain's checkpoint."""

    model: str
    parameters: int
    input_size: str  # "WxH"
    frames: int
    crop: str  # rows kept, as fractions of the camera height
    train: dict[str, float]
    val: dict[str, float]


def checkpoint_facts(path: Path) -> CheckpointFacts:
    """Read a checkpoint (torch) and count its network's parameters. Raises CheckpointError (one line)."""
    from brains.neural.checkpoint import build_model, load_checkpoint

    ckpt = load_checkpoint(path)
    parameters = sum(p.numel() for p in build_model(ckpt).parameters())
    metrics = ckpt.metrics or {}
    spec = ckpt.input
    return CheckpointFacts(
        model=ckpt.model,
        parameters=parameters,
        input_size=f"{spec.width_px}x{spec.height_px}",
        frames=len(spec.offsets_frames),
        crop=f"{spec.crop_top_fraction:g}..{spec.crop_bottom_fraction:g}",
        train=_paper_metrics(metrics.get("train")),
        val=_paper_metrics(metrics.get("val")),
    )


def _paper_metrics(figures: Any) -> dict[str, float]:
    """MAE and MSE in the paper's normalisation; older checkpoints carry only physical MAEs, from which the MAE
    follows exactly (v / 17.5, w / 14.2) and the MSE does not."""
    from brains.nets.preprocess import V_SCALE, W_SCALE

    if not isinstance(figures, dict):
        return {}
    found = {key: float(figures[key]) for key in ("mae_paper", "mse_paper") if key in figures}
    if "mae_paper" not in found and {"mae_speed_mps", "mae_yaw_rate_radps"} <= figures.keys():
        found["mae_paper"] = (figures["mae_speed_mps"] / V_SCALE + figures["mae_yaw_rate_radps"] / W_SCALE) / 2
    return found


def _count_text(parameters: int) -> str:
    if parameters >= 1_000_000:
        return f"{parameters / 1e6:.2f}M ({parameters:,})"
    return f"{parameters / 1e3:.0f}k ({parameters:,})"


def checkpoint_tables(results: Sequence[EpisodeResult], folder: Path) -> list[Table | str]:
    """Tables 1 and 2 from the weights of every brain that has them."""
    weights = {}
    for r in results:
        if r.brain_entry.weights is not None and r.brain not in weights:
            weights[r.brain] = r.brain_entry.weights
    if not weights:
        return ["No brain of this run has a checkpoint: tables 1 and 2 are empty."]
    if importlib.util.find_spec("torch") is None:
        return ["torch is not installed: tables 1 and 2 read the checkpoints with it (`pip install drivebench[ml]`)."]
    from brains.neural.checkpoint import CheckpointError

    rows1, rows2, notes = [], [], []
    for brain in _brains(results):
        if brain not in weights:
            continue
        path = weights[brain] if weights[brain].is_absolute() else folder / weights[brain]
        try:
            facts = checkpoint_facts(path)
        except CheckpointError as error:
            notes.append(f"{_name(brain)}: {error}")
            continue
        paper1 = TABLE1.get(brain, (None,) * 4)
        ours1 = [
            facts.train.get("mae_paper"),
            facts.val.get("mae_paper"),
            facts.train.get("mse_paper"),
            facts.val.get("mse_paper"),
        ]
        rows1.append([_name(brain), *(cell(_figure(o), paper_text(p)) for o, p in zip(ours1, paper1))])
        paper2 = TABLE2.get(brain, (None, None))
        rows2.append(
            [
                _name(brain),
                facts.model,
                cell(_count_text(facts.parameters), paper_text(paper2[0])),
                cell(facts.input_size, paper_text(paper2[1])),
                str(facts.frames),
                facts.crop,
            ]
        )
    blocks: list[Table | str] = [
        Table(
            ["Brain", "MAE train", "MAE val", "MSE train", "MSE val"],
            rows1,
            numeric=[False] + [True] * 4,
            caption="Table 1: internal metrics, both outputs in the paper's normalisation (v / 17.5, w / 14.2); "
            "ours / paper",
        ),
        Table(
            ["Brain", "Model", "Parameters", "Input (W x H)", "Frames", "Rows kept"],
            rows2,
            numeric=[False, False, True, True, True, True],
            caption="Table 2: size and input; ours / paper",
        ),
    ]
    return blocks + notes


def _figure(value: float | None) -> str:
    return PAPER_ONLY if value is None else f"{value:.4g}"


# -- the sections the report shows -----------------------------------------------------------------------------------


def paper_sections(results: Sequence[EpisodeResult], folder: Path) -> list[Section]:
    """The six tables as report sections (tables 3-6 from the parts that ran, 1-2 from the checkpoints)."""
    legend = (
        "Each cell: ours / the paper's. A lap time is the mean first-lap time (BM lap seconds) when every "
        f"repetition lapped; {FAIL_MARK} with how the others ended and how many otherwise. Position deviation "
        "is Behavior Metrics' mean of 1000^d (1 on the path, 31.6 at 0.5 m off), not metres. The paper ran "
        "Gazebo at 640x480 on its own circuits; see docs/paper.md for what compares and what does not."
    )
    section = Section("The paper's tables", [legend])
    section.blocks.extend(checkpoint_tables(results, folder))
    for part, number in PARTS.items():
        episodes = _in_part(results, part)
        if not episodes:
            section.blocks.append(f"Table {number}: no episode of part `{part}` in this run (yet).")
            continue
        section.blocks.append({3: table3, 4: table4, 5: table5, 6: table6}[number](episodes))
    if episodes := _in_part(results, CIRCUITS_PART):
        section.blocks.append(circuits_table(episodes))
    return [section]


def circuits_table(results: Sequence[EpisodeResult]) -> Table:
    """Beyond the paper: one lap of each circuit, per direction; lap time or how it failed."""
    cells = list(dict.fromkeys((r.circuit, r.spec.direction) for r in results))
    rows = [
        [
            _name(brain),
            *(
                our_lap_cell([r for r in results if r.brain == brain and (r.circuit, r.spec.direction) == c])
                for c in cells
            ),
        ]
        for brain in _brains(results)
    ]
    titles = [circuit + (" (reverse)" if direction == "reverse" else "") for circuit, direction in cells]
    return Table(
        ["Brain", *titles],
        rows,
        numeric=[False] + [True] * len(cells),
        caption="Every circuit, one lap each way: lap time or ✗ (beyond the paper)",
    )


# -- smoke form ------------------------------------------------------------------------------------------------------


SMOKE_RUNS_PER_BRAIN = 2  # a study's smoke form: the first two training runs of each brain (an interval needs two)


def smoke_matrix(matrix):
    """The paper's matrix cut to seconds: the explicit and tiny brains, the first cells of every part, one
    repetition, a few simulated seconds on a small camera; keys stay the full matrix's so every episode still lands in
    its table's cell. A study's file (brains over training seeds, without those two) keeps the first
    SMOKE_RUNS_PER_BRAIN training runs of each brain instead."""
    from orchestrator.matrix.load import smoke_form

    return smoke_form(
        matrix,
        brains=_smoke_brains(matrix),
        cells_per_part=SMOKE_CELLS_PER_PART,
        sim_seconds=SMOKE_SIM_SECONDS,
        camera_wh=SMOKE_CAMERA,
    )


def _smoke_brains(matrix) -> tuple[str, ...]:
    labels = [brain.label for brain in matrix.brains]
    if set(SMOKE_BRAINS) & set(labels):
        return SMOKE_BRAINS
    runs: dict[str, list[str]] = {}
    for brain in matrix.brains:
        runs.setdefault(brain.compared_as, []).append(brain.label)
    return tuple(label for group in runs.values() for label in group[:SMOKE_RUNS_PER_BRAIN])


# -- command line ----------------------------------------------------------------------------------------------------
