"""Closed-mesh test: rays leaving the inside of the watertight camel must all hit it.

A ray from inside a closed mesh that hits nothing went through a crack between two
triangles. Three families of rays, all from points inside (winding number > 1/2, from
libigl):
- axis-aligned rays through vertices *exactly*: the origin is the vertex moved inward
  along one axis only, so the ray's other two coordinates are the vertex's own;
- the same through edge midpoints;
- rays from random interior points aimed at random vertices.
``watertight`` must have zero cracks under every structure (the `structure` fixture of
conftest.py: brute force, BVH, kd-tree, octree, BSP tree, grid). The other two kernels
leak through shared edges by design; the stability suite measures by how much (case 1,
``tests/test_stability.py``).
"""

from __future__ import annotations

import igl
import numpy as np
import pytest

import jrt

PER_FAMILY = 8_000


def _inside(mesh, points):
    wn = igl.winding_number(mesh.vertices.astype(np.float64), mesh.faces.astype(np.int64),
                            points.astype(np.float64))
    return wn > 0.5


def _axis_aligned_through(mesh, targets, normals, rng, step):
    """Rays along ±x/±y/±z (closest to the outward normal) ending at ``targets``."""
    axis = np.argmax(np.abs(normals), axis=1)
    sign = np.sign(normals[np.arange(len(normals)), axis])
    directions = np.zeros_like(targets)
    directions[np.arange(len(targets)), axis] = sign
    origins = targets - step * directions  # only the axis coordinate changes
    keep = _inside(mesh, origins)
    return origins[keep].astype(np.float32), directions[keep].astype(np.float32)


@pytest.fixture(scope="module")
def crack_rays(camel):
    rng = np.random.default_rng(7)
    v, f = camel.vertices, camel.faces
    step = 2e-3 * camel.diagonal
    vn = igl.per_vertex_normals(v.astype(np.float64), f.astype(np.int64))
    pick = rng.choice(len(v), PER_FAMILY, replace=False)
    families = {"vertices": _axis_aligned_through(camel, v[pick], vn[pick], rng, step)}

    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    pick = rng.choice(len(edges), PER_FAMILY, replace=False)
    midpoints = ((v[edges[pick, 0]] + v[edges[pick, 1]]) / 2).astype(np.float32)
    edge_normals = vn[edges[pick, 0]] + vn[edges[pick, 1]]
    families["edge midpoints"] = _axis_aligned_through(camel, midpoints, edge_normals, rng, step)

    lo, hi = camel.bounds
    candidates = lo + rng.uniform(size=(20 * PER_FAMILY, 3)) * (hi - lo)
    interior = candidates[_inside(camel, candidates)][:PER_FAMILY].astype(np.float32)
    targets = v[rng.choice(len(v), len(interior))]
    directions = targets - interior
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    families["interior to vertices"] = (interior, directions.astype(np.float32))
    for name, (o, _) in families.items():
        assert len(o) > PER_FAMILY // 4, f"too few interior origins for {name}"
    return families


def test_no_cracks_from_inside(structure, crack_rays):
    cracks = {}
    for name, (origins, directions) in crack_rays.items():
        hits = jrt.closest_hit(structure, origins, directions, kernel="watertight")
        cracks[name] = (int((np.asarray(hits.triangle) < 0).sum()), len(origins))
    print(f"\n{structure.kind} / watertight: cracks (misses / rays): {cracks}")
    assert all(missed == 0 for missed, _ in cracks.values()), cracks
