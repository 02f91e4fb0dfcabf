"""Uniform grid traversal: a 3-D DDA with leaps over empty cells (layout in ``accel.grid``).

Amanatides & Woo, "A fast voxel traversal algorithm for ray tracing" (Eurographics 1987):
a lane walks the cells its ray pierces in order, handing each non-empty cell's reference
range to the engine's leaf loop. Stackless: the engine's stack is never pushed nor popped
(``stack_width`` is 1 only because the engine wants one).

**Leaps over empty space** (Cohen & Sheffer, "Proximity clouds: an acceleration technique
for 3D grid traversal", The Visual Computer 1994): the builder stores with every cell its
Chebyshev distance ``d`` (in cells) to the nearest non-empty cell, so the cube of
``2k + 1`` cells a side around it, ``k = max(d - 1, 0)``, is empty, and a step leaves that
cube in one go. ``k = 0`` (a non-empty cell, or an empty one beside one) is the plain DDA
step to the neighbour across the nearest exit plane. On the camel the leaps cut the steps
per ray about 7x (a cell-by-cell walk spends most of its steps in empty cells) and the
trace time 2.5-4x (``accel.build("grid", ..., max_skip=0)`` walks cell by cell).

**State**, one [L] vector per field: the cell index on each axis (ix, iy, iz) and the
distance ``te`` at which the ray entered the cell. A fresh lane (``start``) holds
ix = -1, and its first step clips the ray to the grid box (``jrt.engine.box_interval``:
widened, tnear narrowed, so the entry point lies at or just before the box), takes the
cell holding the entry point, clamped to the grid, and goes on from it in the same step;
a ray that misses the box finishes there. (Doing this in the step rather than in
``start``, which the engine evaluates for every lane on every iteration, halves the
cost of an iteration.) Exit distances are recomputed from the plane positions on every
step, ``t = (lo_a + m * size_a - o_a) * (1 / d_a)``, never accumulated (Amanatides &
Woo's tDelta sums drift by an ulp a cell); the grid's outer faces are the box's, widened
as ``box_interval`` widens them (the last plane ``lo + n * size`` may fall an ulp short of
``hi``, and a ray running along the box's face must not leave early). An axis whose
direction component is +0.0 or -0.0 (1/d = ±inf, and 0 * inf = NaN for an origin on a
face) is never crossed: its exit distance is +inf and its index stays.

**Step**: the current cell is culled (the lane finishes) once the cull bound ``best_t``
(the best hit plus the tie window, or tmax) is at most ``te`` narrowed by BOX_MARGIN.
Otherwise the cell's references go to the leaf loop and the lane moves on: across the
cube's nearest exit plane (at ``tjump``, the least of the three exit distances; x before
y before z on a tie), its other two indices those of the point at ``tjump``, kept within
the cube and never behind the current cell (so every step advances at least one index,
and a walk ends within nx + ny + nz steps). The lane finishes on leaving the grid (or the
point at ``tjump`` lying beyond the grid's widened face it moves towards), or when the
cull bound is already at most ``tjump`` narrowed: the closest hit then lies in a cell
visited so far. A hit found in this cell but lying beyond it (a triangle referenced by
several cells) does not end the walk early: the walk goes on until it has passed the hit
point, so a nearer triangle in a cell in between is still tested.

**Local frame**: the grid row holds coordinates relative to the grid's ``frame`` (a point
of the triangles' box, ``accel.geometry.frame_origin``), and the engine hands every step
the ray origin moved into it (``ray.origin_axes = o - frame``, rounded to float32, and
``ray.scale``, the magnitude its margins use); the triangle kernels still read the
world-coordinate triangles and origin. All the walk's arithmetic below is in the frame.

**Why the hits are brute force's**: the exit distances carry a relative error of a few
float32 ulps, so the walk follows the ray through every cell it pierces, except that where
two crossings (or the point located after a leap) lie within those ulps of a cell face it
may take a neighbour for the cell. The part of the ray it then skips lies within a few
ulps of the ray's travel (and of the origin's local coordinates, the rounding of ``o -
frame`` included: 2^-24 of ``|o - frame|``) of a visited cell, and every cell references
the triangles within CELL_MARGIN = 2^-16 of the grid's local magnitude (its largest
local corner coordinate, at least half its largest extent) of its box (``accel.grid``).
With errors of at most about 8 ulps (2^-21) of the travel, that covers rays whose origin
and hits lie within 2^-16 / 2^-21 = 32 times the grid's local magnitude of the frame (at
least 16 times the grid's largest extent around a point of its box), wherever it sits; the
camera and incoherent ray sets stay within a few scene sizes. Beyond that, a ray grazing
a cell edge far from its origin could in principle skip a triangle's corner in the cell
it misses. (This holds for the kernels whose rounding is relative to ``|v - o|``,
watertight and Möller–Trumbore; the plane-and-barycentric kernel's rounding grows with
the world coordinates, see ``accel.grid``.)
"""

from __future__ import annotations

import functools

import jax.numpy as jnp
from jax import lax

from jrt.engine import BOX_MARGIN, Step, Traversal, as_ray, box_interval
from jrt.fusion import computed_once

_SHRINK = 1.0 - BOX_MARGIN


def _grid_row(g):
    """The grid row: lo, hi, size, inv_size (three scalars each) and n (three int32)."""
    n = lax.bitcast_convert_type(g[12:15], jnp.int32)
    return ([g[0], g[1], g[2]], [g[3], g[4], g[5]], [g[6], g[7], g[8]], [g[9], g[10], g[11]],
            [n[0], n[1], n[2]])


def _entry(ray, lo, hi, inv_size, n):
    """A fresh lane's entry cell (three indices), entry distance, and whether the ray
    meets the grid box at all."""
    tnear, tfar = box_interval(ray, lo, hi)
    inside = tnear <= tfar  # False for NaN too
    t0 = jnp.where(inside, tnear, 0.0)
    index = []
    for axis in range(3):
        p = ray.origin_axes[axis] + t0 * ray.direction[:, axis]  # finite
        cell = jnp.clip(jnp.floor((p - lo[axis]) * inv_size[axis]), 0, n[axis] - 1)
        index.append(cell.astype(jnp.int32))
    return (*index, t0, inside)


def _leap(ray, lo, hi, size, inv_size, n, index, k):
    """The cell after the cube of half-width ``k`` around ``index``: three indices, the
    distance ``tjump`` at which the ray leaves the cube, and whether it leaves the grid."""
    parallel, up, far, bound = [], [], [], []
    for axis in range(3):
        inv, o = ray.inv_direction[axis], ray.origin_axes[axis]
        parallel.append(jnp.abs(inv) == jnp.inf)
        up.append(inv > 0)
        m = jnp.where(up[axis], index[axis] + k + 1, index[axis] - k)
        plane = lo[axis] + m.astype(jnp.float32) * size[axis]
        # The grid's own faces are the box's, widened as box_interval widens them: the
        # last plane lo + n * size may fall an ulp short of hi (a ray running along the
        # box's face must not leave early), and a flat axis has size 0.
        top = hi[axis] + BOX_MARGIN * (jnp.abs(hi[axis]) + ray.scale(axis))
        bottom = lo[axis] - BOX_MARGIN * (jnp.abs(lo[axis]) + ray.scale(axis))
        plane = jnp.where(m >= n[axis], jnp.maximum(plane, top), plane)
        plane = jnp.where(m <= 0, jnp.minimum(plane, bottom), plane)
        bound.append(jnp.where(up[axis], top, bottom))
        far.append(jnp.where(parallel[axis], jnp.inf, (plane - o) * inv))
    tjump = jnp.minimum(jnp.minimum(far[0], far[1]), far[2])
    exit_axis = [(far[0] <= far[1]) & (far[0] <= far[2])]
    exit_axis.append(~exit_axis[0] & (far[1] <= far[2]))
    exit_axis.append(~exit_axis[0] & ~exit_axis[1])
    at = jnp.where(tjump < jnp.inf, tjump, 0.0)
    new, out = [], jnp.zeros(k.shape, bool)
    for axis in range(3):
        i = index[axis]
        across = jnp.where(up[axis], i + k + 1, i - k - 1)
        # The other axes: the point at tjump, kept within the cube and not behind.
        p = ray.origin_axes[axis] + at * ray.direction[:, axis]
        located = jnp.floor((p - lo[axis]) * inv_size[axis])
        # Past the (widened) face of the grid that it moves towards: the ray left the grid
        # inside the cube.
        beyond = jnp.where(up[axis], p > bound[axis], p < bound[axis])
        low = jnp.where(up[axis], i, jnp.maximum(i - k, 0)).astype(jnp.float32)
        high = jnp.where(up[axis], jnp.minimum(i + k, n[axis] - 1), i).astype(jnp.float32)
        located = jnp.clip(located, low, high).astype(jnp.int32)
        located = jnp.where(parallel[axis], i, located)
        j = jnp.where(exit_axis[axis], across, located)
        out |= jnp.where(exit_axis[axis], (j < 0) | (j >= n[axis]),
                         beyond & ~parallel[axis] & (k > 0))
        new.append(j)
    return (*new, tjump, out)


def _start(arrays, ray):
    fresh = jnp.full(ray.tmax.shape, -1, jnp.int32)
    return fresh, fresh, fresh, jnp.zeros(ray.tmax.shape, jnp.float32)


def _lane_ray(origin, direction, frame, pad):
    """The lane's :class:`jrt.engine.Ray` rebuilt from its world origin and direction, the
    grid's ``frame`` and the margin ``pad`` (``jrt.engine.as_ray``): inside a conditional,
    two [L, 3] operands rather than ten (1/d and ``o - frame`` are recomputed, to the same
    bits: IEEE arithmetic is correctly rounded)."""
    return as_ray(origin, direction, None, frame, pad)


def _entry_of(row, origin, direction, frame, pad):
    ray = _lane_ray(origin, direction, frame, pad)
    lo, hi, _, inv_size, n = _grid_row(row)
    return _entry(ray, lo, hi, inv_size, n)


def _leap_of(row, origin, direction, frame, pad, index, k):
    ray = _lane_ray(origin, direction, frame, pad)
    lo, hi, size, inv_size, n = _grid_row(row)
    return _leap(ray, lo, hi, size, inv_size, n, index, k)


def _step(arrays, ray, state, best_t, top, has_top):
    row = arrays["grid"]
    n = lax.bitcast_convert_type(row[12:15], jnp.int32)
    ix, iy, iz, te = state
    fresh = ix < 0
    # A fresh lane's entry (computed once, skipped when no lane is fresh).
    frame = arrays["frame"]
    *entry, inside = computed_once(jnp.any(fresh), _entry_of, row, ray.origin, ray.direction,
                                   frame, ray.pad)
    ix, iy, iz, te = (jnp.where(fresh, a, b) for a, b in zip(entry, (ix, iy, iz, te),
                                                              strict=True))
    live = (inside | ~fresh) & (best_t > jnp.maximum(te, 0.0) * _SHRINK)
    cell = ix + n[0] * (iy + n[1] * iz)
    starts = arrays["cell_start"]
    first = starts[cell]
    count = starts[cell + 1] - first
    k = jnp.maximum(arrays["skip"][cell].astype(jnp.int32) - 1, 0)
    jx, jy, jz, tjump, out = computed_once(jnp.any(live), _leap_of, row, ray.origin,
                                           ray.direction, frame, ray.pad, (ix, iy, iz), k)
    # tjump = inf (a ray with no direction) makes the bound test true.
    finished = ~live | out | (best_t <= jnp.maximum(tjump, 0.0) * _SHRINK)
    zeros = jnp.zeros(ix.shape, bool)
    return Step(state=(jx, jy, jz, tjump), leaf_first=first,
                leaf_count=jnp.where(live, count, 0), push=zeros,
                entry=jnp.zeros((ix.shape[0], 1), jnp.int32), pop=zeros, finished=finished)


def traversal(structure) -> Traversal:
    """The engine traversal of a grid built by ``accel.grid``."""
    return make()


@functools.cache
def make() -> Traversal:
    """The grid's :class:`jrt.engine.Traversal` (one for every grid: no static layout)."""
    return Traversal(start=_start, step=_step, stack_width=1)
