"""Standard ray sets on a mesh, shared by the tests, the benchmarks and the reports.

- camera rays: one per pixel of a 3/4 view that frames the mesh (coherent);
- incoherent rays: origins uniform on a sphere around the mesh, each aimed at a uniform
  random point of the mesh's bounding box (rays cross the scene in all directions).
"""

from __future__ import annotations

import math

import numpy as np

from jrt.camera import camera_rays, frame_mesh

#: The camera set's framing margin: tighter than a picture's (:data:`jrt.camera.FRAME_MARGIN`),
#: so about 15 % of the camel's camera rays hit it rather than 10 %. It is a ray set for
#: measuring traversals, and every published figure was measured on it.
CAMERA_SET_MARGIN = 0.85


def camera_set(vertices, count: int, aspect: float = 4 / 3, **frame) -> tuple[np.ndarray, ...]:
    """About ``count`` camera rays (the image is ``width x height`` with the given aspect),
    framed by :func:`jrt.camera.frame_mesh` with ``margin=CAMERA_SET_MARGIN`` unless
    ``frame`` says otherwise.

    Returns float32 origins and unit directions [N, 3] with N = width * height >= count.
    """
    frame.setdefault("margin", CAMERA_SET_MARGIN)
    height = max(1, math.ceil(math.sqrt(count / aspect)))
    width = max(1, math.ceil(count / height))
    camera = frame_mesh(vertices, width=width, height=height, **frame)
    origins, directions = camera_rays(camera)
    return np.asarray(origins), np.asarray(directions)


def incoherent_set(vertices, count: int, seed: int = 0, radius_scale: float = 1.5):
    """``count`` rays from a sphere of ``radius_scale`` x the bounding radius, aimed inside.

    Returns float32 origins and unit directions [count, 3]; deterministic for a seed.
    """
    v = np.asarray(vertices, np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre = (lo + hi) / 2
    radius = np.linalg.norm(hi - lo) / 2 * radius_scale
    rng = np.random.default_rng(seed)
    on_sphere = rng.normal(size=(count, 3))
    on_sphere /= np.linalg.norm(on_sphere, axis=1, keepdims=True)
    origins = centre + radius * on_sphere
    targets = lo + rng.uniform(size=(count, 3)) * (hi - lo)
    directions = targets - origins
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return origins.astype(np.float32), directions.astype(np.float32)
