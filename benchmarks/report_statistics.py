"""What the report's comparison with intervals costs on a large results file, side by side in one run: writing the
matrix report of N synthetic episodes without the comparison section, then with it.

    .venv/bin/python benchmarks/report_statistics.py [--episodes 10000] [--brains 2] [--seeds 5]

The episodes are brains x seeds x conditions, each scored by a real EpisodeScore (progress drawn per brain and
condition); there are no trajectory files, so the report's trajectory plots are skipped for both cases alike.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import msgspec
import numpy as np

from orchestrator.matrix.plan import BrainEntry
from orchestrator.matrix.results import BASELINE_FACT, EpisodeResult, ResultStore
from orchestrator.report import comparison as comparison_module
from orchestrator.report import matrix as matrix_report
from orchestrator.report.document import Section
from protocol.episode_spec import EpisodeSpec
from protocol.messages import EndReason, EpisodeMetrics, EpisodeScore, Header


def metrics_with(progress_laps: float) -> EpisodeMetrics:
    # Raw values of the struct's fields, of several types (bool, float, int, list, None): msgspec.convert checks them.
    fields: dict[str, object] = {
        field.name: False if field.type is bool else 0.0 for field in msgspec.structs.fields(EpisodeMetrics)
    }
    fields.update(
        steps=100, completed_laps=int(progress_laps >= 1.0), lap_times_s=[], off_track_events=0,
        bm_lap_seconds=None, progress_laps=progress_laps,
    )  # fmt: skip
    return msgspec.convert(fields, EpisodeMetrics)


def fill(folder: Path, *, brains: int, seeds: int, episodes: int) -> None:
    conditions = max(1, episodes // (brains * seeds))
    rng = np.random.default_rng(0)
    with ResultStore(folder) as store:
        store.set_fact("name", "bench")
        store.set_fact("source_text", "name: bench\n")
        store.set_fact("variation_keys", [])
        store.set_fact(BASELINE_FACT, "default")
        store.set_fact("created_at", 1_700_000_000.0)
        index = 0
        for brain in range(brains):
            skill = 0.5 + 0.1 * brain
            for seed in range(seeds):
                for condition in range(conditions):
                    progress = float(np.clip(rng.normal(skill, 0.3), 0.0, 1.0))
                    label, circuit = f"b{brain}-s{seed}", f"random:{condition}"
                    spec = EpisodeSpec(circuit=circuit, laps=1, seed=0, active_brain=label)
                    reason = EndReason.LAPS_COMPLETED if progress >= 1.0 else EndReason.CRASH
                    score = EpisodeScore(
                        header=Header(run_id=f"r{index}", episode=0, seq=0, stamp_ns=0), spec=spec, reason=reason,
                        brain=label, metrics=metrics_with(progress),
                    )  # fmt: skip
                    store.record(
                        EpisodeResult(
                            key=f"{label}/{circuit}/default/none/r0", index=index, brain=label, circuit=circuit,
                            variation="default", perturbation="none", repetition=0, spec=spec,
                            brain_entry=BrainEntry(label=label, brain="x", group=f"b{brain}", training_seed=seed),
                            status="done", run_id=f"r{index}", started_at=0.0, ended_at=1.0, reason=str(reason),
                            score=score,
                        )
                    )  # fmt: skip
                    index += 1


def timed_report(folder: Path, output: Path) -> float:
    started = time.perf_counter()
    matrix_report.write_report(folder, output=output)
    return time.perf_counter() - started


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=10_000)
    parser.add_argument("--brains", type=int, default=2)
    parser.add_argument("--seeds", type=int, default=5)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "results"
        folder.mkdir()
        print(f"filling {args.episodes} episodes ...", file=sys.stderr)
        fill(folder, brains=args.brains, seeds=args.seeds, episodes=args.episodes)
        with_statistics = matrix_report.MatrixReport.comparison
        matrix_report.MatrixReport.comparison = lambda self: Section("Comparison with intervals")  # type: ignore[method-assign]
        without = timed_report(folder, Path(tmp) / "without")
        matrix_report.MatrixReport.comparison = with_statistics  # type: ignore[method-assign]
        with_ = timed_report(folder, Path(tmp) / "with")
        results = ResultStore(folder, create=False).results()
        started = time.perf_counter()
        comparison_module.brain_scores(results)
        scores_s = time.perf_counter() - started
    print(f"| report of {args.episodes} episodes ({args.brains} brains x {args.seeds} seeds) | seconds |")
    print("|---|---:|")
    print(f"| without the comparison section | {without:.1f} |")
    print(f"| with it (2,000 resamples per interval) | {with_:.1f} |")
    print(f"| the statistics' share | {with_ - without:.1f} ({(with_ - without) / with_:.0%}) |")
    print(f"| of which gathering the score arrays | {scores_s:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
