"""drivebench paper: the paper's matrix file, the table writer (each episode in its cell, the paper's figure beside
it, scored by the real scorer core) and the smoke form run end to end as a real command."""

from __future__ import annotations

import math
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

from brains.registry import shipped_weights
from circuits import load_circuit
from orchestrator.matrix.load import load_matrix
from orchestrator.matrix.plan import BrainEntry
from orchestrator.matrix.results import EpisodeResult, ResultStore
from orchestrator.report.document import Table
from orchestrator.report.matrix import write_report
from orchestrator.report.paper import PAPER_FILE, PARTS, paper_sections, smoke_matrix
from protocol.episode_spec import EpisodeSpec, SaltPepper
from protocol.messages import EndReason, EpisodeScore, Header
from protocol.variations import apply_variation
from services.scorer.metrics import EpisodeScorer

ROOT = Path(__file__).resolve().parents[1]
PAPER_ROWS = ("explicit", "pilotnet", "deepest_lstm_tiny_pilotnet", "pilotnet_x3", "memdccp")
STEP_S = 0.05


def test_paper_yaml_expands_to_exactly_the_episodes_of_the_six_tables():
    matrix = load_matrix(PAPER_FILE)
    assert matrix.parts == tuple(PARTS)
    assert [brain.label for brain in matrix.brains] == list(PAPER_ROWS)
    # The networks serve the weights drivebench ships, so the file runs from a wheel as from a checkout.
    assert all(
        brain.weights is not None and brain.weights == shipped_weights(brain.brain) for brain in matrix.brains[1:]
    )
    by_part = Counter(episode.part for episode in matrix.episodes)
    assert by_part == {"montmelo": 5 * 3, "generalisation": 5 * 7, "camera": 5 * 3, "noise": 5 * 3}
    for episode in matrix.episodes:
        assert episode.spec.laps == 1 and episode.spec.seed == episode.repetition
    montmelo = [e for e in matrix.episodes if e.part == "montmelo"]
    assert {(e.circuit, e.variation, e.perturbation) for e in montmelo} == {("montmelo", "default", "none")}
    assert sorted({e.repetition for e in montmelo}) == [0, 1, 2]
    worlds = {
        (e.spec.world.line, e.spec.world.road, e.spec.world.walls, e.spec.direction)
        for e in matrix.episodes
        if e.part == "generalisation"
    }
    assert worlds == {
        ("red", "grey", True, "forward"),
        ("red", "white", True, "forward"),
        ("white", "grey", True, "forward"),
        ("none", "grey", True, "forward"),
        ("none", "white", True, "forward"),
        ("none", "grey", False, "forward"),
        ("red", "grey", True, "reverse"),
    }
    assert {e.circuit for e in matrix.episodes if e.part == "generalisation"} == {"simple"}
    camera = {
        (e.circuit, e.spec.camera.lateral_offset_m, e.spec.camera.pitch_down_rad)
        for e in matrix.episodes
        if e.part == "camera"
    }
    assert camera == {("montreal", 0.20, 0.0), ("montreal", -0.20, 0.0), ("montreal", -0.20, 0.2)}
    noise = {(e.circuit, tuple(e.spec.noise)) for e in matrix.episodes if e.part == "noise"}
    assert noise == {("montreal", (SaltPepper(probability=p),)) for p in (0.2, 0.4, 0.6)}


def test_the_smoke_form_keeps_the_cells_keys_and_cuts_the_time():
    full = load_matrix(PAPER_FILE)
    smoke = smoke_matrix(full)
    full_keys = {e.key for e in full.episodes}
    assert {e.key for e in smoke.episodes} <= full_keys
    assert {e.brain.label for e in smoke.episodes} == {"explicit", "deepest_lstm_tiny_pilotnet"}
    assert {e.part for e in smoke.episodes} == set(PARTS)
    assert all(e.spec.max_sim_seconds <= 5 for e in smoke.episodes)
    assert [e.index for e in smoke.episodes] == list(range(len(smoke.episodes)))


# -- the table writer --------------------------------------------------------------------------------------------


def drive(circuit: str, speed_mps: float, *, fraction: float) -> object:
    """The real scorer core fed poses on the centre line at a constant speed, for ``fraction`` of a lap."""
    track = load_circuit(circuit)
    scorer = EpisodeScorer(circuit=track, laps_target=1, step_s=STEP_S)
    count = int(fraction * track.length_m / (speed_mps * STEP_S))
    for i in range(count + 1):
        x, y, heading = track.centreline.pose_at(i * STEP_S * speed_mps)
        scorer.add_pose(seq=i, stamp_ns=round(i * STEP_S * 1e9), x_m=x, y_m=y, yaw_rad=heading)
    return scorer.finish(wall_time_s=1.0)


CELLS = [
    # (part, brain, circuit, variation text, perturbation, speed m/s, lap fraction): 1.05 laps, or a crash at 30 %
    ("montmelo", "explicit", "montmelo", "", "none", 9.0, 1.05),
    ("montmelo", "memdccp", "montmelo", "", "none", 8.0, 1.05),
    ("generalisation", "memdccp", "simple", "line=none,road=grey,walls=on", "none", 8.0, 1.05),
    ("generalisation", "explicit", "simple", "line=none,road=grey,walls=on", "none", 8.0, 0.3),
    ("generalisation", "mybrain", "simple", "line=red,road=grey,walls=on,direction=reverse", "none", 10.0, 1.05),
    ("camera", "explicit", "montreal", "", "camera=left", 9.0, 1.05),
    ("noise", "memdccp", "montreal", "", "salt_pepper=0.6", 9.0, 1.05),
    ("circuits", "mybrain", "monaco", "direction=reverse", "none", 9.0, 1.05),
    ("circuits", "mybrain", "monaco", "direction=forward", "none", 9.0, 0.5),
]


@pytest.fixture(scope="module")
def paper_results(tmp_path_factory) -> tuple[Path, list[EpisodeResult]]:
    folder = tmp_path_factory.mktemp("paper")
    with ResultStore(folder) as store:
        store.set_fact("name", "paper")
        store.set_fact("paper", True)
        for index, (part, brain, circuit, variation, perturbation, speed, fraction) in enumerate(CELLS):
            spec = EpisodeSpec(circuit=circuit, active_brain=brain)
            spec = apply_variation(spec, variation) if variation else spec
            spec = apply_variation(spec, perturbation) if perturbation.startswith("camera") else spec
            label = variation or "default"
            metrics = drive(circuit, speed, fraction=fraction)
            reason = EndReason.LAPS_COMPLETED if fraction > 1 else EndReason.CRASH
            score = EpisodeScore(
                header=Header(run_id=f"r{index}", episode=0, seq=0, stamp_ns=0),
                spec=spec,
                reason=reason,
                brain=brain,
                metrics=metrics,
            )
            store.record(
                EpisodeResult(
                    key=f"{part}:{brain}/{circuit}/{label}/{perturbation}/r0",
                    index=index,
                    brain=brain,
                    circuit=circuit,
                    variation=label,
                    perturbation=perturbation,
                    repetition=0,
                    spec=spec,
                    brain_entry=BrainEntry(label=brain, brain=brain),
                    status="done",
                    run_id=f"r{index}",
                    started_at=0.0,
                    ended_at=1.0,
                    reason=str(reason),
                    score=score,
                )
            )
        results = store.results()
    return folder, results


def tables(folder: Path, results: list[EpisodeResult]) -> dict[int, Table]:
    """The tables by number; the beyond-the-paper circuits table as 0."""
    blocks = [block for block in paper_sections(results, folder)[0].blocks if isinstance(block, Table)]
    return {
        int(block.caption.split(":")[0].split()[1]) if block.caption.startswith("Table ") else 0: block
        for block in blocks
    }


def row(table: Table, name: str) -> dict[str, str]:
    found = [r for r in table.rows if r[0] == name]
    assert len(found) == 1, (name, table.rows)
    return dict(zip(table.columns, found[0]))


def test_each_episode_lands_in_its_cell_beside_the_papers_figure(paper_results):
    folder, results = paper_results
    found = tables(folder, results)
    assert set(found) == {0, 3, 4, 5, 6}  # no checkpoints here: tables 1 and 2 say so instead
    lap_montmelo = load_circuit("montmelo").length_m / 9.0
    explicit = row(found[3], "Explicit brain (PID)")
    assert explicit["Lapped"] == "1/1"
    assert math.isclose(float(explicit["Lap (s)"]), lap_montmelo, abs_tol=1.5)
    assert float(explicit["Avg speed (m/s)"]) == pytest.approx(9.0, abs=0.1)
    assert list(found[3].rows[0][3::2]) == ["78", "3.01", "9.34"]  # the paper's, beside each of ours
    assert row(found[3], "memDCCP")["Lap (s)"] != explicit["Lap (s)"]

    table4 = found[4]
    assert table4.columns == ["Brain", "none / grey / walls", "red / grey / walls / reverse"]
    lap_simple = load_circuit("simple").length_m / 8.0
    memdccp = row(table4, "memDCCP")["none / grey / walls"]
    ours, paper = memdccp.split(" / ")
    assert math.isclose(float(ours.removesuffix(" s")), lap_simple, abs_tol=1.0) and paper == "72 s"
    assert row(table4, "Explicit brain (PID)")["none / grey / walls"] == "✗ crash 1/1 / ✗"
    assert row(table4, "mybrain")["red / grey / walls / reverse"].endswith(" s / –")  # the paper has no such row
    assert row(table4, "mybrain")["none / grey / walls"] == "– / –"  # and no episode here

    assert row(found[5], "Explicit brain (PID)")["camera moved left"].endswith(" / 123 s, 5.2")
    assert row(found[6], "memDCCP")["salt and pepper 0.6"].endswith(" s / ✗")
    circuits = row(found[0], "mybrain")
    assert circuits["monaco"] == "✗ crash 1/1" and circuits["monaco (reverse)"].endswith(" s")


def test_the_report_of_a_paper_run_carries_the_tables_and_paper_md(paper_results):
    folder, _ = paper_results
    files = write_report(folder)
    paper_md = (folder / "paper.md").read_text()
    for number in (3, 4, 5, 6):
        assert f"Table {number}:" in paper_md and f"Table {number}:" in files.markdown.read_text()
    assert "Table 4: simple" in files.html.read_text()


@pytest.mark.slow
def test_drivebench_paper_smoke_runs_end_to_end(tmp_path):
    out = tmp_path / "paper"
    done = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", "paper", "--smoke", "-o", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    paper_md = (out / "paper.md").read_text()
    for number in range(1, 7):
        assert f"Table {number}:" in paper_md, paper_md
    assert "| DeepestLSTMTinyPilotNet | deepest_lstm_tiny_pilotnet | 62k (62,470) / 62k |" in paper_md
    with ResultStore(out, create=False) as store:
        results = store.results()
    assert len(results) == len(smoke_matrix(load_matrix(PAPER_FILE)).episodes)
    assert all(r.status == "done" and r.score is not None for r in results)
    assert {r.key.split(":")[0] for r in results} == set(PARTS)


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--file", "experiments/smoke.yaml"], "not a paper matrix"),
        (["--file", "experiments/nothing.yaml"], "cannot read the matrix file"),
        (["--resume"], "--resume needs -o DIR"),
    ],
)
def test_paper_mistakes_are_one_line(args, words):
    done = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", "paper", *args], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 2 and words in done.stderr and done.stderr.count("\n") == 1, done.stderr


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.timeout(900)  # 20 short episodes, each on its own stack, on a loaded machine
def test_a_study_file_regenerates_its_tables_from_shipped_checkpoints_in_smoke_form(tmp_path):
    """`drivebench paper --file experiments/memory_study.yaml --smoke`: two training runs of each brain (shipped under
    brains/weights/study), the first cells of each part, and the report compares them with intervals."""
    out = tmp_path / "study"
    done = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", "paper", "--file", "experiments/memory_study.yaml", "--smoke"]
        + ["-o", str(out), "--renderer", "gl"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    with ResultStore(out, create=False) as store:
        results = store.results()
    assert {r.key.split(":")[1].split("/")[0] for r in results} == {"tiny-s0", "tiny-s1", "memdccp-s0", "memdccp-s1"}
    assert all(r.status == "done" and r.score is not None for r in results)
    report = (out / "report.md").read_text()
    assert "Comparison with intervals" in report and "P(X > Y), all conditions [95 % CI: these conditions" in report
    assert "| memdccp | tiny |" in report or "| tiny | memdccp |" in report
