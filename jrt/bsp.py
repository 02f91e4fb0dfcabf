"""BSP-tree traversal: the plane-tree step of ``jrt.planes`` on a general plane
``n . x = c`` (layout in ``accel.bsp``)."""

from __future__ import annotations

import functools

import jax.numpy as jnp
from jax import lax

from jrt import planes
from jrt.engine import BOX_MARGIN, Traversal


def traversal(structure) -> Traversal:
    """The engine traversal of a BSP tree built by ``accel.bsp``."""
    return make(structure.layout_value("leaf_bits"))


def _crossings(ray, rows):
    """The plane's crossing distances (moved by ±delta): dot products per lane."""
    nx, ny, nz, c = rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3]
    children = lax.bitcast_convert_type(rows[:, 4:6], jnp.int32)
    ox, oy, oz = ray.origin_axes
    px, py, pz = nx * ox, ny * oy, nz * oz
    n_o = px + py + pz
    n_d = nx * ray.direction[:, 0] + ny * ray.direction[:, 1] + nz * ray.direction[:, 2]
    sx, sy, sz = (ray.scale(k) for k in range(3))
    delta = BOX_MARGIN * (jnp.abs(c) + jnp.abs(nx) * sx + jnp.abs(ny) * sy + jnp.abs(nz) * sz)
    t_a = (c - delta - n_o) / n_d
    t_b = (c + delta - n_o) / n_d
    return t_a, t_b, jnp.signbit(n_d), children[:, 0], children[:, 1]


@functools.cache
def make(leaf_bits: int) -> Traversal:
    """The BSP tree's :class:`jrt.engine.Traversal` for leaf references of ``leaf_bits``."""
    return planes.make(_crossings, leaf_bits)
