"""The traversal engine every acceleration structure runs on.

The engine owns what all structures share: the lanes, the stack, the leaf loop, the hit
record, the counters and the status flags. A structure contributes a :class:`Traversal`:
how a lane starts (``start``) and one step from node to node (``step``), which may name a
leaf (a range of triangle rows to test), push one stack entry or pop one.

**Persistent lanes with refill** (Aila & Laine, "Understanding the efficiency of ray
traversal on GPUs", HPG 2009). A batched per-ray loop runs until its slowest ray ends;
here a fixed set of ``lanes`` (a few thousand) each hold one ray, and every iteration of
one ``lax.while_loop`` advances every lane by one triangle test (if its current leaf has
rows left) and one traversal step. A lane whose leaf still has rows left steps as well,
unless the step names another leaf (a lane holds one leaf at a time): the descent to the
next leaf overlaps the tests of this one, culling with the best hit known so far (on the
camel's incoherent rays 1.7 tests a ray in 1.0 leaves; 1.05x on 1M-ray calls, camera rays
unchanged). A lane whose ray is finished writes the hit to the output and takes the next
ray, so lanes stay busy until the rays run out.
The lanes take rays from a queue of those that can hit at all: a ray that misses the box
of all the triangles (widened as every box test is) is a miss without a step. On the
camel's camera rays that spared half the rays' root step (steps per ray 3.3 to 2.8 at
width 4). A structure may decide this itself, in a pass over all the rays before the
loop (:attr:`Traversal.entry`): the BVH takes its root's step there, vectorised with no
gather, so a ray that enters none of the root's children never takes a lane and one
that enters exactly one starts in it (camel, width 4: steps per ray 2.86 to 2.49 on
camera rays, 8.29 to 7.70 on incoherent rays; 1M-ray calls 1.09x and 1.05-1.07x).

**The stack** is [lanes, stack_size + max_push - 1, width] int32 (a structure chooses
what an entry holds; floats travel as their bit pattern; a step pushes up to its
traversal's ``max_push`` entries, a wide BVH all the children it enters but the nearest).
Each iteration writes the step's ``max_push`` entries from the stack pointer
unconditionally (slots above the top are free, so a lane that pushes fewer writes garbage
nobody reads) and then reads the new top: one scatter and one gather, no copy of the
stack. A push past ``stack_size`` sets the overflow flag and ends the loop (the answers
are wrong from then on), which leaves jit with the hits; the public functions raise
:class:`StackOverflowError` (never a silent miss).

**Termination** is guaranteed, whatever the arrays hold: the loop also stops after an
iteration budget that a valid structure cannot reach (see :func:`iteration_budget`), and
then flags its unfinished rays; the public functions raise :class:`TraversalError`. A
structure whose arrays contradict its kind (a cycle, a leaf range past the references)
fails loudly instead of spinning forever.

**Counters** (steps, triangle tests, leaves per ray) are a static option: without them
the compiled loop carries none. A ray the loop left unanswered (a stack overflow, the
budget) counts the work done on it so far.

**Tie rule** (shared with brute force, ``jrt.hits.prefer``): the smallest ``t``; among
hits tied within 2^-20 of ``t``, the lowest face index. Every leaf row is tested with the
same kernel as brute force, and the winner's t, u, v are evaluated once after the loop
(``jrt.hits.winner_hits``), so a structure whose box tests are conservative returns
brute force's hits bit for bit.

**Devices**: on XLA:CPU a while loop runs on one thread, so the rays are split over the
host's CPU devices (``jrt`` asks XLA for one per core, see ``jrt._xla``) with
``shard_map``: ray i goes to device i mod k, and each device packs and runs its own share.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.sharding import Mesh, PartitionSpec

from jrt.fusion import computed_once
from jrt.hits import Hits, gather_triangles, prefer, tie_window, winner_hits
from jrt.kernels import get_kernel
from jrt.programs import bounded_jit

#: Persistent lanes per device, by backend. CPU: a few hundred, with every loop compiled
#: as one function (``jrt._xla``'s small-loop threshold): 1M camel rays a set on 2
#: devices, paired rounds against 2048 lanes, gave 1.08-1.14x (camera rays) and
#: 1.11-1.16x (incoherent rays) from 384 to 768 lanes, and less at 256 and from 1024 up.
#: (Run as a sequence of thunks, the loop paid a fixed cost per operation and iteration,
#: and 2048 lanes were best.) GPU: tens of thousands fill the device (an H100 measured
#: 32k-64k best, 0.34-0.35x Embree's 16 threads on camera rays at 64k against 0.17x at
#: 1M and far less at 2048).
DEFAULT_LANES = {"cpu": 512, "gpu": 65536}
FALLBACK_LANES = 2048

DEFAULT_STACK_SIZE = 64
_NO_RAY = np.iinfo(np.int32).max
#: What a :attr:`Traversal.entry` gives a ray that cannot hit (no start may take it).
ENTRY_MISS = int(np.iinfo(np.int32).min)


def default_lanes(devices=None) -> int:
    """The default lane count for ``devices`` (default: the default backend's)."""
    platform = (devices[0] if devices else jax.local_devices()[0]).platform
    return DEFAULT_LANES.get("gpu" if platform in ("cuda", "rocm", "gpu") else platform,
                             FALLBACK_LANES)


class TraversalError(RuntimeError):
    """A traversal could not answer every ray correctly (see the subclasses)."""


class StackOverflowError(TraversalError):
    """A lane pushed onto a full traversal stack; its ray's answer would be wrong."""


#: Bits of the status word the engine returns with the hits.
STATUS_STACK_OVERFLOW = 1
STATUS_UNFINISHED = 2
#: Some ray has a NaN or infinite origin or direction, a direction whose length is out of
#: :data:`DIRECTION_LENGTHS` (zero, say) or a NaN tmax (:func:`ray_problems`): the public
#: functions then name the first one and raise.
STATUS_BAD_RAYS = 4

#: The lengths a ray's direction may have, [1e-6, 1e6]; ``t`` (and ``tmax``) are in units
#: of that length, so a unit direction measures distance and ``d = p1 - p0`` with
#: ``tmax = 1`` is the segment from p0 to p1. Every test is invariant under the direction's
#: scale: the kernels are affine in it (a power-of-two scale gives the unit direction's t
#: divided by it, bit for bit, and the same u, v), and the engine's margins are relative
#: (boxes by the magnitudes of corners and origin, intervals and ties by t itself). The
#: bounds keep ``t`` and the kernels' products inside float32's normal range for scenes
#: from 1e-6 to 1e7 units (XLA:CPU flushes subnormals to zero: a direction of length 1e30
#: would turn a hit at t = 1e-10 into t = 0, a miss); ``tests/test_api.py`` checks every
#: structure with lengths 2^-19 to 2^19 against brute force with unit directions.
DIRECTION_LENGTHS = (1e-6, 1e6)
DIRECTION_LENGTHS_TEXT = "a length within [1e-06, 1e+06] (t is in units of that length)"


def direction_length_squared(xp, d):
    """|d|^2 [n], written out (the same expression in NumPy and in the engine)."""
    return d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]


def ray_problems(xp, o, d, t):
    """The rays' validity rules, (name, bad [n], what is allowed) each, in NumPy or
    jax.numpy: the engine folds them into its status word (one pass over the rays it
    reads anyway), and ``jrt.trace`` and ``jrt.rays_io`` name the first bad ray from them.
    A direction's length is checked only where it is finite (its square, in the rays'
    float32)."""
    finite_d = xp.isfinite(d).all(axis=1)
    lo, hi = DIRECTION_LENGTHS
    length2 = direction_length_squared(xp, d)
    return (("origins", ~xp.isfinite(o).all(axis=1), "finite"),
            ("directions", ~finite_d, "finite"),
            ("directions", finite_d & ~((length2 >= lo * lo) & (length2 <= hi * hi)),
             DIRECTION_LENGTHS_TEXT),
            ("tmax", xp.isnan(t), "a number (inf for no limit)"))


def describe_bad_ray(o, d, t) -> str | None:
    """The first rule of :func:`ray_problems` that some ray breaks, in words (NumPy
    arrays; None if every ray is valid): the ray's index and value, the length of a
    direction refused for its length, how many rays break the rule, what is allowed."""
    o, d, t = (np.asarray(a, np.float32) for a in (o, d, t))
    with np.errstate(over="ignore", under="ignore", invalid="ignore"):
        problems = ray_problems(np, o, d, t)
    for name, bad, allowed in problems:
        if bad.any():
            first = int(np.flatnonzero(bad)[0])
            value = (o if name == "origins" else d if name == "directions" else t)[first]
            length = ""
            if allowed == DIRECTION_LENGTHS_TEXT:
                length = f"length {np.linalg.norm(d[first].astype(np.float64)):.6g}; "
            return (f"{name} of ray {first} is {np.asarray(value).tolist()} ({length}"
                    f"{int(bad.sum())} such rays of {len(bad)}); allowed: {allowed}")
    return None


def pad_rays(origins, directions, tmax, size: int, xp=jnp):
    """The rays followed by ``size - n`` padding rays, which can hit nothing: origin 0,
    direction +z, tmax -inf (no ``0 < t < tmax``; the engine's queue and a BVH's entry
    pass answer them without a step, brute force skips a chunk of them). Valid rays for
    :func:`ray_problems`, so they never raise. ``xp``: jax.numpy or NumPy."""
    pad = size - origins.shape[0]
    if pad <= 0:
        return origins, directions, tmax
    return (xp.concatenate([origins, xp.zeros((pad, 3), origins.dtype)]),
            xp.concatenate([directions, xp.tile(
                xp.asarray([[0.0, 0.0, 1.0]], directions.dtype), (pad, 1))]),
            xp.concatenate([tmax, xp.full((pad,), -np.inf, tmax.dtype)]))


def _bad_rays_status(o, d, t):
    """:data:`STATUS_BAD_RAYS` if any ray breaks :func:`ray_problems`, else 0 (int32)."""
    bad = jnp.any(jnp.stack([b.any() for _, b, _ in ray_problems(jnp, o, d, t)]))
    return jnp.where(bad, jnp.int32(STATUS_BAD_RAYS), jnp.int32(0))


def iteration_budget(arrays, n: int, lanes: int) -> int:
    """Loop iterations after which a traversal is certainly broken (int32-safe).

    In a valid structure a ray steps through each node or cell at most once and tests
    each of its leaf rows once per leaf, so a ray needs at most ``2 W + 2`` iterations,
    ``W`` the total number of rows of the structure's arrays (nodes, cells, references,
    triangles). The lanes take rays greedily, so the loop ends within
    ``(n / lanes + 1)`` times that (Graham's list-scheduling bound); the budget is four
    times this, clipped to int32.
    """
    rows = sum(int(np.shape(a)[0]) for a in jax.tree.leaves(arrays) if np.ndim(a) > 0)
    per_ray = 2 * rows + 2
    return int(min(4 * (-(-n // lanes) + 1) * per_ray, np.iinfo(np.int32).max))


class Ray(NamedTuple):
    """One lane's ray, with what every step reuses.

    The triangle kernels read ``origin`` in world coordinates (the stored triangles are
    world coordinates: the hits are brute force's). The box, cell and plane tests read
    ``origin_axes``, the origin in the structure's local frame (``o - frame``, see
    ``accel.geometry.frame_origin``; the world origin for a structure without one), and
    widen their tests by :data:`BOX_MARGIN` of :meth:`scale`, the magnitude to which
    the rounding of that origin and of the kernel's hit point is relative.
    """

    origin: jax.Array  # [L, 3], world coordinates, for the triangle kernels
    direction: jax.Array  # [L, 3]
    origin_axes: tuple  # three [L], the origin by axis in the structure's frame
    inv_direction: tuple  # three [L], 1/d by axis (±inf for a zero component)
    tmax: jax.Array  # [L]
    pad: Any = None  # None, or float32 [3] added to |origin_axes| (see margin_pad)

    def scale(self, axis: int):
        """[L]: the origin's magnitude on ``axis`` for the margins, ``|origin_axes[axis]|``
        (+ ``pad[axis]``). Computed where it is used: as a field of [L] vectors it was one
        more array for XLA to materialise at every conditional the ray enters."""
        size = jnp.abs(self.origin_axes[axis])
        return size if self.pad is None else size + self.pad[axis]


class Step(NamedTuple):
    """What one traversal step of a lane decides.

    Attributes:
        state: the lane's traversal state after the step (a pytree of [L] arrays).
        leaf_first, leaf_count: int32 [L], rows of the leaf to test next (count 0: none).
        push: bool [L], push ``entry`` onto the stack; or, for a traversal whose
            ``max_push`` P is above 1, int32 [L], how many entries of ``entry`` to push.
        entry: int32 [L, width], the entry to push; with P above 1, int32
            [L, P, width], entry j going to the j-th free slot, so the last one pushed
            (index ``push - 1``) is the next one popped.
        pop: bool [L], the step consumed the top entry (given to it as ``top``).
        finished: bool [L], the lane's traversal is over (no node left to visit).
    """

    state: Any
    leaf_first: jax.Array
    leaf_count: jax.Array
    push: jax.Array
    entry: jax.Array
    pop: jax.Array
    finished: jax.Array


class Traversal(NamedTuple):
    """A structure's part of the traversal: a pair of pure functions (as jax-md's pairs).

    ``start(arrays, ray) -> state`` gives a fresh lane's state;
    ``step(arrays, ray, state, best_t, top, has_top) -> Step`` advances a lane by one node,
    culling what lies beyond ``best_t``; ``top`` [L, width] is the stack's top entry and
    ``has_top`` whether the stack holds any. ``stack_width`` is the entry's int32 count;
    ``max_push`` how many entries one step may push (a wide BVH pushes all the children it
    enters but the nearest in one step).

    ``entry(arrays, ray, best_t) -> first``, optional, is evaluated once for every ray
    before the loop, vectorised over all of them (``ray`` holds [N] vectors): ``first``
    int32 [N] is :data:`ENTRY_MISS` for a ray that certainly hits nothing (it never takes
    a lane), and is otherwise handed to ``start(arrays, ray, first)`` when a lane takes
    the ray. A BVH tests its root's children there: the root's row is the same for every
    ray, so that first step costs no gather, and a ray that enters exactly one of them
    starts in it. Without ``entry``, the engine's own test against the box of all the
    triangles decides which rays can hit, and ``start`` takes no ``first``.
    """

    start: Callable[..., Any]
    step: Callable[..., Step]
    stack_width: int
    max_push: int = 1
    entry: Callable[..., Any] | None = None


class Counters(NamedTuple):
    """Per-ray work, int32 [N] each: traversal steps, triangle tests, leaves visited.

    A ray that misses the box of all the triangles is answered before any lane takes it
    and counts no work at all (the engine's queue)."""

    steps: jax.Array
    tests: jax.Array
    leaves: jax.Array


def _pack_rays(origins, directions, tmax):
    """Rays packed as rows [n, 7]: origin, direction, tmax.

    The lanes gather a row on every iteration, and its width is what that costs: the
    reciprocal direction stored in the row as well (rows of 10) made 1M-ray calls on the
    camel 2-3.5 % slower than taking it again after each gather (three divisions, vectorised
    over the lanes; see :func:`_as_ray`).
    """
    return jnp.concatenate([origins, directions, tmax[:, None]], axis=1)


def _lane_rays(rays, ids, n, frame=None, pad=None):
    """The lanes' rays, gathered from the packed rows by ray id (ids >= n: a dummy ray).

    Rays are gathered on every iteration rather than carried in the loop state: a row
    gather costs less than the selects that refilling ten carried fields would.
    """
    return _as_ray(rays[jnp.minimum(ids, n - 1)], frame, pad)


#: Kernels whose rounding grows with the magnitude of the coordinates themselves, not
#: only with the distance from the ray's origin: the lecture's plane test forms
#: ``d - N.O`` and the point ``O + tD`` in world coordinates. Watertight and
#: Möller–Trumbore subtract the origin first (``v - O``), so their errors do not depend
#: on where the scene sits.
POSITION_DEPENDENT_KERNELS = frozenset({"plane_barycentric"})


def margin_pad(frame, kernel: str):
    """float32 [3] added to ``|o - frame|`` in every margin, or None.

    For a kernel of :data:`POSITION_DEPENDENT_KERNELS`, ``2 |frame|``: then the margins
    in the local frame are at least those in world coordinates (``|c| + |o| <= |c -
    frame| + |o - frame| + 2 |frame|``), as wide as that kernel's rounding there. For the
    others (and a structure without a frame), None: the margins follow the scene's
    extent and the ray's distance from it, wherever the scene sits.
    """
    if frame is None or kernel not in POSITION_DEPENDENT_KERNELS:
        return None
    return 2.0 * jnp.abs(frame)


def as_ray(origin, direction, tmax, frame=None, pad=None) -> Ray:
    """A :class:`Ray` from its parts: ``origin``, ``direction`` [L, 3], ``tmax`` [L] (or
    None), the structure's ``frame`` [3] (or None) and its :func:`margin_pad` (or None).

    ``1/d`` is IEEE division, so every evaluation gives the same bits; a zero component
    gives ±inf, its sign kept from ±0.0 (the slab tests handle it). ``o - frame`` is
    rounded to float32: its error, 2^-24 of ``|o - frame|``, is far inside the margin
    (2^-16 of the same magnitude).
    """
    # Box tests run on [L] vectors, one per axis: XLA:CPU vectorises elementwise code
    # along the lanes only when no small trailing axis (of 3) is broadcast.
    axes = tuple(origin[:, k] for k in range(3))
    if frame is not None:
        axes = tuple(axes[k] - frame[k] for k in range(3))
    return Ray(origin, direction, axes, tuple(1.0 / direction[:, k] for k in range(3)),
               tmax, pad)


def _as_ray(r, frame=None, pad=None):
    """A :class:`Ray` from packed rows [L, 7] (see :func:`_pack_rays`)."""
    return as_ray(r[:, 0:3], r[:, 3:6], r[:, 6], frame, pad)


def _select(mask, new, old):
    return jax.tree.map(
        lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - 1)), a, b), new, old)


def _run_lanes(traversal: Traversal, arrays, rays, *, kernel, any_hit, lanes, stack_size,
               counters, references, rows_out=False, capacity=0):
    """All rays of ``rays`` [n, 7] (see :func:`_pack_rays`) through one device's lanes.

    One iteration: refill the lanes that finished (write their winner, take the next
    rays), gather every lane's ray, start the refilled lanes, one traversal step (for a
    lane with leaf rows left, only if the step names no leaf), one triangle test for
    lanes with leaf rows left. The loop
    carries as few arrays as it can: XLA:CPU runs each elementwise update of a carried
    array as its own pass over the lanes, and those passes, not the arithmetic, bound
    the iteration.

    With ``capacity`` K > 0 (all hits, :func:`jrt.all_hits`) nothing is culled by a hit:
    every lane keeps a list of the distinct rows it hit (the K nearest, by the loop's
    ``t``) and how many distinct rows it hit, and the result is ``(rows [n, K], count
    [n])`` instead of the hit record. A row met again (a kd-tree, grid, octree or BSP tree
    references a triangle from every leaf it overlaps) is recognised while the list holds
    it; once a ray has more than K hits an evicted row met again is counted again, so the
    count is then an upper bound (the caller retraces with room for it).
    """
    fn = get_kernel(kernel)
    n = rays.shape[0]
    lanes = max(1, min(lanes, n))
    width = traversal.stack_width
    max_push = traversal.max_push
    triangles = arrays["triangles"]
    triangle_ids = arrays["triangle_ids"]
    lane_index = jnp.arange(lanes, dtype=jnp.int32)
    frame = arrays.get("frame")
    pad = margin_pad(frame, kernel)

    def fresh():
        """The per-ray part of a lane's state, for a lane that takes a new ray."""
        lane = {
            "trav_done": jnp.zeros(lanes, bool),
            "cursor": jnp.zeros(lanes, jnp.int32),
            "end": jnp.zeros(lanes, jnp.int32),
            "sp": jnp.zeros(lanes, jnp.int32),
        }
        if capacity:  # the hit list in place of the best hit (which nothing reads then)
            lane["list_t"] = jnp.full((lanes, capacity), jnp.inf, jnp.float32)
            lane["list_row"] = jnp.full((lanes, capacity), -1, jnp.int32)
            lane["hit_count"] = jnp.zeros(lanes, jnp.int32)
        else:
            # best_t is meaningful only once best_id >= 0; until then the ray's tmax bounds.
            lane["best_t"] = jnp.full(lanes, jnp.inf, jnp.float32)
            lane["best_id"] = jnp.full(lanes, -1, jnp.int32)
            lane["best_row"] = jnp.full(lanes, -1, jnp.int32)
        if counters:
            lane["count"] = jnp.zeros((lanes, 3), jnp.int32)
        return lane

    # The queue: rays that can hit, in order. A ray that misses the box of all the
    # triangles, or ends before it, cannot hit (the box is widened as every box test is,
    # BOX_MARGIN), so it is answered here, a miss, without a step; the lanes take only
    # the others. Camera rays around a mesh mostly miss it (52 % of the camel's).
    #
    # The queue is a stream compaction: each ray's rank among those that can hit (an
    # inclusive prefix sum) and one scatter of the ray ids to their ranks. jnp.nonzero
    # compiled to a slower scatter-add loop and a prefix sum that recomputed the box test;
    # here the test is materialised once (computed_once, both branches computing it, so
    # any run-time predicate will do; a constant one would be folded with the conditional)
    # for the sum and the scatter. The conditional takes the packed rows and slices them
    # itself: given the sliced origins and reciprocal directions, XLA materialised those
    # as seven arrays first (the queue's pass over 1M camel camera rays on 2 devices,
    # loop skipped: 24.5 against 20.3 ms).
    #
    # A traversal with an ``entry`` decides it itself (the BVH from its root's children,
    # which also gives each ray the node it starts in), culling as its first step would.
    corners = triangles.reshape(-1, 3)

    def can_hit(rays):
        # slices, not a gather of every row (10 ms on 500k rays)
        every = _as_ray(rays, frame, pad)
        # A ray with tmax <= 0 has no 0 < t < tmax: a miss, whatever the box says (the
        # renderer's padding and its unneeded shadow rays; from inside the box they were
        # queued and stepped: 8 ms for 32k such shadow rays on the camel).
        empty = every.tmax <= 0
        if traversal.entry is not None:
            entry = traversal.entry(arrays, every, every.tmax + tie_window(every.tmax))
            return jnp.where(empty, jnp.int32(ENTRY_MISS), entry)
        lo, hi = jnp.min(corners, 0), jnp.max(corners, 0)
        if frame is not None:  # rounded by 2^-24 of |corner - frame|: inside the margin
            lo, hi = lo - frame, hi - frame
        near, far = box_interval(every, tuple(lo), tuple(hi))
        return jnp.where((near <= far) & (near <= every.tmax) & ~empty, jnp.int32(0),
                         jnp.int32(ENTRY_MISS))

    # One int32 output, the miss folded in: as two outputs (a flag and the start), XLA:CPU
    # computed the BVH root's box tests once for each (6 against 1.5 ms a 1M-ray call
    # more than the box test alone).
    first_of_ray = computed_once(rays[0, 6] > 0, can_hit, rays, always=True)
    hit_box = (first_of_ray != ENTRY_MISS).astype(jnp.int32)
    rank = jnp.cumsum(hit_box, dtype=jnp.int32) - 1
    queued = rank[-1] + 1
    queue = jnp.full(n, n, jnp.int32).at[jnp.where(hit_box > 0, rank, n)].set(
        jnp.arange(n, dtype=jnp.int32), mode="drop", unique_indices=True)

    def dequeue(position):
        """The ray at ``position`` in the queue (``_NO_RAY`` past its end)."""
        return jnp.where(position < queued, queue[jnp.minimum(position, n - 1)], _NO_RAY)

    def start(ray, ids):
        """Fresh traversal states for lanes holding the rays ``ids`` (their ``ray``)."""
        if traversal.entry is None:
            return traversal.start(arrays, ray)
        return traversal.start(arrays, ray, first_of_ray[jnp.minimum(ids, n - 1)])

    first_rays = dequeue(lane_index)
    state = {
        **fresh(),
        "ray_id": first_rays,
        "renewed": jnp.ones(lanes, bool),
        "trav": start(_lane_rays(rays, first_rays, n, frame, pad), first_rays),
        # max_push - 1 spare slots, so that a push of max_push entries from the top slot
        # stays inside the array (its overflow is flagged, not written out of bounds).
        "stack": jnp.zeros((lanes, stack_size + max_push - 1, width), jnp.int32),
        "top": jnp.zeros((lanes, width), jnp.int32),
        "next_ray": jnp.int32(lanes),
        "overflow": jnp.zeros((), bool),
        "iteration": jnp.int32(0),
        # The winning row of every ray (-1: a miss, or not traced: outside the box), and
        # the lanes' spare slots.
        "out": jnp.full((n + lanes, capacity) if capacity else (n + lanes,), -1, jnp.int32),
    }
    if capacity:
        state["out_hits"] = jnp.zeros(n + lanes, jnp.int32)
    if counters:
        state["out_count"] = jnp.zeros((n + lanes, 3), jnp.int32)

    def finished(s):
        active = s["ray_id"] < n
        done = active & s["trav_done"] & (s["cursor"] >= s["end"])
        if any_hit:
            done |= active & (s["best_id"] >= 0)
        return done

    def refill(s):
        """Finished lanes write their winner and take the next rays, in order."""
        done = finished(s)
        # Lanes with nothing to write aim at their own slot past the end (unique indices).
        target = jnp.where(done, s["ray_id"], n + lane_index)
        new = dict(s, out=s["out"].at[target].set(
            s["list_row"] if capacity else s["best_row"], unique_indices=True))
        if capacity:
            new["out_hits"] = s["out_hits"].at[target].set(s["hit_count"], unique_indices=True)
        if counters:
            new["out_count"] = s["out_count"].at[target].set(s["count"], unique_indices=True)
        rank = jnp.cumsum(done, dtype=jnp.int32) - 1
        new["ray_id"] = jnp.where(done, dequeue(s["next_ray"] + rank), s["ray_id"])
        new["next_ray"] = s["next_ray"] + jnp.sum(done, dtype=jnp.int32)
        new.update(_select(done, fresh(), {k: s[k] for k in fresh()}))
        new["renewed"] = done
        return new

    def best_bound(s, ray):
        """The distance a hit must beat: the best hit's, or the ray's tmax before one
        (always the ray's tmax when every hit is wanted)."""
        if capacity:
            return ray.tmax
        return jnp.where(s["best_id"] >= 0, s["best_t"], ray.tmax)

    def step(s, ray):
        """One traversal step for every lane (one with leaf rows left only if the step
        names no leaf), then the new stack top."""
        stepping = (s["ray_id"] < n) & ~s["trav_done"]
        if any_hit:
            stepping &= s["best_id"] < 0
        sp = s["sp"]
        has_top = sp > 0
        bound = best_bound(s, ray)
        # Cull only beyond the tie window: a tied hit with a lower face index may lie there.
        st = traversal.step(arrays, ray, s["trav"], bound + tie_window(bound), s["top"],
                            has_top)
        # A lane whose leaf still has rows to test steps as well, unless its step names
        # a leaf (a lane holds one leaf at a time): the tests and the descent overlap.
        stepping &= (s["cursor"] >= s["end"]) | (st.leaf_count == 0)
        new_leaf = stepping & (st.leaf_count > 0)
        pushed = jnp.where(stepping, st.push.astype(jnp.int32), 0)
        pop = stepping & st.pop
        new = dict(
            s,
            trav=_select(stepping, st.state, s["trav"]),
            trav_done=s["trav_done"] | (stepping & (st.finished | (st.pop & ~has_top))),
            cursor=jnp.where(new_leaf, st.leaf_first, s["cursor"]),
            end=jnp.where(new_leaf, st.leaf_first + st.leaf_count, s["end"]),
            overflow=s["overflow"] | jnp.any(sp + pushed > stack_size),
            sp=jnp.clip(sp + pushed - pop.astype(jnp.int32), 0, stack_size))
        # The pushes go to the slots from the old pointer (free unless the step pushed),
        # then the new top is read: writing before reading spares XLA a copy of the stack.
        # One window of max_push entries per lane (a [L, width] entry is a window of one).
        entries = st.entry.reshape(lanes, max_push, width)
        new["stack"] = jax.vmap(lambda stack, entry, at: lax.dynamic_update_slice(
            stack, entry, (at, jnp.int32(0))))(s["stack"], entries, jnp.minimum(sp, stack_size - 1))
        # The top's slot is materialised first (computed_once): fused into the gather, the
        # whole push/pop logic was recomputed for every gathered int (28 against 10 µs an
        # iteration at 2048 lanes, jax.profiler).
        top_slot = computed_once(s["iteration"] >= 0, lambda sp: jnp.maximum(sp - 1, 0),
                                 new["sp"])
        new["top"] = new["stack"][lane_index, top_slot]
        if counters:
            new["count"] = s["count"] + jnp.stack(
                [stepping, jnp.zeros_like(stepping), new_leaf], axis=1).astype(jnp.int32)
        return new

    def test(s, ray):
        """The leaf loop: one triangle test for every lane that has rows left."""
        testing = (s["ray_id"] < n) & (s["cursor"] < s["end"])
        slot = jnp.where(testing, s["cursor"], 0)
        row = references[slot] if references is not None else slot
        tri = gather_triangles(triangles, row)
        face = triangle_ids[row]
        t = computed_once(jnp.any(testing),
                          lambda o, d, tri: fn(o, d, tri[:, 0], tri[:, 1], tri[:, 2])[0],
                          ray.origin, ray.direction, tri)
        if capacity:
            new = _collect(s, t, row, testing & (t < ray.tmax), capacity)
        else:
            best_t, best_id = s["best_t"], s["best_id"]
            better = testing & (t < ray.tmax) & prefer(t, face, best_t, best_id)
            new = dict(s, best_t=jnp.where(better, t, best_t),
                       best_id=jnp.where(better, face, best_id),
                       best_row=jnp.where(better, row, s["best_row"]))
        new["cursor"] = s["cursor"] + testing.astype(jnp.int32)
        if counters:
            zero = jnp.zeros_like(testing)
            new["count"] = s["count"] + jnp.stack([zero, testing, zero], 1).astype(jnp.int32)
        return new

    def body(s):
        s = refill(s)
        ray = _lane_rays(rays, s["ray_id"], n, frame, pad)
        s["trav"] = _select(s["renewed"], start(ray, s["ray_id"]), s["trav"])
        # Lanes step far more often than they test (5-15 steps per ray on the camel
        # against 0.5-1.6 tests), but a phase costs all lanes whichever lanes use it.
        s = test(step(s, ray), ray)
        s["iteration"] = s["iteration"] + 1
        return s

    budget = iteration_budget(arrays, n, lanes)
    # An overflow ends the loop at once: the answers are wrong whatever follows, and a BVH
    # lane whose pushes fall off its stack pops the same entry again and again, to the
    # budget (25 s against 2.8 for 128 rays of the 19k camel and a stack of 1).
    s = lax.while_loop(lambda s: jnp.any(s["ray_id"] < n) & (s["iteration"] < budget)
                       & ~s["overflow"], body, state)
    rows = s["out"][:n]
    if capacity:
        hits = (rows, s["out_hits"][:n])
    else:
        hits = winner_hits(fn, rays, triangles, triangle_ids, rows)
    if rows_out and not capacity:  # the winners' rows too (jrt.trace's derivative rule)
        hits = (hits, rows)
    count = None
    if counters:  # a lane the loop left in flight (an overflow, the budget): its work so far
        flying = jnp.where(s["ray_id"] < n, s["ray_id"], n + lane_index)
        count = s["out_count"].at[flying].set(s["count"], unique_indices=True)[:n]
    # The rays' validity (ray_problems), from the packed rows: one place for one device
    # and for each device's share, in the program that reads the rays anyway.
    zero = jnp.int32(0)
    # (Unfinished: the budget ended the loop; rays an overflow left unanswered are that
    # overflow's, the first bit.)
    status = (jnp.where(s["overflow"], jnp.int32(STATUS_STACK_OVERFLOW), zero)
              | jnp.where(jnp.any(s["ray_id"] < n) & ~s["overflow"],
                          jnp.int32(STATUS_UNFINISHED), zero)
              | _bad_rays_status(rays[:, 0:3], rays[:, 3:6], rays[:, 6]))
    return hits, count, status


def _collect(s, t, row, hit, capacity):
    """The all-hits leaf test's update of the lanes ``s``: a ``hit`` [L] on ``row`` at
    ``t`` joins the lane's list unless the list holds that row already; into a free slot,
    or, once the list is full, in place of its farthest entry if nearer (the list keeps
    the K nearest). The lane's count grows by every hit on a row not in the list."""
    new_hit = hit & ~jnp.any(s["list_row"] == row[:, None], axis=1)
    count = s["hit_count"]
    full = count >= capacity
    far = jnp.argmax(s["list_t"], axis=1).astype(jnp.int32)
    far_t = jnp.max(s["list_t"], axis=1)
    slot = jnp.where(full, far, count)
    write = new_hit & (~full | (t < far_t))
    at = write[:, None] & (lax.broadcasted_iota(jnp.int32, s["list_row"].shape, 1)
                           == slot[:, None])
    return dict(s, list_t=jnp.where(at, t[:, None], s["list_t"]),
                list_row=jnp.where(at, row[:, None], s["list_row"]),
                hit_count=count + new_hit.astype(jnp.int32))


def cpu_devices() -> list:
    """The devices the rays are split over: all local devices of the default backend."""
    return list(jax.local_devices())


def compiled_programs() -> int:
    """How many traversal programs this process holds compiled (one per ray count, layout
    and static option set): what the size buckets of :func:`jrt.closest_hit` keep low."""
    return _traverse._cache_size()


@bounded_jit
@functools.partial(jax.jit, static_argnames=(
    "traversal", "kernel", "any_hit", "lanes", "stack_size", "counters", "devices",
    "rows_out", "capacity"))
def _traverse(arrays, origins, directions, tmax, *, traversal, kernel, any_hit, lanes,
              stack_size, counters, devices, rows_out=False, capacity=0):
    n = origins.shape[0]
    if arrays["triangles"].shape[0] == 0:
        # No triangle at all (an empty or all-degenerate mesh): one zero triangle, which
        # no kernel ever hits, keeps the leaf loop's gathers in range.
        arrays = dict(arrays, triangles=jnp.zeros((1, 3, 3), jnp.float32),
                      triangle_ids=jnp.full((1,), -1, jnp.int32))
    references = arrays.get("references")
    run = functools.partial(
        _run_lanes, traversal, kernel=kernel, any_hit=any_hit, lanes=lanes,
        stack_size=stack_size, counters=counters, references=references, rows_out=rows_out,
        capacity=capacity)
    if devices is None or len(devices) == 1 or n < 2 * len(devices):
        return run(arrays, _pack_rays(origins, directions, tmax))
    k = len(devices)
    per = -(-n // k)
    # Padding rays test nothing and are cut off below.
    origins, directions, tmax = pad_rays(origins, directions, tmax, per * k)
    mesh = Mesh(np.asarray(devices), ("rays",))

    # Ray i goes to device i mod k (interleaved, not in blocks): neighbouring rays cost
    # alike (a camera's rows above the mesh are cheap misses), and blocks left one device
    # idle while the other traced the mesh (measured 1.8x on camera rays, 2 devices). The
    # rays enter as [per, k, ...] split along the device axis, so each device's program
    # reads only its own share (PjRt still copies the committed inputs for the second
    # device, 7 % of that call below), and the results are gathered along that axis,
    # [per, k, ...], which is already ray order. Replicated inputs and results
    # gathered as [k, per, ...] and interleaved afterwards cost a copy more of each (memmove
    # took 17 % of a 1M-ray call whose rays all miss, perf; that call 63.8 against 58.8 ms
    # now, best of 16 rounds; paired 1M-ray calls on the camel: camera 1.00-1.02x,
    # incoherent 1.03-1.04x).
    def shard(arrays, origins, directions, tmax):
        mine = [a.reshape((per,) + a.shape[2:]) for a in (origins, directions, tmax)]
        hits, count, status = run(arrays, _pack_rays(*mine))  # padding rays are valid

        def gather(a):  # [per, ...] of each device -> [per, k, ...] on every device
            return lax.all_gather(a, "rays", axis=1)

        return (jax.tree.map(gather, hits), None if count is None else gather(count),
                lax.all_gather(status, "rays"))

    rep = jax.tree.map(lambda _: PartitionSpec(), arrays)
    split = PartitionSpec(None, "rays")
    hits, count, status = jax.shard_map(
        shard, mesh=mesh, in_specs=(rep, split, split, split), out_specs=PartitionSpec(),
        check_vma=False)(arrays, origins.reshape(per, k, 3), directions.reshape(per, k, 3),
                         tmax.reshape(per, k))

    def merge(a):  # [per, k, ...] is ray order
        return a.reshape((k * per,) + a.shape[2:])[:n]

    hits = jax.tree.map(merge, hits)
    count = None if count is None else merge(count)
    status = sum(jnp.where(jnp.any(status & bit), jnp.int32(bit), jnp.int32(0))
                 for bit in (STATUS_STACK_OVERFLOW, STATUS_UNFINISHED, STATUS_BAD_RAYS))
    return hits, count, status


def traverse(traversal: Traversal, arrays, origins, directions, tmax, *, kernel: str,
             any_hit: bool, lanes: int | None = None, stack_size: int = DEFAULT_STACK_SIZE,
             counters: bool = False, devices=None, rows_out: bool = False,
             capacity: int = 0):
    """Runs every ray through ``traversal``: (hits, counters or None, status).

    ``status`` is an int32 scalar of ``STATUS_*`` bits (0: every ray answered);
    ``lanes=None`` takes :func:`default_lanes` of the devices. With ``rows_out`` the
    first element is ``(hits, rows)``: each winner's row of ``arrays["triangles"]`` as
    well (int32 [N], -1 for a miss). With ``capacity`` K > 0 (all hits) the first element
    is ``(rows, count)``: int32 [N, K] and [N] (see :func:`_run_lanes`)."""
    if origins.shape[0] == 0:
        if capacity:
            empty = (jnp.zeros((0, capacity), jnp.int32), jnp.zeros(0, jnp.int32))
        else:
            empty = Hits(jnp.zeros(0, jnp.float32), jnp.zeros(0, jnp.int32),
                         jnp.zeros(0, jnp.float32), jnp.zeros(0, jnp.float32))
            if rows_out:
                empty = (empty, jnp.zeros(0, jnp.int32))
        return empty, (jnp.zeros((0, 3), jnp.int32) if counters else None), jnp.int32(0)
    devs = tuple(devices) if devices is not None else tuple(cpu_devices())
    if not devs:
        raise ValueError("devices must name at least one device (None: all local devices)")
    if lanes is None:
        lanes = default_lanes(devs)
    return _traverse(arrays, origins, directions, tmax, traversal=traversal, kernel=kernel,
                     any_hit=any_hit, lanes=lanes, stack_size=stack_size, counters=counters,
                     devices=devs, rows_out=rows_out, capacity=capacity)


#: Relative widening of every box test. Ize ("Robust BVH ray traversal", JCGT 2013)
#: shows ``tfar * (1 + 2 gamma_3)`` (about 4 ulps) makes a float32 slab test conservative.
#: The margin here is wider, in space as well as in t: each box grows by 2^-16 of the
#: magnitude of its corners and of the ray's origin, and the interval by 2^-16 of t, so
#: that it also absorbs the rounding of the triangle kernels, whose hit point (the
#: textbook kernel computes it as O + tD) may stray from the triangle by a few ulps of
#: those magnitudes. The magnitudes are taken in the structure's local frame
#: (``Ray.origin_axes``, ``accel.geometry.frame_origin``): the scene's extent and the
#: ray's distance from it, not where the scene sits (``margin_pad`` restores the world
#: magnitude for the one kernel whose rounding depends on it). A box is never culled while
#: a kernel could still report a hit in it, which keeps every structure's hits equal to
#: brute force's; the builders cover the rest, the part of a kernel's rounding that grows
#: with the triangle's own size (``accel.geometry.reference_margin``).
BOX_MARGIN = 2.0**-16


def box_interval(ray: Ray, lo, hi):
    """Entry and exit distances (tnear, tfar) [L] of each lane's ray through its box.

    ``lo``, ``hi``: the box corners by axis, sequences of three [L] arrays. Kay & Kajiya
    1986 slabs with Williams et al. 2005's inverse direction. A zero direction component
    gives ±inf and, for an origin exactly on that slab's face, 0 * inf = NaN: that axis
    then puts no bound (the ray lies in the face, which belongs to the closed box). The
    box and the interval are widened by :data:`BOX_MARGIN`; tnear is at least 0.
    """
    near, far = [], []
    for axis in range(3):
        o, inv = ray.origin_axes[axis], ray.inv_direction[axis]
        size = ray.scale(axis)
        t0 = (lo[axis] - BOX_MARGIN * (jnp.abs(lo[axis]) + size) - o) * inv
        t1 = (hi[axis] + BOX_MARGIN * (jnp.abs(hi[axis]) + size) - o) * inv
        lo_t, hi_t = jnp.minimum(t0, t1), jnp.maximum(t0, t1)
        near.append(jnp.where(lo_t == lo_t, lo_t, -jnp.inf))
        far.append(jnp.where(hi_t == hi_t, hi_t, jnp.inf))
    tnear = jnp.maximum(jnp.maximum(near[0], near[1]), jnp.maximum(near[2], 0.0))
    tfar = jnp.minimum(jnp.minimum(far[0], far[1]), far[2])
    return tnear * (1 - BOX_MARGIN), tfar * (1 + BOX_MARGIN)
