"""Moving geometry without a rebuild: a structure refit to new vertex positions.

    moved = jrt.refit(structure, vertices, faces)   # pure, jit-able, differentiable

The faces stay those the structure was built from (``faces``, the same int [F, 3] array);
only the vertices move. The structure keeps its topology (the same tree, the same leaves,
the same triangle order) and gets new triangle rows and, for a BVH, new node boxes, so
the hits of any query on it are exactly those of brute force on the moved mesh: every
box still holds the triangles below it, which is all a traversal needs to be exact. How
*fast* it traces depends on how far the mesh moved: a tree built for one pose and refit
to a very different one has boxes that overlap more than a rebuilt tree's (the usual
trade of refitting, Wald, Boulos & Shirley, "Ray tracing deformable scenes using dynamic
bounding volume hierarchies", ACM TOG 2007). Rebuild with ``accel.build`` when the shape
changed a lot.

Which kinds can be refit is each kind's declaration (``accel.StructureKind.refit``):
brute force (new triangles) and the BVH (new triangles and boxes, bottom-up). The
spatial subdivisions (kd-tree, octree, BSP tree, uniform grid) cannot be refit exactly:
their cells and planes were placed for the old positions, and a moved triangle may leave
the cells that reference it. ``refit`` raises for them and names ``accel.build``.

Derivatives: the triangle rows are ``vertices[faces[triangle_ids]]`` (a gather), so a
loss of the hits on the refit structure differentiates with respect to ``vertices``
(``jrt.hit_derivatives``); the boxes are piecewise constant and carry none.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Float, Int

import accel
from accel.bvh import (
    EMPTY_SLOT,
    FRAME_WORDS,
    MIN_SCALE_EXPONENT,
    QUANT_MAX,
    bound_words,
    reference_column,
)
from accel.structure import Structure
from jrt import structure as _structure  # noqa: F401  (registers Structure as a pytree)


def refit(structure: Structure, vertices: Float[Array, "v 3"],
          faces: Int[Array, "f 3"]) -> Structure:
    """The structure for the mesh ``(vertices, faces)``: the faces it was built from,
    with their vertices moved (module docstring). Pure and jit-able; differentiable with
    respect to ``vertices``.

    Args:
        structure: from ``accel.build`` of a kind that can be refit (brute force, BVH).
        vertices: float [V, 3], the new positions (converted to float32).
        faces: int [F, 3], the faces the structure was built from.

    Raises:
        ValueError: a kind that cannot be refit (it names ``accel.build``), arrays of the
            wrong shape, or (where the values are known, outside a ``jit``) faces that
            do not fit the vertices or the structure, or non-finite vertices.
    """
    if not isinstance(structure, Structure):
        raise TypeError(f"refit takes a structure from accel.build, got "
                        f"{type(structure).__name__}")
    kind = accel.kind(structure.kind)
    function = kind.refit_function()
    if function is None:
        raise ValueError(
            f"a {structure.kind} cannot be refit exactly: its cells and planes were placed "
            f"for the old vertex positions, and a moved triangle may leave the cells that "
            f"reference it. Rebuild it for the new positions: accel.build("
            f"{structure.kind!r}, vertices, faces). Kinds that can be refit: "
            f"{', '.join(k.name for k in accel.kinds() if k.refit is not None)}")
    vertices = jnp.asarray(vertices, jnp.float32)
    faces = jnp.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"refit: vertices must have shape [V, 3], got {tuple(vertices.shape)}")
    if faces.ndim != 2 or faces.shape[1] != 3 or not jnp.issubdtype(faces.dtype, jnp.integer):
        raise ValueError(f"refit: faces must be integers of shape [F, 3], got "
                         f"{faces.dtype} {tuple(faces.shape)}")
    ids = structure["triangle_ids"]
    _check_values(vertices, faces, ids)
    return function(structure, triangle_rows(structure, vertices, faces))


def _check_values(vertices, faces, ids) -> None:
    """Where the values are known: faces within the vertices, the structure's faces
    within ``faces``, finite vertices."""
    if any(isinstance(a, jax.core.Tracer) for a in (vertices, faces, ids)):
        return
    v, f, ids = np.asarray(vertices), np.asarray(faces), np.asarray(ids)
    if f.size and (f.min() < 0 or f.max() >= v.shape[0]):
        raise ValueError(f"refit: faces index vertices 0..{v.shape[0] - 1}, got indices "
                         f"{int(f.min())}..{int(f.max())}")
    if ids.size and ids.max() >= f.shape[0]:
        raise ValueError(f"refit: the structure holds face {int(ids.max())}, but faces has "
                         f"{f.shape[0]} rows: pass the faces the structure was built from")
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        raise ValueError(f"refit: vertex {int(np.flatnonzero(bad)[0])} is not finite "
                         f"({v[bad][0].tolist()})")


def triangle_rows(structure: Structure, vertices: Float[Array, "v 3"],
                  faces: Int[Array, "f 3"]) -> Float[Array, "t 3 3"]:
    """float32 [T, 3, 3]: the structure's triangle rows for these vertices (a row that
    holds no face, padding, keeps its values)."""
    ids = jnp.asarray(structure["triangle_ids"])
    rows = vertices[jnp.asarray(faces)[jnp.maximum(ids, 0)]]
    return jnp.where((ids >= 0)[:, None, None], rows,
                     jnp.asarray(structure["triangles"], jnp.float32))


def refit_brute(structure: Structure, triangles: Float[Array, "t 3 3"]) -> Structure:
    """Brute force reads nothing but the triangles."""
    return _replaced(structure, triangles=triangles)


def _replaced(structure: Structure, **arrays) -> Structure:
    return Structure(kind=structure.kind, arrays={**structure.arrays, **arrays},
                     layout=structure.layout)


# --------------------------------------------------------------------------------------------
# The BVH: every node's boxes, bottom-up, quantised as accel.bvh stores them
# --------------------------------------------------------------------------------------------


def refit_bvh(structure: Structure, triangles: Float[Array, "t 3 3"]) -> Structure:
    """New triangle rows, frame and node rows (``accel.bvh``'s layout): each leaf's box
    is the box of its triangles, each interior child's the union of its children's, and
    every box is quantised conservatively in its parent's frame, as the builder does
    (:func:`accel.bvh.node_rows`; in float32, so a box may come out one quantum wider
    than a fresh build's, never narrower). The references, the leaves and the triangle
    order are unchanged."""
    width = structure.layout_value("width")
    leaf_bits = structure.layout_value("leaf_bits")
    # A structure closed over by a caller's jit is a constant there, and XLA would fold
    # everything computed from its topology alone (the leaf runs over 69k rows took it
    # seconds of compiling): the barrier makes the topology an ordinary value.
    ids, nodes = lax.optimization_barrier((jnp.asarray(structure["triangle_ids"]),
                                           jnp.asarray(structure["nodes"])))
    if ids.shape[0] == 0:  # no triangle: nothing to bound
        return _replaced(structure, triangles=triangles)
    fixed = lax.stop_gradient(triangles)
    frame = _frame_origin(fixed, ids >= 0)
    lo, hi = _triangle_boxes(fixed, frame, ids >= 0)
    column = reference_column(width)
    refs = nodes[:, column:column + width]
    leaf_lo, leaf_hi = _leaf_boxes(refs, lo, hi, leaf_bits)
    child_lo, child_hi = _child_boxes(refs, leaf_lo, leaf_hi)
    nodes = _quantised_rows(nodes, refs, child_lo, child_hi, width)
    return _replaced(structure, triangles=triangles, nodes=nodes, frame=frame)


def _frame_origin(triangles, real):
    """:func:`accel.geometry.frame_origin` of the real rows: the point of their box
    nearest the coordinate origin."""
    corners_lo = jnp.where(real[:, None], triangles.min(axis=1), jnp.inf).min(axis=0)
    corners_hi = jnp.where(real[:, None], triangles.max(axis=1), -jnp.inf).max(axis=0)
    frame = jnp.clip(jnp.float32(0), corners_lo, corners_hi)
    return jnp.where(jnp.isfinite(frame), frame, 0).astype(jnp.float32)


def _triangle_boxes(triangles, frame, real):
    """Each row's box in the frame, rounded outward: ``triangles - frame`` rounds to
    nearest (half an ulp), one ulp outward holds the exact difference; exact, and kept,
    on an axis where the frame is 0. Rows that hold no face get an empty box."""
    local = triangles - frame
    lo, hi = local.min(axis=1), local.max(axis=1)
    moved = frame != 0
    lo = jnp.where(moved, jnp.nextafter(lo, jnp.float32(-jnp.inf)), lo)
    hi = jnp.where(moved, jnp.nextafter(hi, jnp.float32(jnp.inf)), hi)
    return (jnp.where(real[:, None], lo, jnp.inf), jnp.where(real[:, None], hi, -jnp.inf))


def _leaf_boxes(refs, lo, hi, leaf_bits):
    """The box of every leaf slot of ``refs`` [K, W] (rows ``first .. first+count-1``;
    empty for interior children and empty slots): [K, W, 3] each. Leaves own disjoint
    runs of rows, so a row's leaf is the last leaf start at or before it (a running
    maximum) and one segment reduction gives every leaf's box."""
    rows = lo.shape[0]
    code = ~refs
    first, count = code >> leaf_bits, code & ((1 << leaf_bits) - 1)
    leaf = (refs < 0) & (refs != EMPTY_SLOT) & (count > 0)
    at = jnp.where(leaf, first, rows)  # out of range: dropped
    starts = jnp.full(rows, -1, jnp.int32).at[at].max(first, mode="drop")
    ends = jnp.zeros(rows, jnp.int32).at[at].max(first + count, mode="drop")
    owner = lax.cummax(starts)
    inside = (owner >= 0) & (jnp.arange(rows) < ends[jnp.maximum(owner, 0)])
    segment = jnp.where(inside, owner, rows)
    box_lo = jax.ops.segment_min(lo, segment, num_segments=rows + 1)
    box_hi = jax.ops.segment_max(hi, segment, num_segments=rows + 1)
    slot = jnp.where(leaf, first, rows)
    return (jnp.where(leaf[..., None], box_lo[slot], jnp.inf),
            jnp.where(leaf[..., None], box_hi[slot], -jnp.inf))


def _child_boxes(refs, leaf_lo, leaf_hi):
    """Every child's box [K, W, 3]: a leaf's from its triangles, an interior child's the
    union of its own children's. Repeated until nothing changes: pass k completes the
    nodes of height k, so the loop runs the tree's depth plus one times."""
    interior = (refs >= 0)[..., None]
    child = jnp.maximum(refs, 0)

    def boxes(node_lo, node_hi):
        return (jnp.where(interior, node_lo[child], leaf_lo),
                jnp.where(interior, node_hi[child], leaf_hi))

    def step(state):
        node_lo, node_hi, _, passes = state
        lo, hi = boxes(node_lo, node_hi)
        new_lo, new_hi = lo.min(axis=1), hi.max(axis=1)
        same = (jnp.array_equal(new_lo, node_lo, equal_nan=True)
                & jnp.array_equal(new_hi, node_hi, equal_nan=True))
        return new_lo, new_hi, ~same, passes + 1

    k = refs.shape[0]
    empty = jnp.full((k, 3), jnp.inf, jnp.float32)
    state = (empty, -empty, jnp.bool_(True), jnp.int32(0))
    node_lo, node_hi, _, _ = lax.while_loop(lambda s: s[2] & (s[3] <= k), step, state)
    return boxes(node_lo, node_hi)


def _power_of_two_at_least(x):
    """The smallest power of two >= x (float32, x > 0)."""
    mantissa, exponent = jnp.frexp(x)  # x = mantissa 2^exponent, mantissa in [0.5, 1)
    return jnp.ldexp(jnp.float32(1), exponent - (mantissa == 0.5).astype(exponent.dtype))


def _quantised_rows(nodes, refs, lo, hi, width):
    """``nodes`` with new frames (origin, scale) and 8-bit child bounds: the conservative
    quantisation of :func:`accel.bvh.node_rows` in float32. The scale is a power of two
    with ``255 scale`` at least the rounded-up extent; each bound is stepped outward until
    ``origin + q scale`` (the traversal's decoding, ``q scale`` exact) holds it."""
    f32 = jnp.float32
    filled = (refs != EMPTY_SLOT)[..., None]
    origin = jnp.where(filled, lo, jnp.inf).min(axis=1)
    top = jnp.where(filled, hi, -jnp.inf).max(axis=1)
    finite = jnp.isfinite(origin) & jnp.isfinite(top)
    origin, top = jnp.where(finite, origin, 0), jnp.where(finite, top, 0)
    extent = jnp.nextafter(top - origin, f32(jnp.inf))  # >= the exact extent
    step = jnp.nextafter(extent / QUANT_MAX, f32(jnp.inf))  # >= extent / 255
    scale = _power_of_two_at_least(jnp.maximum(step, f32(2.0 ** MIN_SCALE_EXPONENT)))
    o, s = origin[:, None, :], scale[:, None, :]
    lo, hi = jnp.where(filled, lo, o), jnp.where(filled, hi, o)

    def decode(q):
        return o + q.astype(f32) * s

    q_lo = jnp.clip(jnp.floor((lo - o) / s), 0, QUANT_MAX).astype(jnp.int32)
    q_hi = jnp.clip(jnp.ceil((hi - o) / s), 0, QUANT_MAX).astype(jnp.int32)

    def outside(state):
        q_lo, q_hi = state
        return (decode(q_lo) > lo) & filled, (decode(q_hi) < hi) & filled

    def widen(state):
        low, high = outside(state)
        return state[0] - low, state[1] + high

    # q = 0 decodes to the origin and q = 255 to at least the top: a step or two at most.
    q_lo, q_hi = lax.while_loop(lambda st: jnp.any(jnp.stack([b.any() for b in outside(st)])),
                                widen, (q_lo, q_hi))
    q_lo = jnp.where(filled, q_lo, QUANT_MAX)
    q_hi = jnp.where(filled, q_hi, 0)
    k = refs.shape[0]
    # Bytes field-major: byte f * W + c is field f (lower x, y, z, upper x, y, z) of child c.
    fields = jnp.concatenate([q_lo, q_hi], axis=2).transpose(0, 2, 1).reshape(k, 6 * width)
    fields = jnp.pad(fields, ((0, 0), (0, 4 * bound_words(width) - 6 * width)))
    b = fields.reshape(k, bound_words(width), 4).astype(jnp.uint32)
    words = lax.bitcast_convert_type(b[..., 0] | (b[..., 1] << 8) | (b[..., 2] << 16)
                                     | (b[..., 3] << 24), jnp.int32)
    return (nodes.at[:, 0:3].set(lax.bitcast_convert_type(origin.astype(f32), jnp.int32))
            .at[:, 3:FRAME_WORDS].set(lax.bitcast_convert_type(scale.astype(f32), jnp.int32))
            .at[:, FRAME_WORDS:FRAME_WORDS + bound_words(width)].set(words))
