"""Public ray queries: any structure, any triangle kernel, one call site.

    hits = jrt.closest_hit(structure, origins, directions, kernel="watertight", tmax=None)
    mask = jrt.occluded(structure, origins, directions, tmax)

``structure`` comes from ``accel.build(name, vertices, faces)``. Directions are expected to
be unit vectors (seed, Proposition 2.1: a ray is a point and a unit vector), so that ``t``
is a distance; the kernels themselves are affine and return ``t`` in units of the
direction's length.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from accel.structure import Structure
from jrt import brute
from jrt import structure as _structure  # noqa: F401  (registers Structure as a pytree)
from jrt.hits import Hits
from jrt.kernels import DEFAULT_KERNEL, get_kernel


def _check_rays(origins, directions, tmax):
    origins = jnp.asarray(origins, jnp.float32)
    directions = jnp.asarray(directions, jnp.float32)
    if origins.ndim != 2 or origins.shape[1] != 3:
        raise ValueError(f"origins must have shape [N, 3], got {tuple(origins.shape)}")
    if directions.shape != origins.shape:
        raise ValueError(
            f"directions must have the shape of origins {tuple(origins.shape)}, "
            f"got {tuple(directions.shape)}"
        )
    n = origins.shape[0]
    if tmax is None:
        tmax = jnp.full((n,), jnp.inf, jnp.float32)
    else:
        tmax = jnp.broadcast_to(jnp.asarray(tmax, jnp.float32), (n,))
    return origins, directions, tmax


def _check_structure(structure):
    if not isinstance(structure, Structure):
        raise TypeError(
            f"structure must be an accel.Structure (from accel.build), got {type(structure)}"
        )
    if structure.kind != "brute":
        raise ValueError(f"no traversal for structure kind {structure.kind!r}; allowed: brute")


def closest_hit(
    structure: Structure,
    origins: Float[Array, "n 3"],
    directions: Float[Array, "n 3"],
    kernel: str = DEFAULT_KERNEL,
    tmax: Float[Array, " n"] | float | None = None,
) -> Hits:
    """The closest hit of every ray with ``0 < t < tmax``.

    Args:
        structure: from ``accel.build``.
        origins, directions: float32 [N, 3]; directions of unit length.
        kernel: ``"watertight"`` (default), ``"moller_trumbore"`` or ``"plane_barycentric"``.
        tmax: float32 [N] or a scalar; ``None`` for no limit.

    Returns:
        :class:`jrt.Hits` (t inf and triangle -1 for a miss). Ties: the smallest t, then
        the lowest face index.
    """
    _check_structure(structure)
    get_kernel(kernel)
    origins, directions, tmax = _check_rays(origins, directions, tmax)
    return brute.closest_hit(
        structure["triangles"], structure["triangle_ids"], origins, directions, tmax,
        kernel=kernel,
    )


def occluded(
    structure: Structure,
    origins: Float[Array, "n 3"],
    directions: Float[Array, "n 3"],
    tmax: Float[Array, " n"] | float | None = None,
    kernel: str = DEFAULT_KERNEL,
) -> Bool[Array, " n"]:
    """bool [N]: is there any hit with ``0 < t < tmax``? Stops at the first one found."""
    _check_structure(structure)
    get_kernel(kernel)
    origins, directions, tmax = _check_rays(origins, directions, tmax)
    return brute.occluded(structure["triangles"], origins, directions, tmax, kernel=kernel)


def as_numpy(hits: Hits) -> dict[str, np.ndarray]:
    """The hit record as NumPy arrays, keyed t, triangle, u, v."""
    return {k: np.asarray(v) for k, v in hits._asdict().items()}
