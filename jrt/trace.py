"""Public ray queries: any structure, any triangle kernel, one call site.

    hits = jrt.closest_hit(structure, origins, directions, kernel="watertight", tmax=None)
    mask = jrt.occluded(structure, origins, directions, tmax)

``structure`` comes from ``accel.build(name, vertices, faces)``. Directions are expected to
be unit vectors (seed, Proposition 2.1: a ray is a point and a unit vector), so that ``t``
is a distance; the kernels themselves are affine and return ``t`` in units of the
direction's length.
"""

from __future__ import annotations

import importlib

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

import accel
from accel.structure import Structure
from jrt import brute, engine
from jrt import structure as _structure  # noqa: F401  (registers Structure as a pytree)
from jrt.engine import Counters, StackOverflowError, TraversalError
from jrt.hits import Hits
from jrt.kernels import DEFAULT_KERNEL, get_kernel

#: Every structure kind. Each but brute force is stepped by the engine: module
#: ``jrt.<kind>`` gives ``traversal(structure) -> jrt.engine.Traversal``.
KINDS = accel.NAMES


def traversal_of(structure: Structure) -> engine.Traversal:
    """The engine traversal of a structure (from its module ``jrt.<kind>``)."""
    return importlib.import_module(f"jrt.{structure.kind}").traversal(structure)


def _check_rays(origins, directions, tmax, values: bool = True):
    """The rays as float32 arrays of consistent shapes (else a ValueError); their values
    too with ``values`` (the engine's structures check them in their own pass, see
    :func:`_raise_on_status`)."""
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
    if values:
        _check_ray_values(origins, directions, tmax)
    return origins, directions, tmax


def _check_ray_values(origins, directions, tmax):
    """NaN or infinite origins and directions, zero directions and NaN tmax are errors,
    never silent misses. Checked where the values are known (outside a caller's jit);
    inside one, such rays trace as misses (``t = inf``), which is documented."""
    if any(isinstance(a, jax.core.Tracer) for a in (origins, directions, tmax)):
        return
    # One fused pass on the device first (NumPy's took 53 ms of a 283 ms call on 1M rays);
    # the rays are copied to the host only to name a bad one.
    if not bool(_any_bad_ray(origins, directions, tmax)):
        return
    o, d, t = np.asarray(origins), np.asarray(directions), np.asarray(tmax)
    for name, bad, allowed in engine.ray_problems(np, o, d, t):
        if bad.any():
            first = int(np.flatnonzero(bad)[0])
            value = (o if name == "origins" else d if name == "directions" else t)[first]
            raise ValueError(
                f"{name} of ray {first} is {np.asarray(value).tolist()} ({int(bad.sum())} "
                f"such rays of {len(bad)}); allowed: {allowed}")


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
    if structure.kind not in KINDS:
        raise ValueError(f"no traversal for structure kind {structure.kind!r}; "
                         f"allowed: {', '.join(KINDS)}")
    arrays, layout = accel.SIGNATURES[structure.kind]
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
    if status & engine.STATUS_BAD_RAYS:
        _check_ray_values(*rays)
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


def _engine_query(structure, origins, directions, tmax, kernel, any_hit, counters, lanes,
                  stack_size):
    _check_options(lanes, stack_size)
    # The arrays and layout were checked against the kind (_check_structure).
    hits, count, status = engine.traverse(
        traversal_of(structure), structure.arrays, origins, directions, tmax, kernel=kernel,
        any_hit=any_hit, lanes=lanes, stack_size=stack_size, counters=counters)
    _raise_on_status(status, stack_size, (origins, directions, tmax))
    if count is not None:
        count = Counters(steps=count[:, 0], tests=count[:, 1], leaves=count[:, 2])
    return hits, count


def closest_hit(
    structure: Structure,
    origins: Float[Array, "n 3"],
    directions: Float[Array, "n 3"],
    kernel: str = DEFAULT_KERNEL,
    tmax: Float[Array, " n"] | float | None = None,
    *,
    counters: bool = False,
    lanes: int | None = None,
    stack_size: int = engine.DEFAULT_STACK_SIZE,
) -> Hits | tuple[Hits, Counters]:
    """The closest hit of every ray with ``0 < t < tmax``.

    Args:
        structure: from ``accel.build``.
        origins, directions: float32 [N, 3]; directions of unit length.
        kernel: ``"watertight"`` (default), ``"moller_trumbore"`` or ``"plane_barycentric"``.
        tmax: float32 [N] or a scalar; ``None`` for no limit.
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
        Ties: the smallest t, then the lowest face index.
    """
    _check_structure(structure)
    get_kernel(kernel)
    origins, directions, tmax = _check_rays(origins, directions, tmax,
                                            values=structure.kind == "brute")
    if structure.kind != "brute":
        hits, count = _engine_query(structure, origins, directions, tmax, kernel, False,
                                    counters, lanes, stack_size)
        return (hits, count) if counters else hits
    if counters:
        raise ValueError("counters are available for the engine's structures, not brute "
                         "force (which tests every triangle)")
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
    *,
    counters: bool = False,
    lanes: int | None = None,
    stack_size: int = engine.DEFAULT_STACK_SIZE,
) -> Bool[Array, " n"] | tuple[Bool[Array, " n"], Counters]:
    """bool [N]: is there any hit with ``0 < t < tmax``? Stops at the first one found.

    Options as :func:`closest_hit`.
    """
    _check_structure(structure)
    get_kernel(kernel)
    origins, directions, tmax = _check_rays(origins, directions, tmax,
                                            values=structure.kind == "brute")
    if structure.kind != "brute":
        hits, count = _engine_query(structure, origins, directions, tmax, kernel, True,
                                    counters, lanes, stack_size)
        mask = hits.triangle >= 0
        return (mask, count) if counters else mask
    if counters:
        raise ValueError("counters are available for the engine's structures, not brute "
                         "force (which tests every triangle)")
    return brute.occluded(structure["triangles"], origins, directions, tmax, kernel=kernel)


def as_numpy(hits: Hits) -> dict[str, np.ndarray]:
    """The hit record as NumPy arrays, keyed t, triangle, u, v."""
    return {k: np.asarray(v) for k, v in hits._asdict().items()}
