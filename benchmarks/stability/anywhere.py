"""Case 5: scale (10^-6..10^6) and translation (10^0..10^7) of the camel: every
structure's build against the camel at the origin, aimed rays (a miss is a crack), hits
against brute force bit for bit, primary hit sets against the untranslated float64
reference, case 4's self-hits per offset method; pbrt-style random triangles with
coordinates 10^U(-8, 8)."""

from __future__ import annotations

import numpy as np

import accel
from benchmarks.stability.closed_mesh import aimed_rays
from benchmarks.stability.common import (
    KERNEL_NAMES,
    build,
    build_guarded,
    combos,
    load,
    max_or_none,
    progress_bar,
    record,
    trace,
)
from benchmarks.stability.float64_oracle import oracle, pairwise_hits
from benchmarks.stability.offsets import (
    METHOD_LABELS,
    METHODS,
    lamp_position,
    method_totals,
    renderer_offset,
    self_intersection,
    spawn,
    surface_frame,
)


def transformed(mesh, scale: float, shift: float):
    """Vertices ``float32(scale x V + shift x (1, 0.75, 0.5))`` (the transform in float64)."""
    vec = np.array([1.0, 0.75, 0.5])
    return (mesh.vertices.astype(np.float64) * scale + shift * vec).astype(np.float32), vec


def random_triangle_reintersection(count: int, directions: int, pairs_kernels,
                                   methods=METHODS, seed: int = 6, offset_fn=None) -> dict:
    """pbrt-v4's "Triangle reintersect" test: triangles with coordinates 10^U(-8, 8), a
    random point on each (from barycentrics, with its error bound), rays in random
    directions spawned there: any hit of the same triangle is a self-hit."""
    rng = np.random.default_rng(seed)
    tris = (10.0 ** rng.uniform(-8, 8, (count, 3, 3))).astype(np.float32)
    area2 = np.linalg.norm(np.cross((tris[:, 1] - tris[:, 0]).astype(np.float64),
                                    (tris[:, 2] - tris[:, 0]).astype(np.float64)), axis=1)
    ok = area2 > 0
    tris = tris[ok]
    b = rng.dirichlet([1, 1, 1], len(tris)).astype(np.float32)
    u, v = b[:, 1].astype(np.float64), b[:, 2].astype(np.float64)
    verts = tris.reshape(-1, 3)
    faces = np.arange(len(verts)).reshape(-1, 3)
    point, error, ng, _ = surface_frame(verts, faces, np.arange(len(tris)), u, v)
    rep = np.repeat(np.arange(len(tris)), directions)
    w = rng.normal(size=(len(rep), 3))
    w = (w / np.linalg.norm(w, axis=1, keepdims=True)).astype(np.float32)
    diag = np.linalg.norm((tris.max(axis=1) - tris.min(axis=1)).astype(np.float64), axis=1)
    out = {}
    for method in methods:
        if method == "scaled":  # each triangle is its own scene: its own diagonal
            side = np.where(((w * ng[rep]).sum(axis=1) >= 0)[:, None], 1.0, -1.0)
            starts = (point[rep] + (1e-4 * diag[rep])[:, None].astype(np.float32)
                      * (side * ng[rep]).astype(np.float32)).astype(np.float32)
        else:
            starts = spawn(method, point[rep], error[rep], ng[rep], w, 1.0, offset_fn)
        out[method] = {}
        for kernel in pairs_kernels:
            t, _ = pairwise_hits(tris[rep], starts, w, kernel, np.float32)
            out[method][kernel] = {"rays": int(len(rep)),
                                   "self_hits": int(np.isfinite(t).sum()),
                                   "nan": int(np.isnan(t).sum())}
    return {"triangles": int(len(tris)), "skipped_degenerate": int((~ok).sum()),
            "directions_per_triangle": directions, "table": out}


def case5(mesh: str = "camel-19k", rays: int = 2048,
          scales=(1e-6, 1e-4, 1e-2, 1.0, 1e2, 1e4, 1e6),
          shifts=(1.0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7), pairs=None, methods=METHODS,
          random_triangles: int = 1000, directions: int = 10, reference=True,
          aimed: int = 2048) -> dict:
    """Scale and translation sweeps of the camel: every structure's build (time, memory,
    references per leaf, against the camel at the origin), ``aimed`` rays from inside
    aimed at the placed camel's vertices and edge midpoints (a miss is a crack), every
    structure's hits against brute force's bit for bit, primary hit sets against the
    untranslated float64 reference, and case 4's self-hits per offset method; then
    pbrt's random triangles with coordinates 10^U(-8, 8)."""
    from jrt.raysets import incoherent_set

    if pairs is None:  # every kernel on brute force, watertight on every structure
        pairs = combos(KERNEL_NAMES, ("brute",)) + combos(("watertight",),
                                                          accel.names(engine=True))
    pairs = list(pairs)
    m = load(mesh)
    o0, d0 = incoherent_set(m.vertices, rays, seed=5)
    t_ref, tri_ref = oracle(m.vertices[m.faces], o0, d0)  # untranslated, unscaled, float64
    configs = [(s, 0.0) for s in scales] + [(1.0, t) for t in shifts]
    records = []
    offset_fn = renderer_offset() if "pbrt" in methods else None
    sweep = {(k, s): [] for k, s in pairs}
    builds = {kind: [] for _, kind in pairs if kind != "brute"}
    for scale, shift in progress_bar(configs, "case 5 sweep"):
        v, vec = transformed(m, scale, shift)
        o = (o0.astype(np.float64) * scale + shift * vec).astype(np.float32)
        ao, ad = aimed_rays(v, m.faces, aimed, seed=12) if aimed else (o[:0], d0[:0])
        diag = float(np.linalg.norm(v.max(axis=0).astype(np.float64) - v.min(axis=0)))
        lamp = lamp_position(m.vertices) * scale + shift * vec
        built, brute_hits = {}, {}
        for kernel, kind in pairs:
            if kind not in built:  # a failed build is a finding, not a crash
                built[kind] = (build(kind, v, m.faces) if kind == "brute"
                               else build_guarded(kind, v, m.faces, repeat=2))
                if kind != "brute":
                    builds[kind].append(_build_row(built[kind], scale, shift))
            s = built[kind]
            if isinstance(s, str):
                sweep[(kernel, kind)].append({"scale": scale, "shift": shift,
                                              "build_error": s})
                continue
            if kernel not in brute_hits:  # brute force's hits on both sets, this kernel
                b = built["brute"] if kind == "brute" else build("brute", v, m.faces)
                brute_hits[kernel] = (trace(b, o, d0, kernel), trace(b, ao, ad, kernel))
            hits, at_aim = (brute_hits[kernel] if kind == "brute" else
                            (trace(s, o, d0, kernel), trace(s, ao, ad, kernel)))
            differ = (_bits_differ(hits, brute_hits[kernel][0])
                      + _bits_differ(at_aim, brute_hits[kernel][1]))
            h, hr = hits["triangle"] >= 0, tri_ref >= 0
            t = hits["t"] / scale
            with np.errstate(invalid="ignore"):
                rel = np.abs(t - t_ref) / np.abs(t_ref)
                tie = h & hr & (rel <= 1e-4)
            mism = (h != hr) | (h & hr & (hits["triangle"] != tri_ref) & ~tie)
            res = self_intersection(v, m.faces, s, kernel, o, d0, lamp, diag, methods,
                                    reference, offset_fn)
            totals = method_totals(res["table"])
            sweep[(kernel, kind)].append({
                "scale": scale, "shift": shift, "aimed_rays": int(len(ao)),
                "cracks": int((at_aim["triangle"] < 0).sum()),
                "mismatches_vs_brute": differ, "hit_mismatches": int(mism.sum()),
                "hit_or_miss_changed": int((h != hr).sum()),
                "max_rel_t_error": max_or_none(rel[h & hr & (hits["triangle"] == tri_ref)]),
                "nan": int(np.isnan(hits["t"]).sum()), "secondary_rays": totals})
    for (kernel, kind), all_rows in sweep.items():
        rows = [r for r in all_rows if "build_error" not in r]
        self_hits = {mm: sum(r["secondary_rays"][mm]["self_hits"] for r in rows)
                     for mm in methods}
        records.append(record(5, kernel, kind, rays=rays, sweep=rows, self_hits=self_hits,
                              cracks=sum(r["cracks"] for r in rows
                                         if r["shift"] <= ANYWHERE_UP_TO),
                              cracks_beyond=sum(r["cracks"] for r in rows
                                                if r["shift"] > ANYWHERE_UP_TO),
                              mismatches_vs_brute=sum(r["mismatches_vs_brute"] for r in rows),
                              hit_mismatches=sum(r["hit_mismatches"] for r in rows),
                              nan=sum(r["nan"] + sum(v["nan"] for v in
                                                     r["secondary_rays"].values())
                                      for r in rows),
                              build_errors=[r for r in all_rows if "build_error" in r]))
    anywhere = [_anywhere_record(kind, rows, [r for r in records if r["structure"] == kind])
                for kind, rows in builds.items()]
    rand = random_triangle_reintersection(random_triangles, directions, KERNEL_NAMES, methods,
                                          offset_fn=offset_fn) if random_triangles else None
    return {"records": anywhere + records, "random_triangles": rand,
            "findings": _findings_anywhere(anywhere) + " " + _findings5(records, rand),
            "parameters": {"mesh": mesh, "rays": rays, "scales": list(scales),
                           "shifts": list(shifts), "shift_direction": [1, 0.75, 0.5],
                           "methods": METHOD_LABELS,
                           "reference": "primary: the untranslated, unscaled camel in "
                                        "float64 (t divided by the scale); secondary: the "
                                        "float64 oracle on the transformed float32 mesh"}}


def _bits_differ(a: dict, b: dict) -> int:
    """Rays whose t, triangle, u or v differ in any bit (NaN equal to NaN)."""
    out = np.zeros(len(a["t"]), bool)
    for key in ("t", "triangle", "u", "v"):
        x, y = np.asarray(a[key]), np.asarray(b[key])
        same = (x == y) | (np.isnan(x) & np.isnan(y)) if x.dtype.kind == "f" else x == y
        out |= ~same
    return int(out.sum())


def _build_row(s, scale: float, shift: float) -> dict:
    """One build of the sweep: time, bytes, references per leaf (triangles for the BVH)."""
    if isinstance(s, str):
        return {"scale": scale, "shift": shift, "build_error": s}
    per_leaf = s.stats.get("references_per_leaf_mean", s.stats.get("triangles_per_leaf_mean"))
    return {"scale": scale, "shift": shift, "build_seconds": s.stats["build_seconds"],
            "bytes": s.nbytes, "triangles": s.num_triangles,
            "references": int(s.stats.get("references", s.num_triangles)),
            "references_per_leaf": per_leaf, "leaves": s.stats.get("leaves")}


#: The shifts up to which every structure must build as at the origin (float32 keeps
#: 24 - log2(shift / size) bits of the camel's shape: about 4 at 10^6, none at 10^7).
ANYWHERE_UP_TO = 1e6


def _anywhere_record(kind: str, rows: list, traced: list) -> dict:
    """One structure over the sweep: its build's worst ratios to the camel at the origin
    (scale 1, shift 0) up to :data:`ANYWHERE_UP_TO`, cracks and mismatches with brute
    force (watertight), and what happened beyond."""
    origin = next((r for r in rows if r["scale"] == 1.0 and r["shift"] == 0.0
                   and "build_error" not in r), None)
    within = [r for r in rows if r["shift"] <= ANYWHERE_UP_TO]
    failed = [r for r in within if "build_error" in r]
    ok = [r for r in within if "build_error" not in r]

    def worst(key):
        if origin is None or not ok:
            return None, None
        r = max(ok, key=lambda r: r[key] / origin[key])
        return r[key] / origin[key], _config(r)

    time_x, time_at = worst("build_seconds")
    memory_x, memory_at = worst("bytes")
    per_leaf = [r["references_per_leaf"] for r in ok if r["references_per_leaf"]]
    water = [r for r in traced if r["kernel"] == "watertight"]
    beyond = [r for r in rows if r["shift"] > ANYWHERE_UP_TO]
    return {"case": 5, "check": "builds anywhere", "kernel": "watertight", "structure": kind,
            "configs": len(within), "build_failures": len(failed),
            "worst_build_time_x_origin": time_x, "at": time_at,
            "worst_memory_x_origin": memory_x, "memory_at": memory_at,
            "references_per_leaf_at_origin": origin and origin["references_per_leaf"],
            "references_per_leaf_max": max(per_leaf) if per_leaf else None,
            # (Not "cracks": the per-kernel records count those, and the report sums them.)
            "aimed_misses": sum(c["cracks"] for r in water for c in r["sweep"]
                                if c["shift"] <= ANYWHERE_UP_TO),
            "mismatches_vs_brute": sum(c["mismatches_vs_brute"] for r in water
                                       for c in r["sweep"] if c["shift"] <= ANYWHERE_UP_TO),
            "beyond": [{"shift": r["shift"], **({"build_error": r["build_error"]}
                                                if "build_error" in r else
                                                {"triangles": r["triangles"],
                                                 "bytes": r["bytes"]})} for r in beyond],
            "builds": rows,
            "traced": [{k: c[k] for k in ("scale", "shift", "cracks", "mismatches_vs_brute")}
                       for r in water for c in r["sweep"]]}


def _findings_anywhere(records) -> str:
    if not records:
        return ""
    parts = []
    fine = [r for r in records if not r["build_failures"]
            and (r["worst_build_time_x_origin"] or 0) <= 2
            and (r["worst_memory_x_origin"] or 0) <= 2 and not r["aimed_misses"]
            and not r["mismatches_vs_brute"]]
    if fine:
        parts.append(
            "Every scale and every shift up to 10^6: " + ", ".join(
                f"{r['structure']} (at most {r['worst_build_time_x_origin']:.2f}x the build "
                f"time and {r['worst_memory_x_origin']:.2f}x the memory at the origin)"
                for r in fine)
            + " build as at the origin, with no crack and brute force's hits bit for bit "
              "(watertight, on the incoherent and the aimed rays). The structures are built "
              "in a local frame (a point of the mesh's box) and a reference's margin is "
              "2^-16 of its cell's size and of its triangle's own extent "
              "(accel.geometry.reference_margin), neither of which depends on where the "
              "mesh sits.")
    for r in records:
        if r in fine:
            continue
        parts.append(f"{r['structure']}: {r['build_failures']} failed builds, worst time "
                     f"{r['worst_build_time_x_origin'] or 0:.2f}x ({r['at']}), worst memory "
                     f"{r['worst_memory_x_origin'] or 0:.2f}x ({r['memory_at']}), "
                     f"{r['aimed_misses']} aimed rays missing (up to 10^6), "
                     f"{r['mismatches_vs_brute']} rays unlike brute "
                     "force's.")
    beyond = {b["shift"] for r in records for b in r["beyond"]}
    for shift in sorted(beyond):
        tri = {b.get("triangles") for r in records for b in r["beyond"]
               if b["shift"] == shift}
        cracks = sum(c["cracks"] for r in records for c in r.get("traced", [])
                     if c["shift"] == shift)
        parts.append(f"At shift {shift:g} float32 has no bits left for the camel's shape "
                     f"(its ulp there exceeds the camel's size): "
                     f"{', '.join(str(t) for t in sorted(x for x in tri if x is not None))} "
                     "of its triangles keep a non-zero area, every structure builds over "
                     "what is left, and what is left is no longer a closed surface: "
                     f"{cracks} of the aimed rays pass through it, under every structure "
                     "and brute force alike.")
    return " ".join(parts)


def _config(row) -> str:
    return f"scale {row['scale']:g}" if row["shift"] == 0 else f"shift {row['shift']:g}"


def _findings5(records, rand) -> str:
    parts = []
    for method in METHODS:
        if not any(method in r["self_hits"] for r in records):
            continue
        bad = {}
        for r in records:
            for row in r["sweep"]:
                e = row["secondary_rays"].get(method)
                if e and e["self_hits"]:
                    where = bad.setdefault(r["kernel"], {})
                    where[_config(row)] = max(where.get(_config(row), 0), e["self_hits"])
        kernels = sorted({r["kernel"] for r in records})
        clean = [k for k in kernels if k not in bad]
        text = f"{METHOD_LABELS[method]}: "
        if clean:
            text += f"zero self-hits across the whole sweep for {', '.join(clean)}"
        if bad:
            text += ("; " if clean else "") + "self-hits " + "; ".join(
                f"{k} at " + ", ".join(f"{c} ({v})" for c, v in w.items())
                for k, w in bad.items())
        parts.append(text + ".")
    wrong = {}
    for r in records:
        for row in r["sweep"]:
            for mth, e in row["secondary_rays"].items():
                if e["wrong"] > 0.01 * max(e["rays"], 1):
                    wrong.setdefault(mth, []).append(_config(row))
    if wrong:
        parts.append("More than 1 % of the secondary rays hit something else than the "
                     "float64 reference (an offset too small: self-hits; too large: "
                     "nearby geometry skipped, or the float32 geometry too coarse): " +
                     "; ".join(f"{m}: {', '.join(sorted(set(v), key=v.index))}"
                               for m, v in wrong.items()) + ".")
    mism = {}
    for r in records:
        for row in r["sweep"]:
            if row["hit_mismatches"]:
                mism[_config(row)] = max(mism.get(_config(row), 0), row["hit_mismatches"])
    failed = {}
    for r in records:
        for e in r.get("build_errors", []):
            failed.setdefault(r["structure"], {})[_config(e)] = e["build_error"]
    for kind, where in failed.items():
        parts.append(f"The {kind} build failed at " + ", ".join(
            f"{c} ({msg})" for c, msg in where.items()) + ".")
    rays = records[0]["rays"] if records else 0
    parts.append(f"Primary hits against the untranslated float64 reference ({rays:,} rays): "
                 + (", ".join(f"{k} {v}" for k, v in mism.items()) if mism else "no mismatch")
                 + " (float32 vertices keep 24 bits: a shift of 2^k times the size leaves "
                   "24 - k bits for the shape; scaling alone changes nothing).")
    if rand:
        kernels = list(next(iter(rand["table"].values())))
        parts.append(f"pbrt-style random triangles ({rand['triangles']} triangles with "
                     f"coordinates 10^U(-8, 8) x {rand['directions_per_triangle']} directions), "
                     f"self-hits ({'/'.join(kernels)}): " + ", ".join(
                         f"{m} " + "/".join(str(t[k]["self_hits"]) for k in kernels)
                         for m, t in rand["table"].items())
                     + ". pbrt's offset bounds the error of the point only; watertight also "
                       "requires t to exceed its own error bound (pbrt-v4 6.8.7), which the "
                       "other two kernels do not.")
    return " ".join(parts)
