"""Host-side geometry helpers shared by the builders (NumPy only)."""

from __future__ import annotations

import numpy as np


def triangle_vertices(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """float32 [F, 3, 3]: the three corners of every face."""
    return np.ascontiguousarray(np.asarray(vertices, np.float32)[np.asarray(faces)])


def doubled_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """float64 [F]: |(x_j - x_i) x (x_k - x_i)| (seed, Proposition 3.1), twice the area.

    Evaluated in float64 from the float32 corners, so that "zero" means the corners are
    truly collinear (or repeated) in the stored float32 geometry.
    """
    corners = triangle_vertices(vertices, faces).astype(np.float64)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return np.linalg.norm(normal, axis=1)


def degenerate_mask(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """bool [F]: faces of zero area (repeated or collinear corners). They are never hit."""
    return doubled_areas(vertices, faces) == 0.0


def bounds(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) corners of the axis-aligned bounding box, float32 [3] each."""
    v = np.asarray(vertices, np.float32)
    return v.min(axis=0), v.max(axis=0)
