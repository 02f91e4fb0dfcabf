"""Ray–triangle intersection: three interchangeable kernels with one signature.

    kernel(origin, direction, v0, v1, v2) -> (t, u, v)

All arguments broadcast against each other over their leading axes; the last axis holds
the three coordinates. The hit point is ``origin + t * direction`` and, on the triangle,
``(1 - u - v) * v0 + u * v1 + v * v2``. A hit needs ``t > 0`` (strictly: a ray never hits
at its own origin) and the point inside or on the border of the triangle. A miss is
``t = +inf`` with ``u = v = 0``: never NaN, whatever the input (parallel rays, degenerate
triangles, zero direction components). Ties on a shared edge are resolved by the caller
(closest t, then the lower triangle index).

Dot and cross products are written out component by component rather than with matmul
or einsum: GPUs run float32 matmul as TF32, which would cost 13 bits of mantissa.
"""

from __future__ import annotations

from collections.abc import Callable

import jax.numpy as jnp
from jaxtyping import Array, Float

Vec = Float[Array, "*batch 3"]
Scalar = Float[Array, "*batch"]
Kernel = Callable[[Vec, Vec, Vec, Vec, Vec], tuple[Scalar, Scalar, Scalar]]


def dot(a: Vec, b: Vec) -> Scalar:
    """a · b over the last axis."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def cross(a: Vec, b: Vec) -> Vec:
    """a × b (seed, Définition 3.1)."""
    return jnp.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


def _abs_cross(a: Vec, b: Vec) -> Vec:
    """|a| × |b| with the signs dropped: bounds the rounding error of ``a × b``."""
    a, b = jnp.abs(a), jnp.abs(b)
    return jnp.stack(
        [
            a[..., 1] * b[..., 2] + a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] + a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] + a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


def _resolvable(value: Scalar, magnitude: Scalar) -> Scalar:
    """|value| exceeds 8 ε x magnitude: its sign is not rounding noise.

    A triple product such as Möller–Trumbore's ``det`` or the seed's ``N·D`` is exactly 0
    for a ray in the triangle's plane or a degenerate triangle, but the compiled code may
    evaluate it with fused multiply-adds and leave a residue of a few ulps of the terms'
    magnitude, which a plain ``!= 0`` test would take for a (wildly wrong) hit.
    """
    eps = jnp.finfo(value.dtype).eps
    return jnp.abs(value) > 8 * eps * magnitude


def _finish(hit, t, u, v):
    """Masks a miss to (inf, 0, 0). NaN comparisons are False, so NaN never passes ``hit``."""
    inf = jnp.asarray(jnp.inf, t.dtype)
    zero = jnp.zeros_like(t)
    return jnp.where(hit, t, inf), jnp.where(hit, u, zero), jnp.where(hit, v, zero)


def plane_barycentric(origin: Vec, direction: Vec, v0: Vec, v1: Vec, v2: Vec):
    """The seed's method ("Triangle et rayon"): plane first, then barycentric coordinates.

    With ``N = (v1 - v0) × (v2 - v0)`` (seed, Proposition 3.1) and ``d = N · v0`` the plane is
    ``N · X = d``; the ray meets it at ``t = (d - N·O) / (N·D)``. The point ``I = O + t D``
    has barycentric coordinates ``β_i = ((P_{i+2} - P_{i+1}) × (I - P_{i+1})) · N / |N|²``
    and is inside iff all three lie in [0, 1].

    The seed writes ``β_i`` with norms, ``|(P_{i+2} - P_{i+1}) × (I - P_{i+1})| / |N|``; those
    are unsigned and also accept points just outside an edge (all three stay within [0, 1]
    while their sum exceeds 1). Projecting on ``N`` instead keeps the sign, which is the
    same quantity inside the triangle and the right test outside it.

    A ray parallel to the plane and a degenerate triangle (``N·D`` zero up to its rounding
    error, see ``_resolvable``) miss.
    The form ``d - N·O`` is kept as the seed gives it: it loses digits when the origin is far
    from the plane, which the numerical-stability study measures.
    """
    e1 = v1 - v0
    e2 = v2 - v0
    normal = cross(e1, e2)
    n_dot_d = dot(normal, direction)
    plane_d = dot(normal, v0)
    t = (plane_d - dot(normal, origin)) / n_dot_d
    point = origin + t[..., None] * direction
    inv_nn = 1.0 / dot(normal, normal)
    b0 = dot(cross(v2 - v1, point - v1), normal) * inv_nn
    b1 = dot(cross(v0 - v2, point - v2), normal) * inv_nn
    b2 = dot(cross(e1, point - v0), normal) * inv_nn
    inside = (b0 >= 0) & (b0 <= 1) & (b1 >= 0) & (b1 <= 1) & (b2 >= 0) & (b2 <= 1)
    parallel = ~_resolvable(n_dot_d, dot(jnp.abs(direction), _abs_cross(e1, e2)))
    hit = ~parallel & (t > 0) & (t < jnp.inf) & inside
    return _finish(hit, t, b1, b2)


def moller_trumbore(origin: Vec, direction: Vec, v0: Vec, v1: Vec, v2: Vec):
    """Möller & Trumbore (1997), "Fast, minimum storage ray–triangle intersection".

    Solves ``O + t D = (1 - u - v) v0 + u v1 + v v2`` by Cramer's rule with the scalar
    triple products of ``e1 = v1 - v0``, ``e2 = v2 - v0`` and ``s = O - v0``. Both faces are
    hit (no culling); ``det`` zero up to its rounding error (a ray in the triangle's plane, a
    degenerate triangle; see ``_resolvable``) is a miss. Borders
    are inclusive: ``u >= 0, v >= 0, u + v <= 1``. Shared edges can still leak a ray in
    float32, since the two neighbours round their edge tests differently.
    """
    e1 = v1 - v0
    e2 = v2 - v0
    p = cross(direction, e2)
    det = dot(e1, p)
    inv_det = 1.0 / det
    s = origin - v0
    u = dot(s, p) * inv_det
    q = cross(s, e1)
    v = dot(direction, q) * inv_det
    t = dot(e2, q) * inv_det
    parallel = ~_resolvable(det, dot(jnp.abs(e1), _abs_cross(direction, e2)))
    hit = ~parallel & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (t < jnp.inf)
    return _finish(hit, t, u, v)


def _permute(a: Vec, kx, ky, kz):
    """Components (a[kx], a[ky], a[kz]) for per-ray axis indices, as selects (no gather)."""

    def pick(k):
        return jnp.where(k == 0, a[..., 0], jnp.where(k == 1, a[..., 1], a[..., 2]))

    return pick(kx), pick(ky), pick(kz)


def _edge_function(ax, ay, bx, by):
    """``a.x b.y - a.y b.x``, exactly antisymmetric in (a, b).

    The two triangles sharing an edge walk it in opposite directions. Evaluating the
    product difference always from the lexicographically smaller endpoint, and negating
    for the other orientation, makes the two edge functions exact negatives of each other,
    whatever the compiler does (FMA contraction included). With zero accepted on both
    sides (the tie rule of ``watertight``), no ray can slip between two neighbours.
    """
    swap = (ax > bx) | ((ax == bx) & (ay > by))
    lox, loy = jnp.where(swap, bx, ax), jnp.where(swap, by, ay)
    hix, hiy = jnp.where(swap, ax, bx), jnp.where(swap, ay, by)
    e = lox * hiy - loy * hix
    return jnp.where(swap, -e, e)


def gamma(n: int, dtype) -> float:
    """pbrt's γ_n = n ε / (1 - n ε), ε the unit roundoff (half the machine epsilon)."""
    eps = float(jnp.finfo(dtype).eps) * 0.5
    return n * eps / (1 - n * eps)


def watertight(origin: Vec, direction: Vec, v0: Vec, v1: Vec, v2: Vec):
    """Woop, Benthin & Wald (2013), "Watertight ray/triangle intersection", after pbrt-v4.

    Translate the corners to the ray origin, permute the axes so that the direction's
    largest component is z, shear so that the ray becomes the +z axis, then evaluate the
    three 2D edge functions at the origin. The signs of the edge functions decide the hit:
    all >= 0 or all <= 0 (either facing). Where pbrt re-evaluates an edge function that is
    exactly zero in double precision, this kernel uses a tie rule instead: zero counts as
    inside for both neighbours of the edge, and the edge functions are exactly antisymmetric
    (see ``_edge_function``), so a ray through an edge or a vertex hits at least one of the
    triangles around it: a closed mesh has no cracks. The caller picks among tied hits.

    A hit must also lie certainly in front of the origin. Either certificate will do:

    - pbrt's: ``t`` exceeds its conservative bound ``δt`` on its own rounding error
      (pbrt-v4, section 6.8.7, "Avoiding Intersections behind Ray Origins"), so that a ray
      leaving a surface does not hit it again at t ≈ 0;
    - all three corners lie strictly ahead of the origin (sheared ``z_i > 0``), and the
      triangle is neither degenerate nor seen edge-on. The signs of the ``z_i`` are exact
      (a rounded difference and a product keep their signs), and with the three edge
      functions of one sign ``t = Σ e_i z_i / Σ e_i`` is a weighted mean of the ``z_i``, so
      ``t > 0`` whatever the rounding of the edge functions. Non-degeneracy is
      ``moller_trumbore``'s test (``det = e1 · (D × e2)`` beyond its rounding error, see
      ``_resolvable``): it works on the corners' differences, so unlike ``δt`` it does not
      grow with the distance to the origin.

    The second certificate is what keeps the kernel watertight. ``δt`` scales every edge
    function's error by the largest corner coordinates (and the shear's error by the
    distance) and divides by ``|det|``, so for a sliver (the camel has triangles with one
    edge 1e-4 of the others) it can exceed ``t`` itself, hundreds of units away. A ray
    through the sliver's short edge may hit only the sliver (the one triangle there whose
    rounded edge functions agree), and the ``δt`` test alone then left a crack, at any
    scale. ``δt`` still decides for triangles that straddle the origin's plane, where ``t``
    can be near 0.
    """
    dtype = direction.dtype
    abs_d = jnp.abs(direction)
    # Axis indices as int32 (explicit, so that they stay so under jax_enable_x64).
    zero, one, two = jnp.int32(0), jnp.int32(1), jnp.int32(2)
    kz = jnp.where(
        (abs_d[..., 0] >= abs_d[..., 1]) & (abs_d[..., 0] >= abs_d[..., 2]),
        zero,
        jnp.where(abs_d[..., 1] >= abs_d[..., 2], one, two),
    )
    kx = jnp.where(kz == two, zero, kz + one)
    ky = jnp.where(kx == two, zero, kx + one)
    dx, dy, dz = _permute(direction, kx, ky, kz)
    sx = -dx / dz
    sy = -dy / dz
    sz = 1.0 / dz

    def transform(vertex):
        px, py, pz = _permute(vertex - origin, kx, ky, kz)
        return px + sx * pz, py + sy * pz, pz

    p0x, p0y, p0z = transform(v0)
    p1x, p1y, p1z = transform(v1)
    p2x, p2y, p2z = transform(v2)

    e0 = _edge_function(p1x, p1y, p2x, p2y)
    e1 = _edge_function(p2x, p2y, p0x, p0y)
    e2 = _edge_function(p0x, p0y, p1x, p1y)
    mixed = ((e0 < 0) | (e1 < 0) | (e2 < 0)) & ((e0 > 0) | (e1 > 0) | (e2 > 0))
    det = e0 + e1 + e2

    p0z, p1z, p2z = p0z * sz, p1z * sz, p2z * sz
    t_scaled = e0 * p0z + e1 * p1z + e2 * p2z
    inv_det = 1.0 / det
    t = t_scaled * inv_det

    # pbrt-v4 (6.8.7): a conservative bound on the rounding error of t.
    max_zt = jnp.maximum(jnp.maximum(jnp.abs(p0z), jnp.abs(p1z)), jnp.abs(p2z))
    max_xt = jnp.maximum(jnp.maximum(jnp.abs(p0x), jnp.abs(p1x)), jnp.abs(p2x))
    max_yt = jnp.maximum(jnp.maximum(jnp.abs(p0y), jnp.abs(p1y)), jnp.abs(p2y))
    delta_z = gamma(3, dtype) * max_zt
    delta_x = gamma(5, dtype) * (max_xt + max_zt)
    delta_y = gamma(5, dtype) * (max_yt + max_zt)
    delta_e = 2 * (gamma(2, dtype) * max_xt * max_yt + delta_y * max_xt + delta_x * max_yt)
    max_e = jnp.maximum(jnp.maximum(jnp.abs(e0), jnp.abs(e1)), jnp.abs(e2))
    delta_t = 3 * (gamma(3, dtype) * max_e * max_zt + delta_e * max_zt + delta_z * max_e)
    delta_t = delta_t * jnp.abs(inv_det)

    # The second certificate (see the docstring): every corner ahead of the origin, and
    # Möller–Trumbore's determinant resolvable (not a degenerate triangle or a ray in its
    # plane).
    e1_3d = v1 - v0
    e2_3d = v2 - v0
    det_3d = dot(e1_3d, cross(direction, e2_3d))
    proper = _resolvable(det_3d, dot(jnp.abs(e1_3d), _abs_cross(direction, e2_3d)))
    ahead = (p0z > 0) & (p1z > 0) & (p2z > 0) & proper

    hit = (~mixed) & (det != 0) & (ahead | (t > delta_t)) & (t > 0) & (t < jnp.inf)
    return _finish(hit, t, e1 * inv_det, e2 * inv_det)


KERNELS: dict[str, Kernel] = {
    "plane_barycentric": plane_barycentric,
    "moller_trumbore": moller_trumbore,
    "watertight": watertight,
}

DEFAULT_KERNEL = "watertight"


def get_kernel(name: str) -> Kernel:
    """The kernel called ``name``; a clear error lists the allowed names."""
    try:
        return KERNELS[name]
    except KeyError:
        raise ValueError(
            f"unknown triangle kernel {name!r}; allowed: {', '.join(KERNELS)}"
        ) from None
