"""The surface at a hit (jrt.interaction) and the sky (jrt.sky) against closed forms.

The hit point's bound is pbrt-v4's claim (§6.8.5): the float32 point from the barycentrics
lies within ``γ7 Σ|b_i p_i|`` of the exact point, computed here in float64 from the same
float32 corners and barycentrics.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jrt.interaction import face_forward, normalise, surface_interaction
from jrt.sky import SKY_BOTTOM, SKY_TOP, sky_rgb, sky_rgb_by_row


def random_triangles(n=2000, seed=0):
    rng = np.random.default_rng(seed)
    scale = 10.0 ** rng.uniform(-3, 4, (n, 1, 1))
    vertices = (rng.normal(size=(n, 3, 3)) * scale + rng.normal(size=(n, 1, 3)) * 100 * scale)
    vertices = vertices.reshape(-1, 3).astype(np.float32)
    faces = np.arange(3 * n, dtype=np.int32).reshape(n, 3)
    u = rng.uniform(0, 1, n).astype(np.float32)
    v = (rng.uniform(0, 1, n) * (1 - u)).astype(np.float32)
    directions = normalise(rng.normal(size=(n, 3))).astype(np.float32)
    return vertices, faces, u, v, directions


def test_point_lies_within_its_error_bound_of_the_exact_point():
    vertices, faces, u, v, directions = random_triangles()
    tri = np.arange(len(faces), dtype=np.int32)
    surface = surface_interaction(jnp.asarray(vertices), jnp.asarray(faces), jnp.asarray(tri),
                                  jnp.asarray(u), jnp.asarray(v), jnp.asarray(directions))
    p = vertices[faces].astype(np.float64)
    u64, v64 = u.astype(np.float64), v.astype(np.float64)
    b = np.stack([(1 - u64) - v64, u64, v64], axis=-1)  # 1 - u - v exact in float64
    exact = np.einsum("nk,nkc->nc", b, p)
    point, error = np.asarray(surface.point, np.float64), np.asarray(surface.error, np.float64)
    assert surface.point.dtype == jnp.float32
    assert np.all(np.abs(point - exact) <= error)
    assert np.all(error > 0)


def test_normals_and_entering_on_a_known_triangle():
    vertices = np.float32([[0, 0, 0], [2, 0, 0], [0, 2, 0], [5, 5, 5]])
    faces = np.int32([[0, 1, 2], [0, 2, 1]])  # the same triangle, both windings
    corner = np.float32([[[0, 0, 1], [0, 0, 1], [0, 0, 1]], [[1, 0, 1], [1, 0, 1], [1, 0, 1]]])
    down = np.float32([[0, 0, -1], [0, 0, -1], [0, 0, 1]])
    surface = surface_interaction(vertices, faces, np.int32([0, 1, -1]),
                                  np.float32([0.25, 0.25, 0]), np.float32([0.5, 0.5, 0]), down,
                                  corner)
    np.testing.assert_array_equal(surface.point[:2], [[0.5, 1, 0], [1, 0.5, 0]])
    # Counter-clockwise seen from +z: outward +z; the other winding: -z.
    np.testing.assert_array_equal(surface.geometric_normal[:2], [[0, 0, 1], [0, 0, -1]])
    np.testing.assert_allclose(surface.shading_normal[:2], [[0, 0, 1], [0.5**0.5, 0, 0.5**0.5]],
                               rtol=1e-6)
    # A ray going down enters the +z winding and leaves the -z one; a miss reads triangle 0.
    np.testing.assert_array_equal(surface.entering, [True, False, False])
    no_corners = surface_interaction(vertices, faces, np.int32([0]), np.float32([0.25]),
                                     np.float32([0.5]), down[:1])
    np.testing.assert_array_equal(no_corners.shading_normal, no_corners.geometric_normal)


def test_numpy_and_jax_inputs_give_the_same_float32_surface():
    vertices, faces, u, v, directions = random_triangles(n=300, seed=1)
    tri = np.arange(len(faces), dtype=np.int32)
    host = surface_interaction(vertices, faces, tri, u, v, directions)
    device = surface_interaction(*(jnp.asarray(a) for a in (vertices, faces, tri, u, v,
                                                             directions)))
    assert isinstance(host.point, np.ndarray) and host.point.dtype == np.float32
    for mine, theirs in zip(host, device, strict=True):
        np.testing.assert_allclose(mine, np.asarray(theirs), rtol=1e-6, atol=1e-30)


def test_float64_inputs_stay_float64():
    vertices, faces, u, v, directions = random_triangles(n=50, seed=2)
    tri = np.arange(len(faces), dtype=np.int32)
    surface = surface_interaction(vertices.astype(np.float64), faces, tri, u.astype(np.float64),
                                  v.astype(np.float64), directions.astype(np.float64))
    assert surface.point.dtype == surface.geometric_normal.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(surface.geometric_normal, axis=1), 1, rtol=1e-15)


def test_face_forward_turns_n_into_the_hemisphere_of_v():
    n = np.float32([[0, 0, 1], [0, 0, 1], [0, 1, 0]])
    v = np.float32([[0, 0, -1], [1, 0, 0.1], [1, 0, 0]])
    np.testing.assert_array_equal(face_forward(n, v), [[0, 0, -1], [0, 0, 1], [0, 1, 0]])
    np.testing.assert_array_equal(face_forward(jnp.asarray(n), jnp.asarray(v)),
                                  face_forward(n, v))


def test_sky_matches_its_documented_gradient():
    d = normalise(np.random.default_rng(3).normal(size=(100, 3)))
    w = np.clip((1 - d[:, 1]) / 2, 0, 1)[:, None]
    want = np.asarray(SKY_TOP) * (1 - w) + np.asarray(SKY_BOTTOM) * w
    np.testing.assert_allclose(sky_rgb(d), want, rtol=1e-6)
    np.testing.assert_allclose(sky_rgb(np.float32([[0, 1, 0], [0, -1, 0]])),
                               [SKY_TOP, SKY_BOTTOM], rtol=1e-7)
    rows = np.asarray(sky_rgb_by_row(5, 3)).reshape(5, 3, 3)
    np.testing.assert_allclose(rows[0], np.broadcast_to(SKY_TOP, (3, 3)), rtol=1e-7)
    np.testing.assert_allclose(rows[-1], np.broadcast_to(SKY_BOTTOM, (3, 3)), rtol=1e-7)
    np.testing.assert_allclose(rows[2, 0], (np.asarray(SKY_TOP) + SKY_BOTTOM) / 2, rtol=1e-6)
    # Blue above red everywhere: the renderers' silhouette test relies on it.
    assert np.all(np.asarray(sky_rgb(d))[:, 2] > np.asarray(sky_rgb(d))[:, 0])
