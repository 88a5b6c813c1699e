"""The simulator's pure core: one episode of one car on one circuit, stepped by (speed, yaw rate) commands.

No bus here: the service (``services/simulator/service.py``) and the in-process benchmark both drive this class.
The simulator owns the clock: step n covers sim time [n, n+1) * step_s, and frame n is rendered at the pose the
car has at the start of step n.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from circuits import Circuit, load_circuit
from protocol.episode_spec import EpisodeSpec, WorldVariation
from protocol.messages import EndReason
from services.simulator.car import CarState, integrate_unicycle
from services.simulator.renderers import Renderer, make_scene, resolve_renderer

# Behavior Metrics' F1 car is ~1 m long and ~0.4 m wide (the 0.2-scaled Renault mesh). It touches a wall when its
# centre is closer than half its width to the road edge.
CAR_HALF_WIDTH_M = 0.2


class SceneCache:
    """Scenes by circuit, world variation and renderer: building one costs far more than a step, and episodes reuse
    them.

    A circuit is known by its name *and* its geometry (:func:`geometry_key`): a circuit driven in reverse keeps its
    name, but its scene is built from the centreline in the other order, and the two rasterise differently by a few
    edge pixels a frame. One scene for both made an episode on a warm simulator see other frames than on a fresh one.

    Keeps at most ``capacity`` scenes (each holds a PyBullet client or GL buffers, and the circuit's meshes); the
    least recently used goes first.
    """

    def __init__(self, *, capacity: int = 4) -> None:
        self._scenes: dict[tuple[str, str, WorldVariation, str], Renderer] = {}
        self._capacity = capacity

    def get(
        self, circuit: Circuit, world: WorldVariation = WorldVariation(), *, renderer: str = "pybullet"
    ) -> Renderer:
        """The scene, drawn by ``renderer`` ("pybullet" or "gl"; "auto" is resolved here, in the rendering thread)."""
        renderer = resolve_renderer(renderer).name
        key = (circuit.name, geometry_key(circuit), world, renderer)
        scene = self._scenes.pop(key, None)
        if scene is None:
            while len(self._scenes) >= self._capacity:
                self._scenes.pop(next(iter(self._scenes))).close()
            scene = make_scene(circuit, world, renderer=renderer)
        self._scenes[key] = scene  # most recently used last
        return scene

    def close(self) -> None:
        for scene in self._scenes.values():
            scene.close()
        self._scenes.clear()


def geometry_key(circuit: Circuit) -> str:
    """A digest of everything of ``circuit`` a scene is built from: the centreline's points in driving order (a
    reversed circuit has the same points in the other order), the road and line widths and the wall height."""
    digest = hashlib.sha256(np.ascontiguousarray(circuit.centreline.points_m, dtype=np.float64).tobytes())
    digest.update(
        np.array([circuit.road_half_width_m, circuit.line_width_m, circuit.wall_height_m], dtype=np.float64).tobytes()
    )
    return digest.hexdigest()


@dataclass(frozen=True)
class StepResult:
    """What one step produced. ``end`` is None while the episode goes on; ``lap`` is the lap just completed, or 0."""

    car: CarState
    stamp_ns: int
    seq: int
    lateral_m: float
    lap: int
    end: EndReason | None


class EpisodeSim:
    """One episode: the car starts ``spec.start_m`` along the circuit (0: its start line); ``step`` applies a command
    for one period. Progress and laps count from where it started.

    The scene is the circuit's own whatever ``start_m`` is: only the car's first pose moves. (A circuit re-ordered to
    begin at ``start_m`` would be another key of the scene cache, rebuilt, and rasterised a few pixels apart.)
    """

    def __init__(self, spec: EpisodeSpec, *, scenes: SceneCache, circuit: Circuit | None = None):
        self.spec = spec
        self.circuit = circuit or load_circuit(spec.circuit, direction=spec.direction)
        x_m, y_m, yaw_rad = self.circuit.start_pose(start_m=spec.start_m)  # first: a bad start_m builds no scene
        self._scene = scenes.get(self.circuit, spec.world, renderer=spec.renderer)
        self.car = CarState(x_m=x_m, y_m=y_m, yaw_rad=yaw_rad)
        self.seq = 0
        self._s_m = float(spec.start_m)  # the first projection searches near where the car is
        self.progress_m = 0.0
        self.laps_completed = 0
        self._max_steps = int(np.ceil(spec.max_sim_seconds / spec.step_s - 1e-9))
        # Without walls the car is off track when its centre leaves the road; with them it crashes when its side
        # touches the wall on the road edge.
        self.walls = spec.world.walls
        self._edge_m = self.circuit.road_half_width_m - (CAR_HALF_WIDTH_M if self.walls else 0.0)

    @property
    def stamp_ns(self) -> int:
        return self.seq * self.spec.step_ns

    def render(self) -> np.ndarray:
        """The camera image at the current pose (H x W x 3 uint8 RGB)."""
        return self._scene.render(self.car, self.spec.camera)

    def step(self, *, speed_mps: float, yaw_rate_radps: float) -> StepResult:
        """Move the car for one period with the command, then check how the episode stands."""
        self.car = integrate_unicycle(
            self.car, speed_mps=speed_mps, yaw_rate_radps=yaw_rate_radps, dt_s=self.spec.step_s
        )
        self.seq += 1
        projection = self.circuit.centreline.project(self.car.x_m, self.car.y_m, near_s_m=self._s_m)
        self.progress_m += float(self.circuit.centreline.wrap_ds(projection.s_m - self._s_m))
        self._s_m = projection.s_m
        lap = 0
        laps_now = int(self.progress_m // self.circuit.length_m)
        if laps_now > self.laps_completed:
            self.laps_completed = lap = laps_now
        return StepResult(
            car=self.car,
            stamp_ns=self.stamp_ns,
            seq=self.seq,
            lateral_m=projection.lateral_m,
            lap=lap,
            end=self._end_reason(projection.lateral_m),
        )

    def _end_reason(self, lateral_m: float) -> EndReason | None:
        if abs(lateral_m) > self._edge_m:
            return EndReason.CRASH if self.walls else EndReason.OFF_TRACK
        if self.laps_completed >= self.spec.laps:
            return EndReason.LAPS_COMPLETED
        if self.seq >= self._max_steps:
            return EndReason.TIME_LIMIT
        return None
