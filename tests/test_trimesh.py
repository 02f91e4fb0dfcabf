"""jrt.trimesh.RayMeshIntersector against trimesh's own intersector (trimesh.ray.ray_triangle,
float64) and Embree's (trimesh.ray.ray_pyembree, where embreex is installed), and against
closed forms on a box: vertices and edges counted once, contains on a cube, an open mesh,
a box at 1e4, a camera grid, trimesh's own functions through ``mesh.ray``."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from trimesh.ray import ray_triangle

import jrt
from jrt.trimesh import RayMeshIntersector

try:
    from trimesh.ray import ray_pyembree
    EMBREE = ray_pyembree.RayMeshIntersector
except Exception:  # noqa: BLE001  (no embreex: the Embree comparisons are skipped)
    EMBREE = None


def cube(scale=1.0):
    """trimesh's box, [-scale/2, scale/2]^3, 12 triangles."""
    return trimesh.creation.box(extents=[scale] * 3)


def grid_rays(mesh, n=24, seed=0):
    """A camera's grid of rays at the mesh from outside its box (slightly tilted, so that
    few rays meet an edge exactly), and the same rays with lengths from 0.1 to 10."""
    lo, hi = mesh.bounds
    centre, size = (lo + hi) / 2, (hi - lo).max()
    u, v = np.meshgrid(np.linspace(-0.6, 0.6, n), np.linspace(-0.6, 0.6, n))
    eye = centre + np.array([0.3137, 0.2113, -2.0419]) * size
    target = centre + np.stack([u.ravel(), v.ravel(), np.zeros(n * n)], axis=1) * size
    d = target - eye
    rng = np.random.default_rng(seed)
    return np.tile(eye, (n * n, 1)), d * rng.uniform(0.1, 10, (n * n, 1))


def by_ray(index_ray, index_tri, locations):
    """{ray: sorted list of (face, location)} for comparing hit lists in any order."""
    out = {}
    for r, f, p in zip(index_ray, index_tri, locations, strict=True):
        out.setdefault(int(r), []).append((int(f), tuple(p)))
    return {r: sorted(v) for r, v in out.items()}


def assert_same_hits(got, want, atol):
    """(locations, index_ray, index_tri) triples: the same faces per ray, locations to
    ``atol``."""
    a, b = by_ray(got[1], got[2], got[0]), by_ray(want[1], want[2], want[0])
    assert a.keys() == b.keys()
    for r in a:
        assert [f for f, _ in a[r]] == [f for f, _ in b[r]], r
        np.testing.assert_allclose([p for _, p in a[r]], [p for _, p in b[r]], atol=atol)


# --------------------------------------------------------------------------- conventions


def test_the_return_conventions_are_trimeshs():
    mesh = cube()
    ours, theirs = RayMeshIntersector(mesh), ray_triangle.RayMeshIntersector(mesh)
    origins = [[0.1, 0.2, -2.0], [5.0, 5.0, 5.0], [0.0, 0.0, 3.0]]
    directions = [[0, 0, 3.0], [0, 0, 1.0], [0, 0, -0.5]]  # lists, not unit
    for method in ("intersects_first", "intersects_any"):
        a = getattr(ours, method)(origins, directions)
        b = getattr(theirs, method)(origins, directions)
        assert a.dtype == b.dtype and a.shape == b.shape == (3,)
        np.testing.assert_array_equal(a, b)
    got = ours.intersects_location(origins, directions)
    want = theirs.intersects_location(origins, directions)
    assert [x.dtype for x in got] == [np.float64, np.int64, np.int64]
    assert_same_hits(got, want, atol=1e-6)
    index_tri, index_ray = ours.intersects_id(origins, directions)
    assert index_tri.dtype == index_ray.dtype == np.int64 and list(index_ray) == [0, 0, 2, 2]
    # One ray as a flat triple; the first hit only.
    tri, ray, loc = ours.intersects_id([0.1, 0.2, -2.0], [0, 0, 1.0], multiple_hits=False,
                                       return_locations=True)
    assert list(ray) == [0] and loc.shape == (1, 3)
    np.testing.assert_allclose(loc, [[0.1, 0.2, -0.5]], atol=1e-6)
    assert ours.mesh is mesh


def test_bad_input_is_named():
    ours = RayMeshIntersector(cube())
    with pytest.raises(ValueError, match="directions of ray 1"):
        ours.intersects_location([[0, 0, -2.0]] * 2, [[0, 0, 1.0], [0, 0, 0]])
    with pytest.raises(ValueError, match="one row per ray"):
        ours.intersects_any(np.zeros((2, 3)), np.ones((3, 3)))
    with pytest.raises(ValueError, match="max_hits must be a positive integer"):
        ours.intersects_id([[0, 0, -2.0]], [[0, 0, 1.0]], max_hits=0)
    with pytest.raises(ValueError, match="unknown structure 'quadtree'"):
        RayMeshIntersector(cube(), structure="quadtree")


# --------------------------------------------------------------------------- a box


@pytest.mark.parametrize("scale", [1.0, 1e4])
def test_vertices_and_edges_are_hit_once(scale):
    """Rays through the cube's vertices (each shared by 4-6 triangles), two opposite
    edges, and the top and the bottom face's diagonals (the edges between their two
    triangles) enter and leave once each: two locations, never a duplicate, also at
    1e4."""
    mesh = cube(scale)
    h = scale / 2
    origins = np.array([[-2, -2, -2], [-2, -2, 0.1], [0.2, 0.2, -2], [-0.3, 0.3, -2],
                        [2, -2, -2]]) * h
    directions = np.array([[1, 1, 1], [1, 1, 0], [0, 0, 1], [0, 0, 1], [-1, 1, 1]], float)
    locations, index_ray, index_tri = RayMeshIntersector(mesh).intersects_location(
        origins, directions)
    assert np.bincount(index_ray, minlength=5).tolist() == [2] * 5
    want = [[[-1, -1, -1], [1, 1, 1]], [[-1, -1, 0.1], [1, 1, 0.1]],
            [[0.2, 0.2, -1], [0.2, 0.2, 1]], [[-0.3, 0.3, -1], [-0.3, 0.3, 1]],
            [[1, -1, -1], [-1, 1, 1]]]
    np.testing.assert_allclose(locations, np.reshape(want, (-1, 3)) * h, atol=1e-6 * scale)
    for method in ("intersects_first", "intersects_any"):
        assert np.all(getattr(RayMeshIntersector(mesh), method)(origins, directions) >= 0)


def test_contains_on_a_cube():
    mesh = cube()
    rng = np.random.default_rng(1)
    inside = rng.uniform(-0.49, 0.49, (200, 3))
    outside = rng.uniform(-0.49, 0.49, (200, 3))
    outside[np.arange(200), rng.integers(0, 3, 200)] = rng.choice([-1, 1], 200) * \
        rng.uniform(0.51, 0.9, 200)
    far = rng.normal(size=(50, 3)) * 1e3
    points = np.concatenate([inside, outside, far, [[0, 0, 0]]])
    got = RayMeshIntersector(mesh).contains_points(points)
    assert got.dtype == bool
    np.testing.assert_array_equal(got, np.all(np.abs(points) < 0.5, axis=1))
    np.testing.assert_array_equal(got, ray_triangle.RayMeshIntersector(mesh).contains_points(
        points))
    # On the surface (trimesh leaves it undefined): a hit needs t > 0, so a point's own
    # face is not crossed, and on a convex mesh one of its rays leaves into free space:
    # outside, on faces, edges and corners alike.
    surface = rng.uniform(-0.5, 0.5, (60, 3))
    surface[np.arange(60), np.arange(60) % 3] = np.where(np.arange(60) % 2, 0.5, -0.5)
    corners = np.array([[x, y, z] for x in (-.5, .5) for y in (-.5, .5) for z in (-.5, .5)])
    edges = np.array([[0.5, 0.5, 0.1], [-0.5, 0.2, 0.5], [0.3, -0.5, -0.5]])
    on = RayMeshIntersector(mesh).contains_points(np.concatenate([surface, corners, edges]))
    assert not on.any()


def test_trimeshs_own_functions_cast_through_jrt(camel19k):
    """``mesh.ray = RayMeshIntersector(mesh)``: ``mesh.contains`` calls it and answers as
    trimesh's own float64 intersector does, on points around the 19k camel."""
    mesh = trimesh.Trimesh(camel19k.vertices, camel19k.faces, process=False)
    rng = np.random.default_rng(2)
    lo, hi = mesh.bounds
    points = rng.uniform(lo, hi, (600, 3))
    want = ray_triangle.RayMeshIntersector(mesh).contains_points(points)
    ours = RayMeshIntersector(mesh)
    calls = []
    original = ours.contains_points
    ours.contains_points = lambda p: calls.append(len(p)) or original(p)
    mesh.ray = ours
    got = mesh.contains(points)
    assert calls == [600]
    assert 0.05 < want.mean() < 0.95
    np.testing.assert_array_equal(got, want)


# --------------------------------------------------------------------------- real meshes


def test_an_open_mesh_gives_trimeshs_hits():
    """The teapot (open patches): every hit of a camera grid, as trimesh's float64
    intersector finds them, locations to 1e-4 of the teapot's size."""
    teapot = jrt.load_mesh(jrt.mesh_path("teapot"))
    mesh = trimesh.Trimesh(teapot.vertices, teapot.faces, process=False)
    origins, directions = grid_rays(mesh)
    got = RayMeshIntersector(mesh).intersects_location(origins, directions)
    want = ray_triangle.RayMeshIntersector(mesh).intersects_location(origins, directions)
    assert len(got[1]) > 100
    assert_same_hits(got, want, atol=1e-4 * mesh.scale)


@pytest.mark.parametrize("multiple_hits", [True, False])
def test_a_camera_grid_against_a_box(multiple_hits):
    mesh = cube(3.0)
    origins, directions = grid_rays(mesh, seed=3)
    ours = RayMeshIntersector(mesh, structure="kdtree")
    got = ours.intersects_id(origins, directions, multiple_hits=multiple_hits,
                             return_locations=True)
    want = ray_triangle.RayMeshIntersector(mesh).intersects_id(
        origins, directions, multiple_hits=multiple_hits, return_locations=True)
    assert_same_hits((got[2], got[1], got[0]), (want[2], want[1], want[0]), atol=1e-5)
    if EMBREE is not None:
        embree = EMBREE(mesh).intersects_id(origins, directions,
                                            multiple_hits=multiple_hits,
                                            return_locations=True)
        assert_same_hits((got[2], got[1], got[0]), (embree[2], embree[1], embree[0]),
                         atol=1e-4)


def test_max_hits_keeps_the_nearest(camel19k):
    mesh = trimesh.Trimesh(camel19k.vertices, camel19k.faces, process=False)
    origins, directions = grid_rays(mesh, n=16)
    ours = RayMeshIntersector(mesh)
    every = ours.intersects_location(origins, directions)
    counts = np.bincount(every[1], minlength=len(origins))
    assert counts.max() > 2  # rays that cross the camel several times
    two = ours.intersects_location(origins, directions, max_hits=2)
    np.testing.assert_array_equal(np.bincount(two[1], minlength=len(origins)),
                                  np.minimum(counts, 2))
    keep = np.concatenate([np.arange(c)[:2] + s for c, s in
                           zip(counts, np.cumsum(counts) - counts, strict=True)])
    np.testing.assert_array_equal(two[2], every[2][keep])
    # Nearest first along each ray.
    t = np.einsum("ij,ij->i", every[0] - origins[every[1]], directions[every[1]])
    assert np.all(np.diff(t)[np.diff(every[1]) == 0] > 0)


def test_every_hit_also_past_the_default_width():
    """40 stacked squares (80 triangles) crossed by slanted rays: 40 hits each, more than
    the 4 a first pass keeps, as trimesh's float64 intersector finds them; and with
    ``max_hits`` the nearest of them."""
    vertices, faces = [], []
    for k in range(40):
        z = k * 0.05
        vertices += [[-1, -1, z], [1, -1, z], [1, 1, z], [-1, 1, z]]
        faces += [[4 * k, 4 * k + 1, 4 * k + 2], [4 * k, 4 * k + 2, 4 * k + 3]]
    mesh = trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces), process=False)
    origins = np.array([[0.1, 0.2, -1.0], [-0.3, 0.1, 3.0], [0.05, -0.4, -2.0]])
    directions = np.array([[0.05, 0.02, 1.0], [0.01, -0.03, -1.0], [0.0, 0.1, 1.0]])
    ours = RayMeshIntersector(mesh)
    got = ours.intersects_location(origins, directions)
    assert np.bincount(got[1]).tolist() == [40, 40, 40]
    assert_same_hits(got, ray_triangle.RayMeshIntersector(mesh).intersects_location(
        origins, directions), atol=1e-5)
    # (max_hits 4: the first pass's own programs, no new compile)
    four = ours.intersects_location(origins, directions, max_hits=4)
    np.testing.assert_array_equal(four[2], got[2].reshape(3, 40)[:, :4].ravel())


def test_the_readme_example_runs():
    """The README's all-hits and trimesh example, as printed, after its first example in a
    fresh interpreter: the first of every hit is the closest hit, and ``tm.contains``
    answers as trimesh's Embree intersector does."""
    import re
    import subprocess
    import sys
    import textwrap
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    blocks = re.findall(r"```python\n(.*?)```", (root / "README.md").read_text(), flags=re.S)
    example = next(b for b in blocks if "jrt.all_hits(" in b)
    check = textwrap.dedent("""
        import numpy as _np
        _np.testing.assert_array_equal(_np.asarray(every.triangle[:, 0]),
                                       _np.asarray(hits.triangle))
        _np.testing.assert_array_equal(_np.asarray(every.t[:, 0]), _np.asarray(hits.t))
        if __import__("importlib").util.find_spec("embreex"):
            from trimesh.ray import ray_pyembree
            _want = ray_pyembree.RayMeshIntersector(tm).contains_points(targets)
            _np.testing.assert_array_equal(inside, _want)
        print("INSIDE", float(inside.mean()))
    """)
    code = blocks[0] + example + check
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=root, env={**__import__("os").environ, "PYTHONPATH": str(root)},
                         timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    assert 0 < float(out.stdout.split("INSIDE")[1]) < 1, out.stdout
