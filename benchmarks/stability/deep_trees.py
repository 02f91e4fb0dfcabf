"""Case 9: deep trees and long traversals: stack capacity and overflow reporting (probed
in subprocesses, so that an XLA abort, or a traversal that runs to its iteration budget,
cannot take the suite down; an overflow ends the traversal at once), and stacks of nearly
coplanar layers (the tie window is not transitive)."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import jax.numpy as jnp
import numpy as np

import accel
import jrt
from benchmarks.stability.common import (
    build,
    combos,
    joined_or_none,
    load,
    progress_bar,
    record,
    repo_process,
    trace,
)
from benchmarks.stability.float64_oracle import oracle, ulp32
from jrt.engine import StackOverflowError, TraversalError


def deep_chain(n: int = 3000):
    """``n`` parallel triangles at x = 2^-(120 i / n), each spanning [-1, 1]^2 in (y, z):
    a geometric progression that the SAH BVH turns into a deep tree, and rays that enter
    every box while missing every triangle (so they walk the whole tree)."""
    x = 2.0 ** -np.linspace(0, 120, n)
    corners = np.array([[0.0, -1, -1], [0, 1, -1], [0, -1, 1]])
    tris = np.repeat(corners[None], n, axis=0)
    tris[:, :, 0] = x[:, None]
    v = tris.reshape(-1, 3).astype(np.float32)
    f = np.arange(len(v), dtype=np.int32).reshape(-1, 3)
    o = np.array([[-1, 0.5, 0.5], [-1, 0.3, 0.3], [2, 0.5, 0.5], [-1, -0.5, -0.5]], np.float32)
    d = np.array([[1, 0, 0], [1, 0, 0], [-1, 0, 0], [1, 0, 0]], np.float32)
    return v, f, o, d


def probe_worker(spec: dict) -> dict:
    """Runs in a subprocess: closest_hit with the given stack sizes; reports per size
    whether it raised, how long it took, and the engine's status bits."""
    from jrt import engine
    from jrt.trace import traversal_of

    if spec["scene"] == "chain":
        v, f, o, d = deep_chain(spec.get("n", 3000))
    else:
        from jrt.raysets import incoherent_set

        m = load(spec["scene"])
        v, f = m.vertices, m.faces
        o, d = incoherent_set(v, spec["rays"], seed=9)
    s = accel.build(spec["kind"], v, f)
    out = {"depth": s.stats.get("depth"), "sizes": {}}
    checked = False
    for size in spec["sizes"]:
        start = time.perf_counter()
        try:
            jrt.closest_hit(s, o, d, kernel=spec["kernel"], stack_size=size,
                            lanes=spec["lanes"])
            outcome = "ok"
        except StackOverflowError:
            outcome = "StackOverflowError"
        except TraversalError as exc:
            outcome = f"{type(exc).__name__}"
        elapsed = time.perf_counter() - start
        status = None
        # A slow failure: did the loop run to its iteration budget? (Re-run for the bits.)
        if (outcome != "ok" and spec.get("status") and elapsed > spec.get("slow", 3.0)
                and not checked):
            checked = True  # once per probe: the re-run costs as much again
            _, _, st = engine.traverse(traversal_of(s), s.arrays, jnp.asarray(o),
                                       jnp.asarray(d), jnp.full(len(o), jnp.inf, jnp.float32),
                                       kernel=spec["kernel"], any_hit=False,
                                       lanes=spec["lanes"], stack_size=size)
            st = int(st)
            status = {"overflow": bool(st & engine.STATUS_STACK_OVERFLOW),
                      "unfinished (ran to the iteration budget)":
                          bool(st & engine.STATUS_UNFINISHED)}
        out["sizes"][str(size)] = {"outcome": outcome, "seconds": round(elapsed, 3),
                                   "status": status}
    return out


def stack_probe(scene: str, kind: str, sizes, kernel="watertight", rays: int = 64,
                lanes: int = 64, timeout: float = 300, status=True, n: int = 3000) -> dict:
    """:func:`probe_worker` in a fresh Python process, so that a traversal that runs to its
    iteration budget (or an XLA abort) cannot take the suite down; a crash or a timeout is
    itself recorded."""
    spec = {"scene": scene, "kind": kind, "sizes": list(sizes), "kernel": kernel,
            "rays": rays, "lanes": lanes, "status": status, "n": n}
    code = ("import json, sys; from benchmarks.stability.deep_trees import probe_worker; "
            "print('@@' + json.dumps(probe_worker(json.loads(sys.argv[1]))))")
    root, env = repo_process()
    start = time.perf_counter()
    try:
        proc = subprocess.run([sys.executable, "-c", code, json.dumps(spec)], cwd=root,
                              env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {timeout:g} s", "seconds": timeout}
    elapsed = time.perf_counter() - start
    for line in proc.stdout.splitlines():
        if line.startswith("@@"):
            return {**json.loads(line[2:]), "process_seconds": round(elapsed, 1)}
    tail = (proc.stderr or "").strip().splitlines()[-3:]
    return {"error": f"process exited {proc.returncode}: " + " | ".join(tail),
            "process_seconds": round(elapsed, 1)}


def stacked_layers(pairs, n: int = 1000) -> list[dict]:
    """Ties along a long traversal: ``n`` parallel layers at x = 2^-(120 i / n) crossed by
    one axis ray. The tie window (2^-20 t, lowest face wins) is not transitive, so the
    winner depends on the visiting order. Per kernel x structure: the triangle, t - 1
    (the first crossing is t = 1 + x), the error in ulps against the float64 oracle."""
    v, f, _, _ = deep_chain(n)
    o = np.array([[-1, -0.5, -0.5]], np.float32)
    d = np.array([[1, 0, 0]], np.float32)
    t_ref, tri_ref = oracle(v[f], o, d)
    out, brute_of = [], {}
    for kernel, kind in pairs:
        s = build(kind, v, f, key=f"layers{n}")
        h = trace(s, o, d, kernel)
        if kind == "brute":
            brute_of[kernel] = h
        out.append(record(9, kernel, kind, check="stacked layers", triangle=int(h["triangle"][0]),
                          t_minus_1=float(h["t"][0] - 1), oracle_triangle=int(tri_ref[0]),
                          oracle_t_minus_1=float(t_ref[0] - 1),
                          error_ulps=float(abs(h["t"][0] - t_ref[0]) / ulp32(t_ref[0])[()]),
                          nan=int(np.isnan(h["t"]).sum())))
    for r in out:
        b = brute_of.get(r["kernel"])
        r["same_as_brute"] = None if b is None else bool(r["triangle"] == int(b["triangle"][0]))
    return out


def case9(scene: str = "camel-19k", kinds=None,
          sizes=(1, 2, 4, 8, 16, 64), chain_sizes=(8, 16, 32, 64), pairs=None,
          rays: int = 256, lanes: int = 64, layers: int = 1000, timeout: float = 900) -> dict:
    """Stack capacity and overflow reporting (subprocess probes; ``kinds`` None: every
    structure the traversal engine steps, ``accel.names(engine=True)``), and tie chains."""
    pairs = combos() if pairs is None else list(pairs)
    kinds = accel.names(engine=True) if kinds is None else tuple(kinds)
    records = []
    for kind in progress_bar(kinds, "case 9 stacks"):
        res = stack_probe(scene, kind, sizes, rays=rays, lanes=lanes, timeout=timeout)
        records.append(record(9, "watertight", kind, check=f"stack sizes on {scene}",
                              nan=0, **res))
    chain = stack_probe("chain", "bvh", chain_sizes, rays=rays, lanes=lanes)
    records.append(record(9, "watertight", "bvh", check="deep chain (3000 layers)", nan=0,
                          **chain))
    records += stacked_layers(pairs, layers)
    return {"records": records, "findings": _findings9(records),
            "parameters": {"scene": scene, "sizes": list(sizes), "rays": rays, "lanes": lanes,
                           "default_stack_size": jrt.engine.DEFAULT_STACK_SIZE,
                           "layers": layers}}


def _findings9(records) -> str:
    parts = []
    for r in records:
        if not r.get("check", "").startswith(("stack sizes", "deep chain")):
            continue
        if "error" in r:
            parts.append(f"{r['structure']} ({r['check']}): probe failed: {r['error']}.")
            continue
        sizes = r["sizes"]
        ok = [int(k) for k, v in sizes.items() if v["outcome"] == "ok"]
        over = [int(k) for k, v in sizes.items() if v["outcome"] == "StackOverflowError"]
        other = {k: v["outcome"] for k, v in sizes.items()
                 if v["outcome"] not in ("ok", "StackOverflowError")}
        spin = [f"{k} ({v['seconds']:.1f} s)" for k, v in sizes.items()
                if v.get("status") and v["status"].get("unfinished (ran to the iteration "
                                                        "budget)")]
        text = f"{r['structure']} ({r['check']}, depth {r['depth']}): "
        text += (f"smallest stack that answered: {min(ok)}" if ok else "no size answered")
        text += f"; StackOverflowError raised for {over}" if over else "; no overflow"
        if other:
            text += f"; other outcomes {other}"
        if spin:
            text += ("; after the overflow the traversal ran to the iteration budget for "
                     "sizes " + ", ".join(spin))
        parts.append(text + ".")
    lay = [r for r in records if r.get("check") == "stacked layers"]
    if lay:
        diff = [f"{r['kernel']}/{r['structure']} face {r['triangle']} ({r['error_ulps']:.0f} "
                f"ulps)" for r in lay if r["same_as_brute"] is False]
        worst = max(lay, key=lambda r: r["error_ulps"])
        parts.append(f"Stacked layers ({len(lay)} runs): the oracle's first crossing is face "
                     f"{lay[0]['oracle_triangle']} at t - 1 = {lay[0]['oracle_t_minus_1']:.3g}; "
                     f"worst answer {worst['kernel']}/{worst['structure']} face "
                     f"{worst['triangle']}, {worst['error_ulps']:.0f} ulps away; structures "
                     f"that differ from brute force: {joined_or_none(diff)}. Hits within "
                     f"2^-20 t are ties won by the lowest face, and a chain of ties is not "
                     f"transitive, so the winner depends on the order of the visit.")
    return " ".join(parts)
