"""What a Ray episode task (or an episode slot's ``drive``) streams back to the driver, and what the driver reads when
the task failed instead: typed items, decided on by their type (issue 41: they were dicts keyed by strings, and the
error was raised only to be caught)."""

from __future__ import annotations

import dataclasses

from orchestrator.matrix.ray_options import import_ray
from orchestrator.matrix.results import EpisodeResult


@dataclasses.dataclass(frozen=True)
class LiveItem:
    """A stream item: a running episode's live metrics, encoded (:mod:`protocol.codec`, as on the bus)."""

    data: bytes


@dataclasses.dataclass(frozen=True)
class OutcomeItem:
    """A stream's last item: the episode's result and its small files (path relative to its folder -> bytes)."""

    result: EpisodeResult
    files: dict[str, bytes]


@dataclasses.dataclass(frozen=True)
class TaskError:
    """What the driver reads instead of an item when the task failed (Ray raises it where the item would be)."""

    error: BaseException


StreamItem = LiveItem | OutcomeItem


def next_item(stream) -> StreamItem | TaskError:
    """The next item of a task's stream, or :class:`TaskError` when the task failed (Ray raises it where the item
    would be)."""
    ray = import_ray()
    try:
        return ray.get(next(stream))
    except StopIteration:
        return TaskError(RuntimeError("the episode's task ended without a result"))
    except ray.exceptions.RayError as error:
        return TaskError(error)
