"""``--resume`` against the results a folder already holds: the same matrix, or the same one with episodes added.

A results folder holds one matrix's episodes. Resuming it with a matrix file that changed what an episode is (its
limits, seed, camera, world, noise, brain, weights, options, shadows) would put episodes of two experiments in one
report, so it is refused, naming what changed; so is a file that dropped episodes the results hold (a circuit
removed). A file that only adds episodes (a repetition, a brain, a circuit) resumes: the finished episodes are
kept and the new ones run.

Episode folders are ``episodes/<index>`` and rows are ordered by index: finished episodes keep the index they ran
under, and the others take the free ones in expansion order, so no new episode lands in a kept episode's folder.
Pure functions of the matrix and the stored results, but for :func:`resume_matrix`, which reads them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Any

import msgspec

from orchestrator.matrix.plan import Matrix, PlannedEpisode
from orchestrator.matrix.results import EpisodeResult, ResultsError, ResultStore

PLANNED_KEYS_FACT = "planned_keys"  # results fact: the keys of every episode the matrix planned, in order
SHOWN_CHANGES = 3  # differences named in the error; the rest are counted


class MatrixChangedError(ResultsError):
    """The matrix file changed what the stored results ran (one line: the folder and what changed)."""


@dataclass(frozen=True)
class Resumed:
    """A matrix fitted to the results it resumes: ``matrix`` with indices that keep the finished episodes' folders;
    ``kept`` finished episodes it holds; ``added`` planned episodes the results' matrix did not have."""

    matrix: Matrix
    kept: int
    added: int

    def note(self) -> str | None:
        """What a resume with added episodes does (one line), or None when the matrix is the same."""
        if not self.added:
            return None
        return f"the matrix file adds episodes: {self.kept} finished episode(s) kept, {self.added} new"


def resume_matrix(matrix: Matrix, store: ResultStore) -> Resumed:
    """``matrix`` fitted to the results in ``store`` (see :func:`fit_to_results`), named by the store's folder."""
    results = store.results()
    return fit_to_results(
        matrix,
        results,
        shadows=store.fact("shadows") if results else None,
        planned_before=store.fact(PLANNED_KEYS_FACT),
        where=str(store.path.parent),
    )


def fit_to_results(
    matrix: Matrix,
    results: list[EpisodeResult],
    *,
    shadows: list[dict] | None,
    planned_before: list[str] | None,
    where: str,
) -> Resumed:
    """``matrix`` as it resumes ``results`` (the folder's rows); raises :class:`MatrixChangedError` when it changed
    them. ``shadows``: the shadow entries the results ran with; ``planned_before``: the episode keys the results'
    matrix planned (each None when the folder does not say: results written before these were kept)."""
    changes = list(_changes(matrix, results, shadows=shadows))
    if changes:
        shown = "; ".join(changes[:SHOWN_CHANGES]) + (
            f"; and {len(changes) - SHOWN_CHANGES} more" if len(changes) > SHOWN_CHANGES else ""
        )
        raise MatrixChangedError(
            f"{where}: the matrix file changed since these results ({shown}); resume with the file as it was, "
            "or run it into another -o folder"
        )
    stored = {result.key: result.index for result in results}
    # Without the earlier plan (results written before it was kept) an unfinished episode and a new one look
    # alike: nothing is called new then.
    before = set(planned_before or ()) | set(stored)
    added = 0 if planned_before is None else sum(1 for episode in matrix.episodes if episode.key not in before)
    return Resumed(matrix=_keep_indices(matrix, stored), kept=len(stored), added=added)


def _changes(matrix: Matrix, results: list[EpisodeResult], *, shadows: list[dict] | None) -> Iterator[str]:
    planned = {episode.key: episode for episode in matrix.episodes}
    gone = [result for result in results if result.key not in planned]
    if gone:
        yield _gone(gone, matrix.episodes)
    if shadows is not None and shadows != [shadow.to_dict() for shadow in matrix.shadows]:
        yield f"shadows {_labels(shadows)} -> {_labels(shadow.to_dict() for shadow in matrix.shadows)}"
    seen: set[str] = set()
    for result in results:
        episode = planned.get(result.key)
        if episode is None:
            continue
        for change in (*_spec_changes(result, episode), *_brain_changes(result, episode)):
            if change not in seen:  # one line per change, however many episodes it touches
                seen.add(change)
                yield change


def _gone(gone: list[EpisodeResult], planned: Iterable[PlannedEpisode]) -> str:
    """What the file dropped, by axis where one names it (``circuits removed: montreal``)."""
    planned = list(planned)
    for axis in ("brain", "circuit", "variation", "perturbation", "repetition"):
        # A result names its brain by label; a planned episode holds the whole entry.
        now = {episode.brain.label if axis == "brain" else getattr(episode, axis) for episode in planned}
        removed = sorted({str(getattr(result, axis)) for result in gone if getattr(result, axis) not in now})
        if removed:
            return f"{axis}s removed: {', '.join(removed)}"
    return f"{len(gone)} finished episode(s) no longer in the matrix (first: {gone[0].key})"


def _spec_changes(result: EpisodeResult, episode: PlannedEpisode) -> list[str]:
    before, after = _flat(msgspec.to_builtins(result.spec)), _flat(msgspec.to_builtins(episode.spec))
    return [
        f"{field} {before.get(field)!r} -> {after.get(field)!r}"
        for field in dict.fromkeys([*before, *after])
        if before.get(field) != after.get(field)
    ]


def _brain_changes(result: EpisodeResult, episode: PlannedEpisode) -> list[str]:
    before, after = result.brain_entry.to_dict(), episode.brain.to_dict()
    return [
        f"brain {episode.brain.label!r} {field} {before.get(field)!r} -> {after.get(field)!r}"
        for field in dict.fromkeys([*before, *after])
        if before.get(field) != after.get(field)
    ]


def _flat(value: Any, prefix: str = "") -> dict[str, Any]:
    """Nested mappings as ``{"camera.width_px": 160, ...}``, so a change is named by its field."""
    if not isinstance(value, dict):
        return {prefix: value}
    flat: dict[str, Any] = {}
    for key, item in value.items():
        flat.update(_flat(item, f"{prefix}.{key}" if prefix else str(key)))
    return flat


def _labels(entries: Iterable[dict]) -> str:
    return "[" + ", ".join(str(entry.get("label")) for entry in entries) + "]"


def _keep_indices(matrix: Matrix, stored: dict[str, int]) -> Matrix:
    """``matrix`` with each stored episode at its stored index and the others at the free indices, in order."""
    if all(stored.get(episode.key, episode.index) == episode.index for episode in matrix.episodes):
        return matrix
    taken = set(stored.values())
    free = (index for index in range(len(matrix.episodes) + len(taken)) if index not in taken)
    episodes = tuple(
        dataclasses.replace(episode, index=stored[episode.key] if episode.key in stored else next(free))
        for episode in matrix.episodes
    )
    return dataclasses.replace(matrix, episodes=episodes)
