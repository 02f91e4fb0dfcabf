"""Case 4: self-intersection of reflected, refracted (n = 1.5) and shadow rays spawned at
hits, with no offset, a fixed epsilon 1e-4, a scene-scaled epsilon 1e-4 x diagonal, the
integer-ulp offset of Wächter & Binder (2019) and the renderer's pbrt-v4 offset.

The offsets, the hit frame and the secondary rays here serve case 5 (the same count
across scale and translation) and case 7 (the glass camel) as well.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from benchmarks.stability.common import (
    build,
    combos,
    joined_or_none,
    load,
    progress_bar,
    record,
    trace,
)
from benchmarks.stability.float64_oracle import oracle
from jrt import optics
from jrt.interaction import offset_ray_origin, surface_interaction

#: Offsets compared in cases 4 and 5.
METHODS = ("none", "fixed", "scaled", "ulp", "pbrt")
METHOD_LABELS = {
    "none": "no offset",
    "fixed": "fixed epsilon 1e-4 along the normal",
    "scaled": "scene-scaled epsilon 1e-4 x diagonal along the normal",
    "ulp": "integer-ulp offset along the normal (Wächter & Binder 2019)",
    "pbrt": "the renderer's pbrt-v4 error-bound offset (jrt.whitted)",
}
#: The secondary rays spawned at each hit (:func:`secondary_rays`).
SECONDARY = ("reflected", "refracted", "shadow")


def renderer_offset():
    """The renderers' pbrt-v4 origin offset (:func:`jrt.interaction.offset_ray_origin`)."""
    return offset_ray_origin


def pbrt_offset_numpy(point, error, n, w):
    """pbrt-v4 OffsetRayOrigin (section 6.8.6) in NumPy float32: a local copy for case 7,
    which must not depend on the renderer."""
    point, error, n, w = (np.asarray(a, np.float32) for a in (point, error, n, w))
    dist = (np.abs(n) * error).sum(axis=-1)
    offset = dist[..., None] * n
    offset = np.where(((w * n).sum(axis=-1) < 0)[..., None], -offset, offset)
    moved = (point + offset).astype(np.float32)
    away = np.where(offset > 0, np.inf, np.where(offset < 0, -np.inf, moved)).astype(np.float32)
    return np.nextafter(moved, away)


def ulp_offset(point, n):
    """Wächter & Binder, "A fast and robust method for avoiding self-intersection" (Ray
    Tracing Gems, 2019, ch. 6): move each coordinate by 256 n_i float32 ulps (integer
    arithmetic on the bit pattern), or by n_i / 65536 near the origin (|p_i| < 1/32).
    ``n`` points to the side the ray leaves to."""
    p = np.asarray(point, np.float32)
    n = np.asarray(n, np.float32)
    of_i = (256.0 * n).astype(np.int32)
    bits = p.view(np.int32)
    moved = (bits + np.where(p < 0, -of_i, of_i)).astype(np.int32).view(np.float32)
    return np.where(np.abs(p) < 1 / 32, p + np.float32(1 / 65536) * n, moved).astype(np.float32)


def surface_frame(vertices, faces, tri, u, v):
    """The hit point as the renderers compute it (:func:`jrt.interaction.surface_interaction`
    in float32: from the barycentrics, with its pbrt-v4 error bound gamma_7 sum |b_i p_i|),
    the outward geometric normal, and the float64 point from the same barycentrics."""
    vertices32 = np.asarray(vertices, np.float32)
    u32, v32 = u.astype(np.float32), v.astype(np.float32)
    tri = np.asarray(tri)
    zero = np.zeros((len(tri), 3), np.float32)  # no direction: only the point and normal
    surface = surface_interaction(vertices32, np.asarray(faces), tri, u32, v32, zero)
    p = vertices32[np.asarray(faces)[tri]]
    u64, v64 = u.astype(np.float64), v.astype(np.float64)
    b64 = np.stack([1 - u64 - v64, u64, v64], axis=-1)[..., None]
    point64 = (b64 * p.astype(np.float64)).sum(axis=1)
    return (np.asarray(surface.point, np.float32), np.asarray(surface.error, np.float32),
            np.asarray(surface.geometric_normal, np.float32), point64)


def spawn(method: str, point, error, n_facing, w, diagonal: float, offset_fn=None):
    """Origins of secondary rays ``w`` leaving ``point`` (normal ``n_facing`` on the side
    the primary ray came from) by one of :data:`METHODS`."""
    side = np.where(((w * n_facing).sum(axis=1) >= 0)[:, None], 1.0, -1.0).astype(np.float32)
    n_out = (side * n_facing).astype(np.float32)
    if method == "none":
        return point.astype(np.float32)
    if method == "fixed":
        return (point + np.float32(1e-4) * n_out).astype(np.float32)
    if method == "scaled":
        return (point + np.float32(1e-4 * diagonal) * n_out).astype(np.float32)
    if method == "ulp":
        return ulp_offset(point, n_out)
    if method == "pbrt":
        fn = offset_fn or renderer_offset()
        return np.asarray(fn(jnp.asarray(point), jnp.asarray(error), jnp.asarray(n_facing),
                             jnp.asarray(w)), np.float32)
    raise ValueError(f"unknown offset method {method!r}; allowed: {', '.join(METHODS)}")


def secondary_rays(vertices, faces, o, d, hits, lamp, n_glass=1.5):
    """Reflected, refracted and shadow directions at each hit (jrt.optics, float32).
    Returns (rows of hit rays, point, error, facing normal, point64, {type: (dirs, valid,
    tmax)})."""
    rows = np.flatnonzero(hits["triangle"] >= 0)
    tri = hits["triangle"][rows]
    point, error, ng, point64 = surface_frame(vertices, faces, tri, hits["u"][rows],
                                              hits["v"][rows])
    d = np.asarray(d, np.float32)[rows]
    nf, entering = (np.asarray(a) for a in optics.orient(d, ng))
    n1, n2 = (np.asarray(a) for a in optics.interface_indices(entering, np.float32(n_glass),
                                                              np.float32(1.0)))
    refl = np.asarray(optics.reflect(d, nf), np.float32)
    refr, tir = (np.asarray(a) for a in optics.refract(d, nf, n1, n2))
    to_lamp = (np.asarray(lamp, np.float32)[None] - point).astype(np.float32)
    dist = np.linalg.norm(to_lamp.astype(np.float64), axis=1)
    w = (to_lamp / np.maximum(dist, 1e-30)[:, None]).astype(np.float32)
    lit = (w * nf).sum(axis=1) > 0
    types = {"reflected": (refl, np.ones(len(rows), bool), None),
             "refracted": (refr.astype(np.float32), ~tir, None),
             "shadow": (w, lit, dist)}
    return rows, tri, point, error, nf, point64, types


def self_intersection(vertices, faces, structure, kernel, o, d, lamp, diagonal,
                      methods=METHODS, reference=True, offset_fn=None) -> dict:
    """Spawn reflected, refracted and shadow rays at every hit of (o, d) and count, per
    offset method, the re-hits of the source triangle ("self-hits") and, against a float64
    reference (the same directions from the float64 point, offset by 1e-9 of the scene
    size), the secondary rays whose hit differs ("wrong": self-hits, and geometry skipped
    by too large an offset)."""
    hits = trace(structure, o, d, kernel)
    rows, tri, point, error, nf, point64, types = secondary_rays(vertices, faces, o, d, hits,
                                                                 lamp)
    tris = vertices[faces]
    batch_o, batch_d, batch_tmax, tags = [], [], [], []
    refs = {}
    for kind_, (w, valid, dist) in types.items():
        sel = np.flatnonzero(valid)
        if reference and len(sel):
            side = np.where(((w[sel] * nf[sel]).sum(axis=1) >= 0)[:, None], 1.0, -1.0)
            eps = 1e-9 * (diagonal + np.abs(point64[sel]).max(axis=1, keepdims=True))
            o64 = point64[sel] + side * nf[sel].astype(np.float64) * eps
            tm = None if dist is None else dist[sel]
            refs[kind_] = oracle(tris, o64, w[sel].astype(np.float64), tm)
        for method in methods:
            start = spawn(method, point[sel], error[sel], nf[sel], w[sel], diagonal, offset_fn)
            batch_o.append(start)
            batch_d.append(w[sel])
            if dist is None:
                batch_tmax.append(np.full(len(sel), np.inf, np.float32))
            else:
                seg = np.asarray(lamp, np.float64)[None] - start.astype(np.float64)
                batch_tmax.append(np.linalg.norm(seg, axis=1).astype(np.float32))
            tags.append((kind_, method, sel))
    if not batch_o:
        return {"hits": 0, "table": {}}
    sec = trace(structure, np.concatenate(batch_o), np.concatenate(batch_d), kernel,
                np.concatenate(batch_tmax))
    table = {m: {} for m in methods}
    at = 0
    for kind_, method, sel in tags:
        part = {k: v[at:at + len(sel)] for k, v in sec.items()}
        at += len(sel)
        self_hit = part["triangle"] == tri[sel]
        entry = {"rays": int(len(sel)), "self_hits": int(self_hit.sum()),
                 "nan": int(np.isnan(part["t"]).sum())}
        if kind_ in refs:
            t_ref, tri_ref = refs[kind_]
            h, hr = part["triangle"] >= 0, tri_ref >= 0
            with np.errstate(invalid="ignore"):
                near = np.abs(part["t"] - t_ref) <= 1e-4 * diagonal + 1e-3 * np.abs(t_ref)
            wrong = (h != hr) | (h & hr & (part["triangle"] != tri_ref) & ~near)
            entry["wrong"] = int(wrong.sum())
        table[method][kind_] = entry
    return {"hits": int(len(rows)), "table": table}


def method_totals(table) -> dict:
    """Per offset method, the counts of :func:`self_intersection`'s table summed over the
    secondary ray types."""
    return {m: {"self_hits": sum(e["self_hits"] for e in t.values()),
                "wrong": sum(e.get("wrong", 0) for e in t.values()),
                "rays": sum(e["rays"] for e in t.values()),
                "nan": sum(e["nan"] for e in t.values())} for m, t in table.items()}


def lamp_position(vertices) -> np.ndarray:
    """The shadow rays' point light: 1.5 box diagonals from the box's centre, up and to
    one side (float64)."""
    v = np.asarray(vertices, np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    c = (lo + hi) / 2
    return c + 1.5 * np.linalg.norm(hi - lo) * np.array([0.3, 0.85, 0.43])


def case4(mesh: str = "camel", rays: int = 4096, pairs=None, methods=METHODS) -> dict:
    """Self-intersection of reflected, refracted (n = 1.5) and shadow rays spawned at the
    hits of incoherent rays, per offset method and kernel x structure."""
    from jrt.raysets import incoherent_set

    pairs = combos() if pairs is None else list(pairs)
    m = load(mesh)
    o, d = incoherent_set(m.vertices, rays, seed=4)
    records = []
    for kernel, kind in progress_bar(pairs, "case 4"):
        s = build(kind, m.vertices, m.faces, key=mesh)
        res = self_intersection(m.vertices, m.faces, s, kernel, o, d, lamp_position(m.vertices),
                                m.diagonal, methods)
        totals = method_totals(res["table"])
        records.append(record(4, kernel, kind, hits=res["hits"], methods=res["table"],
                              totals=totals,
                              self_hits={k: v["self_hits"] for k, v in totals.items()},
                              nan=sum(v["nan"] for v in totals.values())))
    return {"records": records, "findings": _findings4(records),
            "parameters": {"mesh": mesh, "primary_rays": rays, "methods": METHOD_LABELS,
                           "index": 1.5, "wrong": "secondary hit differs from the float64 "
                           "reference (hit/miss, or another triangle beyond 1e-4 diagonal + "
                           "1e-3 t)"}}


def _findings4(records) -> str:
    parts = []
    for method in METHODS:
        rows = [(r["kernel"], r["structure"], r["totals"][method]) for r in records
                if method in r["totals"]]
        if not rows:
            continue
        sh = [f"{k}/{s} {t['self_hits']}" for k, s, t in rows if t["self_hits"]]
        wr = max(t["wrong"] for _, _, t in rows)
        total = max(t["rays"] for _, _, t in rows)
        parts.append(f"{METHOD_LABELS[method]}: self-hits "
                     f"{joined_or_none(sh) if sh else f'0 in {total:,} rays everywhere'}, "
                     f"at most {wr} wrong hits.")
    return " ".join(parts)
