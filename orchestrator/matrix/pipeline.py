"""One matrix run from its parsed file to its results (:class:`MatrixRun`): what ``drivebench matrix`` and
``drivebench paper`` do between parsing their command line and printing.

Before the first episode, in one walk over the planned episodes: each episode's renderer chosen (the command line's
over the file's; "auto" resolved here, where the stacks run, or left to each node on a Ray cluster) and its look
checked against that renderer; then the noise models' extras and every brain (weights load and fit, options are
taken). Then the output folder: refused when it holds results and this is no resume, fitted to them when it is. Then
the episodes, on this machine's workers (:class:`orchestrator.matrix.runner.MatrixRunner`) or on a Ray cluster
(:class:`orchestrator.matrix.ray_runner.RayMatrixRunner`). A mistake the user can fix is :class:`RunRefused`, one
line naming what and where.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import msgspec

from orchestrator.matrix.executor import RunOptions, brain_launch
from orchestrator.matrix.plan import Matrix
from orchestrator.matrix.ray_options import RayOptions
from orchestrator.matrix.results import DATABASE_NAME, ResultsError, ResultStore
from orchestrator.matrix.resume import resume_matrix
from orchestrator.matrix.runner import MatrixProgress, MatrixRunner


class RunRefused(ValueError):
    """The matrix cannot run as asked (a renderer this machine lacks, a look its renderer cannot draw, a missing
    extra, a brain that fails its preflight, a folder that holds other results): one line."""


class MatrixRun:
    """Runs ``matrix`` into ``out_dir`` as ``options`` say, on a Ray cluster when ``ray_options`` is given.

    renderer: the command line's renderer for every episode (None: each episode's own). notify: where a line for the
    user goes (what a resume adds to the results). :meth:`prepare` checks and fits everything before the first
    episode (and :attr:`matrix` is then the matrix as it runs); :meth:`run` runs it.
    """

    def __init__(
        self,
        matrix: Matrix,
        *,
        out_dir: Path,
        options: RunOptions,
        ray_options: RayOptions | None = None,
        renderer: str | None = None,
        notify: Callable[[str], None] = lambda line: None,
    ):
        self.matrix = matrix
        self.out_dir = Path(out_dir)
        self.options = options
        self.ray_options = ray_options
        self._renderer = renderer
        self._notify = notify

    def prepare(self) -> Matrix:
        """Every check before the first episode, then the output folder made; the matrix as it will run."""
        self.matrix = self._checked(self.matrix)
        self._preflight_brains()
        if not self.options.resume and (self.out_dir / DATABASE_NAME).exists():
            raise RunRefused(
                f"{self.out_dir} already holds matrix results: add --resume to finish that run, or choose another "
                "-o folder"
            )
        if self.options.resume:
            self.matrix = self._fitted(self.matrix)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        return self.matrix

    def run(self, *, on_change: Callable[[MatrixProgress], None] | None = None) -> MatrixProgress:
        """Run the (prepared) matrix's episodes; ``on_change`` follows the progress. Ctrl-C propagates (finished
        episodes are kept; a resume runs the rest)."""
        if self.ray_options is None:
            return MatrixRunner(self.matrix, self.out_dir, self.options, on_change=on_change).run()
        from orchestrator.matrix.ray_runner import RayMatrixRunner  # ray only when asked for

        return RayMatrixRunner(
            self.matrix, self.out_dir, self.options, ray_options=self.ray_options, on_change=on_change
        ).run()

    def _checked(self, matrix: Matrix) -> Matrix:
        """Each episode with its renderer chosen and its look checked, in one walk; then the noise's extras."""
        from protocol.variations import VariationError, check_look
        from services.noise.models import MissingExtra, require_extras

        chosen: dict[str, str] = {}
        episodes = []
        stages = []  # every episode's noise stages, for the extras they need
        for episode in matrix.episodes:
            spec = msgspec.structs.replace(episode.spec, renderer=self._choose(episode.spec.renderer, chosen))
            try:
                check_look(spec)
            except VariationError as error:
                raise RunRefused(f"{matrix.name}: {error}") from None
            episodes.append(dataclasses.replace(episode, spec=spec))
            stages.extend(spec.noise)
        try:
            require_extras(stages)
        except MissingExtra as error:
            raise RunRefused(f"{matrix.name}: {error}") from None
        return dataclasses.replace(matrix, episodes=tuple(episodes))

    def _choose(self, renderer: str, chosen: dict[str, str]) -> str:
        """An episode's renderer: the command line's over the file's, "auto" resolved where the stacks run (one
        notice on stderr when it falls back; on a cluster, each node's simulator resolves it: this machine's EGL
        says nothing about theirs), "gl" checked before the first episode."""
        from services.simulator.renderers import choose_renderer

        wanted = self._renderer or renderer
        if self.ray_options is not None and wanted == "auto":
            return wanted
        if wanted not in chosen:
            try:
                chosen[wanted] = choose_renderer(wanted)
            except ValueError as error:
                raise RunRefused(f"{self.matrix.name}: {error}") from None
        return chosen[wanted]

    def _preflight_brains(self) -> None:
        """Every brain of the matrix checked before the first episode (weights load and fit, options are taken)."""
        from orchestrator.stack.launcher import preflight_launches

        for entry in self.matrix.brains + self.matrix.shadows:
            try:
                preflight_launches([brain_launch(entry)])
            except ValueError as error:
                raise RunRefused(f"{self.matrix.name}: brain {entry.label!r}: {error}") from None

    def _fitted(self, matrix: Matrix) -> Matrix:
        """``--resume``: ``matrix`` fitted to the folder's results; refused when it changed what they ran, noted
        when it adds episodes to them."""
        if not (self.out_dir / DATABASE_NAME).is_file():
            return matrix
        try:
            with ResultStore(self.out_dir, create=False) as store:
                resumed = resume_matrix(matrix, store)
        except ResultsError as error:
            raise RunRefused(str(error)) from None
        if (note := resumed.note()) is not None:
            self._notify(f"resume: {note}")
        return resumed.matrix


__all__ = ["MatrixRun", "RunRefused"]
