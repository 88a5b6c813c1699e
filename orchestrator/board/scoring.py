"""A submission's scores from its evaluation's results, and the leaderboard's ranking.

Over the hidden conditions: lap success (k of n, Clopper-Pearson) and normalised progress (its IQM, with a
bootstrap interval that resamples the conditions). A submission is one training run, so both intervals are over
conditions: how it would score on other conditions drawn alike, not how its recipe would score retrained; the page
says so. The public conditions are shown cell by cell. The bootstrap's seed is fixed: the same results give the
same numbers.

Ranking: by IQM progress; an entry's rank is one more than the number of entries whose interval lies wholly above
its own, so entries whose intervals overlap share a rank (they are not ordered with confidence).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from orchestrator.board.challenge import HIDDEN, PUBLIC
from orchestrator.board.store import Rejection
from orchestrator.matrix.results import EpisodeResult
from orchestrator.report.comparison import progress_of, success_of
from orchestrator.report.statistics import clopper_pearson, iqm, run_bootstrap
from orchestrator.stack.failures import FailureKind
from protocol.messages import EndReason

OVER_CONDITIONS = "over the hidden conditions (one submission is one training run: the interval is over conditions)"
_BOOTSTRAP_SEED = 0

# A stack failure or an episode ending that the brain caused, by its kind (the sandbox's kinds included); every
# other kind is the server's side (the evaluation runs again).
REJECTION_OF_FAILURE = {
    FailureKind.BRAIN_DIED: Rejection.CRASHED,
    FailureKind.SANDBOX_VIOLATION: Rejection.SANDBOX_VIOLATION,
    FailureKind.LIMIT_EXCEEDED: Rejection.EXCEEDED_LIMIT,
    FailureKind.BRAIN_START_TIMEOUT: Rejection.TOO_SLOW,
}
REJECTION_OF_END = {
    EndReason.BRAIN_LOST: Rejection.CRASHED,
    EndReason.BRAIN_TIMEOUT: Rejection.TOO_SLOW,
    EndReason.BRAIN_INVALID: Rejection.BREAKS_CONTRACT,
}


@dataclass(frozen=True)
class Verdict:
    """The outcome of an evaluation: scores, or a rejection (typed, with one line), or a server-side error."""

    scores: dict[str, Any] | None = None
    rejection: Rejection | None = None
    detail: str = ""
    server_error: bool = False


def verdict(results: list[EpisodeResult]) -> Verdict:
    """Scores when every episode ran and the brain caused no ending; else what went wrong, the brain's fault first."""
    for result in results:
        rejection = _brain_fault(result)
        if rejection is not None:
            where = f"on public condition {result.circuit} {result.variation}" if _part(result) == PUBLIC else ""
            return Verdict(rejection=rejection, detail=f"{rejection} {where or 'on a hidden condition'}".strip())
    failed = [result for result in results if result.status != "done"]
    if failed:
        return Verdict(server_error=True, detail=f"{len(failed)} episode(s) failed on the server's side")
    return Verdict(scores=scores_of(results))


def _brain_fault(result: EpisodeResult) -> Rejection | None:
    if result.failure is not None:
        return REJECTION_OF_FAILURE.get(result.failure.kind)
    if result.score is not None:
        return REJECTION_OF_END.get(result.score.reason)
    return None


def _part(result: EpisodeResult) -> str:
    return result.key.partition(":")[0]


def scores_of(results: list[EpisodeResult]) -> dict[str, Any]:
    """JSON-able scores: ``hidden`` (aggregates only) and ``public`` (one cell per episode)."""
    hidden = [result for result in results if _part(result) == HIDDEN]
    public = [result for result in results if _part(result) == PUBLIC]
    return {"hidden": hidden_scores(hidden), "public": [_cell(result) for result in public]}


def hidden_scores(results: list[EpisodeResult]) -> dict[str, Any]:
    successes = int(sum(success_of(result) for result in results))
    progress = np.array([progress_of(result) for result in results], dtype=float)
    low, high = clopper_pearson(successes, len(results))
    return {
        "conditions": len(results),
        "success": {"estimate": successes / len(results), "low": low, "high": high, "successes": successes},
        "progress_iqm": _progress_interval(progress),
        "interval": OVER_CONDITIONS,
    }


def _progress_interval(progress: np.ndarray) -> dict[str, float]:
    """IQM of normalised progress with a 95 % bootstrap interval over conditions: each condition a row, so the
    bootstrap that resamples runs resamples conditions (plain percentiles: conditions are not few runs). One
    condition says nothing of the others: the interval is then the whole scale, never of zero width."""
    if len(progress) < 2:
        value = float(progress.mean()) if len(progress) else 0.0
        return {"estimate": value, "low": 0.0, "high": 1.0}
    interval = run_bootstrap([progress.reshape(-1, 1)], iqm, seed=_BOOTSTRAP_SEED, expanded=False)
    return {"estimate": interval.estimate, "low": interval.low, "high": interval.high}


def _cell(result: EpisodeResult) -> dict[str, Any]:
    return {
        "circuit": result.circuit,
        "variation": result.variation,
        "perturbation": result.perturbation,
        "end": str(result.score.reason) if result.score else str(result.failure),
        "success": success_of(result),
        "progress": progress_of(result),
    }


def ranks(estimates: list[tuple[float, float, float]]) -> list[int]:
    """Rank of each (estimate, low, high): 1 + how many intervals lie wholly above its own."""
    return [1 + sum(1 for _, other_low, _ in estimates if other_low > high) for _, _, high in estimates]
