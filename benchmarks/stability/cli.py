"""The stability suite as a program: the cases by number, their sizes (quick, standard,
full), :func:`run` (the JSON-ready result) and :func:`main` (``python -m
benchmarks.stability``, ``jrt stability``)."""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import time
import traceback
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

import accel
from benchmarks.common import comma_names
from benchmarks.stability import common
from benchmarks.stability.anywhere import case5
from benchmarks.stability.boundaries import case8
from benchmarks.stability.closed_mesh import case1
from benchmarks.stability.common import KERNEL_NAMES, combos, default_combos
from benchmarks.stability.deep_trees import case9
from benchmarks.stability.float64_oracle import float64_kernels_ok
from benchmarks.stability.grazing import case2
from benchmarks.stability.offsets import case4
from benchmarks.stability.optics import case7
from benchmarks.stability.planes import case6
from benchmarks.stability.slivers import case3

#: The command's name in usage and errors (``jrt stability`` passes its own).
PROG = "python -m benchmarks.stability"
#: The case numbers.
CASES: tuple[int, ...] = tuple(range(1, 10))


def quick_params(case: int, pairs) -> dict:
    """The arguments of case ``case`` at the quick size (``pairs``: the kernel x structure
    pairs asked for, or None for the case's own: every kernel on brute force and
    watertight on every structure the engine steps, or fewer)."""
    all_engine = combos(("watertight",), accel.names(engine=True))
    defaults = {
        1: {"mesh": "camel-19k", "per_family": 400,
            "pairs": pairs or combos(KERNEL_NAMES, ("brute",)) + all_engine},
        2: {"per_angle": 200, "pairs": pairs or default_combos(True)},
        3: {"per_triangle": 4, "incoherent_rays": 4000, "libigl_sample": 300,
            "pairs": pairs or default_combos(True)},
        4: {"mesh": "camel-19k", "rays": 512, "pairs": pairs or default_combos(True)},
        5: {"rays": 256, "scales": (1e-6, 1e-3, 1.0, 1e3, 1e6), "shifts": (1.0, 1e3, 1e5, 1e7),
            "pairs": pairs or [("watertight", "brute")], "random_triangles": 300,
            "directions": 10, "aimed": 256},
        6: {"rays": 2000, "pairs": pairs or combos(KERNEL_NAMES, ("brute",)) + all_engine},
        7: {"mesh": "camel-19k", "rays": 32, "cap": 200, "pairs": pairs or [("watertight",
                                                                             "bvh")]},
        8: {"pairs": pairs or [("watertight", "brute"), ("watertight", "bvh")]},
        9: {"kinds": ("bvh",), "sizes": (1, 64), "chain_sizes": (8, 64), "rays": 64,
            "pairs": pairs or [("watertight", "brute"), ("watertight", "bvh"),
                               ("watertight", "grid")]},
    }
    return defaults[case]


def standard_params(case: int, pairs) -> dict:
    """The study's default sizes (``jrt study``): every case at a tenth to a quarter of the
    full sweep's rays, over the same pairs except case 5 (every kernel on brute force and
    watertight on the BVH, at three scales and three shifts): about five minutes on two
    cores."""
    full_pairs = {"pairs": pairs} if pairs else {}
    defaults = {
        1: {"per_family": 1000},
        2: {"per_angle": 500},
        3: {"per_triangle": 4, "incoherent_rays": 10_000, "libigl_sample": 1000},
        4: {"rays": 1024},
        5: {"rays": 512, "scales": (1e-6, 1.0, 1e6), "shifts": (1.0, 1e4, 1e7),
            "random_triangles": 300, "aimed": 512, **({} if pairs else {"pairs": combos(
                KERNEL_NAMES, ("brute",)) + [("watertight", "bvh")]})},
        6: {"rays": 5000},
        7: {"rays": 64} if pairs else {"rays": 64, "pairs": [
            ("watertight", "bvh"), ("moller_trumbore", "bvh"), ("plane_barycentric", "bvh")]},
        8: {},
        9: {"sizes": (1, 4, 64), "chain_sizes": (8, 64), "rays": 128},
    }
    return {**defaults[case], **full_pairs}


#: The sizes of a run: ``quick`` (CI, about two minutes), ``standard`` (the study's
#: default, about five), ``full`` (every case at its function's defaults, the published
#: sweep: about 14 minutes on two cores).
SIZES = ("quick", "standard", "full")


CASE_FUNCTIONS = {1: case1, 2: case2, 3: case3, 4: case4, 5: case5, 6: case6, 7: case7,
                  8: case8, 9: case9}
CASE_TITLES = {
    1: "Rays through shared edges and vertices of the closed camel",
    2: "Grazing rays and rays in a triangle's plane",
    3: "Degenerate and sliver triangles",
    4: "Self-intersection of secondary rays",
    5: "Scale and offset",
    6: "Axis-parallel rays on node, cell and split planes",
    7: "Optics",
    8: "Wavelengths at the ends; NaN and infinite inputs",
    9: "Deep trees and long traversals",
}


def _json_safe(value):
    """``value`` with NumPy scalars and arrays as Python values, tuples as lists, keys as
    strings and non-finite floats as strings ("inf", "nan"): what ``json.dumps`` takes."""
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, (np.bool_, bool)):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, (np.floating, float)):
        v = float(value)
        return v if math.isfinite(v) else str(v)
    if isinstance(value, np.ndarray):
        return _json_safe(value.tolist())
    return value


def _names(text: str | None, allowed, what: str):
    if text is None:
        return None
    try:
        return comma_names(text, allowed)
    except ValueError as exc:
        raise SystemExit(f"--{what}: {exc}") from None


def run(cases=CASES, quick=False, kernels=None, structures=None, progress=False,
        output=None, size: str | None = None) -> dict:
    """Run the chosen cases; the JSON-ready result (also written to ``output`` after each
    case, when given). A case that raises is recorded with its error, and the others run.

    ``size``: one of :data:`SIZES` (default ``full``, or ``quick`` when ``quick``)."""
    size = size or ("quick" if quick else "full")
    if size not in SIZES:
        raise ValueError(f"size {size!r}: allowed {', '.join(SIZES)}")
    quick = size == "quick"
    common.PROGRESS["on"] = progress
    pairs = None
    if kernels or structures:
        pairs = combos(kernels or KERNEL_NAMES, structures or None)
    result = {"suite": "jrt numerical stability", "quick": quick, "size": size,
              "environment": {"python": platform.python_version(), "jax": jax.__version__,
                              "numpy": np.__version__, "machine": platform.machine(),
                              "cpu_count": os.cpu_count(), "devices": len(jax.devices()),
                              "float64_kernels": float64_kernels_ok()},
              "oracle": "jrt.kernels.watertight evaluated in float64 (jax.enable_x64) by "
                        "brute force on the same float32 geometry and rays",
              "cases": {}}
    total = time.perf_counter()
    for case in tqdm(cases, desc="stability cases", disable=not progress, dynamic_ncols=True):
        params = (quick_params(case, pairs) if quick else standard_params(case, pairs)
                  if size == "standard" else ({"pairs": pairs} if pairs else {}))
        if case == 7 and size == "full" and pairs is None:
            params = {"pairs": [("watertight", "bvh"), ("moller_trumbore", "bvh"),
                                ("plane_barycentric", "bvh")]}
        start = time.perf_counter()
        try:
            out = CASE_FUNCTIONS[case](**params)
        except Exception as exc:  # record it and go on with the other cases
            tail = traceback.format_exc().strip().splitlines()[-6:]
            out = {"records": [], "error": f"{type(exc).__name__}: {exc}", "traceback": tail,
                   "findings": f"The case failed: {type(exc).__name__}: {exc}"}
        out["seconds"] = round(time.perf_counter() - start, 1)
        out["title"] = CASE_TITLES[case]
        result["cases"][str(case)] = out
        result["seconds"] = round(time.perf_counter() - total, 1)
        if output is not None:
            _write(_json_safe(result), output)
        if progress:
            tqdm.write(f"case {case} ({out['seconds']} s): {out['findings']}\n")
    result["seconds"] = round(time.perf_counter() - total, 1)
    return _json_safe(result)


def _write(result: dict, output) -> Path:
    out = Path(output)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    return out


def main(argv=None, prog: str = PROG) -> int:
    """``python -m benchmarks.stability`` (``jrt stability``): parse, run every chosen
    case, write the JSON and print the findings; 1 if a case failed, else 0. ``prog``
    names the command in usage and errors."""
    parser = argparse.ArgumentParser(
        prog=prog,
        description="Numerical stability on stiff and extreme cases: every case "
                    "over kernel x structure pairs against a float64 oracle; JSON records "
                    "with findings.")
    parser.add_argument("-o", "--output", default="stability.json", help="JSON file to write")
    parser.add_argument("--quick", action="store_true",
                        help="small sizes (about two minutes on two cores); same as "
                             "--size quick")
    parser.add_argument("--size", choices=SIZES, default=None,
                        help="quick (about 2 minutes on two cores), standard (about 5: "
                             "jrt study's default) or full (every case at full size, about "
                             "14; the default)")
    parser.add_argument("--cases", default=None,
                        help=f"comma-separated case numbers (default: all, {CASES[0]}-"
                             f"{CASES[-1]})")
    parser.add_argument("--structures", default=None,
                        help=f"comma-separated structures (default: per case); "
                             f"{', '.join(accel.names())}")
    parser.add_argument("--kernels", default=None,
                        help=f"comma-separated kernels (default: per case); "
                             f"{', '.join(KERNEL_NAMES)}")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    cases = CASES
    if args.cases:
        try:
            cases = tuple(int(c) for c in args.cases.split(",") if c.strip())
        except ValueError:
            parser.error(f"--cases: integers from {CASES[0]} to {CASES[-1]}, got "
                         f"{args.cases!r}")
        bad = [c for c in cases if c not in CASES]
        if bad or not cases:
            parser.error(f"--cases: unknown {bad or '(empty)'}; allowed {list(CASES)}")
    kernels = _names(args.kernels, KERNEL_NAMES, "kernels")
    structures = _names(args.structures, accel.names(), "structures")
    if args.quick and args.size not in (None, "quick"):
        parser.error(f"--quick and --size {args.size} disagree: give one of them")
    result = run(cases, args.quick, kernels, structures, progress=not args.no_progress,
                 output=args.output, size=args.size)
    out = _write(result, args.output)
    for case, body in result["cases"].items():
        print(f"case {case}: {body['title']} ({body['seconds']} s)\n  {body['findings']}")
    print(f"total {result['seconds']} s -> {out}")
    return 1 if any("error" in body for body in result["cases"].values()) else 0
