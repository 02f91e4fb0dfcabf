"""The stability suite's shared pieces: meshes and structures (loaded and built once, or
built in a guarded subprocess), tracing through ``jrt.closest_hit`` in fixed chunks, the
kernel x structure pairs (from the structure registry, ``accel.names()``), the records and
their counts, and the progress bar."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

import accel
import jrt
from jrt.kernels import KERNELS

KERNEL_NAMES: tuple[str, ...] = tuple(KERNELS)

#: Rays per jrt.closest_hit call: every call has this shape, so one compile serves all.
CHUNK = 1024
#: jrt's tie window (jrt.hits.TIE_RELATIVE): hits this close in t are one crossing.
TIE = 2.0**-20

#: Whether :func:`progress_bar` shows (set by ``cli.run``; off under the tests).
PROGRESS = {"on": False}


def progress_bar(iterable, desc: str, total: int | None = None):
    """A tqdm bar when the suite runs as a program; silent under the tests."""
    return tqdm(iterable, desc=desc, total=total, leave=False, disable=not PROGRESS["on"],
                dynamic_ncols=True)


# --- Meshes, structures, tracing ---------------------------------------------------------------

_MESHES: dict = {}
_BUILT: dict = {}


def load(name: str) -> jrt.Mesh:
    """The camel meshes through jrt's resolver, loaded once."""
    if name not in _MESHES:
        _MESHES[name] = jrt.load_mesh(jrt.camel_path(name))
    return _MESHES[name]


def build(kind: str, vertices, faces, key=None):
    """accel.build, cached by ``key`` (a mesh name or a scene label) when one is given."""
    if key is None:
        return accel.build(kind, vertices, faces)
    if (key, kind) not in _BUILT:
        _BUILT[(key, kind)] = accel.build(kind, vertices, faces)
    return _BUILT[(key, kind)]


#: Address-space cap of a guarded build (bytes): a builder that runs away (its references
#: multiplying) fails with MemoryError instead of taking the machine.
BUILD_MEMORY_LIMIT = 3 << 30


def build_guarded(kind: str, vertices, faces, limit: int = BUILD_MEMORY_LIMIT,
                  timeout: float = 600, repeat: int = 1):
    """accel.build in a subprocess (accel never imports JAX) under an address-space cap
    of ``limit`` bytes: the Structure, or a string saying why the build failed (the
    builder's error, MemoryError under the cap, a timeout), so that a builder that runs
    away cannot take the machine or the suite down. With ``repeat`` > 1 the subprocess
    builds that many times and ``stats["build_seconds"]`` is the fastest build."""
    import pickle
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "mesh.npz", Path(tmp) / "structure.pickle"
        np.savez(src, vertices=np.asarray(vertices), faces=np.asarray(faces))
        code = ("import pickle, resource, sys, numpy as np; "
                "resource.setrlimit(resource.RLIMIT_AS, (int(sys.argv[4]),) * 2); "
                "import accel; m = np.load(sys.argv[2]); "
                "runs = [accel.build(sys.argv[1], m['vertices'], m['faces']) "
                "for _ in range(int(sys.argv[5]))]; s = runs[-1]; "
                "s.stats['build_seconds'] = min(r.stats['build_seconds'] for r in runs); "
                "pickle.dump(s, open(sys.argv[3], 'wb'))")
        root, env = repo_process()
        start = time.perf_counter()
        try:
            proc = subprocess.run([sys.executable, "-W", "ignore", "-c", code, kind, str(src),
                                   str(dst), str(limit), str(max(int(repeat), 1))],
                                  cwd=root, env=env,
                                  capture_output=True, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            return f"timed out after {timeout:g} s"
        elapsed = time.perf_counter() - start
        if proc.returncode != 0 or not dst.exists():
            last = (proc.stderr or "").strip().splitlines()[-1:] or [f"exit {proc.returncode}"]
            return f"{last[0][:200]} (after {elapsed:.1f} s, {limit / 2**30:g} GiB cap)"
        with open(dst, "rb") as fh:
            return pickle.load(fh)


def repo_process() -> tuple[Path, dict]:
    """The folder and environment for a child Python that imports this checkout's
    ``accel``, ``jrt`` and ``benchmarks`` (installed or not)."""
    root = Path(__file__).resolve().parents[2]  # benchmarks/stability/common.py
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(root), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    return root, env


def combos(kernels=KERNEL_NAMES, structures=None) -> list[tuple[str, str]]:
    """Every (kernel, structure) pair (``structures`` None: every registered structure,
    ``accel.names()``, brute force first)."""
    structures = accel.names() if structures is None else structures
    return [(k, s) for k in kernels for s in structures]


def default_combos(quick: bool) -> list[tuple[str, str]]:
    """Full: every pair. Quick: every kernel on brute force, watertight on the BVH."""
    if not quick:
        return combos()
    return combos(KERNEL_NAMES, ("brute",)) + [("watertight", "bvh")]


def trace(structure, origins, directions, kernel: str, tmax=None, **options) -> dict:
    """jrt.closest_hit in chunks of CHUNK rays; float64 NumPy t, u, v and int triangle."""
    origins = np.asarray(origins, np.float32)
    directions = np.asarray(directions, np.float32)
    n = len(origins)
    tmax = np.full(n, np.inf, np.float32) if tmax is None else np.broadcast_to(
        np.asarray(tmax, np.float32), (n,))
    out = {k: [] for k in ("t", "triangle", "u", "v")}
    for start in range(0, max(n, 1), CHUNK):
        o = np.zeros((CHUNK, 3), np.float32)
        d = np.tile(np.float32([0, 0, 1]), (CHUNK, 1))
        tm = np.zeros(CHUNK, np.float32)  # padding rays: tmax 0, they hit nothing
        m = min(CHUNK, n - start)
        o[:m], d[:m], tm[:m] = origins[start:start + m], directions[start:start + m], \
            tmax[start:start + m]
        hits = jrt.closest_hit(structure, o, d, kernel=kernel, tmax=tm, **options)
        for key, value in hits._asdict().items():
            out[key].append(np.asarray(value)[:m])
    return {k: (np.concatenate(v).astype(np.float64) if k != "triangle"
                else np.concatenate(v).astype(np.int64)) for k, v in out.items()}


# --- Records and their counts ----------------------------------------------------------------

def max_or_none(x) -> float | None:
    """The largest value of ``x`` (as a float), None when it is empty."""
    x = np.asarray(x, np.float64)
    return float(x.max()) if x.size else None


def per_million(count: int, total: int) -> float | None:
    """``count`` per million of ``total`` (one decimal), None when ``total`` is 0."""
    return round(1e6 * count / total, 1) if total else None


def summary(cmp: dict, mask=None) -> dict:
    """Counts of a ``float64_oracle.compare`` result (over ``mask`` if given)."""
    mask = np.ones_like(cmp["miss"]) if mask is None else mask
    n = int(mask.sum())
    cracks = int((cmp["crack"] & mask).sum())
    return {"rays": n, "cracks": cracks, "cracks_per_million": per_million(cracks, n),
            "misses": int((cmp["miss"] & mask).sum()),
            "pass_through": int((cmp["pass_through"] & mask).sum()),
            "false_hits": int((cmp["false"] & mask).sum()),
            "borderline_hits": int((cmp["borderline"] & mask).sum()),
            "near_origin": int((cmp["near"] & mask).sum()),
            **({"skipped_touches": int((cmp["touch"] & mask).sum())} if "touch" in cmp else {}),
            "nan": int((cmp["nan"] & mask).sum()),
            "max_error_ulps": max_or_none(cmp["err_ulps"][mask])}


def record(case: int, kernel: str, structure: str, **fields) -> dict:
    """One record of a case: its number, kernel and structure first, then ``fields``."""
    return {"case": case, "kernel": kernel, "structure": structure, **fields}


def with_mismatches_vs_brute(records_and_hits) -> list[dict]:
    """The records of ``(record, hits)`` pairs, each with ``mismatches_vs_brute``: its hits
    against brute force's with the same kernel (None where brute force did not run)."""
    brute = {rec["kernel"]: hits for rec, hits in records_and_hits
             if rec["structure"] == "brute"}
    for rec, hits in records_and_hits:
        base = brute.get(rec["kernel"])
        rec["mismatches_vs_brute"] = None if base is None else mismatches_vs(hits, base)
    return [rec for rec, _ in records_and_hits]


def mismatches_vs(hits: dict, base: dict) -> int:
    """Rays whose hit differs from ``base`` (same kernel): hit/miss, or t beyond the tie
    window (a different triangle at a tied t is the same answer)."""
    h, b = np.isfinite(hits["t"]), np.isfinite(base["t"])
    with np.errstate(invalid="ignore"):
        far = np.abs(hits["t"] - base["t"]) > TIE * np.abs(base["t"])
    return int(((h != b) | (h & b & far)).sum())


def joined_or_none(items) -> str:
    """``items`` joined by commas, or "none" (for the findings' prose)."""
    return ", ".join(items) if items else "none"


def rows_matching(records, **match) -> list[dict]:
    """The records whose fields equal every ``match`` value."""
    return [r for r in records if all(r.get(k) == v for k, v in match.items())]


def random_rotation(rng) -> np.ndarray:
    """A uniformly random rotation matrix (QR of a Gaussian matrix, signs fixed so that
    the factorisation is unique, det +1)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q
