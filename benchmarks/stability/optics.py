"""Case 7: optics at an interface, in float32 and float64 (total internal reflection at
the critical angle +- 1e-6 rad, Brewster, normal incidence, entering versus leaving,
n = 1.0001 and 4, SF10 dispersion), and a glass camel at n = 2.4 trapping light (bounces
until the weight falls below 1e-3), traced with closest_hit, jrt.optics and a local copy
of pbrt's offset: no renderer."""

from __future__ import annotations

import math

import jax
import numpy as np

from benchmarks.stability.common import build, load, progress_bar, record, trace
from benchmarks.stability.offsets import pbrt_offset_numpy, surface_frame
from jrt import optics


def _incident(theta, dtype):
    """Unit incident directions at angle ``theta`` to the normal (0, 0, 1), coming down."""
    theta = np.asarray(theta, np.float64)
    return np.stack([np.sin(theta), np.zeros_like(theta), -np.cos(theta)], -1).astype(dtype)


def optics_checks() -> list[dict]:
    """TIR at the critical angle +- 1e-6 rad, Brewster, normal incidence, entering vs
    leaving, extreme indices, SF10 dispersion; float32 and float64."""
    out = []
    sf10 = optics.GLASSES["SF10"]
    pairs = {"glass 1.5 -> air": (1.5, 1.0), "diamond 2.4 -> air": (2.4, 1.0),
             "1.0001 -> air": (1.0001, 1.0), "4 -> air": (4.0, 1.0),
             "SF10 at 380 nm -> air": (float(sf10[0] + sf10[1] / 0.38**2), 1.0),
             "SF10 at 780 nm -> air": (float(sf10[0] + sf10[1] / 0.78**2), 1.0)}
    normal = np.array([0.0, 0, 1])
    for dtype in (np.float32, np.float64):
        name = np.dtype(dtype).name
        with jax.enable_x64(dtype == np.float64):
            for label, (n1, n2) in pairs.items():
                n1c, n2c = dtype(n1), dtype(n2)
                crit = math.asin(float(n2c) / float(n1c))
                theta = np.array([crit - 1e-6, crit + 1e-6])
                l = _incident(theta, dtype)
                t, tir = optics.refract(l, normal.astype(dtype), n1c, n2c)
                r, _ = optics.fresnel(np.cos(theta).astype(dtype), n1c, n2c)
                tir, t, r = np.asarray(tir), np.asarray(t, np.float64), np.asarray(r, np.float64)
                out.append({"check": "TIR at critical +- 1e-6 rad", "pair": label,
                            "dtype": name, "critical_deg": math.degrees(crit),
                            "tir_below": bool(tir[0]), "tir_above": bool(tir[1]),
                            "R_below": float(r[0]), "R_above": float(r[1]),
                            "transmitted_below_angle_to_surface_deg": math.degrees(
                                math.asin(min(1.0, abs(float(t[0, 2]))))),
                            "nan": int(np.isnan(t).sum() + np.isnan(r).sum()),
                            "ok": bool(not tir[0] and tir[1] and r[1] == 1 and r[0] < 1
                                       and not np.isnan(t).any())})
            for n1, n2 in ((1.0, 1.5), (1.5, 1.0), (1.0, 4.0), (1.0, 1.0001)):
                theta_b = math.atan(n2 / n1)
                rs, rp = optics.fresnel_sp(dtype(math.cos(theta_b)), dtype(n1), dtype(n2))
                rp = float(rp)
                out.append({"check": "Brewster", "pair": f"{n1} -> {n2}", "dtype": name,
                            "brewster_deg": math.degrees(theta_b), "Rp": rp, "Rs": float(rs),
                            "ok": bool(abs(rp) < (1e-6 if dtype == np.float32 else 1e-12))})
            for n1, n2 in ((1.0, 1.5), (1.5, 1.0), (1.0, 4.0), (1.0, 1.0001)):
                r, tt = optics.fresnel(dtype(1.0), dtype(n1), dtype(n2))
                r0, _ = optics.fresnel_normal(dtype(n1), dtype(n2))
                l = np.array([[0.0, 0, -1]], dtype)
                t, tir = optics.refract(l, normal.astype(dtype), dtype(n1), dtype(n2))
                dev = float(np.abs(np.asarray(t, np.float64) - l).max())
                rel = abs(float(r) - float(r0)) / float(r0)
                eps = float(np.finfo(dtype).eps)
                out.append({"check": "normal incidence", "pair": f"{n1} -> {n2}",
                            "dtype": name, "R": float(r), "R_seed": float(r0),
                            "rel_diff": rel, "R_plus_T_minus_1": float(r) + float(tt) - 1,
                            "direction_deviation": dev,
                            "ok": bool(rel < 64 * eps and dev <= 4 * eps and not bool(tir[0]))})
            theta = np.linspace(0, np.pi / 2, 2001)[:-1]
            for n_in in (1.0001, 1.5, 4.0):
                # Entering (1 -> n), then back out along the reversed transmitted ray:
                # reversibility (-t back to -l) and Stokes (R equal on both sides).
                l = _incident(theta, dtype)
                nrm = np.broadcast_to(normal.astype(dtype), l.shape)
                t, tir = optics.refract(l, nrm, dtype(1.0), dtype(n_in))
                t = np.asarray(t)
                back, tir_back = optics.refract(-t, -nrm, dtype(n_in), dtype(1.0))
                rev = np.abs(np.asarray(back, np.float64) + l).max(axis=1)
                cos2 = np.abs(t[:, 2]).astype(dtype)
                r_in, _ = optics.fresnel(np.cos(theta).astype(dtype), dtype(1.0), dtype(n_in))
                r_out, _ = optics.fresnel(cos2, dtype(n_in), dtype(1.0))
                stokes = np.abs(np.asarray(r_in, np.float64) - np.asarray(r_out, np.float64))
                sin1 = np.sin(theta)
                sin2 = np.hypot(t[:, 0], t[:, 1]).astype(np.float64)
                snell = np.abs(sin1 - n_in * sin2)
                norm = np.abs(np.linalg.norm(t.astype(np.float64), axis=1) - 1)
                # Away from grazing incidence in air (cos i1 < 1e-2), where the way back
                # starts next to the critical angle and float32 loses the angle.
                small = np.cos(theta) > 1e-2
                out.append({"check": "entering vs leaving", "n": n_in, "dtype": name,
                            "angles": len(theta),
                            "max_reversibility_error": float(rev[small].max()),
                            "max_reversibility_error_grazing": float(rev.max()),
                            "max_stokes_R_difference": float(stokes[small].max()),
                            "max_snell_residual": float(snell.max()),
                            "max_norm_error": float(norm.max()),
                            "tir_entering": int(np.asarray(tir).sum()),
                            "tir_leaving_back": int(np.asarray(tir_back)[small].sum()),
                            "nan": int(np.isnan(t).sum() + np.isnan(np.asarray(back)).sum()),
                            "ok": bool(not np.asarray(tir).any() and not np.isnan(t).any()
                                       and float(norm.max()) < 1e-5)})
            lam = np.linspace(380, 780, 41).astype(dtype)
            n_c = np.asarray(optics.cauchy(dtype(sf10[0]), dtype(sf10[1]), lam), np.float64)
            n_s = np.asarray(optics.sellmeier(*optics.SELLMEIER["SF10"], lam), np.float64)
            l = np.broadcast_to(_incident(np.pi / 4, dtype), (len(lam), 3))
            t, _ = optics.refract(l, np.broadcast_to(normal.astype(dtype), l.shape),
                                  dtype(1.0), n_c.astype(dtype))
            ang = np.degrees(np.arcsin(np.hypot(np.asarray(t)[:, 0], np.asarray(t)[:, 1])
                                       .astype(np.float64)))
            out.append({"check": "SF10 dispersion 380-780 nm", "dtype": name,
                        "n_380": float(n_c[0]), "n_780": float(n_c[-1]),
                        "monotone_decreasing": bool(np.all(np.diff(n_c) < 0)),
                        "max_cauchy_minus_sellmeier": float(np.abs(n_c - n_s).max()),
                        "refraction_spread_at_45deg_deg": float(ang.max() - ang.min()),
                        "finite": bool(np.isfinite(n_c).all() and np.isfinite(ang).all()),
                        "ok": bool(np.isfinite(n_c).all() and np.all(np.diff(n_c) < 0))})
    return out


def glass_trapping(mesh: str, kernel: str, kind: str, rays: int = 64, cap: int = 500,
                   n_glass: float = 2.4, floor: float = 1e-3, seed: int = 8) -> dict:
    """Light trapped in a glass camel: rays enter (refracted, weight T), then follow the
    internally reflected branch (weight x R at each bounce) until the weight is below
    ``floor``; closest_hit + jrt.optics + a local pbrt offset, no renderer."""
    from jrt.raysets import incoherent_set

    m = load(mesh)
    s = build(kind, m.vertices, m.faces, key=mesh)
    o, d = incoherent_set(m.vertices, 4 * rays, seed=seed)
    h = trace(s, o, d, kernel)
    sel = np.flatnonzero(h["triangle"] >= 0)[:rays]
    hits = {k: v[sel] for k, v in h.items()}
    d = d[sel]
    point, error, ng, _ = surface_frame(m.vertices, m.faces, hits["triangle"], hits["u"],
                                        hits["v"])
    nf, entering = (np.asarray(a) for a in optics.orient(d, ng))
    cos_i = -(d * nf).sum(axis=1)
    _, big_t = optics.fresnel(cos_i, np.float32(1.0), np.float32(n_glass))
    w, _ = optics.refract(d, nf, np.float32(1.0), np.float32(n_glass))
    w = np.array(w, np.float32)
    weight = np.array(big_t, np.float64)
    origin = np.array(pbrt_offset_numpy(point, error, nf, w))
    alive = np.array(entering)
    bounces = np.zeros(len(sel), int)
    tir_count = np.zeros(len(sel), int)
    leaks = wrong_side = nan = 0
    for _ in range(cap):
        if not alive.any():
            break
        idx = np.flatnonzero(alive)
        hh = trace(s, origin[idx], w[idx], kernel)
        nan += int(np.isnan(hh["t"]).sum())
        miss = hh["triangle"] < 0
        leaks += int(miss.sum())
        alive[idx[miss]] = False
        idx, hh = idx[~miss], {k: v[~miss] for k, v in hh.items()}
        if not len(idx):
            break
        p, err, ng, _ = surface_frame(m.vertices, m.faces, hh["triangle"], hh["u"], hh["v"])
        nf, entering_now = (np.asarray(a) for a in optics.orient(w[idx], ng))
        wrong = entering_now  # inside glass, every hit must be from inside (leaving)
        wrong_side += int(wrong.sum())
        cos_i = -(w[idx] * nf).sum(axis=1)
        big_r, _ = optics.fresnel(cos_i, np.float32(n_glass), np.float32(1.0))
        _, tir = optics.refract(w[idx], nf, np.float32(n_glass), np.float32(1.0))
        tir_count[idx] += np.asarray(tir)
        weight[idx] *= np.asarray(big_r, np.float64)
        bounces[idx] += 1
        w[idx] = np.asarray(optics.reflect(w[idx], nf), np.float32)
        origin[idx] = pbrt_offset_numpy(p, err, nf, w[idx])
        alive[idx[wrong | (weight[idx] < floor)]] = False
    capped = int(alive.sum())
    return {"rays": int(len(sel)), "bounces_min": int(bounces.min()) if len(sel) else None,
            "bounces_median": float(np.median(bounces)) if len(sel) else None,
            "bounces_max": int(bounces.max()) if len(sel) else None,
            "bounces_mean": float(bounces.mean()) if len(sel) else None,
            "tir_share": float(tir_count.sum() / max(bounces.sum(), 1)),
            "reached_cap": capped, "cap": cap, "leaks": leaks, "wrong_side": wrong_side,
            "nan": nan, "final_weight_max": float(weight.max()) if len(sel) else None}


def case7(mesh: str = "camel", rays: int = 256, cap: int = 1000, pairs=None) -> dict:
    """Optics at the interface (float32 and float64) and the glass camel at n = 2.4."""
    pairs = [("watertight", "bvh")] if pairs is None else list(pairs)
    if any(kind != "brute" for _, kind in pairs):  # hundreds of bounces: not by brute force
        pairs = [(k, kind) for k, kind in pairs if kind != "brute"]
    checks = optics_checks()
    records = [record(7, "n/a", "n/a", **c) for c in checks]
    for kernel, kind in progress_bar(pairs, "case 7 glass camel"):
        g = glass_trapping(mesh, kernel, kind, rays, cap)
        records.append(record(7, kernel, kind, check="glass camel n = 2.4", **g))
    return {"records": records, "findings": _findings7(records),
            "parameters": {"mesh": mesh, "rays": rays, "cap": cap, "weight_floor": 1e-3,
                           "index": 2.4}}


def _findings7(records) -> str:
    parts = []
    tir = [r for r in records if r.get("check") == "TIR at critical +- 1e-6 rad"]
    bad = [f"{r['pair']} ({r['dtype']})" for r in tir if not r["ok"]]
    parts.append(f"TIR at the critical angle +- 1e-6 rad: flips for {len(tir) - len(bad)} of "
                 f"{len(tir)} index pairs x dtypes" + (f", not for {', '.join(bad)}" if bad
                                                       else "") +
                 f"; R just below the critical angle {min(r['R_below'] for r in tir):.4f}-"
                 f"{max(r['R_below'] for r in tir):.4f} (R has an infinite slope there).")
    br = [r for r in records if r.get("check") == "Brewster"]
    parts.append("Brewster: |Rp| <= " + ", ".join(
        f"{max(abs(r['Rp']) for r in br if r['dtype'] == dt):.2g} ({dt})"
        for dt in ("float32", "float64")) + ".")
    ni = [r for r in records if r.get("check") == "normal incidence"]
    parts.append(f"Normal incidence: R against ((n1 - n2) / (n1 + n2))^2 within "
                 f"{max(r['rel_diff'] for r in ni):.2g} relative, direction unchanged to "
                 f"{max(r['direction_deviation'] for r in ni):.2g}.")
    el = [r for r in records if r.get("check") == "entering vs leaving"]
    parts.append("Entering then leaving: reversibility error " + ", ".join(
        f"n = {r['n']} {r['max_reversibility_error']:.2g} ({r['dtype']}; "
        f"{r['max_reversibility_error_grazing']:.2g} at grazing)" for r in el) + "; Stokes |dR| "
        f"<= {max(r['max_stokes_R_difference'] for r in el):.2g}.")
    sf = [r for r in records if r.get("check") == "SF10 dispersion 380-780 nm"]
    if sf:
        r = sf[-1]
        parts.append(f"SF10 (Cauchy) from {r['n_380']:.4f} at 380 nm to {r['n_780']:.4f} at "
                     f"780 nm, monotone, at most {r['max_cauchy_minus_sellmeier']:.2g} from "
                     f"Sellmeier over 380-780 (the fit covers 400-700); 45 deg refraction "
                     f"spread {r['refraction_spread_at_45deg_deg']:.3f} deg.")
    for r in records:
        if r.get("check") == "glass camel n = 2.4":
            parts.append(f"Glass camel n = 2.4 ({r['kernel']}/{r['structure']}, {r['rays']} "
                         f"rays): {r['bounces_min']}-{r['bounces_max']} internal bounces "
                         f"(median {r['bounces_median']:g}) before the weight falls below "
                         f"1e-3, {100 * r['tir_share']:.0f} % of them total internal "
                         f"reflections, {r['reached_cap']} still above 1e-3 after "
                         f"{r['cap']}; leaks {r['leaks']}, hits from the wrong side "
                         f"{r['wrong_side']}, NaN {r['nan']}.")
    nan = sum(r.get("nan", 0) for r in records)
    parts.append(f"NaN anywhere: {nan}.")
    return " ".join(parts)
