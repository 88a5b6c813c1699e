"""Power before driving (issue 39): what difference in lap success rate a design of R training runs x C conditions
detects, simulated from a pilot's results folder or a given run-to-run spread; `drivebench matrix FILE --plan
--power PILOT_DIR` prints it before anything runs."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from brains.neural.checkpoint import read_checkpoint, write_checkpoint
from orchestrator.cli import main
from orchestrator.report.power import (
    PowerError,
    Spread,
    detectable,
    power_curve,
    simulate,
    spread_given,
    spread_of_results,
)

ROOT = Path(__file__).resolve().parent.parent
PILOT = ROOT / "tests" / "fixtures" / "results-0.1.0"
TINY = ROOT / "brains" / "weights" / "deepest_lstm_tiny_pilotnet.ckpt"


def test_more_runs_detect_smaller_differences():
    spread = spread_given(run_spread=0.25, base_rate=0.3)
    found = {
        runs: detectable(power_curve(spread, runs=runs, conditions=30, studies=200, resamples=500))
        for runs in (3, 10, 30)
    }
    assert found[30] is not None and found[10] is not None
    assert found[30] < found[10] and (found[3] is None or found[10] < found[3]), found


def test_without_a_run_effect_small_differences_are_found_and_none_is_found_at_random():
    spread = Spread(base_rate=0.5, run_sd=0.0, condition_sd=0.0, source="test")
    curve = power_curve(spread, runs=10, conditions=40, differences=(0.0, 0.15), studies=300, resamples=500)
    assert curve[0].power <= 0.1  # no difference: the interval excludes 0 about 5 % of the time
    assert curve[1].power >= 0.8


def test_a_given_spread_is_the_spread_of_run_success_rates():
    spread = spread_given(run_spread=0.2, base_rate=0.4)
    rates = simulate(spread, runs=4000, conditions=400, studies=1, rng=np.random.default_rng(0))[0].mean(axis=1)
    assert rates.mean() == pytest.approx(0.4, abs=0.01)
    # The run means' spread: the runs' own plus the binomial part of 400 conditions.
    assert np.sqrt(rates.var() - 0.4 * 0.6 / 400) == pytest.approx(0.2, abs=0.02)
    with pytest.raises(PowerError, match="--base-rate"):
        spread_given(run_spread=0.2, base_rate=1.0)


def test_a_pilot_folder_gives_its_spread(tmp_path):
    pilot = tmp_path / "pilot"
    shutil.copytree(PILOT, pilot)
    spread = spread_of_results(pilot)
    assert spread.base_rate == pytest.approx(0.75) and "tiny (2 runs)" in spread.source
    with pytest.raises(PowerError, match="no results database"):
        spread_of_results(tmp_path / "nowhere")


def write_runs(folder: Path, seeds) -> None:
    for seed in seeds:
        raw = read_checkpoint(TINY)
        raw["training"] = {**raw.get("training", {}), "seed": seed}
        (folder / f"seed-{seed}").mkdir(parents=True, exist_ok=True)
        write_checkpoint(raw, folder / f"seed-{seed}" / "model.ckpt")


def write_study(folder: Path, *, brains: str) -> Path:
    path = folder / "study.yaml"
    path.write_text(f"name: study\nbrains:\n{brains}\ncircuits: [simple, many_curves]\nrepetitions: 3\n")
    return path


def test_drivebench_matrix_plan_power_sizes_the_study(tmp_path, capsys):
    write_runs(tmp_path / "runs", (0, 1, 2, 3))
    study = write_study(
        tmp_path, brains="  - {name: deepest_lstm_tiny_pilotnet, label: tiny, weights: runs/seed-*/model.ckpt}"
    )
    pilot = tmp_path / "pilot"
    shutil.copytree(PILOT, pilot)
    assert main(["matrix", str(study), "--plan", "--power", str(pilot)]) == 0
    out = capsys.readouterr().out
    assert "power of 4 training runs per brain x 6 conditions (paired), from pilot" in out, out
    assert "80%" in out
    assert main(["matrix", str(study), "--plan", "--run-spread", "0.1", "--base-rate", "0.3"]) == 0
    assert "runs' success rates spread by 0.10" in capsys.readouterr().out


def test_runs_sizes_a_study_before_its_seeds_are_trained(tmp_path, capsys):
    """One seed trained so far: `--runs 10` sizes the design the study will have (without it, one run has no
    interval to size), and more runs detect a smaller difference."""
    write_runs(tmp_path / "runs", (0,))
    study = write_study(
        tmp_path, brains="  - {name: deepest_lstm_tiny_pilotnet, label: tiny, weights: runs/seed-*/model.ckpt}"
    )
    detected = {}
    for runs in (3, 10):
        assert main(["matrix", str(study), "--plan", "--run-spread", "0.3", "--runs", str(runs)]) == 0
        out = capsys.readouterr().out
        assert f"power of {runs} training runs per brain x 6 conditions" in out, out
        detected[runs] = out.split("power of", 1)[1]
    assert detected[3] != detected[10]


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--power", "PILOT"], "go with --plan"),
        (["--plan", "--power", "nowhere"], "no results database"),
        (["--plan", "--power", "PILOT", "--run-spread", "0.1"], "not both"),
        (["--plan", "--run-spread", "0.1", "--with-explicit"], "no interval, so no power"),
        (["--plan", "--runs", "5"], "--runs goes with --power or --run-spread"),
        (["--plan", "--run-spread", "0.1", "--runs", "1"], "no interval, so no power"),
    ],
    ids=["without-plan", "no-pilot", "both", "one-run", "runs-alone", "runs-one"],
)
def test_power_mistakes_are_one_line(tmp_path, capsys, extra, message):
    write_runs(tmp_path / "runs", (0, 1))
    brains = "  - {name: deepest_lstm_tiny_pilotnet, label: tiny, weights: runs/seed-*/model.ckpt}"
    if "--with-explicit" in extra:
        extra, brains = [e for e in extra if e != "--with-explicit"], brains + "\n  - explicit"
    study = write_study(tmp_path, brains=brains)
    shutil.copytree(PILOT, tmp_path / "pilot")
    argv = ["matrix", str(study), *[str(tmp_path / "pilot") if e == "PILOT" else e for e in extra]]
    assert main(argv) == 2
    error = capsys.readouterr().err.strip()
    assert message in error and "\n" not in error and "Traceback" not in error, error
