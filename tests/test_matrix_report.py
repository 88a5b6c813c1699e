"""The matrix report: a real results database, scores from the real scorer core, real trajectory files."""

from __future__ import annotations

import csv
import functools
import math
import re
import statistics
from pathlib import Path

import numpy as np
import pytest
from needs import require

from circuits import load_circuit
from orchestrator.cli import main
from orchestrator.matrix.load import parse_matrix
from orchestrator.matrix.plan import BrainEntry
from orchestrator.matrix.results import BASELINE_FACT, EpisodeResult, ResultStore
from orchestrator.report.cells import baseline_variation, grid_cell, mean_std
from orchestrator.report.data import ReportError
from orchestrator.report.matrix import write_report
from orchestrator.stack.failures import Failure, FailureKind
from protocol.episode_spec import EpisodeSpec, WorldVariation
from protocol.messages import EndReason, EpisodeScore, Header
from services.scorer.metrics import EpisodeScorer

STEP_S = 0.05
SPEED_MPS = {"explicit": 12.0, "pilotnet": 10.0}
BRAINS = ("explicit", "pilotnet")
CIRCUITS = ("simple", "nurburgring")
BASELINE = "line=red,walls=on"  # the first value of every axis of MATRIX_SOURCE: what a real matrix labels it
VARIATIONS = (BASELINE, "line=white,walls=off")
CRASH = ("pilotnet", "simple", "line=white,walls=off", 1)  # stops at 40 % of the lap: a crash
FAILED = ("explicit", "nurburgring", "line=white,walls=off", 1)  # the brain process died: no score
MATRIX_SOURCE = """name: demo
brains: [{name: explicit}, {name: pilotnet, weights: missing/model.ckpt}]
circuits: [simple, nurburgring]
variations: {line: [red, white], walls: [on, off]}
repetitions: 2
"""


@functools.cache  # the same drive serves every variation: the scorer only sees poses
def drive(circuit_name: str, brain: str, repetition: int, *, fraction: float = 1.03):
    """Score poses along the circuit's centre line at the brain's speed, weaving sideways (amplitude grows with the
    repetition): the real scorer core. Returns (metrics, trajectory arrays)."""
    circuit = load_circuit(circuit_name)
    centreline = circuit.centreline
    speed = SPEED_MPS[brain]
    amplitude = 0.15 + 0.2 * repetition + (0.1 if brain == "pilotnet" else 0.0)
    scorer = EpisodeScorer(circuit=circuit, laps_target=1, step_s=STEP_S)
    poses = {name: [] for name in ("stamp_s", "x_m", "y_m", "yaw_rad", "speed_mps")}
    live = {name: [] for name in ("live_sim_time_s", "live_progress_laps", "live_cross_track_m")}
    count = int(fraction * centreline.length_m / (speed * STEP_S))
    for i in range(count + 1):
        s = i * STEP_S * speed
        x, y, heading = centreline.pose_at(s)
        offset = amplitude * math.sin(s / 15.0)
        x, y = x - offset * math.sin(heading), y + offset * math.cos(heading)
        scorer.add_pose(seq=i, stamp_ns=round(i * STEP_S * 1e9), x_m=x, y_m=y, yaw_rad=heading)
        for name, value in zip(poses, (i * STEP_S, x, y, heading, speed if i else 0.0)):
            poses[name].append(value)
        if i % 5 == 0:
            figures = scorer.live()
            live["live_sim_time_s"].append(figures["sim_time_s"])
            live["live_progress_laps"].append(figures["progress_laps"])
            live["live_cross_track_m"].append(figures["cross_track_m"])
    metrics = scorer.finish(wall_time_s=count * STEP_S / 8.0)
    return metrics, {name: np.asarray(values) for name, values in {**poses, **live}.items()}


def make_results(folder: Path) -> dict:
    """2 brains x 2 circuits x 2 variations x 2 repetitions (one crash, one stack failure) plus 2 episodes with
    salt and pepper and 2 in Behavior Metrics' rain; returns the metrics by (brain, circuit, variation, perturbation,
    repetition)."""
    scores = {}
    plan = [(b, c, v, "none", rep) for b in BRAINS for c in CIRCUITS for v in VARIATIONS for rep in range(2)]
    plan += [("explicit", "simple", BASELINE, "salt_pepper=0.2", rep) for rep in range(2)]
    plan += [("explicit", "simple", BASELINE, "rain", rep) for rep in range(2)]  # Behavior Metrics' rain
    (folder / "trajectories").mkdir(parents=True)
    with ResultStore(folder) as store:
        store.set_fact("name", "demo")
        store.set_fact("source_text", MATRIX_SOURCE)
        store.set_fact("variation_keys", ["line", "walls"])
        store.set_fact(BASELINE_FACT, BASELINE)
        store.set_fact("created_at", 1_700_000_000.0)
        for index, (brain, circuit, variation, perturbation, rep) in enumerate(plan):
            key = f"{brain}/{circuit}/{variation}/{perturbation}/r{rep}"
            world = WorldVariation(line="white", walls=False) if variation != BASELINE else WorldVariation()
            spec = EpisodeSpec(circuit=circuit, laps=1, seed=1000 + index, active_brain=brain, world=world)
            entry = {
                "label": brain,
                "brain": brain,
                "weights": "missing/model.ckpt" if brain == "pilotnet" else None,
                "options": [],
            }
            started = 1_700_000_100.0 + 60 * index
            common = dict(
                key=key,
                index=index,
                brain=brain,
                circuit=circuit,
                variation=variation,
                perturbation=perturbation,
                repetition=rep,
                spec=spec,
                brain_entry=BrainEntry.from_dict(entry),
                run_id=f"r{index}",
                started_at=started,
                logs=f"logs/{index:03d}",
            )
            if (brain, circuit, variation, rep) == FAILED:
                store.record(
                    EpisodeResult(
                        **common,
                        status="failed",
                        ended_at=started + 3.0,
                        failure=Failure(FailureKind.BRAIN_DIED, "brain 'x' exited with code -9"),
                    )
                )
                continue
            crash = (brain, circuit, variation, rep) == CRASH
            metrics, arrays = drive(circuit, brain, rep, fraction=0.4 if crash else 1.03)
            reason = EndReason.CRASH if crash else EndReason.LAPS_COMPLETED
            score = EpisodeScore(
                header=Header(run_id=f"r{index}", episode=0, seq=0, stamp_ns=0),
                spec=spec,
                reason=reason,
                brain=brain,
                metrics=metrics,
            )
            trajectory = f"trajectories/{index:03d}.npz"
            if perturbation == "none":
                np.savez(folder / trajectory, **arrays)
            elif rep == 0:  # a file without live samples: the progress plot takes its progress from the poses
                np.savez(folder / trajectory, **{k: v for k, v in arrays.items() if not k.startswith("live_")})
            # (the other perturbed episode's file is missing on disk)
            store.record(
                EpisodeResult(
                    **common,
                    status="done",
                    ended_at=started + metrics.wall_time_s,
                    reason=str(reason),
                    score=score,
                    trajectory=trajectory,
                    recording=f"recordings/{index:03d}.mcap",
                )
            )
            scores[(brain, circuit, variation, perturbation, rep)] = metrics
    return scores


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    folder = tmp_path_factory.mktemp("matrix")
    scores = make_results(folder)
    files = write_report(folder)
    return folder, scores, files


def test_files_are_written(report):
    folder, _, files = report
    for path in (files.html, files.markdown, files.csv):
        assert path.is_file() and path.stat().st_size > 0 and path.parent == folder
    assert files.parquet is None  # pyarrow is not installed here
    names = {p.name for p in files.plots}
    assert {
        "trajectories_speed_simple.png",
        "trajectories_xte_simple.png",
        "trajectories_speed_nurburgring.png",
        "boxplots.png",
        "progress.png",
    } <= names
    for plot in files.plots:
        assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_main_table_holds_mean_and_std_of_the_repetitions(report):
    _, scores, files = report
    text = files.markdown.read_text()
    assert "| Brain | Circuit | Episodes | Lap (s) | Position deviation (BM) | Cross-track mean (m) |" in text
    main = text.split("## Main table")[1].split("## ")[0]
    row = next(line for line in main.splitlines() if line.startswith("| explicit | simple |"))
    runs = [scores[("explicit", "simple", BASELINE, "none", rep)] for rep in range(2)]
    laps = [m.bm_lap_seconds for m in runs]
    assert all(lap is not None for lap in laps)
    cells = [cell.strip() for cell in row.strip("|").split("|")]
    assert cells[2] == "2"
    assert cells[3] == f"{statistics.fmean(laps):.2f} ± {statistics.stdev(laps):.2f}"
    deviation = [m.position_deviation_mae for m in runs]
    assert cells[4] == f"{statistics.fmean(deviation):.2f} ± {statistics.stdev(deviation):.2f}"
    mean_xte = [m.cross_track_mean_m for m in runs]
    assert cells[5] == f"{statistics.fmean(mean_xte):.3f} ± {statistics.stdev(mean_xte):.3f}"
    assert cells[9] == "2/2" and cells[10] == "–"
    # Only baseline episodes (the baseline variation, no perturbation) are in the main table: 2 per brain and circuit.
    assert "| pilotnet | nurburgring | 2 |" in main


def test_grids_mark_failures_with_reason_and_count(report):
    _, scores, files = report
    text = files.markdown.read_text()
    grid = text.split("## Generalisation")[1].split("## ")[0]
    assert "✗ crash 1/2" in grid
    assert "✗ brain_died 1/2" in grid
    pilot_row = next(line for line in grid.splitlines() if line.startswith("| pilotnet |"))
    laps = [scores[("pilotnet", "nurburgring", BASELINE, "none", rep)].bm_lap_seconds for rep in range(2)]
    assert f"{statistics.fmean(laps):.1f} s" in pilot_row
    robustness = text.split("## Robustness")[1].split("## ")[0]
    assert "salt_pepper=0.2" in robustness and "%" in robustness
    assert "| simple · rain |" in robustness  # BM's perturbations are columns like any other
    failures = text.split("## Failures")[1].split("## ")[0]
    assert "brain_died: brain 'x' exited with code -9" in failures and "logs/" in failures
    # A missing checkpoint is a note, not a crash; a missing trajectory file too.
    assert "missing/model.ckpt" in text
    assert "no readable trajectory" in text


def test_csv_has_one_row_per_episode(report):
    _, scores, files = report
    with open(files.csv, newline="") as file:
        rows = list(csv.DictReader(file))
    assert len(rows) == 20
    by_key = {row["key"]: row for row in rows}
    row = by_key[f"pilotnet/simple/{BASELINE}/none/r1"]
    metrics = scores[("pilotnet", "simple", BASELINE, "none", 1)]
    assert row["status"] == "done" and row["reason"] == "laps_completed" and row["repetition"] == "1"
    assert float(row["bm_lap_seconds"]) == pytest.approx(metrics.bm_lap_seconds)
    assert float(row["position_deviation_mae"]) == pytest.approx(metrics.position_deviation_mae)
    assert [float(v) for v in row["lap_times_s"].split(";")] == pytest.approx(metrics.lap_times_s)
    assert row["recording"].endswith(".mcap") and int(row["seed"]) >= 1000
    failed = by_key["explicit/nurburgring/line=white,walls=off/none/r1"]
    assert failed["status"] == "failed" and failed["failure"].startswith("brain_died:")
    assert failed["bm_lap_seconds"] == "" and float(failed["wall_s"]) == pytest.approx(3.0)
    crash = by_key["pilotnet/simple/line=white,walls=off/none/r1"]
    assert crash["reason"] == "crash" and crash["bm_lap_seconds"] == "" and float(crash["percentage_completed"]) < 50


def test_html_is_self_contained(report):
    _, _, files = report
    page = files.html.read_text()
    assert not re.search(r"""(src|href)\s*=\s*["']?\s*https?://""", page, re.IGNORECASE)
    assert "http://" not in page and "https://" not in page
    assert page.count("data:image/png;base64,") == len(files.plots)
    assert '<table class="sortable">' in page and "✗ crash 1/2" in page


def test_output_folder_and_cli(report, tmp_path, capsys):
    folder, _, _ = report
    assert main(["report", str(folder), "-o", str(tmp_path / "elsewhere")]) == 0
    err = capsys.readouterr().err
    assert str(tmp_path / "elsewhere" / "report.html") in err
    assert (tmp_path / "elsewhere" / "episodes.csv").is_file()
    assert (tmp_path / "elsewhere" / "plots" / "progress.png").is_file()


def test_errors_are_one_line(tmp_path, capsys):
    assert main(["report", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("drivebench: error: ") and "\n" not in err and "results.sqlite" in err
    ResultStore(tmp_path).close()  # a database with no episode yet
    assert main(["report", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "no episodes" in err and "\n" not in err
    with pytest.raises(ReportError, match="no such folder"):
        write_report(tmp_path / "absent")


def test_the_fixture_is_labelled_as_the_matrix_parser_plans_it(tmp_path):
    """The fixture's labels and baseline fact are the real parser's for MATRIX_SOURCE, so the report is tested on
    the path every matrix with ``variations:`` takes (no "default" label; the baseline from the runner's fact)."""
    (tmp_path / "missing").mkdir()
    (tmp_path / "missing" / "model.ckpt").write_bytes(b"")  # the parser checks the file exists, not its content
    matrix = parse_matrix(MATRIX_SOURCE, base_dir=tmp_path)
    assert set(VARIATIONS) <= {episode.variation for episode in matrix.episodes}
    assert matrix.episodes[0].variation == BASELINE


def test_the_stored_baseline_wins_over_the_first_stored_episode(report):
    """A partial run (its first planned episodes not stored yet) still compares against the planned baseline."""
    folder, _, _ = report
    with ResultStore(folder, create=False) as store:
        results, planned = store.results(), store.fact(BASELINE_FACT)
    late = [r for r in results if r.variation != BASELINE] + [r for r in results if r.variation == BASELINE][-1:]
    assert min(late, key=lambda r: r.index).variation != BASELINE
    assert baseline_variation(late, planned) == BASELINE
    assert baseline_variation(late, None) != BASELINE  # what the fact is for


def test_cell_and_number_rules():
    assert mean_std([]) == "–"
    assert mean_std([2.0]) == "2.00"
    assert mean_std([1.0, 3.0], 1) == f"2.0 ± {statistics.stdev([1.0, 3.0]):.1f}"
    assert grid_cell([]) == "–"
    assert baseline_variation([], "line=red,walls=on") is None


def test_damaged_database_is_one_line(tmp_path, capsys):
    (tmp_path / "results.sqlite").write_bytes(b"not a database at all" * 100)
    assert main(["report", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("drivebench: error: ") and "\n" not in err and "results.sqlite" in err


def test_internal_metrics_come_from_the_checkpoint(tmp_path):
    require("torch")
    from brains.nets import make_model
    from brains.neural.checkpoint import default_input, save_checkpoint

    model = "deepest_lstm_tiny_pilotnet"
    save_checkpoint(
        tmp_path / "model.ckpt",
        model_name=model,
        module=make_model(model),
        input=default_input(model),
        normalisation={
            "image_mean": [0.5] * 3,
            "image_std": [0.25] * 3,
            "labels": "zscore",
            "label_mean": [5.0, 0.0],
            "label_std": [2.0, 1.0],
        },
        metrics={
            "train": {"mae_speed_mps": 0.2, "mae_yaw_rate_radps": 0.05, "mse_normalised": 0.0123},
            "val": {"mae_speed_mps": 0.4321, "mae_yaw_rate_radps": 0.0767, "mse_normalised": 0.0456},
            "best_epoch": 7,
        },
    )
    metrics, arrays = drive("simple", "pilotnet", 0)
    spec = EpisodeSpec(circuit="simple", active_brain="tiny")
    score = EpisodeScore(
        header=Header(run_id="r", episode=0, seq=0, stamp_ns=0),
        spec=spec,
        reason=EndReason.LAPS_COMPLETED,
        brain="tiny",
        metrics=metrics,
    )
    with ResultStore(tmp_path) as store:
        store.record(
            EpisodeResult(
                key="tiny/0",
                index=0,
                brain="tiny",
                circuit="simple",
                variation="default",
                perturbation="none",
                repetition=0,
                spec=spec,
                brain_entry=BrainEntry(label="tiny", brain="neural", weights=Path("model.ckpt")),
                status="done",
                run_id="r",
                started_at=0.0,
                ended_at=10.0,
                reason="laps_completed",
                score=score,
                trajectory=None,
            )
        )
    text = write_report(tmp_path).markdown.read_text()
    section = text.split("## Internal metrics")[1].split("## ")[0]
    row = next(line for line in section.splitlines() if line.startswith("| tiny |"))
    assert model in row and "| val |" in row and "0.432" in row and "0.0767" not in row  # 3 decimals
    assert "0.077" in row and "0.0456" in row and "0.0123" in row and row.rstrip().endswith("| 7 |")
    # One variation and one perturbation: the grids point to the main table instead.
    assert "One world variation only" in text and "One perturbation only" in text


def test_the_page_has_a_table_of_contents_and_sortable_tables(report):
    _, _, files = report
    page = files.html.read_text()
    anchors = re.findall(r'<h2 id="([^"]+)">', page)
    assert len(anchors) >= 4
    toc = page[page.index('<nav class="toc">') : page.index("</nav>")]
    assert [f"#{anchor}" for anchor in anchors] == re.findall(r'href="([^"]+)"', toc)
    assert page.count('<table class="sortable">') >= 3 and 'querySelectorAll("table.sortable")' in page


def test_a_lapped_episodes_progress_curve_ends_on_its_lap_target(report):
    from orchestrator.report.plots import _to_the_finish

    folder, _, _ = report
    with ResultStore(folder) as store:
        lapped = [r for r in store.results() if r.reason == "laps_completed" and r.perturbation == "none"]
    assert lapped
    for r in lapped:
        arrays = np.load(folder / r.trajectory)
        time_s, progress = _to_the_finish(r, arrays["live_sim_time_s"], arrays["live_progress_laps"])
        finish_s = sum(r.score.metrics.lap_times_s[:1])
        assert (time_s[-1], progress[-1]) == (pytest.approx(finish_s), 1.0)
        assert np.all(np.diff(time_s) > 0) and np.all(progress[:-1] < 1.0 + 1e-9)


def test_the_cross_track_colour_scale_is_the_datas_not_the_roads():
    from orchestrator.report.plots import _colour_scale

    xte_m = np.linspace(0.0, 0.05, 200)  # a good brain: centimetres off the line on a 3 m road
    data = {"a": (np.zeros(200), np.zeros(200), np.ones(200), xte_m)}
    norm, _, label = _colour_scale("xte", data=data)
    assert norm.vmax == pytest.approx(np.percentile(xte_m, 99)) and "99th" in label


def test_an_episode_started_along_the_circuit_is_marked_where_it_started(report):
    import dataclasses

    import msgspec
    from matplotlib.figure import Figure

    from orchestrator.report.plots import _draw_episode

    folder, _, _ = report
    with ResultStore(folder, create=False) as store:
        result = next(r for r in store.results() if r.status == "done")
    path = (np.array([3.0, 4.0, 5.0]), np.array([7.0, 7.5, 8.0]), np.ones(3), np.zeros(3))
    markers = {}
    for start_m in (0.0, 120.0):
        moved = dataclasses.replace(result, spec=msgspec.structs.replace(result.spec, start_m=start_m))
        ax = Figure().add_subplot()
        _draw_episode(ax, moved, path, colour_by="speed", cmap="viridis", norm=None)
        markers[start_m] = [(line.get_xdata()[0], line.get_ydata()[0]) for line in ax.lines if line.get_marker() == "o"]
    assert markers == {0.0: [], 120.0: [(3.0, 7.0)]}  # the start line has its own mark (the track's arrow)


@pytest.mark.parametrize("direction", ["forward", "reverse"])
def test_a_maps_start_arrow_points_the_way_its_episodes_drove(direction):
    """The legend says the arrow is the driving direction: on a panel of reverse episodes it points the other way
    round from the start line, as the reverse circuit's own start pose faces."""
    from matplotlib.figure import Figure

    from orchestrator.report.plots import _draw_track, _map_layout
    from orchestrator.report.trajectories import Track

    track = Track(load_circuit("simple"))
    data = {"a": (track.points[:, 0], track.points[:, 1], np.ones(len(track.points)), np.zeros(len(track.points)))}
    ax = Figure().add_subplot()
    _draw_track(ax, track, layout=_map_layout(data, track, panels=1), directions=(direction,))
    (arrow,) = [text for text in ax.texts if getattr(text, "arrow_patch", None) is not None]
    (head_x, head_y), (tail_x, tail_y) = arrow.xy, arrow.xyann
    x_m, y_m, heading_rad = load_circuit("simple", direction=direction).centreline.pose_at(0.0)
    assert (tail_x, tail_y) == pytest.approx((x_m, y_m))
    assert math.atan2(head_y - tail_y, head_x - tail_x) == pytest.approx(heading_rad)
