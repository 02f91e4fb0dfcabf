"""Public ray queries: any structure, any triangle kernel, one call site.

    hits = jrt.closest_hit(structure, origins, directions, tmax=None, kernel="watertight")
    mask = jrt.occluded(structure, origins, directions, tmax=None, kernel="watertight")

``structure`` comes from ``accel.build(name, mesh)``. The options are keyword-only and
come in the same order in both.

**Directions** may have any length within :data:`jrt.engine.DIRECTION_LENGTHS`
([1e-6, 1e6]); ``t`` and ``tmax`` are in units of the direction's length (the kernels are
affine in it). A unit direction (seed, Proposition 2.1: a ray is a point and a unit
vector) makes ``t`` a distance; ``d = p1 - p0`` with ``tmax=1`` is the segment from p0 to
p1. The ``jrt trace`` command applies the same rule (``jrt.rays_io``).

**Size buckets.** XLA compiles a program per array shape, 2.5-3 s for a traversal of the
camel, so a caller whose ray count changes from call to call would compile on every call.
Outside a caller's ``jit`` the rays are padded up to the next size of
:func:`bucket_size` (1024, then 2^k and 3 x 2^(k-1): at most 1.5x the rays, two programs
per doubling of the count) and the answers sliced back. A padding ray can hit nothing
(:func:`jrt.engine.pad_rays`): the engine answers it before any lane takes it, brute force
skips chunks of them, and the real rays' answers are those of an unpadded call, bit for
bit. A small structure (:data:`PAD_MAX_BYTES`) is padded to size buckets too
(:func:`padded_structure`), so that the structures of similar small meshes share a
program. ``JRT_SIZE_BUCKETS=0`` turns the buckets off (for a measurement, or a caller that
knows its sizes). Inside a caller's ``jit`` the shapes are the caller's, and the rays go
through as they are.

**vmap.** Both queries vmap natively: the engine call (or brute force's) is a
``jax.custom_batching.custom_vmap`` function (:func:`_flat_query`) whose batching rule
lays the rays of every batch item end to end ([B, N, 3] -> [B*N, 3]; an unbatched
origins, directions or tmax is broadcast), traces them in *one* unbatched call and gives
the answers back per item ([B, N]). Vmapping the engine's loop itself would turn its
conditionals into selects that compute both sides (``jrt.batch`` measured 10x slower),
and every ray's answer is the one a call on its own batch item gives, bit for bit. Nested
``vmap`` flattens every level into the same one call; ``jit`` outside or inside is fine.
A *batched structure* (one per item) cannot share a call: its items are traced one after
another (``lax.map``), each as a single call. Under ``vmap`` the rays are tracers, so the
host-side checks of their values are skipped as under ``jit`` (a bad ray is a miss).

**Precision**: float32 inside, also under ``jax_enable_x64`` (the rays are converted to
float32 on the way in; the hits are float32 and int32).
"""

from __future__ import annotations

import dataclasses
import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Array, Bool, Float

import accel
from accel.structure import Structure
from jrt import brute, engine
from jrt import structure as _structure  # noqa: F401  (registers Structure as a pytree)
from jrt.engine import Counters, StackOverflowError, TraversalError
from jrt.hit_derivatives import hit_tangents
from jrt.hits import Hits
from jrt.kernels import DEFAULT_KERNEL, get_kernel
from jrt.programs import trim_programs


def traversal_of(structure: Structure) -> engine.Traversal:
    """The engine traversal of a structure: its registered kind's ``traversal`` function
    (:class:`accel.StructureKind`; ``jrt.<kind>.traversal`` for the built-in ones)."""
    return accel.kind(structure.kind).traversal_function()(structure)


#: The smallest size bucket (:func:`bucket_size`), a multiple of brute force's ray chunk
#: and of every usual device count.
MIN_BUCKET = 1024

#: ``JRT_SIZE_BUCKETS=0`` turns the size buckets off (read at every call).
BUCKETS_ENV = "JRT_SIZE_BUCKETS"


def bucket_size(n: int) -> int:
    """The ray count a call on ``n`` rays is compiled for: :data:`MIN_BUCKET` up to it,
    then the smallest of 2^k and 3 x 2^(k-1) that holds ``n``.

    Why these: a bucket trades padding work for compiles. Powers of two alone pad up to
    2x; adding their midpoints 3 x 2^(k-1) caps it at 1.5x (1.2x on average over sizes
    spread evenly on a log scale) for two programs per doubling of the count. Padding
    costs the engine little (a padding ray never takes a lane: a pass over the rays and a
    queue entry), so the cap matters mostly for brute force. Every bucket from 1024 up is
    a multiple of 256 (brute force's ray chunk) and of 2, 3, 4, 6 and 8 devices, and the
    usual image sizes (1024^2, 512^2) are buckets themselves.
    """
    if n <= MIN_BUCKET:
        return MIN_BUCKET
    power = 1 << (n - 1).bit_length()  # the smallest power of two >= n
    return 3 * power // 4 if n <= 3 * power // 4 else power


#: Structures up to this many bytes are padded by :func:`padded_structure` (2 MiB: the 19k-triangle
#: camel under every kind). Below it a compile (about a second a traversal on a CPU) costs
#: far more than copying the arrays; above it the arrays are passed as built, so a large
#: structure costs no extra memory or copy.
PAD_MAX_BYTES = 2 << 20


def padded_structure(structure: Structure) -> Structure:
    """``structure`` with the arrays its kind declares as ``rows`` (:class:`accel.StructureKind`)
    padded at the end to a size bucket (:func:`jrt.trace.bucket_size`: 1024 rows, then 2^k
    and 3 x 2^(k-1)). No stored index points past the real rows, so a traversal reads the
    same rows and returns the same hits, bit for bit; but structures of similar sizes (the
    tiny meshes of a test suite, a mesh moved and rebuilt) then share one compiled program.
    Padding rows are zeros (a zero triangle, which no kernel hits), ``triangle_ids`` -1.

    Returned as is: a structure over :data:`PAD_MAX_BYTES`, a kind that declares no rows,
    arrays that are traced (under ``jit``, the caller's program fixes the shapes)."""
    rows = accel.kind(structure.kind).rows
    arrays = structure.arrays
    if not rows or _is_traced(*arrays.values()) or structure.nbytes > PAD_MAX_BYTES:
        return structure
    out = dict(arrays)
    for name in rows:
        a = np.asarray(arrays[name])
        extra = bucket_size(a.shape[0]) - a.shape[0]
        if extra:
            fill = -1 if name == "triangle_ids" else 0
            out[name] = np.concatenate([a, np.full((extra, *a.shape[1:]), fill, a.dtype)])
    return dataclasses.replace(structure, arrays=out)


def _buckets_enabled() -> bool:
    return os.environ.get(BUCKETS_ENV, "1").strip() != "0"


def _padded(origins, directions, tmax, size: int):
    """The rays padded to ``size`` (:func:`jrt.engine.pad_rays`). On the CPU, in NumPy:
    the arrays are host memory already, and a jitted pad would be one more program to
    compile for every ray count (0.1 s each on a busy 2-core host)."""
    if jax.default_backend() == "cpu":
        host = [np.asarray(a) for a in (origins, directions, tmax)]
        return tuple(jnp.asarray(a) for a in engine.pad_rays(*host, size, xp=np))
    return _padded_on_device(origins, directions, tmax, size=size)


@functools.partial(jax.jit, static_argnames=("size",))
def _padded_on_device(origins, directions, tmax, *, size):
    return engine.pad_rays(origins, directions, tmax, size)


def _first(tree, n: int):
    """The first ``n`` rays' answers; on the CPU sliced in NumPy, as :func:`_padded`."""
    if jax.default_backend() == "cpu":
        return jax.tree.map(lambda a: jnp.asarray(np.asarray(a)[:n]), tree)
    return _first_on_device(tree, n=n)


@functools.partial(jax.jit, static_argnames=("n",))
def _first_on_device(tree, *, n):
    return jax.tree.map(lambda a: a[:n], tree)


def _is_traced(*arrays) -> bool:
    return any(isinstance(a, jax.core.Tracer) for a in arrays)


def _check_rays(origins, directions, tmax):
    """The rays as float32 arrays of consistent shapes (else a ValueError); ``tmax`` [N]
    (``None``: inf). Their values are checked later, on the device (see
    :func:`_raise_on_status` and :func:`_check_ray_values`)."""
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
        tmax = np.float32(np.inf)
    if not _is_traced(tmax) and np.ndim(tmax) == 0:
        # A scalar: broadcast on the host (no program compiled per ray count).
        tmax = np.full((n,), np.asarray(tmax, np.float32))
    tmax = jnp.asarray(tmax, jnp.float32)
    if tmax.shape != (n,):
        try:
            tmax = jnp.broadcast_to(tmax, (n,))
        except ValueError:
            raise ValueError(f"tmax must be a scalar or have shape [{n}] (one per ray), "
                             f"got {tuple(tmax.shape)}") from None
    return origins, directions, tmax


def _check_ray_values(origins, directions, tmax, named=None):
    """Bad rays (:func:`jrt.engine.ray_problems`: a NaN or infinite origin or direction, a
    direction's length out of :data:`jrt.engine.DIRECTION_LENGTHS`, a NaN tmax) are
    errors, never silent misses. Checked where the values are known (outside a caller's
    jit); inside one, such rays trace as misses (``t = inf``), which is documented.
    ``named``: the caller's rays (origins, directions, tmax) before padding, which the
    message names (default: these)."""
    if _is_traced(origins, directions, tmax):
        return
    # One fused pass on the device first (NumPy's took 53 ms of a 283 ms call on 1M rays);
    # the rays are copied to the host only to name a bad one.
    if not bool(_any_bad_ray(origins, directions, tmax)):
        return
    problem = engine.describe_bad_ray(*(named or (origins, directions, tmax)))
    if problem is not None:
        raise ValueError(problem)


@jax.jit
def _any_bad_ray(origins, directions, tmax):
    """Whether any ray fails :func:`jrt.engine.ray_problems` (one fused pass on the device)."""
    return jnp.any(jnp.stack([bad.any() for _, bad, _ in
                              engine.ray_problems(jnp, origins, directions, tmax)]))


def _check_structure(structure):
    if not isinstance(structure, Structure):
        raise TypeError(
            f"structure must be an accel.Structure (from accel.build), got {type(structure)}"
        )
    if structure.kind not in accel.names():
        raise ValueError(f"no traversal for structure kind {structure.kind!r}; "
                         f"allowed: {', '.join(accel.names())}")
    declared = accel.kind(structure.kind)
    arrays, layout = declared.arrays, declared.layout
    has_arrays = frozenset(structure.arrays)
    has_layout = frozenset(name for name, _ in structure.layout)
    if has_arrays != arrays or has_layout != layout:
        raise ValueError(
            f"a {structure.kind!r} structure needs the arrays {sorted(arrays)} and the "
            f"layout {sorted(layout)}; this one has the arrays {sorted(has_arrays)} and the "
            f"layout {sorted(has_layout)}. Build it with accel.build({structure.kind!r}, ...).")


def _check_options(lanes, stack_size):
    if not (lanes is None or (isinstance(lanes, int) and lanes >= 1)):
        raise ValueError(f"lanes must be a positive integer or None (the backend's default, "
                         f"jrt.engine.default_lanes), got {lanes!r}")
    if not (isinstance(stack_size, int) and stack_size >= 1):
        raise ValueError(f"stack_size must be a positive integer, got {stack_size!r}")


def _raise_on_status(status, stack_size, rays):
    """Raise what the engine's status word reports (inside a caller's jit: at run time).

    Bad rays (:data:`jrt.engine.STATUS_BAD_RAYS`) are named from ``rays`` (origins,
    directions, tmax) outside a jit; inside one they trace as misses, as documented."""
    if isinstance(status, jax.core.Tracer):
        jax.debug.callback(_status_callback, status, stack_size=stack_size)
        return
    status = int(status)
    problem = engine.describe_bad_ray(*rays) if status & engine.STATUS_BAD_RAYS else None
    if problem is not None:
        raise ValueError(problem)
    _status_callback(status, stack_size=stack_size)


def _status_callback(status, *, stack_size):
    status = int(status)
    if status & engine.STATUS_STACK_OVERFLOW:
        raise StackOverflowError(
            f"a traversal stack of {stack_size} entries overflowed; its rays' answers would "
            f"be wrong. Pass a larger stack_size (e.g. {2 * stack_size}).")
    if status & engine.STATUS_UNFINISHED:
        raise TraversalError(
            "the traversal did not finish within its iteration budget (see "
            "jrt.engine.iteration_budget): the structure's arrays are inconsistent with its "
            "kind (a cycle, or arrays of another kind). Rebuild it with accel.build.")


def _core(structure, origins, directions, tmax, *, kernel, any_hit, counters, lanes,
          stack_size, rows_out=False, capacity=0):
    """The jittable query on checked rays (float32 [N, 3], [N, 3], [N]): (answers, counters
    int32 [N, 3] or None, status int32 scalar). Brute force reports no status (0). With
    ``rows_out`` (closest hits) the answers are ``(hits, rows)``: each winner's row of the
    structure's ``triangles`` too, -1 for a miss. With ``capacity`` K > 0 (all hits) they
    are ``(rows, count)``, int32 [N, K] and [N] (``jrt.engine``'s ``capacity``)."""
    if not accel.kind(structure.kind).engine:  # brute force: no engine, every triangle
        if capacity:
            out = brute.all_rows(structure["triangles"], origins, directions, tmax,
                                 kernel=kernel, capacity=capacity)
        elif any_hit:
            out = brute.occluded(structure["triangles"], origins, directions, tmax,
                                 kernel=kernel)
        else:
            out = brute.closest_hit(structure["triangles"], structure["triangle_ids"],
                                    origins, directions, tmax, kernel=kernel,
                                    rows_out=rows_out)
        return out, None, jnp.int32(0)
    # The arrays and layout were checked against the kind (_check_structure).
    hits, count, status = engine.traverse(
        traversal_of(structure), structure.arrays, origins, directions, tmax,
        kernel=kernel, any_hit=any_hit, lanes=lanes, stack_size=stack_size,
        counters=counters, rows_out=rows_out and not any_hit, capacity=capacity)
    return (hits.triangle >= 0 if any_hit and not capacity else hits), count, status


def _item_map(fn, in_batched, args):
    """``fn(*args)`` for each batch item in turn (``lax.map``): the batched leaves of
    ``args`` are sliced by item, the unbatched ones shared (not broadcast)."""
    leaves, tree = jax.tree.flatten(args)
    flags = jax.tree.leaves(in_batched)

    def one(xs):
        it = iter(xs)
        return fn(*jax.tree.unflatten(tree, [next(it) if b else x
                                             for x, b in zip(leaves, flags, strict=True)]))

    return lax.map(one, [x for x, b in zip(leaves, flags, strict=True) if b])


@functools.cache
def _flat_query(kernel, any_hit, counters, lanes, stack_size, rows_out=False, capacity=0):
    """:func:`_core` for ``(structure, origins, directions, tmax)`` with these static
    options, as a ``custom_vmap`` function: under ``jax.vmap`` it runs *once* on the batch
    items' rays laid end to end (see the module's docstring). One function per set of
    options (cached), so ``jit`` traces each once.

    The rule: with a shared (unbatched) structure, each of origins, directions, tmax is
    broadcast to the batch if unbatched, reshaped [B, N, ...] -> [B*N, ...] and traced in
    one call of this same function (a second ``vmap`` level around this one applies its
    own rule there: nested vmaps become one call); the answers and counters come back
    [B, N, ...], the status word, an OR over all rays, unbatched. With a batched structure
    the items go one at a time through ``lax.map`` (each a single call; their status
    words ORed).
    """
    options = dict(kernel=kernel, any_hit=any_hit, counters=counters, lanes=lanes,
                   stack_size=stack_size, rows_out=rows_out, capacity=capacity)
    flat = jax.custom_batching.custom_vmap(functools.partial(_core, **options))

    @flat.def_vmap
    def _rule(axis_size, in_batched, structure, origins, directions, tmax):
        args = (structure, origins, directions, tmax)
        if any(jax.tree.leaves(in_batched[0])):  # one structure per item: in turn
            out, count, status = _item_map(flat, in_batched, args)
            status = lax.reduce(status, np.int32(0), lax.bitwise_or, (0,))
        else:
            def laid_out(x, batched):
                x = x if batched else jnp.broadcast_to(x, (axis_size, *x.shape))
                return x.reshape((-1, *x.shape[2:]))

            n = tmax.shape[-1]  # rays per item (tmax is [N] or [B, N])
            rays = [laid_out(x, b) for x, b in zip(args[1:], in_batched[1:], strict=True)]
            # Under an eager vmap the laid-out rays are arrays: the plain call (no jaxpr
            # to trace and evaluate); traced (jit, an outer vmap), this same function.
            call = flat if _is_traced(*rays, *jax.tree.leaves(structure)) else \
                functools.partial(_core, **options)
            out, count, status = call(structure, *rays)
            out, count = jax.tree.map(lambda a: a.reshape((axis_size, n, *a.shape[1:])),
                                      (out, count))
        return (out, count, status), (*jax.tree.map(lambda _: True, (out, count)), False)

    return flat


def _query(structure, origins, directions, tmax, *, kernel, any_hit, counters, lanes,
           stack_size, status_out=False, rows_out=False, capacity=0):
    """What :func:`closest_hit` and :func:`occluded` share: checks, size bucket, the
    engine or brute force, the answers of the real rays. Returns (hits, counters or
    None), and with ``status_out`` the engine's status word instead of raising on it
    (:func:`query_status`)."""
    _check_structure(structure)
    get_kernel(kernel)
    is_brute = not accel.kind(structure.kind).engine
    if counters and is_brute:
        raise ValueError("counters are available for the engine's structures, not brute "
                         "force (which tests every triangle)")
    if not is_brute:
        _check_options(lanes, stack_size)
    origins, directions, tmax = _check_rays(origins, directions, tmax)
    n = origins.shape[0]
    rays = (origins, directions, tmax)  # as the caller gave them, for the messages
    traced = _is_traced(*rays)
    size = bucket_size(n) if n and not traced and _buckets_enabled() else n
    if size != n:
        origins, directions, tmax = _padded(origins, directions, tmax, size)
    options = dict(kernel=kernel, any_hit=any_hit, counters=counters, lanes=lanes,
                   stack_size=stack_size, rows_out=rows_out, capacity=capacity)
    if is_brute:
        _check_ray_values(origins, directions, tmax, named=rays)  # padding rays are valid
    if _buckets_enabled():  # (brute force declares no rows: it tests every triangle)
        structure = padded_structure(structure)
    if traced or _is_traced(*jax.tree.leaves(structure)):
        # Traced (jit, vmap): the custom_vmap function, so that a vmap anywhere around
        # this call batches it as one call on all the items' rays (_flat_query).
        out, count, status = _flat_query(**options)(structure, origins, directions, tmax)
    else:
        out, count, status = _core(structure, origins, directions, tmax, **options)
        trim_programs()  # (the answers are computed; a dropped program compiles again)
    if not is_brute and not status_out:
        _raise_on_status(status, stack_size, rays)
    if size != n:
        out, count = _first((out, count), n)
    if count is not None:
        count = Counters(steps=count[:, 0], tests=count[:, 1], leaves=count[:, 2])
    return (out, count, status) if status_out else (out, count)


def _integer_zeros(tree):
    """The tangent of integer or boolean outputs: float0 zeros of their shapes."""
    return jax.tree.map(lambda a: np.zeros(np.shape(a), jax.dtypes.float0), tree)


@functools.cache
def _differentiable_query(kernel, any_hit, counters, lanes, stack_size, status_out=False):
    """:func:`_query` as a ``jax.custom_jvp`` function of ``(structure, origins,
    directions, tmax)`` (checked rays): JAX never differentiates the traversal (its loops
    and the choice of a triangle have no useful derivative). The rule runs the query on
    the primal values and attaches the closed-form tangents of the winner's ``t, u, v``
    (:func:`jrt.hit_derivatives.hit_tangents`: with respect to the origins, the
    directions and the structure's ``triangles`` rows; exactly 0 for a miss). The
    triangle index, the counters, the status word and ``occluded``'s mask are piecewise
    constant: float0 tangents, so a ``grad`` through them is 0 and never NaN. One
    function per set of options (cached), as :func:`_flat_query`."""
    options = dict(kernel=kernel, any_hit=any_hit, counters=counters, lanes=lanes,
                   stack_size=stack_size, status_out=status_out)

    def primal(structure, origins, directions, tmax):
        return _query(structure, origins, directions, tmax, **options)

    query = jax.custom_jvp(primal)

    # Symbolic zeros: a structure that nothing differentiates (a render's fixed mesh) has
    # a zero tangent, and its rows' terms are left out, not gathered from a zero array.
    @functools.partial(query.defjvp, symbolic_zeros=True)
    def _rule(primals, tangents):
        structure, origins, directions, _ = primals
        if any_hit:
            answers = primal(*primals)
            return answers, _integer_zeros(answers)
        # The same query, which also hands over each winner's row of the triangles.
        (out, rows), *rest = _query(*primals, **options, rows_out=True)
        answers = (out, *rest)
        structure_dot, origins_dot, directions_dot, _ = tangents
        t_dot, u_dot, v_dot = hit_tangents(
            structure["triangles"], rows, origins, directions,
            *(None if isinstance(x, SymbolicZero) else x
              for x in (structure_dot["triangles"], origins_dot, directions_dot)))
        out_dot = Hits(t=t_dot, triangle=_integer_zeros(out.triangle), u=u_dot, v=v_dot)
        return answers, (out_dot, *_integer_zeros(tuple(rest)))

    return query


def _query_any(structure, origins, directions, tmax, **options):
    """:func:`_query`, through :func:`_differentiable_query` when anything is traced (a
    ``jit``, ``vmap`` or derivative around the call); concrete calls, which nothing can
    differentiate, go straight to it."""
    if not _is_traced(origins, directions, tmax, *jax.tree.leaves(structure)):
        return _query(structure, origins, directions, tmax, **options)
    origins, directions, tmax = _check_rays(origins, directions, tmax)
    return _differentiable_query(**options)(structure, origins, directions, tmax)


def query_status(structure: Structure, origins: Float[Array, "n 3"],
                 directions: Float[Array, "n 3"], *, tmax, kernel: str, any_hit: bool,
                 stack_size: int = engine.DEFAULT_STACK_SIZE):
    """:func:`closest_hit` (or :func:`occluded` with ``any_hit``) that hands the engine's
    status word back, an int32 scalar of ``jrt.engine.STATUS_*`` bits, instead of raising
    on it. For a program that runs many queries under one ``jit`` (the renderer): it ORs
    the words and raises once, outside, with :func:`raise_on_status`. No host callback
    sits in its program, so JAX's persistent compilation cache can keep it (a program
    with a callback is never cached)."""
    out, _, status = _query_any(structure, origins, directions, tmax, kernel=kernel,
                                any_hit=any_hit, counters=False, lanes=None,
                                stack_size=stack_size, status_out=True)
    return out, status


def raise_on_status(status, stack_size: int = engine.DEFAULT_STACK_SIZE) -> None:
    """Raise :class:`StackOverflowError` or :class:`jrt.engine.TraversalError` for a
    concrete status word from :func:`query_status` (bad rays trace as misses there, as
    inside any ``jit``)."""
    _status_callback(int(status), stack_size=stack_size)


def closest_hit(
    structure: Structure,
    origins: Float[Array, "n 3"],
    directions: Float[Array, "n 3"],
    *,
    tmax: Float[Array, " n"] | float | None = None,
    kernel: str = DEFAULT_KERNEL,
    counters: bool = False,
    lanes: int | None = None,
    stack_size: int = engine.DEFAULT_STACK_SIZE,
) -> Hits | tuple[Hits, Counters]:
    """The closest hit of every ray with ``0 < t < tmax``.

    Args:
        structure: from ``accel.build``.
        origins, directions: float [N, 3] (converted to float32). Directions of any
            length within :data:`jrt.engine.DIRECTION_LENGTHS` ([1e-6, 1e6]); ``t`` and
            ``tmax`` are in units of that length (a distance for unit directions). A NaN
            or infinite origin or direction, a direction's length out of range (zero, say)
            or a NaN tmax is a ``ValueError`` naming the first such ray (inside a caller's
            ``jit``, where the values are unknown, such a ray is a miss).
        tmax: float [N] or a scalar; ``None`` for no limit. Keyword-only, as every option.
        kernel: ``"watertight"`` (default), ``"moller_trumbore"`` or ``"plane_barycentric"``.
        counters: also return :class:`jrt.Counters` (per-ray steps, triangle tests,
            leaves); a static option: without it the compiled traversal counts nothing.
        lanes, stack_size: the engine's persistent lanes per device (``None``: the
            backend's default, ``jrt.engine.default_lanes``: 512 on CPU, 65536 on GPU)
            and per-lane stack entries (both ignored by brute force). A stack overflow
            raises :class:`StackOverflowError`;
            a traversal that cannot end (arrays inconsistent with the structure's kind)
            raises :class:`jrt.engine.TraversalError`.

    Returns:
        :class:`jrt.Hits` (t inf and triangle -1 for a miss), and the counters if asked.
        Ties: the smallest t, then the lowest face index. A call compiles once per size
        bucket (:func:`bucket_size`), not per ray count.

    It vmaps natively: under ``jax.vmap`` (origins, directions, tmax batched or shared;
    nested or inside ``jit``) every item's rays go through one engine call, laid end to
    end, with each item's answers bit for bit those of its own call; a batched
    structure falls back to one call per item in turn (``lax.map``). See the module's
    docstring.
    """
    hits, count = _query_any(structure, origins, directions, tmax, kernel=kernel,
                             any_hit=False, counters=counters, lanes=lanes,
                             stack_size=stack_size)
    return (hits, count) if counters else hits


def occluded(
    structure: Structure,
    origins: Float[Array, "n 3"],
    directions: Float[Array, "n 3"],
    *,
    tmax: Float[Array, " n"] | float | None = None,
    kernel: str = DEFAULT_KERNEL,
    counters: bool = False,
    lanes: int | None = None,
    stack_size: int = engine.DEFAULT_STACK_SIZE,
) -> Bool[Array, " n"] | tuple[Bool[Array, " n"], Counters]:
    """bool [N]: is there any hit with ``0 < t < tmax``? Stops at the first one found.

    Arguments, options, directions and size buckets as :func:`closest_hit`. It vmaps
    natively as :func:`closest_hit` does (one engine call on all the items' rays; a
    batched structure: one call per item, ``lax.map``).
    """
    mask, count = _query_any(structure, origins, directions, tmax, kernel=kernel,
                             any_hit=True, counters=counters, lanes=lanes,
                             stack_size=stack_size)
    return (mask, count) if counters else mask


def as_numpy(hits: Hits) -> dict[str, np.ndarray]:
    """The hit record as NumPy arrays, keyed t, triangle, u, v."""
    return {k: np.asarray(v) for k, v in hits._asdict().items()}
