"""What goes into the report's cells: statistics over an episode's repetitions (:func:`mean_std`, :func:`grid_cell`),
how an episode ended (:func:`lap_seconds`, :func:`reached_target`, :func:`outcome`), the baseline condition
(:func:`baseline_variation`) and the small formatting helpers of numbers, durations, dates and names.

Pure functions of :class:`~orchestrator.matrix.results.EpisodeResult` and plain values, kept apart from the report's
tables and plots so that both, and ``drivebench paper`` (:mod:`orchestrator.report.paper`), read an episode alike.
"""

from __future__ import annotations

import math
import re
import statistics
from collections import Counter
from collections.abc import Iterable, Sequence
from datetime import datetime
from typing import Any

from orchestrator.matrix.results import EpisodeResult
from orchestrator.report.columns import first_lap_s
from orchestrator.report.document import FAIL_MARK
from protocol.messages import EpisodeMetrics

DEFAULT_VARIATION = "default"


# -- small helpers --------------------------------------------------------------------------------------------------


def ordered(values: Iterable[str]) -> list[str]:
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
    """The episode's first-lap time (:func:`~orchestrator.report.columns.first_lap_s`); None when the episode completed
    no lap or was not scored."""
    return None if result.score is None else first_lap_s(result.score.metrics)


def reached_target(result: EpisodeResult) -> bool:
    """Ran and was scored, and completed its lap target."""
    return (
        result.status == "done" and result.score is not None and result.score.metrics.completed_laps >= result.spec.laps
    )


def outcome(result: EpisodeResult) -> str:
    """A short word for how an episode ended: the failure kind of a stack failure, else the episode's end reason."""
    if result.status == "failed":
        return result.failure_kind or "failed"
    if result.reason:
        return str(result.reason)
    return str(result.score.reason) if result.score is not None else "not_scored"


def scored_only(results: Iterable[EpisodeResult]) -> list[EpisodeResult]:
    """Episodes the brain is judged on: ran and scored (stack failures are not the brain's doing)."""
    return [r for r in results if r.status == "done" and r.score is not None]


def metrics_of(result: EpisodeResult) -> EpisodeMetrics:
    """The metrics of an episode known to be scored (one of :func:`scored_only`, or one that reached its target)."""
    assert result.score is not None, f"{result.key} has no score"
    return result.score.metrics


def failure_summary(results: Sequence[EpisodeResult]) -> str:
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
        scored = scored_only(results)
        if scored:
            text += f" · {statistics.fmean(metrics_of(r).percentage_completed for r in scored):.0f} %"
    return text


def baseline_variation(results: Sequence[EpisodeResult], planned: str | None = None) -> str | None:
    """The variation label of the baseline condition: ``"default"`` when present, else ``planned`` (the first planned
    episode's variation, the first value of every axis, which the runner stores as the ``baseline_variation`` fact)
    when some episode has it, else the variation of the first stored episode in matrix order."""
    labels = ordered(r.variation for r in sorted(results, key=lambda r: r.index))
    if not labels:
        return None
    if DEFAULT_VARIATION in labels:
        return DEFAULT_VARIATION
    return planned if planned in labels else labels[0]


def optional_number(value: Any, digits: int) -> str:
    if value is None:
        return "–"
    try:
        return _fmt_number(float(value), digits)
    except (TypeError, ValueError):
        return str(value)


def brief(items: Sequence[Any], limit: int = 160) -> str:
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
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _short(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.3g}"
    return str(value)


def duration_text(seconds: float) -> str:
    seconds = max(0.0, float(seconds))
    if seconds < 60:
        return f"{seconds:.1f} s"
    minutes, secs = divmod(round(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d} min"


def date_text(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, (int, float)):
        return datetime.fromtimestamp(float(value)).strftime("%Y-%m-%d %H:%M:%S")
    return str(value)


def slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("_") or "circuit"
