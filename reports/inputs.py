"""The report's inputs: reading and recognising the JSON results (benchmark suite, stability
suite, work–precision records, worked inverse problems), the views of a benchmark run the
report needs (:class:`Bench`), the command that made each file, what a run supports (quick
runs are marked indicative; power laws are fitted through enough sizes only), and the orders
in which structures, kernels and ray sets are listed."""

from __future__ import annotations

import json
import math
import shlex
from dataclasses import dataclass, field
from pathlib import Path

import accel
from jrt.scenes import parse_label
from reports.document import ReportError, plural

#: The commands that produce each kind of results (shown when a file does not record its own).
BENCH_COMMAND = "python -m benchmarks"
STABILITY_COMMAND = "python -m benchmarks.stability"
#: The runs of the work–precision diagrams (triangle kernel x float32/float64, Whitted
#: depth, wavelength samples, pruning threshold, exact tree versus sampled branches, Fresnel
#: exact versus Schlick) write records of kind "work_precision"; ``jrt study`` runs them.
WORK_PRECISION_COMMAND = "jrt study"
REPORT_COMMAND = "python -m reports.report"
INVERSE_COMMAND = "python -m benchmarks.inverse"

KERNEL_ORDER = ("watertight", "moller_trumbore", "plane_barycentric")
SET_ORDER = ("camera", "shadow", "reflected", "refracted", "incoherent")


def engine_structures() -> tuple[str, ...]:
    """The structures the traversal engine steps (every registered one but brute force),
    in the registry's order."""
    return tuple(n for n in accel.names() if n != "brute")


def structure_order() -> tuple[str, ...]:
    """The order structures are listed and coloured in: the engine's structures in the
    registry's order, brute force (the suite's reference) last."""
    return engine_structures() + ("brute",)


# ============================================================================================
# Reading records
# ============================================================================================


def median(value):
    """A number, or the median of a {median, min, max} summary; None otherwise."""
    if isinstance(value, dict):
        value = value.get("median")
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) else None


def geomean(values) -> float | None:
    """The geometric mean of the positive values; None where there are none."""
    values = [v for v in values if v is not None and v > 0]
    if not values:
        return None
    return math.exp(sum(math.log(v) for v in values) / len(values))


def scene_size(params: dict) -> str:
    """The size (``jrt.scenes.SIZES``) of a benchmark run's mesh: ``small`` for a small
    scene's label (``stadium-small``, ``camel-19k``), ``full`` otherwise."""
    parsed = parse_label(str(params.get("mesh", "")))
    return parsed[1] if parsed else "full"


def dicts(x) -> list[dict]:
    """The objects of a JSON list (nothing for anything else)."""
    return [r for r in x if isinstance(r, dict)] if isinstance(x, list) else []


def count(x) -> int:
    """A JSON integer as it is; 0 for anything else (missing, a bool, a float)."""
    return x if isinstance(x, int) and not isinstance(x, bool) else 0


def preferred_order(names, preferred) -> list:
    """Unique names, the preferred ones first in their order, the others as they came."""
    names = list(dict.fromkeys(names))
    return [n for n in preferred if n in names] + [n for n in names if n not in preferred]


def build_mib(rec) -> float | None:
    """A build record's memory (its arrays' ``bytes``) in MiB; None where not recorded."""
    return rec["bytes"] / 2**20 if isinstance(rec.get("bytes"), int | float) else None


def trace_counter(rec, name) -> float | None:
    """A trace record's engine counter ``name`` (steps, tests, leaves) per ray: its mean,
    or the number recorded; None where the run had no counters."""
    c = rec.get("counters") if isinstance(rec, dict) else None
    v = c.get(name) if isinstance(c, dict) else None
    return median(v.get("mean")) if isinstance(v, dict) else median(v)


def stability_rows(body) -> list[dict]:
    """The record objects of a stability case."""
    return dicts(body.get("records")) if isinstance(body, dict) else []


# ============================================================================================
# Results files
# ============================================================================================

_EXPECTED = (
    "expected a benchmark suite result (top-level \"schema\": \"jrt-bench/1\", from "
    f"`{BENCH_COMMAND}`), a stability suite result (top-level \"cases\", from "
    f"`{STABILITY_COMMAND}`), records of kind \"work_precision\" or a worked inverse "
    f"problem (\"kind\": \"inverse\", from `{INVERSE_COMMAND}`)")


@dataclass
class Bench:
    """One benchmark run and the views of its records the report needs."""

    path: Path
    data: dict
    label: str = ""

    @property
    def records(self) -> list[dict]:
        return self.data["records"]

    @property
    def params(self) -> dict:
        p = self.data.get("parameters")
        return p if isinstance(p, dict) else {}

    @property
    def machine(self) -> dict:
        m = self.data.get("machine")
        return m if isinstance(m, dict) else {}

    def of(self, kind: str, **match) -> list[dict]:
        return [r for r in self.records if r.get("kind") == kind
                and all(r.get(k) == v for k, v in match.items())]

    @property
    def structures(self) -> list[str]:
        named = self.params.get("structures") or []
        seen = [r["structure"] for r in self.records
                if r.get("kind") in ("build", "trace") and isinstance(r.get("structure"), str)]
        return preferred_order([*named, *seen], named or structure_order())

    @property
    def sets(self) -> list[str]:
        named = [s.get("name") for s in self.params.get("sets") or [] if isinstance(s, dict)]
        traced = {r.get("set") for r in self.of("trace")} | set(self.embree)
        return preferred_order([s for s in [*named, *traced] if s in traced], named or SET_ORDER)

    @property
    def builds(self) -> dict:
        return {r["structure"]: r for r in self.of("build")
                if isinstance(r.get("structure"), str)}

    @property
    def traces(self) -> dict:
        return {(r.get("structure"), r.get("set")): r for r in self.of("trace")}

    @property
    def embree(self) -> dict:
        return {r.get("set"): r for r in self.of("peer", peer="embree", status="ok")}

    def query(self, set_name: str) -> str:
        for s in self.params.get("sets") or []:
            if isinstance(s, dict) and s.get("name") == set_name:
                return s.get("query", "")
        rec = next((r for r in self.of("trace", set=set_name)), {})
        return rec.get("query", "")

    @property
    def command(self) -> str:
        return bench_command(self.data, self.path)


@dataclass
class Inputs:
    bench: list[Bench] = field(default_factory=list)
    #: Benchmark runs on a scene of the scene suite (``--scene NAME``): the cross-scene
    #: section's (``reports.scenes``), not the headline sections'.
    scenes: list[Bench] = field(default_factory=list)
    stability: list[tuple[Path, dict]] = field(default_factory=list)
    work_precision: list[tuple[Path, dict, str]] = field(default_factory=list)
    inverse: list[tuple[Path, dict]] = field(default_factory=list)
    kinds: list[tuple[Path, str]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    #: Why a file's numbers are indicative only (a quick run), by file; absent when full.
    indicative: dict[Path, str] = field(default_factory=dict)


def read_json(path: Path):
    """The JSON in ``path``, or a ReportError naming the file and what went wrong."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ReportError(f"{path}: no such file; {_EXPECTED}") from None
    except IsADirectoryError:
        raise ReportError(f"{path}: is a folder, not a JSON file; {_EXPECTED}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ReportError(f"{path}: cannot be read ({exc}); {_EXPECTED}") from None
    if not text.strip():
        raise ReportError(f"{path}: is empty; {_EXPECTED}")
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise ReportError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno}, column "
                          f"{exc.colno}); {_EXPECTED}") from None


def _is_wp(record) -> bool:
    return isinstance(record, dict) and record.get("kind") == "work_precision"


def classify(data) -> str:
    """"bench", "stability", "work_precision" or "inverse"; "" when the content is none of
    them."""
    if isinstance(data, list):
        return "work_precision" if data and all(_is_wp(r) for r in data) else ""
    if not isinstance(data, dict):
        return ""
    if data.get("kind") == "inverse":
        return "inverse"
    schema = data.get("schema")
    if isinstance(schema, str) and schema.startswith("jrt-bench/"):
        return "bench"
    if isinstance(data.get("cases"), dict):
        return "stability"
    records = data.get("records")
    if isinstance(records, list) and records and all(_is_wp(r) for r in records):
        return "work_precision"
    if isinstance(records, list) and "machine" in data and "parameters" in data:
        return "bench"
    return ""


def _describe(data) -> str:
    if isinstance(data, dict):
        keys = ", ".join(list(map(str, data))[:8]) or "none"
        return f"found a JSON object with top-level keys {keys}"
    if isinstance(data, list):
        return f"found a JSON array of {len(data)} items"
    return f"found a JSON {type(data).__name__}"


def load_inputs(paths) -> Inputs:
    """Read and recognise every results file; ReportError for the first one unusable."""
    inputs = Inputs()
    if not paths:
        raise ReportError(f"no results files given; {_EXPECTED}")
    for raw in paths:
        path = Path(raw)
        data = read_json(path)
        kind = classify(data)
        if not kind:
            raise ReportError(f"{path}: not a jrt results file: {_describe(data)}; {_EXPECTED}")
        inputs.kinds.append((path, kind))
        if kind == "bench":
            records = data.get("records")
            if not isinstance(records, list) or not all(isinstance(r, dict) and "kind" in r
                                                        for r in records):
                raise ReportError(f"{path}: a benchmark result whose \"records\" is not a list "
                                  "of objects with a \"kind\"; expected the JSON written by "
                                  f"`{BENCH_COMMAND}`")
            problem = _schema_problem(data)
            if problem:
                inputs.warnings.append(f"`{path}` does not fit the suite's schema "
                                       f"(benchmarks.schema): {problem}; the report uses what "
                                       "it can read")
            params = data.get("parameters")
            if isinstance(params, dict) and isinstance(params.get("scene"), str):
                inputs.scenes.append(Bench(path, data))
                inputs.kinds[-1] = (path, "scene")
            else:
                inputs.bench.append(Bench(path, data))
            cmd = _recorded_command(data) or bench_command(data, path)
            inputs.work_precision += [(path, r, r.get("command") or cmd)
                                      for r in records if _is_wp(r)]
        elif kind == "stability":
            for case, body in data["cases"].items():
                if not isinstance(body, dict) or not isinstance(body.get("records", []), list):
                    raise ReportError(f"{path}: stability case {case} is not an object with a "
                                      f"\"records\" list; expected the JSON written by "
                                      f"`{STABILITY_COMMAND}`")
            inputs.stability.append((path, data))
            if stability_indicative(data):
                inputs.indicative[path] = stability_indicative(data)
        elif kind == "inverse":
            problems = data.get("problems")
            if not isinstance(problems, list) or not all(
                    isinstance(p, dict) and {"problem", "parameters", "truth", "start", "found",
                                             "losses", "values"} <= set(p) for p in problems):
                raise ReportError(f"{path}: an inverse-problem result whose \"problems\" is not "
                                  "a list of problems (problem, parameters, truth, start, "
                                  "found, losses, values); expected the JSON written by "
                                  f"`{INVERSE_COMMAND} --json PATH`")
            inputs.inverse.append((path, data))
            if data.get("quick") is True:
                inputs.indicative[path] = "quick run (one problem, a small image)"
        else:
            records = data if isinstance(data, list) else data["records"]
            cmd = (None if isinstance(data, list) else _recorded_command(data))
            inputs.work_precision += [(path, r, r.get("command") or cmd or "") for r in records]
            if wp_indicative(data):
                inputs.indicative[path] = wp_indicative(data)
    for b in [*inputs.bench, *inputs.scenes]:
        if bench_indicative(b):
            inputs.indicative[b.path] = bench_indicative(b)
    if len(inputs.bench) > 1:
        for i, b in enumerate(inputs.bench, 1):
            b.label = f"run {i} (`{b.path.name}`)"
    return inputs


def _schema_problem(data) -> str | None:
    try:
        from benchmarks.schema import validate
    except Exception:  # the generator works without the benchmarks package
        return None
    records = data.get("records")
    known = dict(data, records=[r for r in records if not _is_wp(r)]) if isinstance(
        records, list) else data
    try:
        validate(known)
    except ValueError as exc:
        return str(exc)
    except Exception as exc:  # a validator that trips on odd input: say so, go on
        return f"{type(exc).__name__}: {exc}"
    return None


# ============================================================================================
# Commands
# ============================================================================================


def _recorded_command(data) -> str | None:
    """The command a results file records (``command``, or ``argv`` joined), at its top
    level or in its ``parameters``; None where it records none."""
    if not isinstance(data, dict):
        return None
    for holder in (data, data.get("parameters") or {}):
        if not isinstance(holder, dict):
            continue
        if isinstance(holder.get("command"), str):
            return holder["command"]
        argv = holder.get("argv")
        if isinstance(argv, list) and all(isinstance(a, str) for a in argv):
            return shlex.join(argv)
    return None


def bench_command(data: dict, path: Path) -> str:
    """The command that made a benchmark result: as recorded, else rebuilt from its
    parameters (the options that shape the data, with their values)."""
    recorded = _recorded_command(data)
    if recorded:
        return recorded
    p = data.get("parameters") if isinstance(data.get("parameters"), dict) else {}
    parts = [BENCH_COMMAND]
    if p.get("quick"):
        parts.append("--quick")
    if isinstance(p.get("scene"), str):  # a scene run: --scene NAME, its size if not implied
        small = scene_size(p) == "small"
        parts += ["--scene", p["scene"]]
        if small != bool(p.get("quick")):
            parts += ["--scene-size", "small" if small else "full"]
    elif p.get("mesh"):
        parts += ["--mesh", str(p["mesh"])]
    structures = p.get("structures")
    if structures and sorted(structures) != sorted(engine_structures()):
        parts += ["--structures", ",".join(structures)]
    if p.get("kernel") and p["kernel"] != "watertight":
        parts += ["--kernel", p["kernel"]]
    if p.get("device"):
        parts += ["--device", p["device"]]
    camera = p.get("camera") if isinstance(p.get("camera"), dict) else {}
    for flag, value in (("--camera-size", camera.get("width")), ("--rays", p.get("rays")),
                        ("--builds", p.get("builds")), ("--repeats", p.get("repeats")),
                        ("--scaling", p.get("scaling_meshes")),
                        ("--interface-rays", p.get("interface_rays"))):
        if value is not None:
            parts += [flag, str(value)]
    if p.get("seed"):
        parts += ["--seed", str(p["seed"])]
    parts += ["-o", str(path)]
    return shlex.join(parts).replace(shlex.quote(BENCH_COMMAND), BENCH_COMMAND)


def stability_command(data: dict, path: Path) -> str:
    """The command that made a stability result: as recorded, else rebuilt from its size
    and cases."""
    recorded = _recorded_command(data)
    if recorded:
        return recorded
    parts = [STABILITY_COMMAND]
    if data.get("quick"):
        parts.append("--quick")
    elif data.get("size") == "standard":
        parts += ["--size", "standard"]
    cases = list(data.get("cases", {}))
    if cases and cases != [str(c) for c in range(1, 10)]:
        parts += ["--cases", ",".join(cases)]
    parts += ["-o", str(path)]
    return shlex.join(parts).replace(shlex.quote(STABILITY_COMMAND), STABILITY_COMMAND)


# ============================================================================================
# What a run supports: indicative runs, power-law fits
# ============================================================================================

#: A power law is fitted only through this many distinct sizes: through two, any power law
#: fits exactly and the exponent carries all the noise of two timings.
MIN_FIT_SIZES = 3
#: The words that mark the numbers of a quick input (top of the report, sections, captions).
INDICATIVE = "indicative only"
#: Where a run does not record whether it is quick: ray sets under this many rays, or fewer
#: warm calls than MIN_REPEATS, make it indicative.
SMALL_RAYS = 65536
MIN_REPEATS = 3


def bench_indicative(b: Bench) -> str:
    """Why a benchmark run's numbers are indicative ("" for a full run): its ``quick`` flag
    (``parameters.quick``), or, where it records none, small ray sets or few warm calls."""
    p = b.params
    rays = [s.get("rays") for s in p.get("sets") or [] if isinstance(s, dict)]
    rays = [r for r in rays if count(r)] or [count(t.get("rays")) for t in b.of("trace")
                                             if count(t.get("rays"))]
    repeats = p.get("repeats") if count(p.get("repeats")) else min(
        (len(t["repeats"]) for t in b.of("trace") if isinstance(t.get("repeats"), list)),
        default=None)
    sizes = {row.get("triangles") for r in b.of("scaling") for row in dicts(r.get("rows"))
             if count(row.get("triangles"))}
    quick = p.get("quick")
    if not isinstance(quick, bool):
        quick = bool(rays and max(rays) < SMALL_RAYS) or (repeats or 0) < MIN_REPEATS
    if not quick:
        return ""
    parts = []
    if rays:
        parts.append(("small ray sets, " if max(rays) < SMALL_RAYS else "") + f"{min(rays):,}"
                     + (f"–{max(rays):,}" if max(rays) > min(rays) else "") + " rays a set")
    if repeats:
        parts.append(plural(repeats, "warm call") + " per set")
    if sizes:
        parts.append(plural(len(sizes), "scaling size"))
    return ("quick run" if p.get("quick") is True else "small run") + (
        f" ({', '.join(parts)})" if parts else "")


def stability_indicative(data: dict) -> str:
    """Why a stability run's numbers are indicative ("" for its standard or full sizes)."""
    return ("quick run (small sizes)" if data.get("quick") is True or data.get("size") == "quick"
            else "")


def wp_indicative(data) -> str:
    """Why work–precision points are indicative ("" unless made with ``--quick``)."""
    p = data.get("parameters") if isinstance(data, dict) else None
    return ("quick points (fewer points, smaller images)"
            if isinstance(p, dict) and p.get("quick") is True else "")


def fit_power(xs, ys) -> float | None:
    """k of ``y ~ c x^k``: the least-squares slope of log y against log x over the points
    with positive x and y, or None with fewer than MIN_FIT_SIZES distinct x among them."""
    pts = [(math.log(x), math.log(y)) for x, y in zip(xs, ys, strict=True)
           if x is not None and y is not None and x > 0 and y > 0]
    if len({x for x, _ in pts}) < MIN_FIT_SIZES:
        return None
    mx, my = (sum(p[i] for p in pts) / len(pts) for i in (0, 1))
    return (sum((x - mx) * (y - my) for x, y in pts) / sum((x - mx) ** 2 for x, _ in pts))


def scaling_fits(rec: dict) -> tuple[float | None, float | None, int]:
    """A scaling record's build- and trace-time exponents, fitted here from its rows'
    medians (not the exponents the run recorded: those are fitted through any two sizes),
    and its number of distinct sizes."""
    rows = [row for row in dicts(rec.get("rows")) if count(row.get("triangles"))]
    n = [row["triangles"] for row in rows]
    fits = [fit_power(n, [median(row.get(key)) for row in rows])
            for key in ("build_seconds", "trace_seconds")]
    return fits[0], fits[1], len(set(n))


def not_fitted(sizes: int) -> str:
    """What stands for an exponent that was not fitted, and why."""
    return f"not fitted ({plural(sizes, 'size')}; {MIN_FIT_SIZES} needed)"
