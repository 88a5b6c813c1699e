"""Renderer backends of one scene, chosen by name (``EpisodeSpec.renderer``, ``--renderer``).

``pybullet``: PyBullet's TinyRenderer (:class:`services.simulator.scene.Scene`), the reference. ``gl``: moderngl on
a headless EGL context (:class:`services.simulator.gl_scene.GLScene`), the same scene description drawn ~10x faster.
``auto``: gl where an EGL context can be made in this process, else pybullet, with a one-line notice saying why.

Both backends satisfy :class:`Renderer`. A GL context is bound to the thread that made it: resolve ``auto`` and
render in the same thread (the simulator's main loop does both).
"""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass
from typing import Protocol, Self

import msgspec
import numpy as np

from circuits import Circuit
from protocol import environment
from protocol.episode_spec import LOOK_RENDERERS, RENDERERS, CameraSpec, EpisodeSpec, WorldVariation
from services.simulator.car import CarState

log = logging.getLogger("drivebench.simulator")

RENDERER_ENV = environment.RENDERER.name  # the default of --renderer where a camera is configured (compose sets it)


class Renderer(Protocol):
    """What the simulator needs of a scene backend."""

    def render(self, car: CarState, camera: CameraSpec) -> np.ndarray:
        """The camera image at ``car``: height_px x width_px x 3 uint8 RGB, row 0 at the top."""

    def close(self) -> None:
        """Release the backend's resources; idempotent."""

    def __enter__(self) -> Self:
        """The scene itself: ``with make_scene(...) as scene`` closes it on the way out."""

    def __exit__(self, *exc_info: object) -> None:
        """:meth:`close`."""


@dataclass(frozen=True)
class Resolution:
    """The renderer to use for a request: ``name`` is "pybullet" or "gl"; ``notice`` says why auto fell back."""

    name: str
    notice: str | None = None


class RendererUnavailable(ValueError):
    """The requested renderer cannot run here (one line: what and why); a ValueError, so that the commands report
    it as the usage mistake it is, in one line."""


def default_renderer(fallback: str = environment.RENDERER_BY_COMMAND["run"]) -> str:
    """The ``--renderer`` default: $DRIVEBENCH_RENDERER when set, else ``fallback``; ValueError names a bad value."""
    value = environment.RENDERER.value().strip() or fallback
    if value not in RENDERERS:
        raise ValueError(f"{RENDERER_ENV} must be one of {', '.join(RENDERERS)}, got {value!r}")
    return value


def resolve_renderer(requested: str) -> Resolution:
    """The concrete renderer for ``requested`` (pybullet, gl or auto), probing EGL in this thread when needed.

    Raises RendererUnavailable for ``gl`` where no EGL context can be made, ValueError for an unknown name.
    """
    if requested not in RENDERERS:
        raise ValueError(f"renderer must be one of {', '.join(RENDERERS)}, got {requested!r}")
    if requested == "pybullet":
        return Resolution("pybullet")
    from services.simulator.gl_scene import egl_unavailable_reason

    reason = egl_unavailable_reason()
    if reason is None:
        return Resolution("gl")
    if requested == "gl":
        raise RendererUnavailable(f"renderer gl: {reason}")
    return Resolution("pybullet", notice=f"renderer auto: using pybullet ({reason})")


def choose_renderer(
    requested: str | None,
    *,
    fallback: str = environment.RENDERER_BY_COMMAND["run"],
    local: bool = True,
    look: str = "flat",
) -> str:
    """The renderer a command puts in its specs: ``requested`` (--renderer), else $DRIVEBENCH_RENDERER, else
    ``fallback``. For a stack started here (``local``) "auto" is resolved now, its notice printed on stderr in one
    line, and "gl" is checked; an attached stack's simulator resolves it there. ValueError says what is wrong,
    RendererUnavailable (one line) where "auto" falls back to a renderer that cannot draw ``look``."""
    name = requested or default_renderer(fallback)
    if not local:
        return name
    resolution = resolve_renderer(name)
    if resolution.notice and resolution.name not in LOOK_RENDERERS[look]:
        raise RendererUnavailable(f"look={look} needs the gl renderer: {resolution.notice}")
    if resolution.notice:
        print(f"drivebench: {resolution.notice}", file=sys.stderr)
    return resolution.name


def resolve_spec(spec: EpisodeSpec) -> EpisodeSpec:
    """``spec`` with ``renderer`` resolved (auto replaced by the choice, its notice logged once as a warning)."""
    resolution = resolve_renderer(spec.renderer)
    if resolution.notice:
        log.warning("%s", resolution.notice)
    if resolution.name == spec.renderer:
        return spec
    return msgspec.structs.replace(spec, renderer=resolution.name)


def make_scene(circuit: Circuit, world: WorldVariation, *, renderer: str) -> Renderer:
    """A scene of ``circuit`` with ``world`` drawn by ``renderer`` ("pybullet" or "gl"; resolve "auto" first).

    RendererUnavailable when ``renderer`` cannot draw ``world.look`` (the commands check that before starting)."""
    if renderer not in LOOK_RENDERERS[world.look]:
        raise RendererUnavailable(
            f"renderer {renderer} cannot draw look={world.look} (it needs {' or '.join(LOOK_RENDERERS[world.look])})"
        )
    if renderer == "pybullet":
        from services.simulator.scene import Scene

        return Scene.for_world(circuit, world)
    if renderer == "gl":
        from services.simulator.gl_scene import GLScene

        return GLScene.for_world(circuit, world)
    raise ValueError(f"make_scene needs a concrete renderer (pybullet or gl), got {renderer!r}")
