"""The float64 oracle and the comparison with it.

The oracle is jrt's ``watertight`` kernel evaluated in float64 (jrt's kernels are
dtype-generic: float64 arrays under ``jax.enable_x64(True)``, checked by
:func:`float64_kernels_ok`), by the suite's own brute force (:func:`brute_hits`), on the
same float32 geometry and rays as the traced ones. :func:`compare` classifies each traced
ray against the oracle's first crossing (cracks, false hits, borderline and near-origin
hits, NaN, the error in float32 ulps); :func:`libigl_like` is libigl 2.6's fixed-threshold
Möller–Trumbore, run by the same brute force.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jrt.kernels import KERNELS, cross, dot

#: Rays per call of the suite's own brute force (the oracle, the libigl-like kernel).
ORACLE_CHUNK = 1024
#: libigl 2.6, ``raytri.c`` (``intersect_triangle1``): |det| below this is "parallel".
LIBIGL_EPSILON = 1e-6


def libigl_like(origin, direction, v0, v1, v2):
    """Möller–Trumbore as libigl 2.6 writes it (``raytri.c``, ``intersect_triangle1``,
    called by ``igl::ray_mesh_intersect`` with ``t > 0``): a fixed absolute threshold,
    ``|det| < 1e-6``, rejects the ray as parallel whatever the triangle's size; the
    barycentric tests compare the unnormalised ``u``, ``u + v`` with ``det``."""
    e1 = v1 - v0
    e2 = v2 - v0
    p = cross(direction, e2)
    det = dot(e1, p)
    s = origin - v0
    q = cross(s, e1)
    u = dot(s, p)
    v = dot(direction, q)
    pos = (det > LIBIGL_EPSILON) & (u >= 0) & (u <= det) & (v >= 0) & (u + v <= det)
    neg = (det < -LIBIGL_EPSILON) & (u <= 0) & (u >= det) & (v <= 0) & (u + v >= det)
    inv = 1.0 / jnp.where(pos | neg, det, 1.0)
    t = dot(e2, q) * inv
    hit = (pos | neg) & (t > 0) & (t < jnp.inf)
    zero = jnp.zeros_like(t)
    return jnp.where(hit, t, jnp.inf), jnp.where(hit, u * inv, zero), jnp.where(hit, v * inv,
                                                                               zero)


_KERNEL_FNS = {**KERNELS, "libigl_like": libigl_like}


def _merge_smallest(best_t, best_i, t, rows):
    """Each ray's k smallest (t, row) pairs, sorted, (``best_t``, ``best_i``) [R, k] with
    a chunk's ``t`` and ``rows`` [T, R] merged in (its rows above every row in ``best_i``).

    The chunk's hits are taken one at a time, smallest (t, row) first, for as long as some
    ray has one below its k-th: a ray crosses few of a chunk's triangles, so this is a few
    passes over the chunk, where a top-k of the concatenation sorts it (XLA:CPU's top-k is
    fast for float32 only: case 1's float64 oracle on 10,000 rays of the camel took 80 s
    that way and 9.5 s this way, 2 cores). An entering hit goes after the entries of equal
    t, which have lower rows.
    """
    slot = lax.broadcasted_iota(jnp.int32, best_t.shape, 1)

    def take_next(state):
        best_t, best_i, t, m = state
        row = jnp.where(t == m[None], rows, jnp.iinfo(jnp.int32).max).min(axis=0)
        enter = (m < best_t[:, -1])[:, None]
        at = (best_t <= m[:, None]).sum(axis=1, dtype=jnp.int32)[:, None]
        after = slot > at

        def insert(best, value):
            shifted = jnp.concatenate([best[:, :1], best[:, :-1]], axis=1)
            new = jnp.where(slot == at, value[:, None], jnp.where(after, shifted, best))
            return jnp.where(enter, new, best)

        best_t, best_i = insert(best_t, m), insert(best_i, row)
        t = jnp.where(rows == row[None], jnp.inf, t)
        return best_t, best_i, t, t.min(axis=0)

    def more(state):
        best_t, _, _, m = state
        return jnp.any(m < best_t[:, -1])

    best_t, best_i, _, _ = lax.while_loop(more, take_next, (best_t, best_i, t, t.min(axis=0)))
    return best_t, best_i


@functools.partial(jax.jit, static_argnames=("kernel", "k", "ray_chunk"))
def _brute_topk(tris, bases, o, d, tmax, *, kernel, k, ray_chunk=256):
    """The ``k`` smallest t of every ray and their triangle rows (lowest row first among
    equal t: the k smallest (t, row) pairs). ``tris`` [C, T, 3, 3] chunked triangles,
    ``bases`` [C] first rows."""
    n = o.shape[0]
    o = o.reshape(n // ray_chunk, ray_chunk, 3)
    d = d.reshape(n // ray_chunk, ray_chunk, 3)
    tmax = tmax.reshape(n // ray_chunk, ray_chunk)
    big = jnp.iinfo(jnp.int32).max

    def per_rays(args):
        o, d, tm = args

        def body(carry, xs):
            best_t, best_i = carry
            tri, base = xs
            t, _, _ = kernel(o[None], d[None], tri[:, None, 0], tri[:, None, 1],
                             tri[:, None, 2])
            t = jnp.where(t < tm[None], t, jnp.inf)  # [T, R]
            rows = base + lax.broadcasted_iota(jnp.int32, t.shape, 0)
            if k == 1:
                m = t.min(axis=0)
                row = jnp.where((t == m[None]) & (t < jnp.inf), rows, big).min(axis=0)
                better = m < best_t[:, 0]
                return (jnp.where(better, m, best_t[:, 0])[:, None],
                        jnp.where(better, row, best_i[:, 0])[:, None]), None
            return _merge_smallest(best_t, best_i, t, rows), None

        init = (jnp.full((ray_chunk, k), jnp.inf, o.dtype),
                jnp.full((ray_chunk, k), big, jnp.int32))
        (best_t, best_i), _ = lax.scan(body, init, (tris, bases))
        return best_t, jnp.where(best_t < jnp.inf, best_i, -1)

    t, i = lax.map(per_rays, (o, d, tmax))
    return t.reshape(n, k), i.reshape(n, k)


def brute_hits(triangles, origins, directions, kernel="watertight", tmax=None, k=1,
               dtype=np.float32, tri_chunk=1024) -> tuple[np.ndarray, np.ndarray]:
    """(t [N, k], row [N, k]): each ray's k nearest hits over ``triangles`` [T, 3, 3] by
    brute force with ``kernel`` (a name of jrt.KERNELS or ``"libigl_like"``), evaluated in
    ``dtype`` (float64 under ``jax.enable_x64``). Rows are triangle indices, -1 for none."""
    fn = _KERNEL_FNS[kernel] if isinstance(kernel, str) else kernel
    tris = np.asarray(triangles, dtype)
    count = len(tris)
    chunks = max(1, -(-count // tri_chunk))
    padded = np.zeros((chunks * tri_chunk, 3, 3), dtype)  # zero triangles: never hit
    padded[:count] = tris
    padded = padded.reshape(chunks, tri_chunk, 3, 3)
    bases = np.arange(chunks, dtype=np.int32) * tri_chunk
    origins = np.asarray(origins, dtype)
    directions = np.asarray(directions, dtype)
    n = len(origins)
    tmax = np.full(n, np.inf) if tmax is None else np.broadcast_to(np.asarray(tmax), (n,))
    out_t, out_i = [], []
    with jax.enable_x64(dtype == np.float64):
        for start in range(0, max(n, 1), ORACLE_CHUNK):
            m = min(ORACLE_CHUNK, n - start)
            o = np.zeros((ORACLE_CHUNK, 3), dtype)
            d = np.tile(np.asarray([0, 0, 1], dtype), (ORACLE_CHUNK, 1))
            tm = np.zeros(ORACLE_CHUNK, dtype)
            o[:m], d[:m] = origins[start:start + m], directions[start:start + m]
            tm[:m] = tmax[start:start + m]
            t, i = _brute_topk(padded, bases, o, d, tm, kernel=fn, k=k)
            out_t.append(np.asarray(t, np.float64)[:m])
            out_i.append(np.asarray(i, np.int64)[:m])
    if n == 0:
        return np.zeros((0, k)), np.zeros((0, k), np.int64)
    return np.concatenate(out_t), np.concatenate(out_i)


def oracle(triangles, origins, directions, tmax=None, k=1):
    """The float64 oracle: watertight in float64, brute force. (t [N], row [N]) for k=1."""
    t, i = brute_hits(triangles, origins, directions, "watertight", tmax, k, np.float64)
    return (t[:, 0], i[:, 0]) if k == 1 else (t, i)


def float64_kernels_ok() -> bool:
    """Do jrt's kernels compute in float64 when given float64 arrays under x64?"""
    with jax.enable_x64(True):
        o = jnp.asarray([[0.1, 0.2, -1.0]], jnp.float64)
        d = jnp.asarray([[0.0, 0.0, 1.0]], jnp.float64)
        v = [jnp.asarray(c, jnp.float64) for c in ([-1.0, -1, 0], [1.0, -1, 0], [0.0, 1, 0])]
        return all(fn(o, d, *v)[0].dtype == jnp.float64 for fn in KERNELS.values())


# --- Comparison with the oracle --------------------------------------------------------------

def ulp32(x) -> np.ndarray:
    """The float32 spacing at |x| (as float64); the smallest subnormal at 0."""
    x = np.abs(np.asarray(x, np.float64))
    with np.errstate(over="ignore", invalid="ignore"):
        return np.spacing(np.minimum(x, np.finfo(np.float32).max).astype(np.float32)).astype(
            np.float64)


#: A hit point no farther than this (relative to the coordinates' magnitude, about 64
#: float32 ulps) outside the reported triangle is a rounding-level ("borderline") hit.
BORDER = 2.0**-17


def outside_distance(triangles, rows, o, d, t) -> np.ndarray:
    """How far (float64, absolute) the point ``o + t d`` lies outside triangle ``rows``,
    measured in its plane: max over edges of -lambda_i x h_i (h_i the triangle's height
    over edge i); and the coordinates' magnitude there, for :data:`BORDER`."""
    tri = np.asarray(triangles, np.float64)[np.maximum(rows, 0)]
    p = np.asarray(o, np.float64) + np.asarray(t, np.float64)[:, None] * np.asarray(d,
                                                                                  np.float64)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    nn = np.maximum((n * n).sum(axis=1), 1e-300)
    lam = np.stack([(np.cross(c - b, p - b) * n).sum(axis=1),
                    (np.cross(a - c, p - c) * n).sum(axis=1),
                    (np.cross(b - a, p - a) * n).sum(axis=1)], axis=1) / nn[:, None]
    edges = [np.linalg.norm(c - b, axis=1), np.linalg.norm(a - c, axis=1),
             np.linalg.norm(b - a, axis=1)]
    heights = np.stack([np.sqrt(nn) / np.maximum(e, 1e-300) for e in edges], axis=1)
    outside = np.maximum(-lam, 0) * heights
    scale = np.maximum(np.abs(p).max(axis=1), np.abs(np.asarray(o, np.float64)).max(axis=1))
    scale = np.maximum(scale, np.abs(tri).max(axis=(1, 2)))
    return outside.max(axis=1), scale


#: Hits closer to the origin than this fraction of the origin's largest coordinate are
#: "near the origin": within the band where a float32 kernel cannot resolve t (watertight
#: rejects them by pbrt's error bound, by design: a ray leaving a surface must not hit it
#: again). They are counted apart, neither cracks nor false hits.
NEAR = 2.0**-12


def compare(hits: dict, t_ref, rel_tol: float, abs_tol=0.0, geometry=None,
            ref_rows=None) -> dict:
    """Classify each ray against the oracle's first crossing ``t_ref`` (inf: none).

    Within ``rel_tol * t_ref + abs_tol`` (plus 64 float32 ulps of the origin's largest
    coordinate) of ``t_ref`` is the same crossing. A crack: the oracle hits and the traced
    ray does not reach that crossing (a miss, or a hit beyond it: a pass-through). A false
    hit: a hit where the oracle has none, or before its crossing. With ``geometry =
    (triangles, origins, directions)``: a false hit whose point lies within
    :data:`BORDER` of the reported triangle is "borderline" instead (a ray grazing an edge
    or a vertex that float32 rounds onto the triangle and float64 just off it), and hits
    within :data:`NEAR` of the origin are "near_origin", as are (with the oracle's
    triangles ``ref_rows``) hits of a ray that starts within 2^-16 |origin| of the plane
    of the triangle it hits (a ray starting on a surface, at a grazing angle). Error:
    |t - t_ref| in float32 ulps of max(t_ref, |origin|), over the agreeing rays.
    """
    t = np.asarray(hits["t"], np.float64)
    t_ref = np.asarray(t_ref, np.float64)
    nan = np.isnan(t) | np.isnan(hits["u"]) | np.isnan(hits["v"])
    hit = np.isfinite(t)
    ref_hit = np.isfinite(t_ref)
    scale = np.zeros_like(t) if geometry is None else np.abs(
        np.asarray(geometry[1], np.float64)).max(axis=1)
    with np.errstate(invalid="ignore"):
        near = (ref_hit & (t_ref <= NEAR * scale)) | (hit & (t <= NEAR * scale))
        if geometry is not None and ref_rows is not None:
            tri = np.asarray(geometry[0], np.float64)[np.maximum(ref_rows, 0)]
            n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
            cos = np.abs((n * np.asarray(geometry[2], np.float64)).sum(axis=1))
            near |= ref_hit & (ref_rows >= 0) & (t_ref * cos <= 2.0**-16 * scale)
        tol = rel_tol * np.where(ref_hit, t_ref, 0.0) + abs_tol + 64 * ulp32(scale)
        same = hit & ref_hit & (np.abs(t - t_ref) <= tol)
        miss = ref_hit & ~hit & ~near
        beyond = ref_hit & hit & (t > t_ref + tol) & ~near
        false = hit & (~ref_hit | (t < t_ref - tol)) & ~near
        err = np.abs(t - t_ref) / ulp32(np.maximum(t_ref, scale))
    border = np.zeros_like(false)
    if geometry is not None and false.any() and "triangle" in hits:
        tris, o, d = geometry
        rows = np.flatnonzero(false)
        dist, mag = outside_distance(tris, hits["triangle"][rows], np.asarray(o)[rows],
                                     np.asarray(d)[rows], t[rows])
        border[rows] = dist <= BORDER * mag
    return {"miss": miss, "pass_through": beyond, "crack": miss | beyond,
            "false": false & ~border, "borderline": border, "near": near, "nan": nan,
            "same": same, "err_ulps": np.where(same, err, 0.0)}


def pairwise_hits(tris, o, d, kernel, dtype, full=False):
    """Ray i against triangle i only, with a kernel evaluated in ``dtype``."""
    fn = _KERNEL_FNS[kernel]
    tris = np.asarray(tris, dtype)
    with jax.enable_x64(dtype == np.float64):
        t, u, v = jax.jit(fn)(jnp.asarray(o, dtype), jnp.asarray(d, dtype),
                              jnp.asarray(tris[:, 0]), jnp.asarray(tris[:, 1]),
                              jnp.asarray(tris[:, 2]))
        t, u, v = (np.asarray(a, np.float64) for a in (t, u, v))
    return (t, u, v) if full else (t, None)
