"""Case 8: wavelengths at the ends of the visible range (spectral tables, Cauchy and
Sellmeier indices, sRGB encoding), and NaN and infinite inputs at the boundary (mesh
vertices, ``accel.build``, rays given to ``jrt.closest_hit``)."""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np

import accel
from benchmarks.stability.common import build, combos, load, record, trace
from jrt import optics
from jrt.mesh import mesh_from_arrays


def _outcome(fn) -> tuple[str, object]:
    try:
        return "ok", fn()
    except Exception as exc:  # the point is to record what happens, whatever it is
        return f"{type(exc).__name__}: {exc}", None


def boundary_checks() -> list[dict]:
    """Spectral ranges, Cauchy and Sellmeier at 380/780 nm, mesh validation."""
    from jrt import spectral

    out = []
    lo_min, hi_max = spectral.WAVELENGTH_MIN, spectral.WAVELENGTH_MAX
    for lo, hi, should in ((380, 780, True), (lo_min, hi_max, True), (lo_min - 1, 780, False),
                           (380, hi_max + 1, False), (500, 500, False), (600, 500, False),
                           (float("nan"), 780, False), (380, float("inf"), False)):
        status, tables = _outcome(lambda lo=lo, hi=hi: spectral.spectral_tables(8, lo=lo,
                                                                              hi=hi))
        finite = None
        if tables is not None:
            finite = bool(all(np.isfinite(np.asarray(a)).all() for a in tables
                              if hasattr(a, "shape")))
        ok = (status == "ok" and finite) if should else status.startswith("ValueError")
        out.append({"check": "spectral_tables range", "lo": lo, "hi": hi, "accepted": should,
                    "outcome": status, "finite": finite, "ok": bool(ok)})
    for lam in (380.0, 780.0, lo_min, hi_max):
        for name, (a, b) in optics.GLASSES.items():
            for dtype in (np.float32, np.float64):
                with jax.enable_x64(dtype == np.float64):
                    n = float(optics.cauchy(dtype(a), dtype(b), dtype(lam)))
                    ns = float(optics.sellmeier(*optics.SELLMEIER[name], dtype(lam)))
                out.append({"check": "index at the ends", "glass": name, "nm": lam,
                            "dtype": np.dtype(dtype).name, "cauchy": n, "sellmeier": ns,
                            "ok": bool(np.isfinite(n) and 1 < n < 2.2 and np.isfinite(ns))})
    enc = np.asarray(spectral.encode_srgb(jnp.asarray([-1.0, 0.0, 0.5, 1.0, 2.0, 1e30],
                                                       jnp.float32)))
    out.append({"check": "encode_srgb extremes", "values": enc.tolist(),
                "ok": bool(np.isfinite(enc).all() and enc.min() >= 0 and enc.max() <= 1)})
    tri = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    faces = np.array([[0, 1, 2]])
    for label, value in (("NaN", np.nan), ("+inf", np.inf), ("-inf", -np.inf),
                         ("1e39 (inf in float32)", 1e39)):
        v = tri.copy()
        v[1, 0] = value
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore")
            status, _ = _outcome(lambda v=v: mesh_from_arrays(v, faces, name="probe"))
        out.append({"check": "mesh vertices", "value": label, "outcome": status,
                    "ok": status.startswith("MeshError") and "finite" in status})
        for kind in accel.names():
            with warnings.catch_warnings(), np.errstate(all="ignore"):
                warnings.simplefilter("ignore")
                status, _ = _outcome(lambda v=v, kind=kind: accel.build(
                    kind, v.astype(np.float32), faces))
            out.append({"check": "accel.build with non-finite vertices", "structure": kind,
                        "value": label, "outcome": status,
                        "ok": None})  # a finding, not a requirement (jrt.Mesh validates)
    return out


def bad_rays():
    """Rays with NaN / inf origins and directions, a zero direction, a far origin."""
    nan, inf = np.float32(np.nan), np.float32(np.inf)
    o = np.array([[nan, 0, 0], [0, 0, -2], [inf, 0, 0], [0, 0, -2], [0, 0, -2], [0, 0, -2],
                  [-inf, 0, 0], [0, 0, -2]], np.float32)
    d = np.array([[0, 0, 1], [0, nan, 1], [0, 0, 1], [0, 0, inf], [0, 0, 0], [inf, -inf, 0],
                  [1, 0, 0], [nan, nan, nan]], np.float32)
    labels = ["NaN origin", "NaN direction", "+inf origin", "inf direction", "zero direction",
              "inf/-inf direction", "-inf origin along x", "all-NaN direction"]
    return o, d, labels


def nan_ray_outcomes(mesh: str, pairs) -> list[dict]:
    """What jrt.closest_hit does with NaN and infinite rays (a scene of the camel)."""
    m = load(mesh)
    o, d, labels = bad_rays()
    c = ((m.vertices.min(axis=0) + m.vertices.max(axis=0)) / 2).astype(np.float32)
    o = np.where(np.isfinite(o), o + c, o).astype(np.float32)
    out = []
    for kernel, kind in pairs:
        s = build(kind, m.vertices, m.faces, key=mesh)
        try:
            h = trace(s, o, d, kernel)
        except (ValueError, TypeError) as exc:
            out.append(record(8, kernel, kind, check="NaN/inf rays", rejected=True,
                              outcome=f"{type(exc).__name__}: {exc}", nan=0, hits=0))
            continue
        nan = int(sum(np.isnan(h[k]).sum() for k in ("t", "u", "v")))
        hit = h["triangle"] >= 0
        out.append(record(8, kernel, kind, check="NaN/inf rays", rejected=False,
                          outcome="traced silently: " + ", ".join(
                              f"{lab}: {'hit' if hh else 'miss'}"
                              for lab, hh in zip(labels, hit, strict=True)),
                          nan=nan, hits=int(hit.sum()), rays=len(o)))
    return out


def case8(mesh: str = "camel-19k", pairs=None) -> dict:
    """Wavelength ranges, indices at 380/780 nm, NaN/inf meshes and rays at the boundary."""
    pairs = combos(("watertight",)) if pairs is None else list(pairs)
    records = [record(8, "n/a", s.get("structure", "n/a"), **{k: v for k, v in s.items()
                                                             if k != "structure"})
               for s in boundary_checks()]
    records += nan_ray_outcomes(mesh, pairs)
    return {"records": records, "findings": _findings8(records),
            "parameters": {"mesh": mesh, "rays": bad_rays()[2]}}


def _findings8(records) -> str:
    parts = []
    spec = [r for r in records if r.get("check") == "spectral_tables range"]
    parts.append(f"spectral_tables: {sum(r['ok'] for r in spec)}/{len(spec)} range probes "
                 f"behave (in-range accepted with finite tables, out-of-range, empty, NaN "
                 f"and inf ranges rejected with ValueError).")
    idx = [r for r in records if r.get("check") == "index at the ends"]
    parts.append(f"Cauchy and Sellmeier at the ends of the range: {sum(r['ok'] for r in idx)}/"
                 f"{len(idx)} finite and plausible.")
    mesh = [r for r in records if r.get("check") == "mesh vertices"]
    parts.append(f"jrt.mesh_from_arrays rejects {sum(r['ok'] for r in mesh)}/{len(mesh)} "
                 f"non-finite vertex probes with a MeshError naming the vertex.")
    raw = [r for r in records if r.get("check") == "accel.build with non-finite vertices"]
    silent = sorted({r["structure"] for r in raw if r["outcome"] == "ok"})
    raised = sorted({r["structure"] for r in raw if r["outcome"] != "ok"})
    if silent:
        parts.append(f"accel.build itself (below the Mesh boundary) accepts non-finite "
                     f"vertices silently for {', '.join(silent)}"
                     + (f"; raises for {', '.join(raised)}." if raised else "."))
    else:
        parts.append(f"accel.build itself rejects non-finite vertices for every structure "
                     f"({', '.join(raised)}).")
    rays = [r for r in records if r.get("check") == "NaN/inf rays"]
    rejected = [f"{r['kernel']}/{r['structure']}" for r in rays if r["rejected"]]
    silent = [r for r in rays if not r["rejected"]]
    if silent:
        hits = sum(r["hits"] for r in silent)
        nan = sum(r["nan"] for r in silent)
        parts.append(f"jrt.closest_hit does not reject NaN/inf origins or directions "
                     f"({len(silent)} kernel x structure pairs traced them silently): they "
                     f"come back as {'misses' if not hits else f'{hits} hits'} with {nan} NaN "
                     f"outputs: a defined answer, but no error at the boundary.")
    if rejected:
        parts.append(f"jrt.closest_hit rejects NaN and infinite origins and directions and "
                     f"zero directions with a ValueError naming the ray "
                     f"({', '.join(rejected)}).")
    return " ".join(parts)
