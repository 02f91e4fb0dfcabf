"""The three ray–triangle kernels (``jrt.kernels.KERNELS``) and the brute-force closest hit.

Contract under test (``jrt/kernels.py``): ``kernel(origin, direction, v0, v1, v2) -> (t, u, v)``;
a hit has ``t > 0`` and the point ``origin + t * direction = (1-u-v) v0 + u v1 + v v2`` inside
the triangle or on its border (borders are inclusive, both facings are hit); a miss is
``t = +inf, u = v = 0`` and never NaN.

Analytic cases use coordinates for which every float32 operation of every kernel is exact
(small dyadic rationals), so their expected values are exact up to a few ulps of slack for
the compiler's freedom (FMA contraction under ``jit``).

The property tests draw float32 triangles and rays and compare with a float64 NumPy solution
of the 3x3 system ``[-D, e1, e2] (t, u, v) = O - v0`` for the *same* (float32) inputs. Error
model used for the tolerances (first-order perturbation analysis of that linear system):
every kernel rounds its inputs' differences, products and sums with relative error ``eps``
(float32 unit roundoff is eps/2; a few operations add up), so the computed solution is the
exact solution of a system perturbed by ``O(eps)`` relative to the magnitudes involved. The
position error of the hit point is therefore at most ``C * eps * kappa * L``, with

- ``kappa`` the 2-norm condition number of the column-normalised matrix
  ``[D/|D|, e1/|e1|, e2/|e2|]``: it grows as ``1/|cos|`` for grazing rays and as ``1/sin``
  of the smallest angle for thin triangles;
- ``L`` the magnitude of the coordinates entering the computation: ``max|O| + max|v_i| +
  t|D|`` (``plane_barycentric`` forms ``N·v0 - N·O`` from absolute coordinates, so the
  scale is absolute coordinates, not only the differences);

and a barycentric error of at most that position error divided by the smallest height of
the triangle, ``|N| / max|edge|``. Measured on 400 000 random cases the ratio of the actual
error to ``eps * kappa * L`` never exceeded 1.5 for any kernel (1.0 for barycentrics);
``C = 16`` gives an order of magnitude of margin. Cases where this bound does not separate
the answer from the border (the barycentric bound exceeds the 0.01 margin of the drawn
point, or ``t`` is within the bound of 0, where ``watertight`` rightly refuses a hit within
its own conservative error bound of ``t``) are skipped with ``hypothesis.assume``, as are
near-grazing rays (``|cos| < 1e-3``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import assume, event, given, settings
from hypothesis import strategies as st

import accel
import jrt
from jrt import brute
from jrt.kernels import KERNELS

NAMES = list(KERNELS)
EPS32 = float(np.finfo(np.float32).eps)
#: Slack on analytic values (exact in float32 arithmetic; a few ulps for FMA contraction).
TIGHT = 4 * EPS32
#: Safety factor over the measured worst case (1.5) of the error model in the docstring.
C_ERR = 16.0
#: Barycentric distance to the border of the drawn points in the property tests.
MARGIN = 0.01

# One compiled function per kernel, shared by all tests (shapes are fixed per test, so each
# property test compiles once per kernel, not once per example).
JITTED = {name: jax.jit(kernel) for name, kernel in KERNELS.items()}

PROPERTY = settings(max_examples=200, deadline=None, database=None)

kernel_names = pytest.mark.parametrize("name", NAMES)


def f32(*xs) -> np.ndarray:
    return np.asarray(xs, np.float32)


def run(name, origin, direction, v0, v1, v2, *, dtype=np.float32):
    """(t, u, v) of the jitted kernel ``name`` as NumPy arrays of ``dtype``."""
    args = [jnp.asarray(np.asarray(a, dtype)) for a in (origin, direction, v0, v1, v2)]
    return tuple(np.asarray(r) for r in JITTED[name](*args))


def assert_miss(result):
    t, u, v = result
    for a in result:
        assert not np.any(np.isnan(a)), result
    assert np.all(t == np.inf), result
    assert np.all(u == 0) and np.all(v == 0), result


def assert_hit(result, t, u, v, tol=TIGHT):
    got_t, got_u, got_v = (float(a) for a in result)
    assert np.isfinite(got_t), result
    np.testing.assert_allclose([got_t, got_u, got_v], [t, u, v], rtol=tol, atol=tol)


def point_from_barycentrics(u, v, v0, v1, v2):
    v0, v1, v2 = (np.asarray(a, np.float64) for a in (v0, v1, v2))
    return (1 - u - v) * v0 + u * v1 + v * v2


# ---------------------------------------------------------------------------------------------
# Analytic cases
# ---------------------------------------------------------------------------------------------

# Triangles with exactly representable corners. "flat" lies in z = 0; "tilted" in z = x + y.
FLAT = (f32(0, 0, 0), f32(2, 0, 0), f32(0, 2, 0))
TILTED = (f32(0, 0, 0), f32(2, 0, 2), f32(0, 2, 2))
# Off the origin, so that "a few ulps outside" is a relative offset (no denormals).
SHIFTED = (f32(1, 1, 0), f32(2, 1, 0), f32(1, 2, 0))

# Directions for which the kernels' intermediate values stay dyadic (exact in float32).
DIRECTIONS = {
    "down": f32(0, 0, -1),
    "up": f32(0, 0, 1),
    "oblique": f32(0.5, 0.25, -1),
    "oblique_up": f32(-0.25, 0.5, 1),
}


def _ray_to(target, direction, t):
    """Origin such that ``origin + t * direction == target`` (exact for dyadic inputs)."""
    origin = np.asarray(target, np.float64) - t * np.asarray(direction, np.float64)
    assert np.array_equal(origin.astype(np.float32).astype(np.float64), origin)
    return origin.astype(np.float32)


@kernel_names
@pytest.mark.parametrize("tri_name", ["flat", "tilted"])
@pytest.mark.parametrize("dir_name", list(DIRECTIONS))
def test_interior_hit_exact(name, tri_name, dir_name):
    tri = {"flat": FLAT, "tilted": TILTED}[tri_name]
    d = DIRECTIONS[dir_name]
    u, v, t = 0.25, 0.5, 2.0
    target = point_from_barycentrics(u, v, *tri)
    o = _ray_to(target, d, t)
    result = run(name, o, d, *tri)
    assert_hit(result, t, u, v)
    got_t, got_u, got_v = (float(a) for a in result)
    on_ray = o.astype(np.float64) + got_t * d.astype(np.float64)
    on_triangle = point_from_barycentrics(got_u, got_v, *tri)
    np.testing.assert_allclose(on_triangle, on_ray, rtol=TIGHT, atol=TIGHT)
    np.testing.assert_allclose(on_ray, target, rtol=TIGHT, atol=TIGHT)


@kernel_names
@pytest.mark.parametrize("tri_name", ["flat", "tilted"])
def test_both_facings_hit(name, tri_name):
    """Rays from either side and either winding hit: no back-face culling."""
    v0, v1, v2 = {"flat": FLAT, "tilted": TILTED}[tri_name]
    u, v = 0.25, 0.5
    target = point_from_barycentrics(u, v, v0, v1, v2)
    for d in (f32(0, 0, -1), f32(0, 0, 1), f32(0.5, 0.25, -1), f32(-0.5, -0.25, 1)):
        o = _ray_to(target, d, 2.0)
        assert_hit(run(name, o, d, v0, v1, v2), 2.0, u, v)
        # Reversed winding (v0, v2, v1): the normal flips and u, v swap.
        assert_hit(run(name, o, d, v0, v2, v1), 2.0, v, u)


BORDER_POINTS = {
    "vertex0": (0.0, 0.0),
    "vertex1": (1.0, 0.0),
    "vertex2": (0.0, 1.0),
    "edge01_mid": (0.5, 0.0),
    "edge12_mid": (0.5, 0.5),
    "edge20_mid": (0.0, 0.5),
}


@kernel_names
@pytest.mark.parametrize("point", list(BORDER_POINTS))
@pytest.mark.parametrize("tri_name", ["flat", "tilted", "shifted"])
@pytest.mark.parametrize("dir_name", ["down", "up", "oblique"])
def test_border_is_inclusive(name, point, tri_name, dir_name):
    """A ray through a vertex or an edge midpoint (exact in float32) hits."""
    tri = {"flat": FLAT, "tilted": TILTED, "shifted": SHIFTED}[tri_name]
    u, v = BORDER_POINTS[point]
    d = DIRECTIONS[dir_name]
    o = _ray_to(point_from_barycentrics(u, v, *tri), d, 2.0)
    assert_hit(run(name, o, d, *tri), 2.0, u, v)


GRAZING = {
    # (origin, direction, triangle): rays lying in the triangle's plane, through it.
    "flat_along_x": (f32(-1, 0.5, 0), f32(1, 0, 0), FLAT),
    "flat_diagonal": (f32(-1, -1, 0), f32(1, 1, 0), FLAT),
    "flat_along_edge01": (f32(-1, 0, 0), f32(1, 0, 0), FLAT),
    "flat_through_vertex2": (f32(0, 3, 0), f32(0, -1, 0), FLAT),
    "flat_from_inside": (f32(0.5, 0.5, 0), f32(1, -1, 0), FLAT),
    "flat_neg_zero": (f32(-1, 0.5, -0.0), f32(1, -0.0, -0.0), FLAT),
    "tilted_along_e1": (f32(-1, 0.5, -0.5), f32(2, 0, 2), TILTED),
    "tilted_along_e2": (f32(0.5, -1, -0.5), f32(0, 1, 1), TILTED),
    "tilted_along_edge12": (f32(3, -1, 2), f32(-1, 1, 0), TILTED),
}


@kernel_names
@pytest.mark.parametrize("case", list(GRAZING))
def test_grazing_ray_in_plane_misses(name, case):
    o, d, tri = GRAZING[case]
    assert_miss(run(name, o, d, *tri))


PARALLEL = {
    "flat_above": (f32(-1, 0.5, 1), f32(1, 0, 0), FLAT),
    "flat_below": (f32(-1, 0.5, -1), f32(1, 1, 0), FLAT),
    "flat_tiny_offset": (f32(-1, 0.5, 2.0**-20), f32(1, 0, 0), FLAT),
    "tilted_above": (f32(-1, 0.5, 0.5), f32(2, 0, 2), TILTED),
}


@kernel_names
@pytest.mark.parametrize("case", list(PARALLEL))
def test_parallel_ray_off_plane_misses(name, case):
    o, d, tri = PARALLEL[case]
    assert_miss(run(name, o, d, *tri))


@kernel_names
@pytest.mark.parametrize("d", [f32(0, 0, 1), f32(0.5, 0.25, 1)], ids=["axis", "oblique"])
def test_triangle_behind_origin_misses(name, d):
    """The triangle lies at t = -1 along the ray."""
    o = _ray_to(point_from_barycentrics(0.25, 0.25, *FLAT), d, -1.0)
    assert_miss(run(name, o, d, *FLAT))
    assert_miss(run(name, o, d, FLAT[0], FLAT[2], FLAT[1]))


@kernel_names
@pytest.mark.parametrize("point", ["interior", *BORDER_POINTS])
@pytest.mark.parametrize("dir_name", ["down", "up", "oblique"])
def test_origin_on_triangle_misses(name, point, dir_name):
    """t = 0 is not a hit: a ray never hits at its own origin."""
    u, v = (0.25, 0.25) if point == "interior" else BORDER_POINTS[point]
    o = point_from_barycentrics(u, v, *FLAT).astype(np.float32)
    assert_miss(run(name, o, DIRECTIONS[dir_name], *FLAT))


DEGENERATE = {
    # (triangle, target point on it)
    "collinear": ((f32(0, 0, 0), f32(1, 1, 0), f32(2, 2, 0)), f32(1, 1, 0)),
    "collinear_between": ((f32(0, 0, 0), f32(1, 1, 0), f32(2, 2, 0)), f32(0.5, 0.5, 0)),
    "collinear_3d": ((f32(1, 2, 3), f32(3, 6, 9), f32(2, 4, 6)), f32(2, 4, 6)),
    "collinear_axis": ((f32(0, 0, 0), f32(1, 0, 0), f32(2, 0, 0)), f32(0.5, 0, 0)),
    "repeated_v1_v2": ((f32(0, 0, 0), f32(1, 0, 0), f32(1, 0, 0)), f32(0.5, 0, 0)),
    "repeated_v0_v1": ((f32(0, 0, 0), f32(0, 0, 0), f32(1, 1, 0)), f32(0, 0, 0)),
    "repeated_v0_v2": ((f32(1, 1, 0), f32(0, 2, 0), f32(1, 1, 0)), f32(0.5, 1.5, 0)),
    "all_equal": ((f32(0.5, 0.5, 0),) * 3, f32(0.5, 0.5, 0)),
    "all_zero": ((f32(0, 0, 0),) * 3, f32(0, 0, 0)),
}


@kernel_names
@pytest.mark.parametrize("case", list(DEGENERATE))
@pytest.mark.parametrize(
    "d", [f32(0, 0, -1), f32(0, 0, 1), f32(0.5, 0.25, -1), f32(1, 0, 0), f32(-1, 1, 0)],
    ids=["down", "up", "oblique", "x", "in_plane_diagonal"],
)
def test_degenerate_triangle_misses(name, case, d):
    tri, target = DEGENERATE[case]
    o = _ray_to(target, d, 2.0)
    assert_miss(run(name, o, d, *tri))


SIGNED_ZERO_DIRECTIONS = {
    # axis -> the direction variants along that axis (all the same ray).
    2: [f32(0, 0, -1), f32(-0.0, 0, -1), f32(0, -0.0, -1), f32(-0.0, -0.0, -1)],
    -2: [f32(0, 0, 1), f32(-0.0, 0, 1), f32(0, -0.0, 1), f32(-0.0, -0.0, 1)],
    0: [f32(1, 0, 0), f32(1, -0.0, 0), f32(1, 0, -0.0), f32(1, -0.0, -0.0)],
    -1: [f32(0, -1, 0), f32(-0.0, -1, 0), f32(0, -1, -0.0), f32(-0.0, -1, -0.0)],
}


def _axis_triangle(axis):
    """SHIFTED rotated so that its plane is perpendicular to ``abs(axis)`` (at 0)."""
    perm = {2: [0, 1, 2], 0: [2, 0, 1], 1: [1, 2, 0]}[abs(axis)]
    return tuple(c[perm] for c in SHIFTED)


@kernel_names
@pytest.mark.parametrize("axis", list(SIGNED_ZERO_DIRECTIONS))
@pytest.mark.parametrize("point", ["interior", *BORDER_POINTS])
def test_signed_zero_directions(name, axis, point):
    """+0.0 and -0.0 direction components give identical results, and the expected hit."""
    tri = _axis_triangle(axis)
    u, v = (0.25, 0.5) if point == "interior" else BORDER_POINTS[point]
    target = point_from_barycentrics(u, v, *tri)
    results = []
    for d in SIGNED_ZERO_DIRECTIONS[axis]:
        o = _ray_to(target, np.abs(d) * np.sign(d.sum()), 3.0)  # origin 3 units back
        result = run(name, o, d, *tri)
        assert_hit(result, 3.0, u, v)
        results.append(result)
    for other in results[1:]:
        for a, b in zip(results[0], other, strict=True):
            np.testing.assert_array_equal(a, b)  # -0.0 == 0.0 here, NaN would fail


def _ulps_from(x, k, toward):
    """``x`` moved by ``k`` float32 ulps toward ``toward``."""
    x = np.float32(x)
    for _ in range(k):
        x = np.nextafter(x, np.float32(toward), dtype=np.float32)
    return float(x)


def _outside_points(k):
    """Points of SHIFTED's plane ``k`` ulps outside each edge (the coordinate at the edge
    moved by k ulps; for the hypotenuse x + y = 3 the x coordinate)."""
    return {
        "edge01": (1.5, _ulps_from(1.0, k, 0.0)),  # y < 1
        "edge20": (_ulps_from(1.0, k, 0.0), 1.5),  # x < 1
        "edge12": (_ulps_from(1.5, k, 2.0), 1.5),  # x + y > 3
        "vertex0": (_ulps_from(1.0, k, 0.0), _ulps_from(1.0, k, 0.0)),
        "vertex1": (_ulps_from(2.0, k, 3.0), 1.0),
        "vertex2": (1.0, _ulps_from(2.0, k, 3.0)),
    }


@kernel_names
@pytest.mark.parametrize("k", [2, 4, 64])
@pytest.mark.parametrize("where", list(_outside_points(1)))
@pytest.mark.parametrize("dir_name", ["down", "up"])
def test_just_outside_misses(name, k, where, dir_name):
    """A few ulps outside an edge or a vertex is a miss.

    (One ulp outside the hypotenuse, Möller–Trumbore's ``u + v = 1 + 2^-24`` rounds to 1 in
    float32 and counts as the border: an inherent rounding limit, hence k >= 2.)
    """
    x, y = _outside_points(k)[where]
    d = DIRECTIONS[dir_name]
    o = f32(x, y, 0) - 2 * d
    assert_miss(run(name, o, d, *SHIFTED))


@kernel_names
@pytest.mark.parametrize("k", [1, 2, 4])
@pytest.mark.parametrize("where", ["edge01", "edge20", "edge12"])
def test_just_inside_hits(name, k, where):
    x, y = {
        "edge01": (1.5, _ulps_from(1.0, k, 2.0)),
        "edge20": (_ulps_from(1.0, k, 2.0), 1.5),
        "edge12": (_ulps_from(1.5, k, 1.0), 1.5),
    }[where]
    d = DIRECTIONS["down"]
    result = run(name, f32(x, y, 0) - 2 * d, d, *SHIFTED)
    assert_hit(result, 2.0, x - 1, y - 1)


@kernel_names
@pytest.mark.parametrize(
    "point", [(1.5, 0.5), (0.5, 1.5), (1.6, 1.6), (3, 3), (-5, -5), (2.5, 1), (1, 2.5)]
)
@pytest.mark.parametrize("dir_name", ["down", "oblique"])
def test_clearly_outside_misses(name, point, dir_name):
    d = DIRECTIONS[dir_name]
    o = _ray_to(f32(*point, 0), d, 2.0)
    assert_miss(run(name, o, d, *SHIFTED))


def _unsigned_barycentrics(p, v0, v1, v2):
    """The seed lecture's norm-based barycentrics |(P_{i+2}-P_{i+1}) x (I-P_{i+1})| / |N|."""
    p, v0, v1, v2 = (np.asarray(a, np.float64) for a in (p, v0, v1, v2))
    n = np.linalg.norm(np.cross(v1 - v0, v2 - v0))
    return np.array([
        np.linalg.norm(np.cross(v2 - v1, p - v1)) / n,
        np.linalg.norm(np.cross(v0 - v2, p - v2)) / n,
        np.linalg.norm(np.cross(v1 - v0, p - v0)) / n,
    ])


@kernel_names
def test_point_outside_with_unsigned_barycentrics_in_range_misses(name):
    """(0.6, 0.6, 0) lies outside the unit right triangle, yet its three unsigned barycentric
    areas (0.2, 0.6, 0.6) all lie in [0, 1]: the seed's norm-based test would accept it. The
    signed (projected on N) barycentrics of ``plane_barycentric`` must reject it."""
    tri = (f32(0, 0, 0), f32(1, 0, 0), f32(0, 1, 0))
    p = np.array([0.6, 0.6, 0.0])
    unsigned = _unsigned_barycentrics(p, *tri)
    assert np.all((unsigned >= 0) & (unsigned <= 1)), unsigned
    assert unsigned.sum() > 1  # the tell-tale: inside points sum to exactly 1
    for d in (f32(0, 0, -1), f32(0, 0, 1), f32(0.5, 0.25, -1)):
        o = (p - 2.0 * d).astype(np.float32)
        assert_miss(run(name, o, d, *tri))


@kernel_names
@pytest.mark.parametrize("t", [2.0**-20, 2.0**12], ids=["tiny_t", "far_t"])
@pytest.mark.parametrize("dir_name", ["down", "oblique"])
def test_exact_hit_at_extreme_distances(name, t, dir_name):
    """Exact hits very close to the origin (above watertight's rounding bound on t, which
    is ~1e-11 here) and far from it (2^12 triangle sizes; beyond ~3e5 sizes watertight's
    conservative pbrt-v4 bound on t exceeds t itself and rejects the hit, as pbrt does)."""
    d = DIRECTIONS[dir_name]
    u, v = 0.25, 0.5
    o = _ray_to(point_from_barycentrics(u, v, *FLAT), d, t)
    assert_hit(run(name, o, d, *FLAT), t, u, v)


# ---------------------------------------------------------------------------------------------
# Regressions: rounding residues taken for hits, structures without triangles
# ---------------------------------------------------------------------------------------------


# Under jax.jit the compiler may fuse a*b - c*d into FMAs: for a ray lying exactly in the
# triangle's plane, det (moller_trumbore) and N·D (plane_barycentric) then come out as a
# rounding residue instead of 0, and t, u, v as ratios of residues. The kernels compare
# those triple products with their rounding bound (kernels._resolvable).


# Found on random input, kept as is: v2 - v1 is parallel to x, so the plane of the triangle
# contains the x direction, and the ray along +x through v0 (reached at t = 2) lies in it.
IN_PLANE_CASE = (
    f32(-2.2226055, -0.23905367, 0.81890917),  # origin: v0 - 2 x (rounded)
    f32(1, 0, 0),
    (
        f32(-0.22260554, -0.23905367, 0.81890917),
        f32(-0.23441607, -0.26431832, 0.8282997),
        f32(-0.26752988, -0.26431832, 0.8282997),
    ),
)


def _in_plane_rays(n=2048, seed=0):
    """Random triangles with an edge v1 -> v2 parallel to an axis, and rays along that axis
    through v0 or v1: every ray lies exactly in its triangle's plane (the float32 corners
    span it; the construction rounds only along the axis, which stays in the plane)."""
    rng = np.random.default_rng(seed)
    axis = rng.integers(0, 3, n)
    rows = np.arange(n)
    v0 = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
    v1 = (v0 + rng.uniform(-0.05, 0.05, (n, 3))).astype(np.float32)
    v2 = v1.copy()
    v2[rows, axis] += rng.uniform(-0.05, 0.05, n).astype(np.float32)
    d = np.zeros((n, 3), np.float32)
    d[rows, axis] = rng.choice([-1.0, 1.0], n)
    o = np.where((rows % 2 == 0)[:, None], v0, v1)
    o[rows, axis] -= 2 * d[rows, axis]
    # In-plane in exact arithmetic: both triple products vanish in float64 (exact here).
    v0_64 = v0.astype(np.float64)
    normal = np.cross(v1 - v0_64, v2 - v0_64)
    assert np.all(np.einsum("ij,ij->i", normal, d.astype(np.float64)) == 0)
    assert np.all(np.einsum("ij,ij->i", normal, o - v0_64) == 0)
    return o, d, v0, v1, v2


@kernel_names
def test_rays_in_plane_miss_eager(name):
    """Op by op (no FMA contraction) every kernel keeps the contract."""
    assert_miss(tuple(np.asarray(a) for a in KERNELS[name](*_in_plane_rays())))
    o, d, tri = IN_PLANE_CASE
    assert_miss(tuple(np.asarray(a) for a in KERNELS[name](o, d, *tri)))


@kernel_names
def test_rays_in_plane_miss_jit(name):
    assert_miss(tuple(np.asarray(a) for a in JITTED[name](*_in_plane_rays())))


@kernel_names
def test_ray_in_plane_misses_jit_single(name):
    o, d, tri = IN_PLANE_CASE
    assert_miss(run(name, o, d, *tri))


@kernel_names
def test_closest_hit_ignores_in_plane_triangle(name):
    """Through the public API: a triangle seen edge-on must not hide the wall behind it
    (moller_trumbore reports it at t = 1.04, where the ray is nowhere near it)."""
    o, d, tri = IN_PLANE_CASE
    wall = np.array([[0, -2, -2], [0, 2, -2], [0, -1, 3]]) + o.astype(np.float64)
    wall[:, 0] = o[0] + 3.0
    vertices = np.concatenate([np.stack(tri), wall]).astype(np.float32)
    structure = accel.build("brute", vertices, np.arange(6).reshape(2, 3))
    hits = jrt.trace.as_numpy(jrt.closest_hit(structure, o[None], d[None], kernel=name))
    assert hits["triangle"][0] == 1, hits
    np.testing.assert_allclose(hits["t"][0], 3.0, rtol=TIGHT)


# Exactly collinear corners (float64 area 0) whose float32 edge v1 - v0 rounds: the computed
# normal / det is a residue, not 0; the rounding bound makes it a miss.
# y = 3x, z = 0: every corner representable, e1 = v1 - v0 is not (25 significant bits).
ROUNDED_COLLINEAR = (f32(2**22 + 1, 3 * (2**22 + 1), 0), f32(0.25, 0.75, 0), f32(0, 0, 0))


@kernel_names
@pytest.mark.parametrize("target", [f32(0.125, 0.375, 0), f32(1, 3, 0)], ids=["mid", "on"])
@pytest.mark.parametrize("dir_name", ["down", "up", "oblique"])
def test_degenerate_triangle_with_rounded_edges_misses(name, target, dir_name):
    corners = np.stack(ROUNDED_COLLINEAR).astype(np.float64)
    assert np.linalg.norm(np.cross(corners[1] - corners[0], corners[2] - corners[0])) == 0
    d = DIRECTIONS[dir_name]
    assert_miss(run(name, target - 2 * d, d, *ROUNDED_COLLINEAR))


@kernel_names
def test_brute_build_drops_rounded_collinear_triangle(name):
    """The builder drops the face as well (float64 area 0)."""
    structure = accel.build("brute", np.stack(ROUNDED_COLLINEAR), np.array([[0, 1, 2]]))
    assert structure.num_triangles == 0
    o, d = f32([0.125, 0.375, 1]), f32([0, 0, -1])
    assert not bool(jrt.occluded(structure, o, d, kernel=name)[0])


@kernel_names
@pytest.mark.parametrize("faces", [[[0, 1, 2]], np.zeros((0, 3), int)],
                         ids=["all_degenerate", "no_faces"])
def test_closest_hit_without_triangles_misses(name, faces):
    structure = accel.build("brute", np.stack(ROUNDED_COLLINEAR), np.asarray(faces))
    assert structure.num_triangles == 0
    hits = jrt.trace.as_numpy(jrt.closest_hit(structure, f32([0.125, 0.375, 1]),
                                              f32([0, 0, -1]), kernel=name))
    assert hits["triangle"][0] == -1 and hits["t"][0] == np.inf


# ---------------------------------------------------------------------------------------------
# Broadcasting, dtypes
# ---------------------------------------------------------------------------------------------


def _random_scene(rng, n_rays, n_tris):
    """Rays and triangles with hits and misses away from every border."""
    tris = rng.uniform(-2, 2, (n_tris, 3, 3)).astype(np.float32)
    # Targets on triangle 0: even rays inside (barycentrics >= 0.1), odd ones well outside.
    b = rng.dirichlet([1, 1, 1], n_rays) * 0.7 + 0.1
    b[1::2, 0] = -0.2 - rng.uniform(0, 1, n_rays // 2)
    b[1::2, 1] = rng.uniform(0, 1, n_rays // 2)
    b[1::2, 2] = 1 - b[1::2, 0] - b[1::2, 1]
    targets = np.einsum("ni,ij->nj", b, tris[0].astype(np.float64))
    d = rng.normal(size=(n_rays, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    origins = targets - 3 * d
    return origins.astype(np.float32), d.astype(np.float32), tris


@kernel_names
def test_broadcasting_matches_loops(name):
    """Batched calls give exactly the numbers of a loop of single calls (op by op, the
    same IEEE operations on each element)."""
    rng = np.random.default_rng(42)
    origins, dirs, tris = _random_scene(rng, 16, 8)
    fn = KERNELS[name]

    def call(o, d, v0, v1, v2):
        return [np.asarray(a) for a in fn(o, d, v0, v1, v2)]

    def assert_same(batch, loop):
        for k in range(3):
            np.testing.assert_array_equal(batch[k], np.stack([row[k] for row in loop]))

    # One ray against a batch of triangles.
    batch = call(origins[0], dirs[0], tris[:, 0], tris[:, 1], tris[:, 2])
    assert batch[0].shape == (8,)
    assert_same(batch, [call(origins[0], dirs[0], *tri) for tri in tris])
    # A batch of rays against one triangle.
    batch = call(origins, dirs, *tris[0])
    assert batch[0].shape == (16,)
    assert np.isfinite(batch[0]).any() and np.isinf(batch[0]).any()
    assert_same(batch, [call(o, d, *tris[0]) for o, d in zip(origins, dirs, strict=True)])
    # The full grid: rays [N, 1, 3] against triangles [T, 3] -> [N, T].
    grid = call(origins[:, None], dirs[:, None], tris[:, 0], tris[:, 1], tris[:, 2])
    assert grid[0].shape == (16, 8)
    assert_same(grid, [call(o, d, tris[:, 0], tris[:, 1], tris[:, 2])
                       for o, d in zip(origins, dirs, strict=True)])
    # Under jit the same hits, and values within rounding (XLA may contract a * b + c into
    # an FMA; plane_barycentric's d - N·O cancels a few digits, hence 1e-5).
    jit_grid = [np.asarray(a) for a in JITTED[name](origins[:, None], dirs[:, None],
                                                    tris[:, 0], tris[:, 1], tris[:, 2])]
    np.testing.assert_array_equal(np.isfinite(jit_grid[0]), np.isfinite(grid[0]))
    for k in range(3):
        np.testing.assert_allclose(jit_grid[k], grid[k], rtol=1e-5, atol=1e-5)


def _enable_x64():
    """``jax.enable_x64(True)`` (current JAX) or ``jax.experimental.enable_x64()`` (older)."""
    if hasattr(jax, "enable_x64"):
        return jax.enable_x64(True)
    from jax.experimental import enable_x64  # pragma: no cover  (JAX < 0.5)

    return enable_x64()


@kernel_names
def test_float64(name):
    fn = KERNELS[name]
    with _enable_x64():
        jitted = jax.jit(fn)
        # t = 1 + 2^-40 is not representable in float32: float64 arithmetic must keep it.
        dz = 2.0**-40
        o = np.array([0.25, 0.5, 1 + dz])
        d = np.array([0.0, 0.0, -1.0])
        tri = (np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]))
        for f in (fn, jitted):
            t, u, v = f(*(jnp.asarray(a) for a in (o, d, *tri)))
            for a in (t, u, v):
                assert a.dtype == jnp.float64
            assert float(t) == 1 + dz
            assert (float(u), float(v)) == (0.25, 0.5)
            # A miss is float64 too.
            t, u, v = f(*(jnp.asarray(a) for a in (o, -d, *tri)))
            for a in (t, u, v):
                assert a.dtype == jnp.float64
            assert_miss((np.asarray(t), np.asarray(u), np.asarray(v)))
            # Just outside by far less than a float32 ulp: float64 sees it.
            outside = np.array([0.5 + 2.0**-40, 0.5, 1.0])
            assert_miss(tuple(np.asarray(a) for a in f(*(jnp.asarray(a) for a in (
                outside, d, *tri)))))


# ---------------------------------------------------------------------------------------------
# Properties (hypothesis)
# ---------------------------------------------------------------------------------------------

coord = st.floats(-10, 10, width=32, allow_subnormal=False)
weight = st.floats(0, 1)
unit = st.floats(-1, 1)


@st.composite
def triangles(draw):
    return np.array([[draw(coord) for _ in range(3)] for _ in range(3)], np.float32)


@st.composite
def directions(draw):
    d = np.array([draw(unit) for _ in range(3)])
    assume(np.linalg.norm(d) > 0.1)
    return d / np.linalg.norm(d)


@st.composite
def inside_barycentrics(draw):
    """Barycentrics with every coordinate >= MARGIN."""
    w = np.array([draw(weight) for _ in range(3)])
    assume(w.sum() > 1e-3)
    return MARGIN + (1 - 3 * MARGIN) * w / w.sum()


@st.composite
def outside_barycentrics(draw):
    """Barycentrics summing to 1 with at least one <= -MARGIN."""
    i = draw(st.integers(0, 2))
    b = np.empty(3)
    b[i] = -MARGIN - draw(st.floats(0, 2))
    j, k = (i + 1) % 3, (i + 2) % 3
    b[j] = draw(st.floats(-2, 3))
    b[k] = 1 - b[i] - b[j]
    return b


def reference(o, d, v0, v1, v2):
    """float64 (t, u, v) of the exact intersection for the given (float32) inputs."""
    o, d, v0, v1, v2 = (np.asarray(a, np.float64) for a in (o, d, v0, v1, v2))
    a = np.stack([-d, v1 - v0, v2 - v0], axis=1)
    return np.linalg.solve(a, o - v0)


def error_bounds(o, d, v0, v1, v2, t_ref):
    """(position bound, barycentric bound, |cos|) of the error model in the module docstring."""
    o, d, v0, v1, v2 = (np.asarray(a, np.float64) for a in (o, d, v0, v1, v2))
    e1, e2, e3 = v1 - v0, v2 - v0, v2 - v1
    n = np.cross(e1, e2)
    n_len = np.linalg.norm(n)
    if n_len == 0:
        return np.inf, np.inf, 0.0
    cols = [d, e1, e2]
    a = np.stack([c / np.linalg.norm(c) for c in cols], axis=1)
    kappa = np.linalg.cond(a)
    scale = np.abs(o).max() + np.abs([v0, v1, v2]).max() + abs(t_ref) * np.linalg.norm(d)
    pos = C_ERR * EPS32 * kappa * scale
    e_max = max(np.linalg.norm(e) for e in (e1, e2, e3))
    cos = abs(n @ d) / (n_len * np.linalg.norm(d))
    return pos, pos * e_max / n_len, cos


def _ray_at(tri, b, d, s):
    """float32 (origin, direction) of a ray reaching the point with barycentrics b after s."""
    target = b @ tri.astype(np.float64)
    return (target - s * d).astype(np.float32), d.astype(np.float32)


def _all_kernels(o, d, tri):
    return {name: tuple(np.asarray(a, np.float64) for a in JITTED[name](o, d, *tri))
            for name in NAMES}


def _resolved_reference(o, d32, tri):
    """The float64 solution and its error bounds; hypothesis skips singular systems and
    near-grazing rays (no accuracy claim there)."""
    try:
        t_ref, u_ref, v_ref = reference(o, d32, *tri)
    except np.linalg.LinAlgError:
        assume(False)
    pos_tol, bary_tol, cos = error_bounds(o, d32, *tri, t_ref)
    assume(cos >= 1e-3)
    return t_ref, u_ref, v_ref, pos_tol, bary_tol


distances = st.floats(0.1, 30)


@PROPERTY
@given(tri=triangles(), b=inside_barycentrics(), d=directions(), s=distances)
def test_property_interior_rays_hit(tri, b, d, s):
    o, d32 = _ray_at(tri, b, d, s)
    t_ref, u_ref, v_ref, pos_tol, bary_tol = _resolved_reference(o, d32, tri)
    assume(bary_tol < MARGIN)  # the bound keeps the hit away from the border
    assume(t_ref * np.linalg.norm(d32) > pos_tol)  # and away from t = 0
    p_ref = o.astype(np.float64) + t_ref * d32.astype(np.float64)
    for name, (t, u, v) in _all_kernels(o, d32, tri).items():
        assert np.isfinite(t), (name, t_ref, u_ref, v_ref)
        d_len = np.linalg.norm(d32)
        assert abs(t - t_ref) * d_len <= pos_tol, (name, t, t_ref, pos_tol)
        assert max(abs(u - u_ref), abs(v - v_ref)) <= bary_tol, (name, u, v, u_ref, v_ref)
        p_ray = o.astype(np.float64) + t * d32.astype(np.float64)
        p_tri = point_from_barycentrics(u, v, *tri)
        assert np.linalg.norm(p_ray - p_ref) <= pos_tol, name
        assert np.linalg.norm(p_tri - p_ref) <= pos_tol, name


@PROPERTY
@given(tri=triangles(), b=outside_barycentrics(), d=directions(), s=distances)
def test_property_exterior_rays_miss(tri, b, d, s):
    o, d32 = _ray_at(tri, b, d, s)
    _, _, _, _, bary_tol = _resolved_reference(o, d32, tri)
    assume(bary_tol < MARGIN)
    for name, result in _all_kernels(o, d32, tri).items():
        assert np.isinf(result[0]), (name, result, b)
        assert_miss(result)


@PROPERTY
@given(
    tri=triangles(),
    b=st.one_of(inside_barycentrics(), outside_barycentrics()),
    d=directions(),
    s=st.one_of(distances, distances.map(lambda x: -x)),
)
def test_property_kernels_agree_on_hit_or_miss(tri, b, d, s):
    """Inside or outside, in front of the origin or behind it: the three kernels agree, and
    agree with the float64 classification, whenever the error bound leaves no doubt."""
    o, d32 = _ray_at(tri, b, d, s)
    t_ref, u_ref, v_ref, pos_tol, bary_tol = _resolved_reference(o, d32, tri)
    assume(bary_tol < MARGIN)
    assume(abs(t_ref) * np.linalg.norm(d32) > pos_tol)
    expected = t_ref > 0 and min(1 - u_ref - v_ref, u_ref, v_ref) >= 0
    event("hit" if expected else "miss")
    hits = {name: bool(np.isfinite(r[0])) for name, r in _all_kernels(o, d32, tri).items()}
    assert set(hits.values()) == {expected}, (hits, expected, t_ref, b)


@PROPERTY
@given(
    axis=st.integers(0, 2),
    c=coord,
    corners=st.lists(coord, min_size=6, max_size=6),
    b=inside_barycentrics(),
    o_n=st.floats(-30, 30, width=32),
    d_n=st.floats(0.125, 8, width=32),
)
def test_property_axis_aligned_flat_triangles(axis, c, corners, b, o_n, d_n):
    """Corners sharing one coordinate, rays along that axis with ±0.0 in-plane components:
    every sign pattern of the zeros gives the same hit."""
    assume(abs(o_n - c) >= 0.1)
    others = [k for k in range(3) if k != axis]
    tri = np.empty((3, 3), np.float32)
    tri[:, axis] = c
    tri[:, others] = np.reshape(corners, (3, 2))
    target = b @ tri.astype(np.float64)
    o = target.astype(np.float32)
    o[axis] = o_n
    sign = np.float32(np.sign(c - o_n))
    t_exact = (np.float64(c) - np.float64(o_n)) / (np.float64(sign) * np.float64(d_n))
    results = []
    for zx in (0.0, -0.0):
        for zy in (0.0, -0.0):
            d = np.empty(3, np.float32)
            d[axis] = sign * d_n
            d[others] = (zx, zy)
            try:
                t_ref, u_ref, v_ref = reference(o, d, *tri)
            except np.linalg.LinAlgError:
                assume(False)
            pos_tol, bary_tol, _ = error_bounds(o, d, *tri, t_ref)
            assume(bary_tol < MARGIN)
            assume(t_ref * d_n > pos_tol)
            np.testing.assert_allclose(t_ref, t_exact, rtol=1e-12)
            got = _all_kernels(o, d, tri)
            for name, (t, u, v) in got.items():
                assert np.isfinite(t), (name, d, tri, o)
                assert abs(t - t_ref) * d_n <= pos_tol, (name, t, t_ref)
                assert max(abs(u - u_ref), abs(v - v_ref)) <= bary_tol, name
            results.append(got)
    for other in results[1:]:
        for name in NAMES:
            np.testing.assert_array_equal(np.array(results[0][name]), np.array(other[name]))


# ---------------------------------------------------------------------------------------------
# Brute-force closest hit and occlusion
# ---------------------------------------------------------------------------------------------

_SQUARE = np.array([[-1, -1], [3, -1], [-1, 3]], np.float64)  # covers (0.5, 0.5) widely


def _tri_at(z):
    return np.column_stack([_SQUARE, np.full(3, z)])


def _mesh(*triangles_):
    vertices = np.concatenate(triangles_).astype(np.float32)
    faces = np.arange(len(vertices), dtype=np.int32).reshape(-1, 3)
    return vertices, faces


@kernel_names
def test_closest_hit_picks_nearest_of_stacked_triangles(name):
    # Face 0 at z = 2, face 1 at z = 1 (the nearer one has the higher index).
    structure = accel.build("brute", *_mesh(_tri_at(2), _tri_at(1)))
    origins = f32([0.5, 0.5, 0], [0.5, 0.5, 3], [0.5, 0.5, 1.5], [0.5, 0.5, 1.5], [9, 9, 0])
    dirs = f32([0, 0, 1], [0, 0, -1], [0, 0, 1], [0, 0, -1], [0, 0, 1])
    hits = jrt.trace.as_numpy(jrt.closest_hit(structure, origins, dirs, kernel=name))
    np.testing.assert_array_equal(hits["triangle"], [1, 0, 0, 1, -1])
    np.testing.assert_allclose(hits["t"], [1, 1, 0.5, 0.5, np.inf], rtol=TIGHT)
    assert not np.isnan(hits["u"]).any() and not np.isnan(hits["v"]).any()
    assert hits["u"][-1] == 0 and hits["v"][-1] == 0


@kernel_names
@pytest.mark.parametrize("reorder", [False, True], ids=["same_winding", "rotated_corners"])
def test_closest_hit_tie_goes_to_lower_index(name, reorder):
    """Two coincident triangles (same corners, different face indices): the lower index
    wins. A degenerate face 0 (dropped by the builder) makes rows differ from indices."""
    coincident = _tri_at(1)
    second = coincident[[1, 2, 0]] if reorder else coincident
    degenerate = np.zeros((3, 3))
    vertices, faces = _mesh(degenerate, _tri_at(5), coincident, second)
    structure = accel.build("brute", vertices, faces)
    assert structure.num_triangles == 3
    origins = f32([0.5, 0.5, 0], [0.25, 0.5, -2], [0, 0, 0])
    dirs = f32([0, 0, 1], [0, 0, 1], [0.5, 0.5, 1])
    hits = jrt.trace.as_numpy(jrt.closest_hit(structure, origins, dirs, kernel=name))
    np.testing.assert_array_equal(hits["triangle"], [2, 2, 2])
    np.testing.assert_allclose(hits["t"], [1, 3, 1], rtol=TIGHT)
    # The same with one triangle per chunk and a ray chunk that needs padding: the tie is
    # then decided across chunks (the earlier chunk must keep it).
    for tri_chunk, ray_chunk in ((1, 2), (2, 4), (3, 1)):
        h = brute.closest_hit(
            jnp.asarray(structure["triangles"]), jnp.asarray(structure["triangle_ids"]),
            jnp.asarray(origins), jnp.asarray(dirs), jnp.full(3, jnp.inf, jnp.float32),
            kernel=name, ray_chunk=ray_chunk, tri_chunk=tri_chunk,
        )
        np.testing.assert_array_equal(np.asarray(h.triangle), [2, 2, 2])
        np.testing.assert_array_equal(np.asarray(h.t), hits["t"])


@kernel_names
def test_tmax(name):
    """Hits count only for 0 < t < tmax (strict), in occluded and closest_hit alike."""
    structure = accel.build("brute", *_mesh(_tri_at(2)))
    n = 6
    origins = np.tile(f32(0.5, 0.5, 0), (n, 1))
    dirs = np.tile(f32(0, 0, 1), (n, 1))
    dirs[-1] = (0, 0, -1)  # pointing away
    tmax = f32(1.5, 2.5, np.inf, 2.0, np.nextafter(np.float32(2), np.float32(3)), np.inf)
    expected = [False, True, True, False, True, False]
    occ = np.asarray(jrt.occluded(structure, origins, dirs, tmax=tmax, kernel=name))
    np.testing.assert_array_equal(occ, expected)
    hits = jrt.trace.as_numpy(jrt.closest_hit(structure, origins, dirs, kernel=name, tmax=tmax))
    np.testing.assert_array_equal(hits["triangle"] >= 0, expected)
    np.testing.assert_array_equal(np.isfinite(hits["t"]), expected)
    # Scalar tmax and no tmax.
    np.testing.assert_array_equal(
        np.asarray(jrt.occluded(structure, origins, dirs, tmax=1.5, kernel=name)), [False] * n)
    np.testing.assert_array_equal(
        np.asarray(jrt.occluded(structure, origins, dirs, tmax=None, kernel=name)),
        [True] * (n - 1) + [False])
