"""Every structure builds and traces wherever the mesh sits: moved far from the origin,
scaled up or down, and two meshes far apart.

Each structure is built in its local frame (``accel.geometry.frame_origin``), so its
margins follow the scene's extent, not its position. Checked here on the 19k camel against
the same camel at the origin, and against brute force on the same float32 triangles:

- the build is as large as at the origin: references within 1.25x of the same float32
  triangles moved back to the origin, bytes within 2x of the camel at the origin;
- rays from inside the closed mesh aimed at its vertices and edge midpoints (where a kernel
  or a structure can let a ray slip between triangles) all hit, and every structure
  returns brute force's hits bit for bit (t, triangle, u, v), with watertight;
- two camels 1e3 apart, far from the origin: the same.

The octree and the grid check their layouts in the frame in their own test files.
"""

from __future__ import annotations

import numpy as np
import pytest

import accel
import jrt
from benchmarks.stability import aimed_rays

STRUCTURES = accel.names(engine=True)
#: (label, scale, shift): the camel is about 1.4 units across.
PLACES = (("moved 1e3", 1.0, (1000.0, -700.0, 1300.0)),
          ("moved 1e5", 1.0, (1e5, -7e4, 1.3e5)),
          ("scaled 1e-4", 1e-4, (0.0, 0.0, 0.0)),
          ("scaled 1e4", 1e4, (0.0, 0.0, 0.0)))
#: Rays per scene, half aimed at vertices and half at edge midpoints.
RAYS = 1024


def size_of(structure) -> int:
    """References of a leaf-referencing structure (triangles for the BVH)."""
    return int(structure.stats.get("references", structure.num_triangles))


@pytest.fixture(scope="module")
def scenes(camel19k):
    """label -> (vertices, faces, origins, directions, brute force's hits)."""
    out = {}
    for label, scale, shift in (("origin", 1.0, (0.0, 0.0, 0.0)),) + PLACES:
        # The transform in float64, then float32: the aim points are the placed mesh's own.
        v = (camel19k.vertices.astype(np.float64) * scale + np.asarray(shift)).astype(
            np.float32)
        o, d = aimed_rays(v, camel19k.faces, RAYS)
        brute = accel.build("brute", v, camel19k.faces)
        out[label] = (v, camel19k.faces, o, d, jrt.closest_hit(brute, o, d))
    return out


def assert_same_hits(got, want):
    for field in ("t", "triangle", "u", "v"):
        np.testing.assert_array_equal(np.asarray(getattr(got, field)),
                                      np.asarray(getattr(want, field)), err_msg=field)


@pytest.mark.parametrize("kind", STRUCTURES)
def test_builds_and_traces_anywhere(scenes, kind):
    v0, f0, *_ = scenes["origin"]
    at_origin = accel.build(kind, v0, f0)
    for label, _, shift in PLACES:
        v, f, o, d, want = scenes[label]
        structure = accel.build(kind, v, f)
        # The same float32 triangles moved back to the origin (exact: the shift is a float32
        # multiple of the far mesh's ulp): far away, float32 rounds the camel itself (at
        # 1e5, 30 % of its faces to zero area), so that mesh is the fair comparison; a
        # scaled camel is compared with the camel at the origin.
        back = (accel.build(kind, (v.astype(np.float64) - np.asarray(shift)).astype(
            np.float32), f) if any(shift) else at_origin)
        refs = size_of(structure) / size_of(back)
        memory = structure.nbytes / at_origin.nbytes
        assert refs <= 1.25, f"{kind}, {label}: {refs:.2f}x the references moved back"
        assert memory <= 2.0, f"{kind}, {label}: {memory:.2f}x the bytes at the origin"
        assert bool((np.asarray(want.triangle) >= 0).all()), f"brute force cracks: {label}"
        assert_same_hits(jrt.closest_hit(structure, o, d), want)


@pytest.mark.parametrize("kind", STRUCTURES)
def test_two_camels_far_apart(camel19k, kind):
    """Two camels 1e3 apart along x, 1e4 from the origin: rays aimed at each one's
    vertices and edges, brute force's hits bit for bit and no crack."""
    base = camel19k.vertices.astype(np.float64)
    first = base + np.array([1e4, 2e3, -3e3])
    second = first + np.array([1e3, 0.0, 0.0])
    v = np.concatenate([first, second]).astype(np.float32)
    f = np.concatenate([camel19k.faces, camel19k.faces + len(base)])
    rays = [aimed_rays(part.astype(np.float32), camel19k.faces, RAYS, seed=k)
            for k, part in enumerate((first, second))]
    half = RAYS // 2  # half of each camel's rays: one compiled shape for every test
    o = np.concatenate([r[0][:half] for r in rays])
    d = np.concatenate([r[1][:half] for r in rays])
    want = jrt.closest_hit(accel.build("brute", v, f), o, d)
    got = jrt.closest_hit(accel.build(kind, v, f), o, d)
    assert (np.asarray(want.triangle) >= 0).all()
    assert_same_hits(got, want)
