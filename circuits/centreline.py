"""A closed centreline: arc length, projection of a point onto it, points at an arc length.

Pure geometry (NumPy + SciPy), shared by the simulator (start pose, off-track test) and the scorer (cross-track
error, progress). Frame: world, metres; lateral offsets are positive to the *left* of the driving direction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# Half-width of the arc-length window searched around a moving point's previous projection: wider than any
# distance a car covers in one step, narrower than the gap between two branches of a track along its length.
TRACKING_WINDOW_M = 8.0


@dataclass(frozen=True)
class Projection:
    """Where a point lies relative to the centreline.

    s_m: arc length of the closest centreline point, in [0, length_m).
    lateral_m: signed distance, + left of the driving direction.
    segment: index i of the closest segment (points i -> i+1).
    """

    s_m: float
    lateral_m: float
    segment: int


class Centreline:
    """A closed polyline in driving order. ``points_m[-1]`` is *not* a repeat of ``points_m[0]``."""

    def __init__(self, points_m: np.ndarray):
        points = np.asarray(points_m, dtype=float)
        if points.ndim != 2 or points.shape[1] != 2 or len(points) < 3:
            raise ValueError(f"a centreline needs N >= 3 points of (x, y), got shape {points.shape}")
        if not np.all(np.isfinite(points)):
            raise ValueError("centreline points must be finite")
        self.points_m = points
        self._next = np.roll(points, -1, axis=0)
        self._segment_vectors = self._next - points
        self._segment_lengths = np.hypot(self._segment_vectors[:, 0], self._segment_vectors[:, 1])
        if np.any(self._segment_lengths <= 0):
            raise ValueError("centreline has repeated consecutive points")
        self.s_m = np.concatenate([[0.0], np.cumsum(self._segment_lengths)[:-1]])
        self.length_m = float(np.sum(self._segment_lengths))
        # Lazy, as every scipy import of circuits/: importing the package (protocol.environment does, for
        # circuits.variables) must not cost a light process scipy's second of start-up.
        from scipy.spatial import cKDTree

        self._tree = cKDTree(points)

    def __len__(self) -> int:
        return len(self.points_m)

    def headings_rad(self) -> np.ndarray:
        """Heading of each segment (points i -> i+1), anticlockwise from world x."""
        return np.arctan2(self._segment_vectors[:, 1], self._segment_vectors[:, 0])

    def left_normals(self) -> np.ndarray:
        """Unit normal pointing left at each point (average of the adjacent segments' normals)."""
        tangent = self._segment_vectors / self._segment_lengths[:, None]
        averaged = tangent + np.roll(tangent, 1, axis=0)
        averaged /= np.linalg.norm(averaged, axis=1)[:, None]
        return np.stack([-averaged[:, 1], averaged[:, 0]], axis=1)

    def pose_at(self, s_m: float) -> tuple[float, float, float]:
        """(x_m, y_m, heading_rad) on the centreline at arc length ``s_m`` (wrapped)."""
        s = s_m % self.length_m
        i = int(np.searchsorted(self.s_m, s, side="right") - 1)
        t = (s - self.s_m[i]) / self._segment_lengths[i]
        x, y = self.points_m[i] + t * self._segment_vectors[i]
        vx, vy = self._segment_vectors[i]
        return float(x), float(y), math.atan2(vy, vx)

    def project(
        self, x_m: float, y_m: float, *, near_s_m: float | None = None, window_m: float = TRACKING_WINDOW_M
    ) -> Projection:
        """Project a point onto the centreline.

        Without ``near_s_m``: the closest point, searched around the 8 nearest vertices. With ``near_s_m`` (the
        previous projection of a moving point), only segments within ``window_m`` of arc length of it are searched,
        so a point cannot jump to another branch where the track passes close to itself (hairpins, parallel
        straights); a best point on the window's edge means the point was lost, and the global search decides.
        """
        if near_s_m is None:
            return self._project_global(x_m, y_m)
        count = len(self.points_m)
        half = int(math.ceil(window_m / (self.length_m / count))) + 1
        if 2 * half + 1 >= count:
            return self._project_global(x_m, y_m)
        centre = int(np.searchsorted(self.s_m, near_s_m % self.length_m, side="right") - 1)
        segments = (centre + np.arange(-half, half + 1)) % count
        best, t, distance, cross = self._closest_of(segments, x_m, y_m)
        if (best == 0 and t == 0.0) or (best == len(segments) - 1 and t == 1.0):
            return self._project_global(x_m, y_m)
        return self._projection(int(segments[best]), t, distance, cross)

    def project_many(self, x_m: np.ndarray, y_m: np.ndarray, *, k: int = 4) -> tuple[np.ndarray, np.ndarray]:
        """(arc lengths s_m, signed distances lateral_m, + left) of many points at once, each by the global search
        (the segments next to its ``k`` nearest vertices): for drawing and statistics over whole trajectories. A
        moving car's figures come from :meth:`project` with ``near_s_m``, which cannot jump between close branches."""
        xy = np.column_stack([np.asarray(x_m, dtype=float), np.asarray(y_m, dtype=float)])
        if len(xy) == 0:
            return np.zeros(0), np.zeros(0)
        _, vertex_ids = self._tree.query(xy, k=min(k, len(self.points_m)))
        vertex_ids = vertex_ids.reshape(len(xy), -1)
        segments = np.concatenate([vertex_ids, (vertex_ids - 1) % len(self.points_m)], axis=1)  # (N, 2k)
        starts, vectors = self.points_m[segments], self._segment_vectors[segments]
        rel = xy[:, None, :] - starts
        t = np.clip(np.sum(rel * vectors, axis=2) / self._segment_lengths[segments] ** 2, 0.0, 1.0)
        gap = rel - t[..., None] * vectors
        distance = np.hypot(gap[..., 0], gap[..., 1])
        best = np.argmin(distance, axis=1)
        rows = np.arange(len(xy))
        cross = vectors[rows, best, 0] * rel[rows, best, 1] - vectors[rows, best, 1] * rel[rows, best, 0]
        segment = segments[rows, best]
        s_m = (self.s_m[segment] + t[rows, best] * self._segment_lengths[segment]) % self.length_m
        return s_m, np.where(cross != 0, np.copysign(distance[rows, best], cross), 0.0)

    def _project_global(self, x_m: float, y_m: float, k: int = 8) -> Projection:
        _, vertex_ids = self._tree.query((x_m, y_m), k=min(k, len(self.points_m)))
        vertex_ids = np.atleast_1d(vertex_ids)
        segments = np.unique(np.concatenate([vertex_ids, (vertex_ids - 1) % len(self.points_m)]))
        best, t, distance, cross = self._closest_of(segments, x_m, y_m)
        return self._projection(int(segments[best]), t, distance, cross)

    def _closest_of(self, segments: np.ndarray, x_m: float, y_m: float) -> tuple[int, float, float, float]:
        """(index into ``segments`` of the closest, its parameter t in [0, 1], distance, cross product sign)."""
        starts = self.points_m[segments]
        vectors = self._segment_vectors[segments]
        rel_x = x_m - starts[:, 0]
        rel_y = y_m - starts[:, 1]
        t = np.clip((rel_x * vectors[:, 0] + rel_y * vectors[:, 1]) / self._segment_lengths[segments] ** 2, 0.0, 1.0)
        dx = rel_x - t * vectors[:, 0]
        dy = rel_y - t * vectors[:, 1]
        d_sq = dx * dx + dy * dy
        best = int(np.argmin(d_sq))
        cross = float(vectors[best, 0] * rel_y[best] - vectors[best, 1] * rel_x[best])
        return best, float(t[best]), math.sqrt(float(d_sq[best])), cross

    def _projection(self, segment: int, t: float, distance: float, cross: float) -> Projection:
        s = float((self.s_m[segment] + t * self._segment_lengths[segment]) % self.length_m)
        lateral = math.copysign(distance, cross) if cross != 0 else 0.0
        return Projection(s_m=s, lateral_m=lateral, segment=segment)

    def wrap_ds(self, ds_m):
        """Wrap an arc-length difference into (-L/2, L/2]: the shorter way round."""
        half = self.length_m / 2
        return half - np.mod(half - np.asarray(ds_m, dtype=float), self.length_m)
