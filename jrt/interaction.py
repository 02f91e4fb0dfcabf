"""From a hit to a surface point: the point, its floating-point error bound, its normals,
and the offset origin of the rays that leave it.

pbrt-v4 is the model: ``Triangle::InteractionFromIntersection`` (§6.8.5) rebuilds the hit
point from the barycentric coordinates with the bound ``γ7 Σ|b_i p_i|``
(:func:`surface_interaction`), and ``OffsetRayOrigin`` (§6.8.6) moves a new ray's origin
just past that bound, so that a reflected, refracted or shadow ray never hits the surface it
leaves (:func:`offset_ray_origin`).

:func:`surface_interaction`, :func:`face_forward` and :func:`normalise` take NumPy or JAX
arrays and compute in the arrays' own precision: jax.numpy (float32) in the renderers,
NumPy (float64 if given) where a benchmark derives rays from another engine's hits.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from jrt.kernels import cross, dot, gamma


class SurfaceInteraction(NamedTuple):
    """What a renderer needs at its rays' hits (a pytree of ``[N, ...]`` arrays).

    Attributes:
        point: ``Σ b_i p_i``, the hit point from the barycentrics ``b = (1-u-v, u, v)`` and
            the triangle's corners ``p_i`` (not ``o + t d``: pbrt-v4 §6.8.5).
        error: ``γ7 Σ|b_i p_i|`` per coordinate, the bound on ``point``'s rounding error.
        geometric_normal: the unit normal of the face's winding, ``(p1 - p0) × (p2 - p0)``
            normalised: outward for a closed, consistently oriented mesh such as the camel.
        shading_normal: the face's corner normals (:func:`jrt.normals.corner_normals`)
            interpolated at ``b`` and normalised, on the side of the winding's outward
            normal when the corner normals are; the geometric normal when there are none.
        entering: ``d · n_g < 0``: the ray arrives from the winding's outward side (from
            outside a closed mesh: seed, Proposition 3.2; :func:`jrt.optics.orient`).
    """

    point: Float[Array, "n 3"]
    error: Float[Array, "n 3"]
    geometric_normal: Float[Array, "n 3"]
    shading_normal: Float[Array, "n 3"]
    entering: Bool[Array, " n"]


def _namespace(*arrays):
    """NumPy when every array is a NumPy one (its float64 kept), jax.numpy otherwise."""
    return np if all(isinstance(a, np.ndarray) for a in arrays) else jnp


def normalise(v: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3"]:
    """``v / |v|``; a zero vector stays zero (its squared length is taken as at least 1e-30)."""
    xp = _namespace(v)
    return v / xp.sqrt(xp.maximum(dot(v, v), 1e-30))[..., None]


def face_forward(n: Float[Array, "*batch 3"], v: Float[Array, "*batch 3"]
                 ) -> Float[Array, "*batch 3"]:
    """pbrt-v4's ``FaceForward``: ``n`` turned into the hemisphere of ``v`` (``-n`` where
    ``n · v < 0``, ``n`` otherwise)."""
    xp = _namespace(n, v)
    return xp.where((dot(n, v) < 0)[..., None], -n, n)


def surface_interaction(
    vertices: Float[Array, "v 3"],
    faces: Int[Array, "f 3"],
    triangle: Int[Array, " n"],
    u: Float[Array, " n"],
    v: Float[Array, " n"],
    directions: Float[Array, "n 3"],
    corner_normals: Float[Array, "f 3 3"] | None = None,
) -> SurfaceInteraction:
    """pbrt-v4 §6.8.5, ``Triangle::InteractionFromIntersection``: the surface at the hits
    ``(triangle, u, v)`` of rays along ``directions`` (a :class:`SurfaceInteraction`).

    A miss (``triangle`` -1) reads triangle 0: its fields are meaningless, for the caller to
    mask. ``corner_normals`` (``[F, 3, 3]``, :func:`jrt.normals.corner_normals`) give the
    shading normal; without them it is the geometric one.
    """
    xp = _namespace(vertices, u, v, directions)
    tri = xp.maximum(triangle, 0)
    p = vertices[faces[tri]]  # [N, 3, 3]
    b = xp.stack([1 - u - v, u, v], axis=-1)[..., None]  # [N, 3, 1]
    point = (b * p).sum(axis=1)
    error = gamma(7, p.dtype) * xp.abs(b * p).sum(axis=1)
    face_cross = np.cross if xp is np else cross
    ng = normalise(face_cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]))
    entering = dot(directions, ng) < 0
    ns = ng if corner_normals is None else normalise((b * corner_normals[tri]).sum(axis=1))
    return SurfaceInteraction(point, error, ng, ns, entering)


def offset_ray_origin(point: Float[Array, "*batch 3"], error: Float[Array, "*batch 3"],
                      n: Float[Array, "*batch 3"],
                      direction: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3"]:
    """pbrt-v4 §6.8.6, ``OffsetRayOrigin``: move ``point`` off the surface of unit normal
    ``n`` by ``d = Σ|n_i| error_i`` to the side ``direction`` goes to, then round each moved
    coordinate one float further away (``NextFloatUp/Down``)."""
    d = dot(jnp.abs(n), error)
    offset = d[..., None] * n
    offset = jnp.where((dot(direction, n) < 0)[..., None], -offset, offset)
    moved = point + offset
    away = jnp.where(offset > 0, jnp.inf, jnp.where(offset < 0, -jnp.inf, moved))
    return _next_float(moved, away)


@jax.custom_jvp
def _next_float(x, toward):
    """``nextafter(x, toward)``, whose derivative is taken as 1 in ``x`` (a one-ulp step
    of rounding: the point it moves is the point it was, for a derivative)."""
    return jnp.nextafter(x, toward)


@_next_float.defjvp
def _next_float_jvp(primals, tangents):
    x, toward = primals
    return jnp.nextafter(x, toward), tangents[0]


__all__ = ["SurfaceInteraction", "face_forward", "normalise", "offset_ray_origin",
           "surface_interaction"]
