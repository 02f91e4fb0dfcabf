"""kd-tree traversal: the plane-tree step of ``jrt.planes`` on an axis-aligned plane
(layout in ``accel.kdtree``)."""

from __future__ import annotations

import functools

import jax.numpy as jnp
from jax import lax

from jrt import planes
from jrt.engine import BOX_MARGIN, Traversal


def traversal(structure) -> Traversal:
    """The engine traversal of a kd-tree built by ``accel.kdtree``."""
    return make(structure.layout_value("leaf_bits"))


def _crossings(ray, rows):
    """The split plane's crossing distances (moved by ±delta), one axis per lane."""
    split = rows[:, 0]
    fields = lax.bitcast_convert_type(rows[:, 1:4], jnp.int32)
    axis = fields[:, 0]
    ox, oy, oz = ray.origin_axes
    ix, iy, iz = ray.inv_direction
    o = jnp.where(axis == 0, ox, jnp.where(axis == 1, oy, oz))
    inv = jnp.where(axis == 0, ix, jnp.where(axis == 1, iy, iz))
    scale = jnp.abs(o)  # the origin's magnitude on the axis (Ray.scale)
    if ray.pad is not None:
        scale = scale + jnp.where(axis == 0, ray.pad[0],
                                  jnp.where(axis == 1, ray.pad[1], ray.pad[2]))
    delta = BOX_MARGIN * (jnp.abs(split) + scale)
    t_a = (split - delta - o) * inv
    t_b = (split + delta - o) * inv
    return t_a, t_b, jnp.signbit(inv), fields[:, 1], fields[:, 2]


@functools.cache
def make(leaf_bits: int) -> Traversal:
    """The kd-tree's :class:`jrt.engine.Traversal` for leaf references of ``leaf_bits``."""
    return planes.make(_crossings, leaf_bits)
