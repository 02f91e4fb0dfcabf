"""Exact derivatives of a closest hit's ``(t, u, v)`` by implicit differentiation.

The traversal decides *which* triangle a ray hits: a piecewise constant answer with no
useful derivative, computed by loops that JAX should not differentiate. Once the winner
is known, its ``(t, u, v)`` is a smooth function of the ray and of that triangle's three
corners, the solution of the linear system ``o + t d = (1 - u - v) v0 + u v1 + v v2``
(the lecture's "Triangle et rayon", ``docs/lecture.md``: the ray meets the triangle's
plane at ``t``, where the point's barycentric coordinates are ``(1 - u - v, u, v)``).
Every kernel (``jrt.kernels``) computes that same point, each with its own rounding, so
the derivative is the one of the exact solution, whichever kernel found the hit. We
differentiate it in the closed form of Möller & Trumbore, "Fast, minimum storage
ray-triangle intersection" (JGT 1997), Cramer's rule on that system:

    e1 = v1 - v0,  e2 = v2 - v0,  p = d x e2,  det = e1 . p,  s = o - v0,  q = s x e1
    t = (e2 . q) / det,  u = (s . p) / det,  v = (d . q) / det

:func:`hit_tangents` is the forward-mode (JVP) rule the queries attach to their hits
(``jrt.trace``): tangents of ``t, u, v`` from the tangents of the origins, directions and
triangle rows, linear in them, so reverse mode (``jax.grad``) follows by transposition.
A miss, or a hit whose system is singular (``det == 0`` in float32, a ray in the
triangle's plane), has a zero tangent: the closed form is evaluated there on a fixed,
well-conditioned stand-in triangle and ray whose tangents are zero (the "double where"
of JAX's FAQ: a ``where`` on the *inputs*, so that no inf or NaN enters the linear map
whose transpose reverse mode takes).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

#: The stand-in of a miss: a right triangle in z = 0 and a ray falling on it from z = 1.
_SAFE_TRIANGLE = ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0))
_SAFE_ORIGIN = (0.25, 0.25, 1.0)
_SAFE_DIRECTION = (0.0, 0.0, -1.0)


def closed_form_hit(triangle: Float[Array, "*n 3 3"], origin: Float[Array, "*n 3"],
                    direction: Float[Array, "*n 3"]):
    """``(t, u, v, det)`` of the line ``origin + t direction`` and the plane of
    ``triangle`` (Möller & Trumbore's closed form, module docstring), any float dtype."""
    v0, v1, v2 = triangle[..., 0, :], triangle[..., 1, :], triangle[..., 2, :]
    e1, e2 = v1 - v0, v2 - v0
    p = jnp.cross(direction, e2)
    det = jnp.sum(e1 * p, axis=-1)
    s = origin - v0
    q = jnp.cross(s, e1)
    t = jnp.sum(e2 * q, axis=-1) / det
    u = jnp.sum(s * p, axis=-1) / det
    v = jnp.sum(direction * q, axis=-1) / det
    return t, u, v, det


def hit_tangents(triangles: Float[Array, "rows 3 3"], rows: Int[Array, "*n"],
                 origins: Float[Array, "*n 3"], directions: Float[Array, "*n 3"],
                 triangles_dot: Float[Array, "rows 3 3"] | None,
                 origins_dot: Float[Array, "*n 3"] | None,
                 directions_dot: Float[Array, "*n 3"] | None):
    """Tangents ``(t_dot, u_dot, v_dot)`` (float32) of the hits on the triangle ``rows``
    (the query's winning rows of ``triangles``, -1 for a miss) for the tangents of the
    triangle rows, origins and directions (None: a zero tangent); exactly 0 for a miss
    and for a singular hit (module docstring)."""
    if triangles.shape[0] == 0:  # no triangle: every ray misses
        zero = jnp.zeros(rows.shape, jnp.float32)
        return zero, zero, zero
    hit = rows >= 0
    row = jnp.where(hit, rows, 0)
    f32 = jnp.float32
    triangle = jnp.asarray(triangles, f32)[row]
    origin, direction = origins.astype(f32), directions.astype(f32)
    _, _, _, det = closed_form_hit(triangle, origin, direction)
    ok = hit & (det != 0) & jnp.isfinite(det)
    mask3, mask33 = ok[..., None], ok[..., None, None]
    primals = (jnp.where(mask33, triangle, jnp.asarray(_SAFE_TRIANGLE, f32)),
               jnp.where(mask3, origin, jnp.asarray(_SAFE_ORIGIN, f32)),
               jnp.where(mask3, direction, jnp.asarray(_SAFE_DIRECTION, f32)))
    zero3 = jnp.zeros(origin.shape, f32)
    tangents = (jnp.zeros(triangle.shape, f32) if triangles_dot is None
                else jnp.where(mask33, triangles_dot.astype(f32)[row], 0),
                zero3 if origins_dot is None else jnp.where(mask3, origins_dot.astype(f32), 0),
                zero3 if directions_dot is None
                else jnp.where(mask3, directions_dot.astype(f32), 0))
    _, (t_dot, u_dot, v_dot, _) = jax.jvp(closed_form_hit, primals, tangents)
    return tuple(jnp.where(ok, x, 0).astype(f32) for x in (t_dot, u_dot, v_dot))
