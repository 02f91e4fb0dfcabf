"""jrt.all_hits: every hit along a ray, against brute force (bit for bit, every structure),
a float64 NumPy enumeration, closed forms on a box (edges and vertices counted once) and
the closest hit.

The camel rays are 1,100 of the 19k-triangle camel's incoherent set (1,536 traced, a size
bucket), so the structures share their compiled programs across the tests.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import accel
import jrt
from jrt.all_hits import AllHits, all_hits, capacity_for
from jrt.raysets import incoherent_set

N = 1100
MAX_HITS = 4


def as_numpy(record: AllHits) -> AllHits:
    return AllHits(*(np.asarray(a) for a in record))


@pytest.fixture(scope="module")
def rays(camel19k):
    return incoherent_set(camel19k.vertices, N, seed=5)


@pytest.fixture(scope="module")
def brute_record(camel19k, rays):
    s = accel.build("brute", camel19k.vertices, camel19k.faces)
    return as_numpy(all_hits(s, *rays, MAX_HITS))


def float64_hits(vertices, faces, origins, directions):
    """Every (t, face) with t > 0 of each ray, Möller–Trumbore in float64 NumPy, sorted."""
    v = np.asarray(vertices, np.float64)[np.asarray(faces)]
    e1, e2 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]
    out = []
    for o, d in zip(np.asarray(origins, np.float64), np.asarray(directions, np.float64),
                    strict=True):
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            s = o - v[:, 0]
            u = np.einsum("ij,ij->i", s, p) * inv
            q = np.cross(s, e1)
            w = (q @ d) * inv
            t = np.einsum("ij,ij->i", e2, q) * inv
        hit = (det != 0) & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 0)
        order = np.argsort(t[hit])
        out.append((t[hit][order], np.flatnonzero(hit)[order]))
    return out


@pytest.mark.parametrize("name", [n for n in accel.names() if n != "brute"])
def test_every_structure_returns_brute_forces_hits(camel19k, rays, brute_record, name):
    s = accel.build(name, camel19k.vertices, camel19k.faces)
    got = as_numpy(all_hits(s, *rays, MAX_HITS))
    for field, a, b in zip(AllHits._fields, got, brute_record, strict=True):
        np.testing.assert_array_equal(a, b, err_msg=f"{name}: {field}")


def test_the_hits_are_float64s_and_the_first_is_the_closest(camel19k, rays, brute_record):
    origins, directions = rays
    closest = jrt.closest_hit(accel.build("brute", camel19k.vertices, camel19k.faces),
                              origins, directions)
    np.testing.assert_array_equal(brute_record.triangle[:, 0], np.asarray(closest.triangle))
    np.testing.assert_array_equal(brute_record.t[:, 0], np.asarray(closest.t))
    some = np.arange(0, N, 7)
    want = float64_hits(camel19k.vertices, camel19k.faces, origins[some], directions[some])
    for i, (t64, face64) in zip(some, want, strict=True):
        count = brute_record.count[i]
        assert count == t64.size, i  # random rays meet no edge: one hit per face
        k = min(count, MAX_HITS)
        np.testing.assert_array_equal(brute_record.triangle[i, :k], face64[:k])
        np.testing.assert_allclose(brute_record.t[i, :k], t64[:k], rtol=1e-5)
        assert np.all(brute_record.t[i, k:] == np.inf) and np.all(
            brute_record.triangle[i, k:] == -1)
    # The camel is closed and the rays start outside it: they cross it an even number of
    # times, some more often than MAX_HITS.
    assert np.all(brute_record.count % 2 == 0)
    assert brute_record.overflow.any() and (brute_record.count > 0).mean() > 0.3
    np.testing.assert_array_equal(brute_record.overflow, brute_record.count > MAX_HITS)


@pytest.mark.parametrize("name", ["bvh", "kdtree"])
def test_a_small_max_hits_keeps_the_nearest_and_counts_all(camel19k, rays, brute_record,
                                                           name):
    """max_hits 1 (a capacity of 6 triangles): rays with more are traced again with room
    for all, and every count is exact."""
    s = accel.build(name, camel19k.vertices, camel19k.faces)
    assert capacity_for(1) < brute_record.count.max()
    one = as_numpy(all_hits(s, *rays, 1))
    np.testing.assert_array_equal(one.count, brute_record.count)
    np.testing.assert_array_equal(one.overflow, brute_record.count > 1)
    np.testing.assert_array_equal(one.t[:, 0], brute_record.t[:, 0])
    np.testing.assert_array_equal(one.triangle[:, 0], brute_record.triangle[:, 0])


def test_tmax_ends_the_ray(camel19k, rays, brute_record):
    tmax = np.float32(0.5 * camel19k.diagonal)
    got = {name: as_numpy(all_hits(accel.build(name, camel19k.vertices, camel19k.faces),
                                   *rays, MAX_HITS, tmax=tmax)) for name in ("brute", "bvh")}
    for a, b in zip(got["bvh"], got["brute"], strict=True):
        np.testing.assert_array_equal(a, b)
    ended = got["bvh"]
    assert np.all(ended.t[ended.t < np.inf] < tmax)
    assert 0 < ended.count.sum() < brute_record.count.sum()
    # The hits before tmax are the nearest hits of the whole ray.
    inside = brute_record.t < tmax
    np.testing.assert_array_equal(np.where(inside, brute_record.t, np.inf)[~ended.overflow],
                                  ended.t[~ended.overflow])
    assert np.all(ended.count <= brute_record.count)


# --------------------------------------------------------------------------- a box


def box(scale=1.0, offset=0.0):
    """The unit cube [0, 1]^3 (times ``scale``, plus ``offset``), 12 triangles."""
    v = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], np.float64)
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return jrt.mesh_from_arrays(v * scale + offset, faces)


def box_rays(scale=1.0, offset=0.0):
    """Rays from outside the cube through its interior, a face's diagonal (the edge of
    its two triangles), an edge of the cube, a vertex, and past it; with how many times
    each crosses the surface."""
    p = np.array([
        [0.5, 0.5, -1.0], [0.3, 0.7, -1.0],        # through two faces' interiors
        [0.25, 0.25, -1.0], [0.6, 0.6, -1.0],      # along z, across both faces' diagonals
        [-1.0, 0.5, 0.5],                          # along x, through two face centres
        [0.0, 0.5, -1.0],                          # in the plane x = 0: along a face
        [-1.0, -1.0, -1.0],                        # the main diagonal: two vertices
        [-1.0, -1.0, 0.5],                         # through two opposite edges
        [0.5, 1.0, -1.0],                          # in the plane y = 1: along a face
        [2.0, 2.0, -1.0],                          # past the box
    ])
    d = np.array([[0, 0, 1], [0, 0, 1], [0, 0, 1], [0, 0, 1], [1, 0, 0], [0, 0, 1],
                  [1, 1, 1], [1, 1, 0], [0, 0, 1], [0, 0, 1]], np.float64)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return (p * scale + offset).astype(np.float32), d.astype(np.float32)


@pytest.mark.parametrize("scale,offset", [(1.0, 0.0), (1e4, 0.0), (1.0, 1e3)])
@pytest.mark.parametrize("name", accel.names())
def test_a_box_is_entered_and_left_once_through_edges_and_vertices(name, scale, offset):
    mesh = box(scale, offset)
    s = accel.build(name, mesh.vertices, mesh.faces)
    origins, directions = box_rays(scale, offset)
    got = as_numpy(all_hits(s, origins, directions, 4))
    # Interior rays, the face diagonals, the edges and the vertices: 2 hits, where the
    # ray enters and leaves; a ray along a face, in its plane (x = 0, y = 1), meets the
    # edges of the faces across it: an even count; the ray past the box, none.
    assert list(got.count[[0, 1, 2, 3, 4, 6, 7]]) == [2] * 7, got.count
    assert got.count[9] == 0
    assert np.all(got.count % 2 == 0)
    assert not got.overflow.any()
    for i in (0, 1, 2, 3, 4):
        np.testing.assert_allclose(got.t[i, :2], [scale, 2 * scale], rtol=1e-5)
    for i, root in ((6, np.sqrt(3)), (7, np.sqrt(2))):
        np.testing.assert_allclose(got.t[i, :2], root * np.array([1, 2]) * scale, rtol=1e-5)


# --------------------------------------------------------------------------- composition


def test_jit_and_vmap_give_the_calls_answers(camel19k, rays, brute_record):
    s = accel.build("bvh", camel19k.vertices, camel19k.faces)
    origins, directions = (jnp.asarray(a[:512]) for a in rays)
    eager = as_numpy(all_hits(s, origins, directions, MAX_HITS))
    jitted = as_numpy(jax.jit(lambda o, d: all_hits(s, o, d, MAX_HITS))(origins, directions))
    halves = as_numpy(jax.vmap(lambda o, d: all_hits(s, o, d, MAX_HITS))(
        origins.reshape(2, 256, 3), directions.reshape(2, 256, 3)))
    for field, a, b, c, want in zip(AllHits._fields, eager, jitted, halves, brute_record,
                                    strict=True):
        np.testing.assert_array_equal(a, want[:512], err_msg=field)
        np.testing.assert_array_equal(b, want[:512], err_msg=field)
        np.testing.assert_array_equal(c.reshape(a.shape), want[:512], err_msg=field)


def test_the_derivative_of_each_hit_is_the_planes():
    """Rays along +z through the cube's bottom and top: t = z_face - z0 for each hit, so
    dt/dz0 = -1 and dt/dx0 = 0 (the faces are planes z = 0 and z = 1); zero past the
    hits."""
    mesh = box()
    s = accel.build("bvh", mesh.vertices, mesh.faces)
    origins = jnp.asarray([[0.3, 0.6, -1.0], [0.7, 0.2, -2.0]], jnp.float32)
    directions = jnp.asarray([[0.0, 0.0, 1.0]] * 2, jnp.float32)

    def ts(o):
        return all_hits(s, o, directions, 3).t

    value, tangent = jax.jvp(ts, (origins,), (jnp.asarray([[0, 0, 1.0], [0, 0, 1.0]]),))
    np.testing.assert_allclose(np.asarray(value)[:, :2], [[1, 2], [2, 3]], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(tangent), [[-1, -1, 0], [-1, -1, 0]], atol=1e-6)
    _, sideways = jax.jvp(ts, (origins,), (jnp.asarray([[1.0, 0, 0], [0, 1.0, 0]]),))
    np.testing.assert_allclose(np.asarray(sideways), 0, atol=1e-6)

    def total(o):  # reverse mode: the sum of every hit's t
        t = ts(o)
        return jnp.sum(jnp.where(jnp.isfinite(t), t, 0.0))

    np.testing.assert_allclose(np.asarray(jax.grad(total)(origins)), [[0, 0, -2]] * 2,
                               atol=1e-6)


@pytest.mark.parametrize("bad", [0, -3, 2.5, True, None])
def test_max_hits_must_be_a_positive_integer(bad):
    mesh = box()
    s = accel.build("bvh", mesh.vertices, mesh.faces)
    with pytest.raises(ValueError, match="max_hits must be a positive integer"):
        all_hits(s, *box_rays(), bad)


def test_no_rays_no_hits():
    mesh = box()
    s = accel.build("grid", mesh.vertices, mesh.faces)
    got = all_hits(s, np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), 5)
    assert got.t.shape == (0, 5) and got.count.shape == (0,)
