"""What every benchmark script shares: timers, summaries, and the JSON record writer."""

from __future__ import annotations

import json
import math
import re
import shlex
import statistics
import sys
import time
from pathlib import Path

import numpy as np


def comma_names(text: str, allowed) -> list[str]:
    """The names of a comma-separated option, each one of ``allowed``; a ValueError names
    the unknown ones (or the empty list) and what is allowed."""
    names = [t.strip() for t in text.split(",") if t.strip()]
    unknown = [n for n in names if n not in allowed]
    if unknown or not names:
        raise ValueError(f"unknown {', '.join(unknown) or '(empty list)'}; allowed: "
                         f"{', '.join(map(str, allowed))}")
    return names


def jsonable(value):
    """``value`` with NumPy scalars and arrays, tuples and paths turned into JSON types.

    Non-finite floats become ``None`` (JSON has no NaN or infinity).
    """
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return [jsonable(v) for v in value.tolist()]
    if isinstance(value, np.bool_ | bool):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.floating | float):
        value = float(value)
        return value if math.isfinite(value) else None
    if isinstance(value, Path):
        return str(value)
    return value


#: A JSON array of numbers only (no strings, objects or arrays inside), as json.dumps
#: indents it: one number per line.
_NUMBER_ARRAY = re.compile(r"\[\s*(-?[\d.eE+-]+(?:,\s*-?[\d.eE+-]+)*)\s*\]")


def dumps(record: dict) -> str:
    """Indented JSON, with each array of plain numbers on one line (a heat map row, a list
    of repeats), so that large records stay readable and diffable."""
    text = json.dumps(jsonable(record), indent=2, allow_nan=False)
    return _NUMBER_ARRAY.sub(lambda m: "[" + ", ".join(
        x.strip() for x in m.group(1).split(",")) + "]", text)


def command_line(prog: str, argv=None) -> str:
    """The command a script's ``main(argv)`` stands for (``argv`` None: the process's own
    arguments), quoted as a shell would need it: what a JSON record says made it."""
    argv = sys.argv[1:] if argv is None else list(argv)
    return " ".join([prog, *map(shlex.quote, argv)]).strip()


def write_record(record: dict, path: str) -> Path:
    """Write ``record`` as indented JSON to ``path`` (folders created) and say where."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(dumps(record))
    print(f"-> {out}")
    return out


def time_calls(fn, repeats: int, budget: float | None = None) -> list[float]:
    """Wall time of each of ``repeats`` calls of ``fn`` (seconds), in call order; with a
    ``budget`` (seconds), no further call once the calls have taken that long (at least
    one call)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
        if budget is not None and sum(times) >= budget:
            break
    return times


def interleaved_times(fns: dict, repeats: int) -> dict[str, list[float]]:
    """Wall times of ``repeats`` rounds in which every function of ``fns`` (label: fn) is
    called once, in turn: each label's times in round order.

    On a shared machine the speed drifts by tens of percent within a minute; called in
    turn, the peers meet the same drift, so the best of each, and the ratio of their
    times round by round, compare like with like (a block of one peer's calls, then a
    block of the other's, can land one block in a slow spell).
    """
    times: dict[str, list[float]] = {label: [] for label in fns}
    for _ in range(repeats):
        for label, fn in fns.items():
            start = time.perf_counter()
            fn()
            times[label].append(time.perf_counter() - start)
    return times


def best_time(fn, repeats: int) -> float:
    """The shortest wall time of ``repeats`` calls of ``fn`` (seconds)."""
    return min(time_calls(fn, repeats))


def summary(values) -> dict:
    """median, min, max and spread (max - min) of a list of numbers."""
    values = [float(v) for v in values]
    return {"median": statistics.median(values), "min": min(values), "max": max(values),
            "spread": max(values) - min(values)}


def rates(rays: int, seconds: list[float]) -> dict:
    """Mrays/s from the times of repeated calls on ``rays`` rays: median, min, max.

    The median rate is the rate of the median time; min and max come from the slowest and
    the fastest call.
    """
    s = summary(seconds)
    return {"median": rays / s["median"] / 1e6, "min": rays / s["max"] / 1e6,
            "max": rays / s["min"] / 1e6}


def cost_model(name: str, traces: list[dict]) -> dict:
    """Fit the time per ray to the per-ray counters over the sets (Havran & Purgathofer).

    time / rays ~ C_0 + C_TS x steps + C_IT x tests, with steps and tests the sets' mean
    counts: Havran and Purgathofer's C_TS (a traversal step) and C_IT (a triangle test),
    plus C_0, what a ray costs whatever its path (loading and storing it, the lanes'
    refill, the call's fixed cost spread over the rays). Non-negative least squares on
    relative errors (each set weighs the same): every subset of the three terms is fitted
    and the feasible one with the least error kept. The residual is the root mean square
    of the relative errors of the fitted times.
    """
    steps = np.array([t["counters"]["steps"]["mean"] for t in traces])
    tests = np.array([t["counters"]["tests"]["mean"] for t in traces])
    per_ray = np.array([t["seconds"]["median"] / t["rays"] for t in traces])
    a = np.stack([steps, tests, np.ones_like(steps)], axis=1) / per_ray[:, None]
    b = np.ones(len(traces))
    best = (np.zeros(3), float("nan"))
    for columns in ((0, 1, 2), (0, 1), (0, 2), (1, 2), (0,), (1,), (2,)):
        if len(columns) > len(traces):
            continue
        sol = np.linalg.lstsq(a[:, columns], b, rcond=None)[0]
        if np.any(sol < 0):
            continue
        coef = np.zeros(3)
        coef[list(columns)] = sol
        err = float(np.sqrt(np.mean((a @ coef - b) ** 2)))
        if not err >= best[1] - 1e-12:  # also true while best is NaN
            best = (coef, err)
    coef, residual = best
    points = [{"set": t["set"], "query": t["query"], "rays": t["rays"],
               "seconds": t["seconds"]["median"], "steps_mean": s, "tests_mean": c,
               "predicted_seconds": t["rays"] * (coef[0] * s + coef[1] * c + coef[2])}
              for t, s, c in zip(traces, steps, tests, strict=True)]
    return {"kind": "cost_model", "structure": name, "c_ts_ns": coef[0] * 1e9,
            "c_it_ns": coef[1] * 1e9, "c_ray_ns": coef[2] * 1e9, "residual": residual,
            "points": points,
            "fit": "time/rays ~ C_0 + C_TS steps + C_IT tests; non-negative least squares "
                   "of relative errors over the ray sets",
            "time_basis": "wall clock with all devices working"}
