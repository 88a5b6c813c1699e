"""A closed centreline: arc length, projection of a point onto it, points at an arc length.

Pure geometry (NumPy + SciPy), shared by the simulator (start pose, off-track test) and the scorer (cross-track
error, progress). Frame: world, metres; lateral offsets are positive to the *left* of the driving direction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


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

    def project(self, x_m: float, y_m: float, *, near_s_m: float | None = None, k: int = 8) -> Projection:
        """Project a point onto the centreline.

        Looks at the segments around the ``k`` nearest vertices. Where the track passes close to itself (hairpins,
        parallel straights) the nearest vertex can be on the wrong branch; given ``near_s_m`` (the previous
        projection), the candidate with the arc length closest to it wins among those at about the same distance.
        """
        k = min(k, len(self.points_m))
        _, vertex_ids = self._tree.query((x_m, y_m), k=k)
        vertex_ids = np.atleast_1d(vertex_ids)
        segments = np.unique(np.concatenate([vertex_ids, (vertex_ids - 1) % len(self.points_m)]))
        starts = self.points_m[segments]
        vectors = self._segment_vectors[segments]
        lengths = self._segment_lengths[segments]
        rel = np.array([x_m, y_m]) - starts
        t = np.clip(np.einsum("ij,ij->i", rel, vectors) / lengths**2, 0.0, 1.0)
        closest = starts + t[:, None] * vectors
        distances = np.hypot(*(np.array([x_m, y_m]) - closest).T)
        s_candidates = (self.s_m[segments] + t * lengths) % self.length_m
        best = int(np.argmin(distances))
        if near_s_m is not None:
            # Among candidates not much farther than the closest, prefer continuity of arc length.
            plausible = distances <= distances[best] + 1.0
            gaps = np.abs(self.wrap_ds(s_candidates - near_s_m))
            gaps[~plausible] = np.inf
            best = int(np.argmin(gaps))
        cross = vectors[best, 0] * rel[best, 1] - vectors[best, 1] * rel[best, 0]
        lateral = math.copysign(float(distances[best]), cross) if cross != 0 else 0.0
        return Projection(s_m=float(s_candidates[best]), lateral_m=lateral, segment=int(segments[best]))

    def wrap_ds(self, ds_m):
        """Wrap an arc-length difference into (-L/2, L/2]: the shorter way round."""
        half = self.length_m / 2
        return half - np.mod(half - np.asarray(ds_m, dtype=float), self.length_m)
