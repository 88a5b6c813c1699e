"""What a matrix report is made from: :class:`ReportData`, an output folder's results and facts, the labels of its
axes, and cached access to the circuits and trajectory files the plots draw.

The tables (:mod:`orchestrator.report.matrix`) and the plots (:mod:`orchestrator.report.plots`) both take one
:class:`ReportData`; what they find out while drawing goes into its ``notes`` and the files they write into its
``plots``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from orchestrator.matrix.results import BASELINE_FACT, DATABASE_NAME, EpisodeResult, ResultStore
from orchestrator.report.cells import baseline_variation, ordered
from orchestrator.report.trajectories import Track, load_trajectory

NO_PERTURBATION = "none"
PAPER_FACT = "paper"  # results-database fact set by drivebench paper: the report then carries the paper's tables
PLOTS_DIR = "plots"


class ReportError(RuntimeError):
    """The report cannot be made (no results database, an empty one, ...); one line that names the path."""


@dataclass(kw_only=True)
class ReportData:
    """A matrix's results as the report reads them.

    folder: the output folder read (``results.sqlite``, trajectory files). plots_dir: where the PNG files go.
    results: the episodes, in matrix order. brains, circuits, variations, perturbations: their labels in order of
    first appearance (``none`` first among perturbations). baseline_variation: the baseline condition's variation.
    notes: problems met while drawing (appended). plots: every file written (appended).
    """

    folder: Path
    plots_dir: Path
    results: list[EpisodeResult]
    name: str
    variation_keys: list[Any]
    created_at: Any
    is_paper: bool
    brains: list[str]
    circuits: list[str]
    variations: list[str]
    perturbations: list[str]
    baseline_variation: str | None
    notes: list[str] = field(default_factory=list)
    plots: list[Path] = field(default_factory=list)
    _tracks: dict[str, Track | None] = field(default_factory=dict)
    _trajectories: dict[str, dict[str, np.ndarray] | None] = field(default_factory=dict)

    @classmethod
    def load(cls, folder: Path, *, output: Path) -> ReportData:
        """Read ``folder/results.sqlite``; :class:`ReportError` when there is no folder, database or episode."""
        database = folder / DATABASE_NAME
        if not folder.is_dir():
            raise ReportError(f"{folder}: no such folder")
        if not database.is_file():
            raise ReportError(f"{database}: no results database (run `drivebench matrix FILE -o {folder}` first)")
        store = ResultStore.read_only(folder)  # a report never changes the results it reads
        try:
            results = store.results()
            facts = {key: store.fact(key) for key in ("name", BASELINE_FACT, "variation_keys")}
            created_at, is_paper = store.fact("created_at"), bool(store.fact(PAPER_FACT))
        finally:
            store.close()
        if not results:
            raise ReportError(f"{database}: no episodes recorded yet (an empty matrix, or one that has not run)")
        perturbations = ordered(r.perturbation for r in results)
        return cls(
            folder=folder,
            plots_dir=output / PLOTS_DIR,
            results=results,
            name=facts["name"] or folder.resolve().name,
            variation_keys=facts["variation_keys"] or [],
            created_at=created_at,
            is_paper=is_paper,
            brains=ordered(r.brain for r in results),
            circuits=ordered(r.circuit for r in results),
            variations=ordered(r.variation for r in results),
            perturbations=([NO_PERTURBATION] if NO_PERTURBATION in perturbations else [])
            + [p for p in perturbations if p != NO_PERTURBATION],
            baseline_variation=baseline_variation(results, facts[BASELINE_FACT]),
        )

    def track(self, circuit: str) -> Track | None:
        """The circuit's drawing, or None (with a note) when it cannot be loaded."""
        if circuit not in self._tracks:
            from circuits import CircuitError, load_circuit

            try:
                self._tracks[circuit] = Track(load_circuit(circuit))
            except (CircuitError, ValueError, OSError) as error:
                self.notes.append(f"circuit {circuit!r} not drawn: {error}")
                self._tracks[circuit] = None
        return self._tracks[circuit]

    def trajectory(self, result: EpisodeResult) -> dict[str, np.ndarray] | None:
        """The episode's trajectory arrays, or None when its file is missing or unreadable."""
        if result.key not in self._trajectories:
            self._trajectories[result.key] = load_trajectory(self.folder, result.trajectory)
        return self._trajectories[result.key]

    def baseline(self) -> tuple[list[EpisodeResult], str]:
        """Episodes of the baseline condition and a sentence saying what it is."""
        chosen = [
            r for r in self.results if r.perturbation == NO_PERTURBATION and r.variation == self.baseline_variation
        ]
        if chosen:
            return chosen, (
                f"Baseline condition: variation `{self.baseline_variation}`, perturbation `{NO_PERTURBATION}`."
            )
        return list(self.results), (
            "The matrix has no episode in the baseline condition (first variation, no "
            "perturbation): every episode is pooled."
        )
