"""The board's verdict on an evaluation's results: which endings are the brain's fault, typed, and intervals that
never have zero width (orchestrator/board/scoring.py, on the result rows the matrix runner writes)."""

from __future__ import annotations

import msgspec

from orchestrator.board.scoring import verdict
from orchestrator.board.store import Rejection
from orchestrator.matrix.plan import BrainEntry
from orchestrator.matrix.results import EpisodeResult
from orchestrator.stack.failures import Failure, FailureKind
from protocol.episode_spec import EpisodeSpec
from protocol.messages import EndReason, EpisodeMetrics, EpisodeScore, Header


def _metrics(progress_laps: float) -> EpisodeMetrics:
    fields = {f.name: False if f.type is bool else 0.0 for f in msgspec.structs.fields(EpisodeMetrics)}
    fields.update(steps=10, completed_laps=int(progress_laps >= 1), lap_times_s=[], off_track_events=0)
    fields.update(bm_lap_seconds=None, progress_laps=progress_laps)
    return msgspec.convert(fields, EpisodeMetrics)


def _result(index: int, *, part: str, progress_laps: float = 0.5, failure: Failure | None = None) -> EpisodeResult:
    spec = EpisodeSpec(circuit="simple", laps=1, active_brain="submission")
    score = None
    if failure is None:
        reason = EndReason.LAPS_COMPLETED if progress_laps >= 1 else EndReason.TIME_LIMIT
        header = Header(run_id=f"r{index}", episode=0, seq=0, stamp_ns=0)
        score = EpisodeScore(
            header=header, spec=spec, reason=reason, brain="submission", metrics=_metrics(progress_laps)
        )
    return EpisodeResult(
        key=f"{part}:submission/simple/c{index}/none/r0", index=index, brain="submission", circuit="simple",
        variation=f"c{index}", perturbation="none", repetition=0, spec=spec,
        brain_entry=BrainEntry(label="submission", brain="submission"), status="failed" if failure else "done",
        run_id=f"r{index}", started_at=0.0, ended_at=1.0, reason="", failure=failure, score=score,
    )  # fmt: skip


def test_a_brain_that_does_not_start_in_time_is_too_slow_not_a_server_error():
    """Before, only the failure's stored text was looked up, and brain_start_timeout was not there: a brain sleeping
    in __init__ cost three evaluations and ended ``error``, as if the server had failed."""
    late = Failure(FailureKind.BRAIN_START_TIMEOUT, "the brain host did not come up within 30 s")
    outcome = verdict([_result(0, part="public"), _result(1, part="hidden", failure=late)])
    assert outcome.rejection == Rejection.TOO_SLOW and not outcome.server_error


def test_a_failure_on_the_servers_side_is_not_the_brains():
    outcome = verdict([_result(0, part="hidden", failure=Failure(FailureKind.SIMULATOR_DIED, "exit 1"))])
    assert outcome.server_error and outcome.rejection is None


def test_one_hidden_condition_gives_an_interval_of_the_whole_scale_never_of_zero_width():
    scores = verdict([_result(0, part="public"), _result(1, part="hidden", progress_laps=0.5)]).scores
    assert scores is not None
    progress = scores["hidden"]["progress_iqm"]
    assert progress["estimate"] == 0.5 and (progress["low"], progress["high"]) == (0.0, 1.0)


def test_several_hidden_conditions_give_a_bootstrap_interval_around_the_iqm():
    results = [_result(i, part="hidden", progress_laps=p) for i, p in enumerate([0.2, 0.4, 0.6, 0.8, 1.0, 0.3])]
    progress = verdict(results).scores["hidden"]["progress_iqm"]
    assert progress["low"] < progress["estimate"] < progress["high"]
