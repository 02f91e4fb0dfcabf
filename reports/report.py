"""The report generator: JSON results in, ``DIR/README.md`` + PNG figures and a
self-contained ``DIR/index.html`` out.

    python -m reports.report RESULTS.json... -o reports/NAME [--image PATH[:caption]]...
    jrt report RESULTS.json... -o reports/NAME            (the same options)

Each results file is recognised by its content:

- a **benchmark** run (``python -m benchmarks``): top-level ``"schema": "jrt-bench/1"``
  (or ``machine`` + ``parameters`` + ``records``), records of kind ``build``, ``trace``,
  ``peer``, ``correctness``, ``scaling``, ``cost_model`` (``benchmarks.schema``);
- a **stability** run (``python -m benchmarks.stability``): top-level ``"cases"``, each case
  with ``records`` and ``findings``;
- **work–precision** points: records of kind ``work_precision`` (in a file of their own,
  ``{"records": [...]}`` or a bare list, or among a benchmark run's records), each with a
  method label (``method`` or ``label``), ``seconds`` (a number or ``{"median": ...}``) and
  error metrics ``psnr``, ``ssim``, ``delta_e`` (also read as ``deltaE`` or ``ciede2000``),
  optionally a ``study`` (or ``group``) naming the diagram it belongs to and a ``command``.

Anything else is an error naming the file and what was expected. Parts that are missing
are left out of the report (a bench-only or a stability-only report works); the section
"Error against run time" says which command produces its data when there is none.

The report has: a reading of the numbers in words (fastest structure per ray set, ratios to
Embree, Havran's kd-tree claim against the measured steps and tests per ray, where each
kernel and offset breaks); the structures side by side (tables and bar charts); scaling
with fitted exponents; the cost model; error against run time; the stability suite's
tables and findings; renders given with ``--image``; the machine and library versions.
Every figure names, in its caption and in the image, the command that made its data.
Figures are drawn by matplotlib's Agg canvas (no pyplot state, no display needed).

What a run can support: a quick run (``parameters.quick``, or, where unrecorded, small ray
sets or fewer than three warm calls) is marked indicative at the top, in its sections and
in its figures; a power law is fitted only through three or more sizes (two fit any); one
structure is ranked ahead of another only where the min..max of their repeats do not
overlap, and the others are called tied within the run's spread.
"""

from __future__ import annotations

import argparse
import base64
import datetime
import html
import json
import math
import os
import platform
import re
import shlex
import shutil
import sys
import textwrap
import time
from dataclasses import dataclass, field
from pathlib import Path

#: The commands that produce each kind of results (shown when a file does not record its own).
BENCH_COMMAND = "python -m benchmarks"
STABILITY_COMMAND = "python -m benchmarks.stability"
#: The runs of the work–precision diagrams (triangle kernel x float32/float64, Whitted
#: depth, wavelength samples, pruning threshold, exact tree versus sampled branches, Fresnel
#: exact versus Schlick) write records of kind "work_precision"; ``jrt study`` runs them.
WORK_PRECISION_COMMAND = "jrt study"
REPORT_COMMAND = "python -m reports.report"

STRUCTURE_ORDER = ("bvh", "kdtree", "octree", "bsp", "grid", "brute")
KERNEL_ORDER = ("watertight", "moller_trumbore", "plane_barycentric")
SET_ORDER = ("camera", "shadow", "reflected", "refracted", "incoherent")
IMAGE_TYPES = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg",
               ".gif": "image/gif"}
#: Metrics of a work–precision record: (key, aliases, axis label, higher is better).
METRICS = (("psnr", ("psnr", "PSNR"), "PSNR (dB)", True),
           ("ssim", ("ssim", "SSIM"), "SSIM", True),
           ("delta_e", ("delta_e", "deltaE", "delta_e_2000", "ciede2000", "mean_delta_e"),
            "mean CIEDE2000 ΔE", False))
#: Rows of one stability table shown before the rest is left to the JSON.
MAX_ROWS = 40
#: Columns of one stability table (labels and the core counts first; the rest is in the JSON).
MAX_COLUMNS = 16
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


class ReportError(ValueError):
    """A results file or an option the report cannot use (the message names it)."""


# ============================================================================================
# Formatting
# ============================================================================================


def num(x, digits: int = 3) -> str:
    """A table cell: ``digits`` significant digits in plain notation between 1e-3 and 1e6,
    scientific outside; integers whole; None as a dash; strings ("nan", "inf") as they are."""
    if x is None:
        return "–"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, str):
        return x
    if isinstance(x, int):
        return str(x)
    x = float(x)
    if not math.isfinite(x):
        return str(x)
    if x == 0:
        return "0"
    e = math.floor(math.log10(abs(x)))
    if -3 <= e < 6:
        return f"{x:.{max(0, digits - 1 - e)}f}"
    return f"{x:.{digits - 1}e}"


def _median(value):
    """A number, or the median of a {median, min, max} summary; None otherwise."""
    if isinstance(value, dict):
        value = value.get("median")
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) else None


def _seconds(x) -> str:
    return f"{x:.3g} s" if isinstance(x, int | float) and not isinstance(x, bool) else "? s"


def _dicts(x) -> list[dict]:
    """The objects of a JSON list (nothing for anything else)."""
    return [r for r in x if isinstance(r, dict)] if isinstance(x, list) else []


def _count(x) -> int:
    return x if isinstance(x, int) and not isinstance(x, bool) else 0


def _geomean(values) -> float | None:
    values = [v for v in values if v is not None and v > 0]
    if not values:
        return None
    return math.exp(sum(math.log(v) for v in values) / len(values))


def _order(names, preferred) -> list:
    """Unique names, the preferred ones first in their order, the others as they came."""
    names = list(dict.fromkeys(names))
    return [n for n in preferred if n in names] + [n for n in names if n not in preferred]


def _plural(n: int, word: str) -> str:
    return f"{n:,} {word}{'' if n == 1 else 's'}"


def _join(items) -> str:
    items = list(items)
    if len(items) <= 1:
        return "".join(items)
    return ", ".join(items[:-1]) + " and " + items[-1]


# ============================================================================================
# The document: one list of blocks, written as Markdown and as HTML
# ============================================================================================


@dataclass
class Block:
    kind: str  # heading, para, bullets, table, figure, code, quote
    text: str = ""
    level: int = 2
    items: list = field(default_factory=list)
    header: list = field(default_factory=list)
    rows: list = field(default_factory=list)
    file: Path | None = None  # figure: the PNG on disk
    rel: str = ""  # figure: its path relative to the report's folder
    anchor: str = ""


class Doc:
    """Headings, paragraphs (inline `code` and **bold**), bullet lists, tables, figures."""

    def __init__(self):
        self.blocks: list[Block] = []
        self._anchors: set[str] = set()

    def heading(self, level: int, text: str) -> None:
        base = re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-") or "section"
        anchor, i = base, 1
        while anchor in self._anchors:
            i += 1
            anchor = f"{base}-{i}"
        self._anchors.add(anchor)
        self.blocks.append(Block("heading", text, level=level, anchor=anchor))

    def para(self, text: str) -> None:
        self.blocks.append(Block("para", text))

    def quote(self, text: str) -> None:
        self.blocks.append(Block("quote", text))

    def bullets(self, items) -> None:
        items = [i for i in items if i]
        if items:
            self.blocks.append(Block("bullets", items=items))

    def table(self, header, rows, caption: str = "") -> None:
        if rows:
            self.blocks.append(Block("table", caption, header=list(header),
                                     rows=[[str(c) for c in r] for r in rows]))

    def figure(self, file: Path, rel: str, caption: str) -> None:
        self.blocks.append(Block("figure", caption, file=file, rel=rel))

    def code(self, text: str) -> None:
        self.blocks.append(Block("code", text))

    # --- Markdown ---

    def markdown(self) -> str:
        out = []
        for b in self.blocks:
            if b.kind == "heading":
                out.append(f"{'#' * b.level} {b.text}")
            elif b.kind == "para":
                out.append(b.text)
            elif b.kind == "quote":
                out.append("> " + b.text.replace("\n", "\n> "))
            elif b.kind == "bullets":
                out.append("\n".join(f"- {item}" for item in b.items))
            elif b.kind == "table":
                lines = ["| " + " | ".join(_md_cell(c) for c in b.header) + " |",
                         "| " + " | ".join("---" for _ in b.header) + " |"]
                lines += ["| " + " | ".join(_md_cell(c) for c in r) + " |" for r in b.rows]
                if b.text:
                    lines += ["", f"*{b.text}*"]
                out.append("\n".join(lines))
            elif b.kind == "figure":
                alt = re.sub(r"[`*\[\]]", "", b.text.split(". ")[0])[:100]
                out.append(f"![{alt}]({b.rel})\n\n*{b.text}*")
            elif b.kind == "code":
                out.append(f"```\n{b.text}\n```")
        return "\n\n".join(out) + "\n"

    # --- HTML ---

    def html(self, title: str) -> str:
        body = []
        for b in self.blocks:
            if b.kind == "heading":
                body.append(f'<h{b.level} id="{b.anchor}">{_inline(b.text)}</h{b.level}>')
            elif b.kind == "para":
                body.append(f"<p>{_inline(b.text)}</p>")
            elif b.kind == "quote":
                body.append(f"<blockquote>{_inline(b.text)}</blockquote>")
            elif b.kind == "bullets":
                body.append("<ul>" + "".join(f"<li>{_inline(i)}</li>" for i in b.items)
                            + "</ul>")
            elif b.kind == "table":
                head = "".join(f"<th>{_inline(c)}</th>" for c in b.header)
                rows = "".join("<tr>" + "".join(f"<td>{_inline(c)}</td>" for c in r) + "</tr>"
                               for r in b.rows)
                cap = f"<caption>{_inline(b.text)}</caption>" if b.text else ""
                body.append(f"<table>{cap}<thead><tr>{head}</tr></thead>"
                            f"<tbody>{rows}</tbody></table>")
            elif b.kind == "figure":
                mime = IMAGE_TYPES.get(b.file.suffix.lower(), "image/png")
                data = base64.b64encode(b.file.read_bytes()).decode("ascii")
                alt = html.escape(re.sub(r"[`*]", "", b.text)[:100], quote=True)
                body.append(f'<figure><img alt="{alt}" src="data:{mime};base64,{data}">'
                            f"<figcaption>{_inline(b.text)}</figcaption></figure>")
            elif b.kind == "code":
                body.append(f"<pre><code>{html.escape(b.text)}</code></pre>")
        return (
            "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            f"<title>{html.escape(title)}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n"
            + "\n".join(body) + "\n</body>\n</html>\n")


_CSS = (
    "body{font-family:system-ui,-apple-system,'Segoe UI',sans-serif;max-width:70em;"
    "margin:2em auto;padding:0 1em;line-height:1.45;color:#222}"
    "table{border-collapse:collapse;margin:1em 0;font-size:.9em}"
    "th,td{border:1px solid #ccc;padding:.25em .6em;text-align:left;vertical-align:top}"
    "th{background:#f3f3f3}caption{caption-side:bottom;font-style:italic;padding:.3em}"
    "code{background:#f3f3f3;padding:0 .2em;border-radius:3px;font-size:.92em}"
    "pre{background:#f3f3f3;padding:.6em;overflow-x:auto}"
    "figure{margin:1.5em 0}img{max-width:100%}figcaption{font-style:italic;font-size:.9em}"
    "blockquote{border-left:4px solid #ccc;margin:1em 0;padding:.1em 1em;color:#444}")


def _md_cell(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _inline(text: str) -> str:
    """HTML of a line with `code` spans and **bold**; everything else escaped."""
    parts = str(text).split("`")
    out = []
    for i, part in enumerate(parts):
        if i % 2 and i < len(parts) - 1:
            out.append(f"<code>{html.escape(part)}</code>")
        else:
            esc = html.escape(part if i % 2 == 0 else "`" + part)
            esc = re.sub(r"\*\*(.+?)\*\*", r"<strong>\1</strong>", esc)
            out.append(re.sub(r"(?<![*\w])\*(?![\s*])(.+?)(?<![\s*])\*(?![*\w])",
                              r"<em>\1</em>", esc))
    return "".join(out)


# ============================================================================================
# Inputs
# ============================================================================================

_EXPECTED = (
    "expected a benchmark suite result (top-level \"schema\": \"jrt-bench/1\", from "
    f"`{BENCH_COMMAND}`), a stability suite result (top-level \"cases\", from "
    f"`{STABILITY_COMMAND}`) or records of kind \"work_precision\"")


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
        return _order([*named, *seen], named or STRUCTURE_ORDER)

    @property
    def sets(self) -> list[str]:
        named = [s.get("name") for s in self.params.get("sets") or [] if isinstance(s, dict)]
        traced = {r.get("set") for r in self.of("trace")} | set(self.embree)
        return _order([s for s in [*named, *traced] if s in traced], named or SET_ORDER)

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
    stability: list[tuple[Path, dict]] = field(default_factory=list)
    work_precision: list[tuple[Path, dict, str]] = field(default_factory=list)
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
    """"bench", "stability" or "work_precision"; "" when the content is none of them."""
    if isinstance(data, list):
        return "work_precision" if data and all(_is_wp(r) for r in data) else ""
    if not isinstance(data, dict):
        return ""
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
        else:
            records = data if isinstance(data, list) else data["records"]
            cmd = (None if isinstance(data, list) else _recorded_command(data))
            inputs.work_precision += [(path, r, r.get("command") or cmd or "") for r in records]
            if wp_indicative(data):
                inputs.indicative[path] = wp_indicative(data)
    for b in inputs.bench:
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
    if p.get("mesh"):
        parts += ["--mesh", str(p["mesh"])]
    structures = p.get("structures")
    if structures and sorted(structures) != sorted(STRUCTURE_ORDER[:5]):
        parts += ["--structures", ",".join(structures)]
    if p.get("kernel") and p["kernel"] != "watertight":
        parts += ["--kernel", p["kernel"]]
    if p.get("device"):
        parts += ["--device", p["device"]]
    camera = p.get("camera") if isinstance(p.get("camera"), dict) else {}
    for flag, value in (("--camera-size", camera.get("width")), ("--rays", p.get("rays")),
                        ("--builds", p.get("builds")), ("--repeats", p.get("repeats")),
                        ("--scaling", p.get("scaling_meshes"))):
        if value is not None:
            parts += [flag, str(value)]
    if p.get("seed"):
        parts += ["--seed", str(p["seed"])]
    parts += ["-o", str(path)]
    return shlex.join(parts).replace(shlex.quote(BENCH_COMMAND), BENCH_COMMAND)


def stability_command(data: dict, path: Path) -> str:
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
# What a run supports: indicative runs, power-law fits, ranks within the spread
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
TIED = "tied within the run's spread"


def bench_indicative(b: Bench) -> str:
    """Why a benchmark run's numbers are indicative ("" for a full run): its ``quick`` flag
    (``parameters.quick``), or, where it records none, small ray sets or few warm calls."""
    p = b.params
    rays = [s.get("rays") for s in p.get("sets") or [] if isinstance(s, dict)]
    rays = [r for r in rays if _count(r)] or [_count(t.get("rays")) for t in b.of("trace")
                                             if _count(t.get("rays"))]
    repeats = p.get("repeats") if _count(p.get("repeats")) else min(
        (len(t["repeats"]) for t in b.of("trace") if isinstance(t.get("repeats"), list)),
        default=None)
    sizes = {row.get("triangles") for r in b.of("scaling") for row in _dicts(r.get("rows"))
             if _count(row.get("triangles"))}
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
        parts.append(_plural(repeats, "warm call") + " per set")
    if sizes:
        parts.append(_plural(len(sizes), "scaling size"))
    return ("quick run" if p.get("quick") is True else "small run") + (
        f" ({', '.join(parts)})" if parts else "")


def stability_indicative(data: dict) -> str:
    return ("quick run (small sizes)" if data.get("quick") is True or data.get("size") == "quick"
            else "")


def wp_indicative(data) -> str:
    p = data.get("parameters") if isinstance(data, dict) else None
    return ("quick points (fewer points, smaller images)"
            if isinstance(p, dict) and p.get("quick") is True else "")


def _mark(reason: str) -> str:
    """The sentence that marks a quick input's section or figure ("" for a full one)."""
    return f"**{INDICATIVE.capitalize()}**: {reason}." if reason else ""


def _section_mark(b: Bench) -> str:
    """The mark as a sentence to open a quick run's section paragraph with ("" if full)."""
    reason = bench_indicative(b)
    return _mark(reason) + " " if reason else ""


def _marked(caption: str, reason: str) -> str:
    """A figure caption with the mark before its ``Data:`` (captions are italic already)."""
    if not reason:
        return caption
    mark = f"{INDICATIVE.capitalize()}: {reason}."
    return caption.replace(" Data: ", f" {mark} Data: ", 1) if " Data: " in caption else (
        f"{caption} {mark}")


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
    rows = [row for row in _dicts(rec.get("rows")) if _count(row.get("triangles"))]
    n = [row["triangles"] for row in rows]
    fits = [fit_power(n, [_median(row.get(key)) for row in rows])
            for key in ("build_seconds", "trace_seconds")]
    return fits[0], fits[1], len(set(n))


def _not_fitted(sizes: int) -> str:
    return f"not fitted ({_plural(sizes, 'size')}; {MIN_FIT_SIZES} needed)"


def _interval(values) -> tuple[float, float] | None:
    """min..max of two or more timings; None with fewer (no spread to order by)."""
    xs = [float(v) for v in values if isinstance(v, int | float) and not isinstance(v, bool)
          and math.isfinite(v) and v > 0] if isinstance(values, list) else []
    return (min(xs), max(xs)) if len(xs) >= 2 else None


def rate_spread(rec: dict) -> tuple[float, float] | None:
    """min..max Mrays/s of a trace's warm calls: from its per-call times (``repeats``) and
    ray count, else its rate's recorded min and max; None with one call."""
    times, rays = _interval(rec.get("repeats")), _count(rec.get("rays"))
    if times and rays:
        return rays / times[1] / 1e6, rays / times[0] / 1e6
    rate = rec.get("mrays_per_s")
    lo, hi = (_median(rate.get(k)) for k in ("min", "max")) if isinstance(rate, dict) else (
        None, None)
    return (lo, hi) if lo and hi and lo < hi else None


def build_spread(rec: dict) -> tuple[float, float] | None:
    """min..max seconds of a structure's builds (``repeats``, else ``seconds``' min, max)."""
    times = _interval(rec.get("repeats"))
    if times:
        return times
    s = rec.get("seconds")
    lo, hi = (_median(s.get(k)) for k in ("min", "max")) if isinstance(s, dict) else (None,
                                                                                      None)
    return (lo, hi) if lo and hi and lo < hi else None


def _ahead(values: dict, a: str, b: str, higher: bool = True) -> bool:
    """``a`` certainly ahead of ``b``: their min..max intervals do not overlap."""
    ia, ib = values[a][1], values[b][1]
    if ia is None or ib is None:
        return False
    return ia[0] > ib[1] if higher else ia[1] < ib[0]


def places(values: dict, higher: bool = True) -> dict[str, tuple[int, int]]:
    """Each name's possible places (best, worst), 1 the first, from {name: (value, min..max
    or None)}: one name is ahead of another only when their intervals do not overlap, so a
    name tied with others spans their places; no interval, no order."""
    return {n: (1 + sum(_ahead(values, o, n, higher) for o in values if o != n),
                len(values) - sum(_ahead(values, n, o, higher) for o in values if o != n))
            for n in values}


def tied_with(name: str, values: dict, higher: bool = True) -> list[str]:
    """The names neither certainly ahead of ``name`` nor certainly behind it."""
    return [o for o in values if o != name and not _ahead(values, o, name, higher)
            and not _ahead(values, name, o, higher)]


def _place(rank: tuple[int, int]) -> str:
    return str(rank[0]) if rank[0] == rank[1] else f"{rank[0]}–{rank[1]}"


# ============================================================================================
# Figures (matplotlib's Agg canvas, no pyplot)
# ============================================================================================


def _colour(name: str, names: list[str]) -> str:
    from matplotlib import colormaps

    palette = colormaps["tab10"].colors
    order = _order(names, STRUCTURE_ORDER)
    index = (STRUCTURE_ORDER.index(name) if name in STRUCTURE_ORDER
             else len(STRUCTURE_ORDER) + order.index(name))
    return palette[index % len(palette)]


def _new_figure(width: float, height: float, ncols: int = 1):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height))
    axes = [fig.add_subplot(1, ncols, i + 1) for i in range(ncols)]
    return fig, axes


def _plain_log(*axes) -> None:
    """Log axes labelled 0.2, 3, 20000 rather than 2 x 10^-1 (the same ticks as matplotlib's
    default, which decides which ones carry a label)."""
    from matplotlib.ticker import LogFormatterSciNotation

    class Plain(LogFormatterSciNotation):
        def __call__(self, x, pos=None):
            return f"{x:g}" if super().__call__(x, pos) else ""

    for ax in axes:
        for axis, scale in ((ax.xaxis, ax.get_xscale()), (ax.yaxis, ax.get_yscale())):
            if scale == "log":
                axis.set_major_formatter(Plain())
                axis.set_minor_formatter(Plain(labelOnlyBase=False))


def _save(fig, file: Path, command: str, layout: bool = True, note: str = "") -> None:
    """Name the command under the plot (after ``note``: why its numbers are indicative, if
    they are), lay out (not for figures whose colour bars tight_layout cannot place:
    ``layout=False``), write a PNG."""
    _plain_log(*fig.axes)
    width, height = fig.get_size_inches()
    text = (f"{INDICATIVE}: {note}; " if note else "") + f"data: {command}"
    lines = textwrap.wrap(text, width=max(40, int(width * 15.5)), break_on_hyphens=False)
    fig.text(0.01, 0.01, "\n".join(lines), fontsize=7, family="monospace", color="0.3",
             ha="left", va="bottom")
    if layout:
        bottom = (0.06 + 0.125 * len(lines)) / height
        fig.tight_layout(rect=(0, min(bottom, 0.4), 1, 1))
    file.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(file, dpi=110, metadata={"Software": None})


def fig_rates(b: Bench, file: Path) -> None:
    """Mrays/s per ray set per structure (min-max whiskers), Embree as a reference line."""
    sets, names, traces, embree = b.sets, b.structures, b.traces, b.embree
    fig, (ax,) = _new_figure(max(6.5, 1.5 * len(sets) + 2.5), 4.4)
    n = max(1, len(names))
    width = 0.8 / n
    for i, name in enumerate(names):
        xs, ys, lo, hi = [], [], [], []
        for j, s in enumerate(sets):
            rec = traces.get((name, s))
            rate = rec and rec.get("mrays_per_s")
            med = _median(rate)
            if med is None:
                continue
            xs.append(j + (i - (n - 1) / 2) * width)
            ys.append(med)
            lo.append(med - (_median(rate.get("min")) or med) if isinstance(rate, dict) else 0)
            hi.append((_median(rate.get("max")) or med) - med if isinstance(rate, dict) else 0)
        if xs:
            ax.bar(xs, ys, width, color=_colour(name, names), label=name,
                   yerr=[lo, hi], capsize=2, error_kw={"elinewidth": 0.8})
    labelled = False
    for j, s in enumerate(sets):
        rate = _median(embree.get(s, {}).get("mrays_per_s"))
        if rate:
            ax.hlines(rate, j - 0.45, j + 0.45, colors="k", linestyles="--", linewidth=1.4,
                      label=None if labelled else "Embree (same rays)")
            labelled = True
    ax.set_yscale("log")
    ax.set_xticks(range(len(sets)), [f"{s}\n({b.query(s)})" for s in sets])
    ax.set_ylabel("Mrays/s (median of warm calls)")
    ax.set_title("Trace rate per ray set" + (f" — {b.path.name}" if b.label else ""))
    ax.grid(axis="y", which="both", alpha=0.3)
    ax.legend(fontsize=8, ncol=min(len(names) + 1, 6), loc="upper center",
              bbox_to_anchor=(0.5, -0.16), frameon=False)
    _save(fig, file, b.command, note=bench_indicative(b))


def fig_bars(b: Bench, file: Path, values: dict, errors: dict | None, ylabel: str,
             title: str) -> None:
    names = [n for n in b.structures if values.get(n) is not None]
    fig, (ax,) = _new_figure(max(5.0, 0.9 * len(names) + 2), 3.6)
    ys = [values[n] for n in names]
    err = None
    if errors:
        err = [[values[n] - errors[n][0] for n in names], [errors[n][1] - values[n]
                                                          for n in names]]
    ax.bar(names, ys, color=[_colour(n, names) for n in names], yerr=err, capsize=3)
    for x, y in enumerate(ys):
        ax.annotate(num(y), (x, y), ha="center", va="bottom", fontsize=8,
                    xytext=(0, 2), textcoords="offset points")
    ax.set_ylabel(ylabel)
    ax.set_title(title + (f" — {b.path.name}" if b.label else ""))
    ax.grid(axis="y", alpha=0.3)
    ax.set_ylim(0, max(ys) * 1.15 if ys else 1)
    _save(fig, file, b.command, note=bench_indicative(b))


def _fit_line(ax, xs, ys, exponent, colour) -> None:
    """The fitted power law y = c N^exponent through the points (least squares in log c)."""
    if exponent is None or len(set(xs)) < MIN_FIT_SIZES:
        return
    logc = sum(math.log(y) - exponent * math.log(x) for x, y in zip(xs, ys, strict=True))
    logc /= len(xs)
    grid = [min(xs), max(xs)]
    ax.plot(grid, [math.exp(logc) * x**exponent for x in grid], ls=":", color=colour, lw=1)


def fig_scaling(b: Bench, file: Path) -> None:
    recs = {r["structure"]: r for r in b.of("scaling") if isinstance(r.get("structure"), str)}
    names = [n for n in b.structures if n in recs] + [n for n in recs if n not in b.structures]
    fig, (ax_b, ax_t) = _new_figure(11.0, 4.4, ncols=2)
    embree_pts, fitted, sizes = {}, False, 0
    for name in names:
        r = recs[name]
        rows = sorted((row for row in _dicts(r.get("rows")) if _count(row.get("triangles"))),
                      key=lambda row: row["triangles"])
        colour = _colour(name, names)
        n = [row["triangles"] for row in rows]
        build = [_median(row.get("build_seconds")) for row in rows]
        rate = [_median(row.get("mrays_per_s")) for row in rows]
        be, te, sizes = scaling_fits(r)
        fitted = fitted or be is not None or te is not None
        pts = [(x, y) for x, y in zip(n, build, strict=True) if y]
        if pts:
            label = name + (f": N^{be:.2f}" if isinstance(be, int | float) else "")
            ax_b.plot(*zip(*pts, strict=True), "o-", color=colour, label=label)
            _fit_line(ax_b, *zip(*pts, strict=True), be if isinstance(be, int | float)
                      else None, colour)
        pts = [(x, y) for x, y in zip(n, rate, strict=True) if y]
        if pts:
            label = name + (f": N^{-te:.2f} (time N^{te:.2f})" if isinstance(te, int | float)
                            else "")
            ax_t.plot(*zip(*pts, strict=True), "o-", color=colour, label=label)
            _fit_line(ax_t, *zip(*pts, strict=True), -te if isinstance(te, int | float)
                      else None, colour)
        for row in rows:
            if _median(row.get("embree_mrays_per_s")):
                embree_pts[row["triangles"]] = _median(row["embree_mrays_per_s"])
    if embree_pts:
        xs = sorted(embree_pts)
        ax_t.plot(xs, [embree_pts[x] for x in xs], "s--", color="k", label="Embree")
    for ax, ylabel, title in ((ax_b, "build time (s, median)", "Build time against N"),
                              (ax_t, "camera Mrays/s (median)", "Trace rate against N")):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("triangles N")
        ax.set_ylabel(ylabel)
        ax.set_title(title + (f" — {b.path.name}" if b.label else ""))
        ax.grid(which="both", alpha=0.3)
        ax.legend(fontsize=7.5, title="fitted exponent" if fitted else
                  f"exponents {_not_fitted(sizes)}", title_fontsize=7.5)
    _save(fig, file, b.command, note=bench_indicative(b))


def fig_cost_model(b: Bench, file: Path) -> None:
    """Measured against predicted time per ray, one point per structure and ray set."""
    recs = b.of("cost_model")
    names = [str(r.get("structure", "?")) for r in recs]
    fig, (ax,) = _new_figure(5.6, 4.8)
    markers = dict(zip(SET_ORDER, "o^sDv", strict=True))
    lo, hi = math.inf, 0.0
    for r in recs:
        for p in _dicts(r.get("points")):
            rays, seconds = _count(p.get("rays")), _median(p.get("seconds"))
            predicted = _median(p.get("predicted_seconds"))
            if not rays or not seconds or predicted is None:
                continue
            x, y = 1e9 * predicted / rays, 1e9 * seconds / rays
            if x <= 0 or y <= 0:
                continue
            ax.scatter(x, y, color=_colour(str(r.get("structure", "?")), names),
                       marker=markers.get(p.get("set"), "o"), s=30)
            lo, hi = min(lo, x, y), max(hi, x, y)
    if hi > 0:
        ax.plot([lo / 1.3, hi * 1.3], [lo / 1.3, hi * 1.3], "k:", lw=1)
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], ls="", marker="o", color=_colour(n, names), label=n)
               for n in names]
    handles += [Line2D([], [], ls="", marker=markers[s], color="0.4", label=s)
                for s in SET_ORDER if any(p.get("set") == s for r in recs
                                          for p in _dicts(r.get("points")))]
    ax.legend(handles=handles, fontsize=7.5, ncol=2)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("predicted ns per ray: C_0 + C_TS steps + C_IT tests")
    ax.set_ylabel("measured ns per ray (wall clock)")
    ax.set_title("Cost model fit" + (f" — {b.path.name}" if b.label else ""))
    ax.grid(which="both", alpha=0.3)
    _save(fig, file, b.command, note=bench_indicative(b))


def fig_work_precision(points: list[dict], metrics: list[tuple], file: Path, title: str,
                       command: str, note: str = "") -> None:
    fig, axes = _new_figure(max(5.0, 4.6 * len(metrics)), 4.2, ncols=len(metrics))
    series = list(dict.fromkeys(p["series"] for p in points))
    from matplotlib import colormaps

    palette = colormaps["tab10"].colors
    for ax, (key, _, label, higher) in zip(axes, metrics, strict=True):
        for i, name in enumerate(series):
            pts = sorted((p["seconds"], p[key], p["method"]) for p in points
                         if p["series"] == name and p.get(key) is not None)
            if not pts:
                continue
            xs, ys, methods = zip(*pts, strict=True)
            ax.plot(xs, ys, "o-" if len(pts) > 1 else "o", color=palette[i % len(palette)],
                    label=name, ms=5)
            for x, y, m in pts:  # a series of several points: name each point
                if m != name:
                    ax.annotate(m, (x, y), fontsize=7, xytext=(3, 3),
                                textcoords="offset points")
        ax.set_xscale("log")
        ax.margins(x=0.08, y=0.1)
        ax.set_xlabel("run time (s)")
        ax.set_ylabel(label + (" (higher is better)" if higher else " (lower is better)"))
        ax.grid(which="both", alpha=0.3)
    axes[0].legend(fontsize=7.5)
    fig.suptitle(title, fontsize=11)
    _save(fig, file, command, note=note)


# ============================================================================================
# Sections
# ============================================================================================


def _mib(rec) -> float | None:
    return rec["bytes"] / 2**20 if isinstance(rec.get("bytes"), int | float) else None


def _counter(rec, name) -> float | None:
    c = rec.get("counters") if isinstance(rec, dict) else None
    v = c.get(name) if isinstance(c, dict) else None
    return _median(v.get("mean")) if isinstance(v, dict) else _median(v)


def _prefix(b: Bench, multi: bool, n: int) -> str:
    return f"bench{n}-" if multi else ""


def section_structures(doc: Doc, b: Bench, out: Path, prefix: str) -> None:
    p, sets, names = b.params, b.sets, b.structures
    builds, traces, embree = b.builds, b.traces, b.embree
    doc.heading(2, "The structures side by side" + (f": {b.label}" if b.label else ""))
    mark = bench_indicative(b)
    mesh = p.get("mesh") or "the mesh"
    tris = p.get("triangles")
    set_desc = []
    for s in sets:
        rays = next((traces[n, s].get("rays") for n in names if (n, s) in traces), None)
        set_desc.append(f"{s} ({b.query(s)}" + (f", {rays:,} rays)" if isinstance(rays, int)
                                                else ")"))
    doc.para(
        _section_mark(b) + f"Mesh: `{mesh}`"
        + (f" ({tris:,} triangles)" if isinstance(tris, int) else "")
        + (f"; kernel `{p['kernel']}`" if p.get("kernel") else "")
        + (f"; ray sets: {_join(set_desc)}" if set_desc else "")
        + (f"; {p['repeats']} warm calls per structure and set (median, min, max)"
           if p.get("repeats") else "")
        + (f", {p['builds']} builds per structure" if p.get("builds") else "")
        + (f"; Embree (embreex, robust mode, {p['embree_threads']} threads) on the same rays "
           "in the same process" if p.get("embree_threads") else "")
        + f". Data: `{b.command}`.")
    if not builds and not traces:
        doc.para("No build or trace records in this run.")
        return
    header = ["structure", "build (s)", "memory (MiB)", "SAH cost"]
    header += [f"{s} Mrays/s (x Embree)" for s in sets]
    rows = []
    if embree:
        rows.append(["Embree", "", "", ""] + [
            f"{num(_median(embree[s].get('mrays_per_s')))} (1)" if s in embree else "–"
            for s in sets])
    for name in names:
        bld = builds.get(name, {})
        row = [name, num(_median(bld.get("seconds"))), num(_mib(bld)), num(bld.get("sah_cost"))]
        for s in sets:
            t = traces.get((name, s))
            row.append(f"{num(_median(t.get('mrays_per_s')))} ({num(t.get('ratio_to_embree'))})"
                       if t else "–")
        rows.append(row)
    doc.table(header, rows, "build: median of the builds; Mrays/s: median of the warm calls; "
                            "x Embree: the ratio to Embree's median rate on the same rays")

    rows = []
    for name in names:
        row = [name]
        for s in sets:
            t = traces.get((name, s))
            row.append(f"{num(_counter(t, 'steps'))} / {num(_counter(t, 'tests'))} / "
                       f"{num(_counter(t, 'leaves'))}" if t and t.get("counters") else "–")
        rows.append(row)
    doc.table(["structure"] + [f"{s}: steps / tests / leaves" for s in sets], rows,
              "per ray, mean over the set, from a run with the engine's counters")

    rows = []
    for name in names:
        bld = builds.get(name)
        if bld:
            rows.append([name, num(bld.get("nodes")), num(bld.get("leaves")),
                         num(bld.get("depth")), num(bld.get("references_per_leaf_mean")),
                         num(bld.get("references_per_leaf_max")),
                         f"{num(_median(bld.get('seconds', {}).get('min')))}–"
                         f"{num(_median(bld.get('seconds', {}).get('max')))}"
                         if isinstance(bld.get("seconds"), dict) else "–"])
    doc.table(["structure", "nodes or cells", "leaves", "depth", "references per leaf",
               "max references per leaf", "build min–max (s)"], rows)

    checks = b.of("correctness")
    if checks:
        by = {(r.get("structure"), r.get("set")): r for r in checks}
        rows = []
        for name in names:
            row = [name]
            for s in sets:
                r = by.get((name, s))
                row.append(f"{r.get('mismatches')} / {num(r.get('rays'))} "
                           f"({r.get('embree_disagreements', '–')})" if r else "–")
            rows.append(row)
        doc.table(["structure"] + [f"{s}: mismatches / rays (Embree)" for s in sets], rows,
                  "hits against brute force with the same kernel, bit for bit (triangle, t, u, "
                  "v; occluded for any-hit rays); in brackets, rays whose triangle differs "
                  "from Embree's over the whole set (Embree has its own kernel)")
    peers = [r for r in b.of("peer") if r.get("peer") != "embree"]
    if peers:
        ok = [r for r in peers if r.get("status") == "ok"]
        doc.table(["peer", "set", "rays", "Mrays/s", "x Embree", "note"],
                  [[r.get("peer", "?"), r.get("set"), num(r.get("rays")),
                    num(_median(r.get("mrays_per_s"))), num(r.get("ratio_to_embree")),
                    r.get("note", "")] for r in ok])
        absent = [f"{r.get('peer', '?')} ({r.get('status')}: {r.get('note', '')})" for r in peers
                  if r.get("status") != "ok"]
        if absent:
            doc.para("Other peers: " + "; ".join(dict.fromkeys(absent)) + ".")

    if traces:
        f = out / "figures" / f"{prefix}rates.png"
        fig_rates(b, f)
        doc.figure(f, f"figures/{f.name}", _marked(
                   "Mrays/s per ray set and structure (bars: median, whiskers: min–max of the "
                   f"warm calls; log scale), Embree's median on the same rays dashed. "
                   f"Data: `{b.command}`.", mark))
    values = {n: _median(builds[n].get("seconds")) for n in names if n in builds}
    if any(v is not None for v in values.values()):
        err = {n: (_median(builds[n]["seconds"].get("min")) or values[n],
                   _median(builds[n]["seconds"].get("max")) or values[n])
               for n in values if isinstance(builds[n].get("seconds"), dict)
               and values[n] is not None}
        f = out / "figures" / f"{prefix}build.png"
        fig_bars(b, f, values, err if len(err) == len([v for v in values.values() if v])
                 else None, "build time (s)", "Build time (median, min–max)")
        doc.figure(f, f"figures/{f.name}", _marked(
                   f"Build time per structure (median of the builds, whiskers min–max). "
                   f"Data: `{b.command}`.", mark))
    values = {n: _mib(builds[n]) for n in names if n in builds}
    if any(v is not None for v in values.values()):
        f = out / "figures" / f"{prefix}memory.png"
        fig_bars(b, f, values, None, "memory (MiB)", "Memory of the structure's arrays")
        doc.figure(f, f"figures/{f.name}", _marked(
                   f"Memory per structure (bytes of its arrays, MiB). Data: `{b.command}`.",
                   mark))


def fig_heatmaps(b: Bench, recs: list[dict], file: Path) -> None:
    """Per-pixel traversal steps (top row) and triangle tests (bottom row) of the camera
    rays, one column per structure; one colour scale per row, so columns compare."""
    import numpy as np
    from matplotlib.colors import Normalize

    n = len(recs)
    fig, _ = _new_figure(max(6.0, 2.3 * n + 1.2), 5.4, ncols=1)
    fig.clf()
    axes = fig.subplots(2, n, squeeze=False)
    for row, key, label in ((0, "steps", "traversal steps"), (1, "tests", "triangle tests")):
        images = [np.asarray(r[key], np.float64) for r in recs]
        top = max(float(np.percentile(im, 99.5)) for im in images) or 1.0
        norm = Normalize(0.0, top)
        for col, (r, im) in enumerate(zip(recs, images, strict=True)):
            ax = axes[row, col]
            shown = ax.imshow(im, cmap="inferno", norm=norm, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if row == 0:
                ax.set_title(f"{r['structure']}", fontsize=9)
            ax.set_xlabel(f"mean {im.mean():.1f}, max {im.max():.0f}", fontsize=7)
        fig.colorbar(shown, ax=list(axes[row]), label=label, shrink=0.85, pad=0.02)
    fig.suptitle("Per-pixel cost of the camera rays" + (f" — {b.path.name}" if b.label else ""),
                 fontsize=10)
    _save(fig, file, b.command, layout=False, note=bench_indicative(b))


def section_heatmaps(doc: Doc, b: Bench, out: Path, prefix: str) -> bool:
    order = {name: i for i, name in enumerate(b.structures)}
    recs = sorted((r for r in b.of("heatmap") if r.get("structure") in order
                   and r.get("steps") and r.get("tests")),
                  key=lambda r: order[r["structure"]])
    if not recs:
        return False
    doc.heading(3, "Per-pixel cost" + (f": {b.label}" if b.label else ""))
    block = recs[0].get("block", 1)
    doc.para(_section_mark(b)
             + "Where each structure spends its work: the engine's counters for every camera "
             "ray (one per pixel), traversal steps and triangle tests, averaged over "
             f"{block}x{block} pixel blocks. Bright cells are rays that visit many nodes or "
             "cells, or test many triangles; the table gives, per structure, the mean, the "
             "brightest cell and how much of the work falls on the 10 % most expensive "
             f"cells. Data: `{b.command}`.")
    rows = []
    for r in recs:
        row = [r["structure"]]
        for key in ("steps", "tests"):
            cells = sorted((x for line in r[key] for x in line), reverse=True)
            total = sum(cells) or 1.0
            top = cells[:max(1, len(cells) // 10)]
            row += [num(sum(cells) / len(cells)), num(cells[0]), f"{sum(top) / total:.0%}"]
        rows.append(row)
    doc.table(["structure", "steps: mean", "max", "top 10 %", "tests: mean", "max",
               "top 10 %"], rows)
    f = out / "figures" / f"{prefix}heatmaps.png"
    fig_heatmaps(b, recs, f)
    doc.figure(f, f"figures/{f.name}", _marked(
               "Traversal steps (top) and triangle tests (bottom) per camera ray, one column "
               "per structure, one colour scale per row (clipped at the 99.5th percentile). "
               f"Data: `{b.command}`.", bench_indicative(b)))
    return True


def section_scaling(doc: Doc, b: Bench, out: Path, prefix: str) -> bool:
    recs = b.of("scaling")
    if not recs:
        return False
    doc.heading(3, "Scaling" + (f": {b.label}" if b.label else ""))
    rays = recs[0].get("rays")
    doc.para(_section_mark(b) + "Build time and camera-ray rate against the number of "
             "triangles N"
             + (f" ({rays:,} camera rays on each mesh)" if isinstance(rays, int) else "")
             + "; exponents are the least-squares slope of log(time) against log(N), fitted "
             f"only through {MIN_FIT_SIZES} or more sizes (through two, any power law fits). "
             f"Data: `{b.command}`.")
    rows = []
    for r in recs:
        for row in sorted(_dicts(r.get("rows")), key=lambda row: _count(row.get("triangles"))):
            rows.append([r.get("structure"), row.get("mesh"), num(row.get("triangles")),
                         num(_median(row.get("build_seconds"))), num(row.get("ns_per_n_log2_n")),
                         num(_median(row.get("mrays_per_s"))), num(row.get("ratio_to_embree"))])
    doc.table(["structure", "mesh", "triangles", "build (s)", "ns per N log2 N", "Mrays/s",
               "x Embree"], rows)
    fits = [(r.get("structure"), *scaling_fits(r)) for r in recs]
    doc.table(["structure", "build time ~ N^", "trace time ~ N^"],
              [[name, *(num(k) if k is not None else _not_fitted(sizes) for k in (be, te))]
               for name, be, te, sizes in fits])
    f = out / "figures" / f"{prefix}scaling.png"
    fig_scaling(b, f)
    legend = ("fitted exponents in the legend" if any(
        k is not None for fit in fits for k in fit[1:3]) else
        f"no exponent fitted ({_plural(max(fit[3] for fit in fits), 'size')}; "
        f"{MIN_FIT_SIZES} needed)")
    doc.figure(f, f"figures/{f.name}", _marked(
               f"Build time and camera Mrays/s against N (log-log), {legend}, Embree's rate "
               f"on the same rays in black. Data: `{b.command}`.", bench_indicative(b)))
    return True


def section_cost_model(doc: Doc, b: Bench, out: Path, prefix: str) -> bool:
    recs = b.of("cost_model")
    if not recs:
        return False
    doc.heading(3, "Cost model" + (f": {b.label}" if b.label else ""))
    fit = recs[0].get("fit", "time per ray ~ C_0 + C_TS x steps + C_IT x tests")
    doc.para(_section_mark(b)
             + f"Havran and Purgathofer's cost model (2003), fitted per structure over the ray "
             f"sets: {fit}; C_TS is the cost of a traversal step, C_IT of a triangle test, C_0 "
             f"what a ray costs whatever its path ({recs[0].get('time_basis', 'wall clock')}). "
             f"The residual is the root mean square of the relative errors of the fitted times. "
             f"Data: `{b.command}`.")
    doc.table(["structure", "C_TS (ns)", "C_IT (ns)", "C_0 (ns)", "residual"],
              [[r.get("structure"), num(r.get("c_ts_ns")), num(r.get("c_it_ns")),
                num(r.get("c_ray_ns")), num(r.get("residual"))] for r in recs])
    if any(_dicts(r.get("points")) for r in recs):
        f = out / "figures" / f"{prefix}cost-model.png"
        fig_cost_model(b, f)
        doc.figure(f, f"figures/{f.name}", _marked(
                   "Measured against predicted nanoseconds per ray, one point per structure "
                   f"and ray set; on the dotted line the model is exact. Data: `{b.command}`.",
                   bench_indicative(b)))
    return True


def section_turntable(doc: Doc, b: Bench) -> bool:
    recs = b.of("turntable")
    if not recs:
        return False
    doc.heading(3, "Batched renders" + (f": {b.label}" if b.label else ""))
    doc.para(_section_mark(b)
             + "A turntable of the glass camel rendered as one batch (`jrt.batch.render_batch`: "
             "one `jax.vmap` of the pure renderer over the cameras) and as a Python loop of "
             "single renders (`jrt.wavefront.renderer`), at the renderer's own level "
             "capacities and at the batch's; the ratio is the batch's images/s over the "
             "faster loop's. The difference is the largest radiance difference between the "
             f"batch and the same-capacities loop. Data: `{b.command}`.")
    doc.table(["frames", "size", "wavelengths", "depth", "batched images/s", "loop",
               "loop, same capacities", "x faster loop", "max difference"],
              [[num(r.get("frames")), f"{r.get('width')}x{r.get('height')}",
                num(r.get("samples")), num(r.get("max_depth")),
                num(r.get("batched_images_per_s")), num(r.get("loop_images_per_s")),
                num(r.get("loop_same_capacities_images_per_s")), num(r.get("ratio")),
                num(r.get("max_abs_difference"))] for r in recs])
    return True


def _wp_points(inputs: Inputs) -> list[dict]:
    """Work–precision records as {study, method, seconds, psnr, ssim, delta_e, command}."""
    points = []
    for path, r, command in inputs.work_precision:
        seconds = _median(r.get("seconds"))
        method = r.get("method", r.get("label"))
        if seconds is None or seconds <= 0 or method is None:
            raise ReportError(f"{path}: a work_precision record needs a method label "
                              f"(\"method\" or \"label\") and positive \"seconds\"; got "
                              f"{json.dumps(r)[:200]}")
        p = {"study": str(r.get("study", r.get("group", r.get("experiment", "")))),
             "method": str(method), "series": str(r.get("series", method)),
             "seconds": seconds, "command": command or None, "path": path}
        errors = r.get("error") if isinstance(r.get("error"), dict) else {}
        for key, aliases, _, _ in METRICS:
            value = next((v for a in aliases for v in (r.get(a), errors.get(a))
                          if v is not None), None)
            p[key] = _median(value)
        points.append(p)
    return points


def section_work_precision(doc: Doc, inputs: Inputs, out: Path) -> None:
    doc.heading(2, "Error against run time")
    points = _wp_points(inputs)
    if not points:
        doc.para("No work–precision records (records of kind `work_precision`: a method label, "
                 "the run time in seconds and the error against a float64, deep, "
                 "many-wavelength reference as PSNR, SSIM and mean CIEDE2000 ΔE) in these "
                 f"results. `{WORK_PRECISION_COMMAND}` produces them (triangle kernel x "
                 "float32/float64, Whitted depth, wavelength samples, pruning threshold, "
                 "exact tree against sampled branches, Fresnel exact against Schlick); pass "
                 "their JSON to the report to draw the diagrams.")
        return
    quick = {p["path"]: inputs.indicative[p["path"]] for p in points
             if p["path"] in inputs.indicative}
    doc.para("Each point is a measured run: its run time against its error relative to the "
             "reference (PSNR and SSIM by scikit-image, higher is better; mean CIEDE2000 ΔE by "
             "colour-science, lower is better)." + "".join(
                 f" {_mark(reason)[:-1]} (`{path.name}`)." for path, reason in quick.items()))
    studies = list(dict.fromkeys(p["study"] for p in points))
    for i, study in enumerate(studies, 1):
        pts = [p for p in points if p["study"] == study]
        commands = list(dict.fromkeys(p["command"] for p in pts if p["command"]))
        unknown = list(dict.fromkeys(str(p["path"]) for p in pts if not p["command"]))
        command = "; ".join(commands + [f"{u} (command not recorded)" for u in unknown])
        caption = "; ".join([f"`{c}`" for c in commands]
                            + [f"`{u}` (its command is not recorded)" for u in unknown])
        if study:
            doc.heading(3, study)
        doc.table(["method", "run time (s)", "PSNR (dB)", "SSIM", "ΔE (CIEDE2000)"],
                  [[p["method"], num(p["seconds"]), num(p["psnr"]), num(p["ssim"]),
                    num(p["delta_e"])] for p in pts])
        metrics = [m for m in METRICS if any(p[m[0]] is not None for p in pts)]
        if metrics:
            f = out / "figures" / f"work-precision-{i}.png"
            note = "; ".join(dict.fromkeys(quick[p["path"]] for p in pts if p["path"] in quick))
            fig_work_precision(pts, metrics, f, study or "Error against run time", command,
                               note=note)
            doc.figure(f, f"figures/{f.name}", _marked(
                       f"Error against run time{': ' + study if study else ''} (each point a "
                       f"measured run). Data: {caption}.", note))


# --- Stability ------------------------------------------------------------------------------

_LABELS = ("kernel", "structure", "check", "ray_set", "pair", "dtype", "glass", "value", "n",
           "nm", "method")
_CORE = ("rays", "cracks", "cracks_per_million", "false_hits", "nan", "max_error_ulps",
         "error_ulps", "mismatches_vs_brute")
_HEADINGS = {"cracks_per_million": "cracks /M", "false_hits": "false hits", "nan": "NaN",
             "max_error_ulps": "max error (ulps)", "error_ulps": "error (ulps)",
             "mismatches_vs_brute": "vs brute", "ray_set": "ray set", "pass_through":
             "pass-through", "borderline_hits": "borderline", "near_origin": "near origin"}


def _scalar(v) -> bool:
    return v is None or isinstance(v, bool | int | float | str)


def _columns(records: list[dict]) -> list[tuple[str, str | None]]:
    """(field, sub-field) columns of a group of stability records: labels, the core
    metrics, the other scalars, then dicts of scalars flattened (``self_hits: none``)."""
    keys = list(dict.fromkeys(k for r in records for k in r if k != "case"))
    scalar = [k for k in keys if all(_scalar(r.get(k)) for r in records)]
    cols = [(k, None) for k in _LABELS if k in scalar
            and not all(r.get(k) in ("n/a", None) for r in records)]
    if len({r.get("check") for r in records}) == 1:
        cols = [c for c in cols if c[0] != "check"]
    cols += [(k, None) for k in _CORE if k in scalar]
    cols += [(k, None) for k in scalar if k not in _LABELS and k not in _CORE
             and k not in ("title",)]
    for k in keys:
        if k in scalar:
            continue
        values = [r.get(k) for r in records if isinstance(r.get(k), dict)]
        if not values or not all(all(_scalar(v) for v in d.values()) for d in values):
            continue
        subs = list(dict.fromkeys(s for d in values for s in d))
        if "cracks" in subs:  # a summary of a subset of rays: its cracks and false hits
            subs = [s for s in ("cracks", "false_hits", "nan") if s in subs]
        if len(subs) <= 8:
            cols += [(k, sub) for sub in subs]
    return cols[:MAX_COLUMNS]


def _cell(record: dict, col: tuple[str, str | None]) -> str:
    key, sub = col
    value = record.get(key)
    if sub is not None:
        value = value.get(sub) if isinstance(value, dict) else None
    text = num(value)
    return text if len(text) <= 90 else text[:87] + "..."


def _heading(col: tuple[str, str | None]) -> str:
    key, sub = col
    name = _HEADINGS.get(key, key.replace("_", " "))
    return f"{name}: {_HEADINGS.get(sub, sub.replace('_', ' '))}" if sub is not None else name


def _stability_rows(body) -> list[dict]:
    return _dicts(body.get("records")) if isinstance(body, dict) else []


def stability_overview(data: dict) -> tuple[list[str], list[list[str]]]:
    """Cracks / false hits / NaN per kernel x structure and case, summed over each case's
    records (cases whose records count cracks)."""
    cases = [c for c, body in data["cases"].items()
             if any("cracks" in r for r in _stability_rows(body))]
    pairs, cells = [], {}
    for c in cases:
        for r in _stability_rows(data["cases"][c]):
            if "cracks" not in r:
                continue
            pair = (str(r.get("kernel")), str(r.get("structure")))
            if pair not in pairs:
                pairs.append(pair)
            acc = cells.setdefault((pair, c), [0, 0, 0])
            for i, k in enumerate(("cracks", "false_hits", "nan")):
                v = r.get(k)
                acc[i] += v if isinstance(v, int | float) and not isinstance(v, bool) else 0
    pairs.sort(key=lambda p: (p[0], STRUCTURE_ORDER.index(p[1]) if p[1] in STRUCTURE_ORDER
                              else 99))
    header = ["kernel", "structure"] + [f"case {c}: cracks / false / NaN" for c in cases]
    rows = [[k, s] + [" / ".join(num(v) for v in cells[(k, s), c]) if ((k, s), c) in cells
                      else "–" for c in cases] for k, s in pairs]
    return header, rows


def section_stability(doc: Doc, path: Path, data: dict, many: bool) -> None:
    doc.heading(2, "Numerical stability" + (f": `{path.name}`" if many else ""))
    command = stability_command(data, path)
    env = data.get("environment") or {}
    doc.para((_mark("a quick run (`--quick`, small sizes)") + " " if stability_indicative(data)
              else "The study's standard sizes (`--size standard`, a tenth to a quarter of the "
              "full sweep's rays; case 5 at three scales and three shifts). "
              if data.get("size") == "standard" else "")
             + f"Every case runs over kernel x structure pairs against an oracle: "
             f"{data.get('oracle', 'see the suite')}. "
             + (f"{len(data['cases'])} cases in {_seconds(data.get('seconds'))}"
                + (f" on {env.get('cpu_count')} cores" if env.get("cpu_count") else "") + ". "
                if data.get("seconds") is not None else "")
             + f"Data: `{command}`.")
    header, rows = stability_overview(data)
    if rows:
        doc.para("Overview: cracks (the oracle hits and the ray misses or passes through), "
                 "false hits and NaN per kernel x structure, summed over each case's ray sets.")
        doc.table(header, rows)
    for case, body in data["cases"].items():
        title = body.get("title", "")
        doc.heading(3, f"Case {case}" + (f": {title}" if title else "")
                    + (f" ({_seconds(body['seconds'])})" if body.get("seconds") is not None
                       else ""))
        if body.get("findings"):
            doc.quote(str(body["findings"]))
        records = _stability_rows(body)
        groups: dict = {}
        for r in records:
            groups.setdefault(r.get("check"), []).append(r)
        for check, recs in groups.items():
            cols = _columns(recs)
            rows = [[_cell(r, c) for c in cols] for r in recs[:MAX_ROWS]]
            note = (f"{len(recs) - MAX_ROWS} more rows in the JSON" if len(recs) > MAX_ROWS
                    else "")
            if check is not None and len(groups) > 1:
                note = f"{check}" + (f"; {note}" if note else "")
            doc.table([_heading(c) for c in cols], rows, note)


# --- Reading --------------------------------------------------------------------------------


def _ranking(b: Bench) -> dict[str, tuple[float, tuple[float, float] | None]]:
    """Per structure, fastest first: the geometric mean over the ray sets of its median
    Mrays/s, and the geometric means of its per-set min and max (None where a set has no
    spread): an interval that holds the geometric mean of any choice of one warm call per
    set."""
    out = {}
    for n in b.structures:
        recs = [b.traces[n, s] for s in b.sets if (n, s) in b.traces
                and _median(b.traces[n, s].get("mrays_per_s"))]
        if not recs:
            continue
        spreads = [rate_spread(r) for r in recs]
        out[n] = (_geomean(_median(r.get("mrays_per_s")) for r in recs),
                  None if None in spreads else (_geomean(lo for lo, _ in spreads),
                                                _geomean(hi for _, hi in spreads)))
    return dict(sorted(out.items(), key=lambda x: -x[1][0]))


def _mean_counter(b: Bench, name: str, counter: str) -> float | None:
    values = [_counter(b.traces.get((name, s)), counter) for s in b.sets]
    values = [v for v in values if v is not None]
    return sum(values) / len(values) if values else None


def _ordinal(k: int) -> str:
    return f"{k}{'th' if 10 <= k % 100 < 20 else {1: 'st', 2: 'nd', 3: 'rd'}.get(k % 10, 'th')}"


def _calls(b: Bench) -> int | None:
    """Warm calls per structure and set (the parameters, else the shortest repeats list)."""
    n = b.params.get("repeats")
    return n if _count(n) else min((len(t["repeats"]) for t in b.of("trace")
                                    if isinstance(t.get("repeats"), list)), default=None)


def _ends(values: dict, higher: bool = True) -> tuple[list[str], list[str]]:
    """The names that may be first and those that may be last, best median first."""
    ranks = places(values, higher)
    order = sorted(values, key=lambda n: -values[n][0] if higher else values[n][0])
    return ([n for n in order if ranks[n][0] == 1],
            [n for n in order if ranks[n][1] == len(order)])


def _fastest(s: str, rated: dict, b: Bench) -> str:
    """A ray set's fastest and slowest structures, or the ones tied within the spread."""
    first, last = _ends(rated)
    top, slow = first[0], last[-1]
    ratio = b.traces[top, s].get("ratio_to_embree")
    vs = (f"{num(ratio)}x Embree's {num(_median(b.embree.get(s, {}).get('mrays_per_s')))}"
          if ratio is not None else "")
    if len(first) == len(rated) > 1:
        return (f"{s}: all {len(rated)} {TIED} ("
                + ", ".join(f"{n} {num(v)}" for n, (v, _) in rated.items()) + " Mrays/s)")
    if len(first) == 1:
        text = f"{s}: **{top}** {num(rated[top][0])} Mrays/s" + (f" ({vs})" if vs else "")
    else:
        text = (f"{s}: {_join(f'{n} {num(rated[n][0])}' for n in first)} Mrays/s {TIED} for "
                "the fastest" + (f" ({top} {vs})" if vs else ""))
    if len(rated) == 1:
        return text
    if len(last) == 1:
        return text + (f", slowest {slow} {num(rated[slow][0])} "
                       f"({num(rated[top][0] / rated[slow][0])}x slower)")
    return text + f", slowest {_join(last)} {TIED}"


def reading_bench(b: Bench) -> tuple[list[str], str]:
    """Bullets of what the numbers say, and the paragraph on Havran's kd-tree claim.

    Orders are stated only where the spread of the repeats separates them: one structure is
    ahead of another when the min..max of their warm calls (or builds) do not overlap, and
    structures that overlap are called tied within the run's spread."""
    traces, sets = b.traces, b.sets
    items = []
    calls = _calls(b)
    basis = (f"the min–max of their {calls} warm calls" if calls and calls > 1 else
             "their warm calls' spread")
    fastest = []
    for s in sets:
        rated = {n: (_median(traces[n, s].get("mrays_per_s")), rate_spread(traces[n, s]))
                 for n in b.structures if (n, s) in traces}
        rated = {n: v for n, v in rated.items() if v[0]}
        if rated:
            fastest.append(_fastest(s, rated, b))
    if fastest:
        items.append(("Fastest per ray set (one warm call each: no spread, so no structure is "
                      "ranked ahead of another): " if calls == 1 else
                      f"Fastest per ray set (a structure is ranked ahead of another only where "
                      f"{basis} do not overlap): ") + "; ".join(fastest) + ".")
    ranking = _ranking(b)
    if len(ranking) > 1:
        ranks = places(ranking)
        parts = []
        for n, (g, _) in ranking.items():
            tied = tied_with(n, ranking)
            place = "–".join(dict.fromkeys(_ordinal(k) for k in ranks[n]))
            parts.append(f"{n} {num(g)} ({place}" + (f", tied with {_join(tied)}" if tied
                                                     else "") + ")")
        items.append(f"Over the {_plural(len(sets), 'ray set')} (geometric mean of Mrays/s; "
                     "places from the geometric means of each set's min and max, shared where "
                     f"they overlap): " + ", ".join(parts) + ".")
    ratios = [(t.get("ratio_to_embree"), n, s) for (n, s), t in traces.items()
              if isinstance(t.get("ratio_to_embree"), int | float)]
    if ratios:
        best, worst = max(ratios), min(ratios)
        items.append(f"Against Embree on the same rays (medians): from {num(worst[0])}x "
                     f"({worst[1]}, {worst[2]}) to {num(best[0])}x ({best[1]}, {best[2]}).")
    builds = {n: (_median(r.get("seconds")), build_spread(r)) for n, r in b.builds.items()}
    builds = {n: v for n, v in builds.items() if v[0]}
    mem = {n: _mib(r) for n, r in b.builds.items() if _mib(r)}
    if builds:
        first, last = _ends(builds, higher=False)
        if len(builds) == 1:
            text = f"Build: {first[0]} ({num(builds[first[0]][0])} s)"
        elif len(first) == len(builds):
            text = f"Build: all {len(builds)} {TIED} of the builds"
        else:
            text = "Build: " + ", ".join(
                f"{word} {n} ({num(builds[n][0])} s)" if len(group) == 1 else
                f"{word} {_join(f'{m} ({num(builds[m][0])} s)' for m in group)} {TIED}"
                for word, group, n in (("fastest", first, first[0]),
                                       ("slowest", last, last[-1])))
        if mem:  # bytes are exact: no spread to separate
            small, big = min(mem, key=mem.get), max(mem, key=mem.get)
            text += f"; memory from {num(mem[small])} MiB ({small}) to {num(mem[big])} MiB ({big})"
        items.append(text + ".")
    checks = b.of("correctness")
    if checks:
        bad = [r for r in checks if r.get("mismatches")]
        total = sum(_count(r.get("rays")) for r in checks)
        if bad:
            items.append("Against brute force: mismatches in " + ", ".join(
                f"{r.get('structure')}/{r.get('set')} ({r['mismatches']} of {r.get('rays')})"
                for r in bad) + ".")
        else:
            items.append(f"Every structure returned brute force's hits bit for bit "
                         f"(0 mismatches in {total:,} checked rays).")
    scaling = b.of("scaling")
    n = sorted({row["triangles"] for r in scaling for row in _dicts(r.get("rows"))
                if _count(row.get("triangles"))})
    if n:
        fits = [(r.get("structure", "?"), *scaling_fits(r)) for r in scaling]
        span = f"Scaling over {n[0]:,}–{n[-1]:,} triangles ({_plural(len(n), 'size')})"
        if all(be is None and te is None for _, be, te, _ in fits):
            items.append(f"{span}: exponents {_not_fitted(len(n))}.")
        else:
            def exps(i):
                return ", ".join(f"{f[0]} N^{f[i]:.2f}" if f[i] is not None else
                                 f"{f[0]} {_not_fitted(f[3])}" for f in fits)
            items.append(f"{span}: build time {exps(1)}; time for a fixed number of camera "
                         f"rays {exps(2)}.")
    return items, havran(b, ranking)


def havran(b: Bench, ranking: dict) -> str:
    """Havran's thesis (2000) against the camel: the kd-tree's place and, as the reason, the
    measured steps and triangle tests per ray (and the cost model's C_TS, C_IT). The run
    agrees only when the kd-tree's interval lies above every other structure's, disagrees
    only when some structure's lies above the kd-tree's, and says neither otherwise."""
    lead = ("Havran's thesis (*Heuristic Ray Shooting Algorithms*, 2000) found the SAH "
            "kd-tree the most efficient scheme on CPUs. ")
    names = list(ranking)
    if "kdtree" not in names:
        return lead + "These results have no kd-tree trace to compare with."
    if len(names) == 1:
        return lead + "The kd-tree is the only structure traced here."
    place = places(ranking)["kdtree"]
    kd_rate = ranking["kdtree"][0]
    ahead = [n for n in names if _ahead(ranking, n, "kdtree")]
    tied = tied_with("kdtree", ranking)
    mesh = str(b.params.get("mesh") or "")
    subject = "The camel" if "camel" in mesh.lower() else f"This mesh (`{mesh or '?'}`)"
    if place == (1, 1):
        verdict, other = "agrees", next(n for n in names if n != "kdtree")
        rate = ranking[other][0]
        text = (f"{subject} agrees: the kd-tree is the fastest here ({num(kd_rate)} Mrays/s, "
                f"geometric mean over the ray sets, {num(kd_rate / rate)}x the next, {other}).")
    elif ahead:
        verdict, other = "disagrees", ahead[0]
        rate = ranking[other][0]
        text = (f"{subject} does not agree on this machine: the kd-tree ranks {_place(place)} of "
                f"{len(names)}" + (f", {TIED} with {_join(tied)}" if tied else "")
                + f" ({num(kd_rate)} Mrays/s, geometric mean over the ray sets, against "
                f"{num(rate)} for the {other}: {num(rate / kd_rate)}x).")
    else:
        verdict, other = "", next(n for n in names if n != "kdtree")
        text = (f"This run neither confirms nor contradicts it on "
                f"{subject[0].lower() + subject[1:]}: the kd-tree ({num(kd_rate)} Mrays/s, "
                f"geometric mean over the ray sets) is {TIED} with {_join(tied)} for the first "
                "place (their warm calls' min–max overlap).")
    steps = {n: _mean_counter(b, n, "steps") for n in (other, "kdtree")}
    tests = {n: _mean_counter(b, n, "tests") for n in (other, "kdtree")}
    if None in steps.values() or None in tests.values():
        return lead + text + " No traversal counters were recorded to say why."
    s_kd, t_kd, s_o, t_o = steps["kdtree"], tests["kdtree"], steps[other], tests[other]
    text += (f" Per ray, averaged over the sets, the kd-tree takes {num(s_kd)} traversal "
             f"steps and {num(t_kd)} triangle tests, the {other} {num(s_o)} and {num(t_o)}")
    cam = [b.traces.get((n, "camera")) for n in ("kdtree", other)]
    if all(cam):
        text += (f" (camera rays: {num(_counter(cam[0], 'steps'))} / "
                 f"{num(_counter(cam[0], 'tests'))} against {num(_counter(cam[1], 'steps'))}"
                 f" / {num(_counter(cam[1], 'tests'))})")
    text += ". "
    costs = {r.get("structure"): r for r in b.of("cost_model")}
    if verdict == "agrees":
        why = ("fewer triangle tests" if t_kd < t_o else "") + (
            " and " if t_kd < t_o and s_kd < s_o else "") + (
            "fewer steps" if s_kd < s_o else "")
        text += (f"The measured reason: {why or 'a cheaper step on this engine'}, which is "
                 "Havran's argument (tight leaves clipped to the node box, empty space cut "
                 "off early).")
    elif not verdict:
        text = text.rstrip()
    elif t_kd < t_o and s_kd > s_o:
        text += (f"The kd-tree does what Havran credits it with, fewer triangle tests "
                 f"({num(t_kd / t_o)}x the {other}'s), but takes {num(s_kd / s_o)}x the "
                 f"steps, and here the steps decide: in jrt's engine every traversal step is "
                 f"an iteration of the whole lane loop, so a kd-tree plane test is not much "
                 f"cheaper than a BVH box test.")
    elif t_kd >= t_o and s_kd >= s_o:
        text += (f"The kd-tree takes both more steps ({num(s_kd / s_o)}x) and more triangle "
                 f"tests ({num(t_kd / t_o)}x) than the {other}: on this mesh its clipped "
                 f"leaves do not save the tests Havran's argument relies on.")
    elif t_kd >= t_o:
        text += (f"It takes fewer steps but {num(t_kd / t_o)}x the {other}'s triangle tests, "
                 f"and the tests decide here.")
    else:
        text += ("It takes fewer steps and fewer tests, yet is slower: each of its steps "
                 "costs more on this engine.")
    fitted = [(n, costs[n]) for n in ("kdtree", other) if n in costs
              and (costs[n].get("c_ts_ns") or costs[n].get("c_it_ns"))]
    if fitted:
        text += " Cost model: " + "; ".join(
            f"{n} C_TS {num(c.get('c_ts_ns'))} ns, C_IT {num(c.get('c_it_ns'))} ns, C_0 "
            f"{num(c.get('c_ray_ns'))} ns per ray" for n, c in fitted) + "."
    return lead + text


def reading_stability(data: dict) -> list[str]:
    """Where each kernel, structure and offset breaks, from the records' counts."""
    items = []
    by_kernel: dict = {}
    for case, body in data["cases"].items():
        for r in _stability_rows(body):
            kernel = r.get("kernel")
            if kernel in (None, "n/a") or "cracks" not in r:
                continue
            acc = by_kernel.setdefault(kernel, {}).setdefault(case, [0, 0, 0, 0])
            for i, k in enumerate(("cracks", "false_hits", "nan", "rays")):
                v = r.get(k)
                acc[i] += v if isinstance(v, int) and not isinstance(v, bool) else 0

    def title(case):
        t = str(data["cases"][case].get("title", ""))
        return f"case {case}" + (f" ({t[:1].lower() + t[1:]})" if t else "")

    for kernel in _order(by_kernel, KERNEL_ORDER):
        cases = by_kernel[kernel]
        broken = [f"{title(c)}: {a[0]:,} cracks" + (f", {a[1]:,} false hits" if a[1] else "")
                  + (f", {a[2]:,} NaN" if a[2] else "") + f" in {a[3]:,} rays"
                  for c, a in cases.items() if a[0] or a[1] or a[2]]
        clean = [c for c, a in cases.items() if not (a[0] or a[1] or a[2])]
        text = f"`{kernel}`: " + ("; ".join(broken) if broken else "no crack, false hit or NaN")
        if clean:
            text += (f"{'; none in' if broken else ' in'} case{'s' if len(clean) > 1 else ''} "
                     f"{', '.join(clean)}")
        items.append(text + ".")
    mism = [(c, r) for c, body in data["cases"].items() for r in _stability_rows(body)
            if isinstance(r.get("mismatches_vs_brute"), int) and r.get("structure") != "brute"]
    if mism:
        bad = [f"{r.get('kernel')}/{r.get('structure')} in case {c} ({r['mismatches_vs_brute']})"
               for c, r in mism if r["mismatches_vs_brute"]]
        items.append("Structures against brute force with the same kernel: " + (
            "mismatches " + ", ".join(bad) if bad else
            f"0 mismatches in {_plural(len(mism), 'kernel x structure run')}") + ".")
    offsets: dict = {}
    for case, body in data["cases"].items():
        for r in _stability_rows(body):
            if isinstance(r.get("self_hits"), dict):
                for method, v in r["self_hits"].items():
                    if isinstance(v, int | float):
                        offsets.setdefault(method, {}).setdefault(case, 0)
                        offsets[method][case] += v
    if offsets:
        items.append("Self-intersection of secondary rays, self-hits per offset method "
                     "(summed over kernels and structures): " + "; ".join(
                         f"`{m}` " + ", ".join(f"{num(v)} (case {c})" for c, v in cs.items())
                         for m, cs in offsets.items()) + ".")
    nan = sum(r.get("nan", 0) for body in data["cases"].values() for r in _stability_rows(body)
              if isinstance(r.get("nan"), int) and not isinstance(r.get("nan"), bool))
    items.append(f"NaN in any output, all cases: {nan}.")
    return items


# --- Machine, renders -----------------------------------------------------------------------


def section_machine(doc: Doc, inputs: Inputs) -> None:
    import matplotlib
    import numpy

    doc.heading(2, "Machine and versions")
    for b in inputs.bench:
        m = b.machine
        if not m:
            continue
        dev = m.get("device") if isinstance(m.get("device"), dict) else {}
        rows = [["CPU", m.get("cpu")],
                ["cores", f"{m.get('cores')}" + (f" ({m['cores_usable']} usable)"
                                                 if m.get("cores_usable") else "")],
                ["OS", m.get("os")], ["Python", m.get("python")],
                ["JAX devices", f"{dev.get('count')} x {dev.get('platform')} "
                                f"({dev.get('kind')})" if dev else None],
                ["XLA_FLAGS", f"`{m['xla_flags']}`" if m.get("xla_flags") else None],
                ["git commit", f"`{m['git_commit']}`" if m.get("git_commit") else None],
                ["date", m.get("date")]]
        versions = m.get("versions") if isinstance(m.get("versions"), dict) else {}
        rows += [[name, v if v is not None else "not installed"] for name, v in versions.items()]
        doc.table(["benchmark machine" + (f": {b.label}" if b.label else ""), "value"],
                  [[k, num(v)] for k, v in rows if v is not None])
    for path, data in inputs.stability:
        env = data.get("environment")
        if isinstance(env, dict) and env:
            doc.table([f"stability run (`{path.name}`)", "value"],
                      [[k.replace("_", " "), num(v)] for k, v in env.items()])
    doc.para(f"Report generated by `{REPORT_COMMAND}` with Python {platform.python_version()}, "
             f"matplotlib {matplotlib.__version__}, NumPy {numpy.__version__} on "
             f"{datetime.datetime.now(datetime.UTC).strftime('%Y-%m-%d %H:%M UTC')}.")


def _is_file(text: str) -> bool:
    """Path(text).is_file(), False where the name cannot be a file (Python 3.11 raises
    OSError for a name longer than the system allows: a long caption)."""
    try:
        return Path(text).is_file()
    except OSError:
        return False


def parse_image(spec: str) -> tuple[Path, str]:
    """``PATH[:caption]``: the longest existing file before a colon, or the whole spec."""
    if _is_file(spec):
        return Path(spec), ""
    for i, ch in enumerate(spec):
        if ch == ":" and _is_file(spec[:i]):
            return Path(spec[:i]), spec[i + 1:].strip()
    raise ReportError(f"--image {spec}: no such image file (expected PATH[:caption], PATH a "
                      f"{', '.join(sorted(IMAGE_TYPES))} file)")


def section_renders(doc: Doc, images: list[tuple[Path, str]], out: Path) -> None:
    if not images:
        return
    doc.heading(2, "Renders")
    used = set()
    for path, caption in images:
        if path.suffix.lower() not in IMAGE_TYPES:
            raise ReportError(f"--image {path}: not an image the report can embed; allowed: "
                              f"{', '.join(sorted(IMAGE_TYPES))}")
        head = path.read_bytes()[:8]
        if path.suffix.lower() == ".png" and head != PNG_SIGNATURE:
            raise ReportError(f"--image {path}: not a PNG file (its first bytes are {head!r})")
        name, i = path.name, 1
        while name in used:
            i += 1
            name = f"{path.stem}-{i}{path.suffix}"
        used.add(name)
        dest = out / "renders" / name
        dest.parent.mkdir(parents=True, exist_ok=True)
        if path.resolve() != dest.resolve():
            shutil.copyfile(path, dest)
        doc.figure(dest, f"renders/{name}", caption or f"`{path.name}` (given with `--image`; "
                   "add `:caption` to name the command that made it).")


# ============================================================================================
# The report
# ============================================================================================


def indicative_notice(inputs: Inputs) -> str:
    """The report's opening caution when any input is a quick run: which, and what runs
    give numbers that can rank the structures."""
    timed = [b.path for b in inputs.bench] + [p for p, _ in inputs.stability]
    head = ("Quick run: small ray sets, indicative only." if any(
        p in inputs.indicative for p in timed) else f"Quick work–precision points: {INDICATIVE}.")
    return (f"**{head}** " + "; ".join(f"`{p.name}`: {reason}" for p, reason in
                                       inputs.indicative.items())
            + ". The report's rankings are stated only where the spread of the repeats "
            f"separates them and no power law is fitted through fewer than {MIN_FIT_SIZES} "
            "sizes. Run `jrt study` for the full benchmark suite and the stability suite's "
            "standard sizes, or `jrt study --full` for the published study (the stability "
            "suite's full sweep and every work–precision point).")


def generate(paths, out_dir, images=(), title: str | None = None) -> dict:
    """Read the results, write ``out_dir/README.md``, ``index.html`` and the figures.

    ``images``: ``PATH[:caption]`` strings or (path, caption) pairs. Returns the paths
    written and the seconds it took; ReportError names any unusable input.
    """
    start = time.perf_counter()
    inputs = load_inputs(paths)
    renders = [parse_image(i) if isinstance(i, str) else (Path(i[0]), i[1]) for i in images]
    for path, _ in renders:
        if not path.is_file():
            raise ReportError(f"--image {path}: no such file")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ReportError(f"-o {out}: exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)

    doc = Doc()
    doc.heading(1, title or "jrt: acceleration structures on the camel")
    kinds = {"bench": "benchmark suite", "stability": "stability suite",
             "work_precision": "work–precision records"}
    # Inputs named relative to the report (beside it, as a study writes them): a path of
    # the machine that made it means nothing to a reader.
    doc.para("Generated from " + _join(f"`{os.path.relpath(p, out)}` ({kinds[k]})"
                                       for p, k in inputs.kinds)
             + f" by `{REPORT_COMMAND}`. Figures are PNG files beside this page; `index.html` "
             "is the same report with the figures embedded.")
    if inputs.indicative:
        doc.para(indicative_notice(inputs))
    if inputs.warnings:
        doc.bullets([f"Note: {w}" for w in inputs.warnings])

    doc.heading(2, "Reading")
    havrans = []
    for b in inputs.bench:
        items, text = reading_bench(b)
        if b.label:
            items = [f"{b.label}: {i}" for i in items]
        doc.bullets(items)
        havrans.append(text)
    for path, data in inputs.stability:
        doc.para("**Numerical stability**" + (f" (`{path.name}`)" if len(inputs.stability) > 1
                                               else "") + ", where each method breaks "
                 "(counts summed over the structures each kernel ran with):")
        doc.bullets(reading_stability(data))
    if havrans:
        doc.para("**Against the literature.** " + " ".join(havrans))
    if not inputs.bench:
        doc.para("No benchmark results were given: the structures, scaling and cost-model "
                 f"sections come from `{BENCH_COMMAND}`.")
    if not inputs.stability:
        doc.para(f"No stability results were given: `{STABILITY_COMMAND}` produces them.")

    multi = len(inputs.bench) > 1
    for i, b in enumerate(inputs.bench, 1):
        prefix = _prefix(b, multi, i)
        section_structures(doc, b, out, prefix)
        section_heatmaps(doc, b, out, prefix)
        section_scaling(doc, b, out, prefix)
        section_cost_model(doc, b, out, prefix)
        section_turntable(doc, b)
    section_work_precision(doc, inputs, out)
    for path, data in inputs.stability:
        section_stability(doc, path, data, len(inputs.stability) > 1)
    section_renders(doc, renders, out)
    section_machine(doc, inputs)

    figures = [b.file for b in doc.blocks if b.kind == "figure"]
    # The report owns figures/ and renders/: PNGs of an earlier report there would be stale.
    written = {f.resolve() for f in figures}
    for folder in (out / "figures", out / "renders"):
        for old in folder.glob("*") if folder.is_dir() else ():
            if old.is_file() and old.suffix.lower() in IMAGE_TYPES and old.resolve() not in written:
                old.unlink()
    readme = out / "README.md"
    readme.write_text(doc.markdown(), encoding="utf-8")
    page = out / "index.html"
    page.write_text(doc.html(doc.blocks[0].text), encoding="utf-8")
    return {"readme": readme, "html": page, "figures": figures,
            "seconds": time.perf_counter() - start}


def build_parser(add_help: bool = True, prog: str = REPORT_COMMAND) -> argparse.ArgumentParser:
    """The report's options (``jrt report`` reuses them: ``add_help=False`` for parents)."""
    parser = argparse.ArgumentParser(
        prog=prog, add_help=add_help,
        description="Turn JSON results of the benchmark suite (jrt bench), the stability "
                    "suite (python -m benchmarks.stability) and the work-precision study "
                    "(python -m benchmarks.work_precision) into DIR/README.md with PNG "
                    "figures and a self-contained DIR/index.html. 'jrt study' runs all of "
                    "them and this report in one command.")
    parser.add_argument("results", nargs="+", metavar="RESULTS",
                        help="JSON files, recognised by their content")
    parser.add_argument("-o", "--output", required=True, metavar="DIR",
                        help="the report's folder (created if missing), e.g. reports/camel")
    parser.add_argument("--image", action="append", default=[], metavar="PATH[:caption]",
                        help="a render to include (copied into DIR/renders); repeatable")
    parser.add_argument("--title", default=None, help="the report's title")
    return parser


def run(args) -> dict:
    """Generate the report of parsed options (``build_parser().parse_args(...)``), print
    where it went; ReportError for an unusable input."""
    result = generate(args.results, args.output, args.image, args.title)
    print(f"{result['readme']} and {result['html']} with {len(result['figures'])} figures "
          f"in {result['seconds']:.1f} s")
    return result


def main(argv=None, prog: str = REPORT_COMMAND) -> int:
    """``python -m reports.report`` (``jrt report``): 0 on success; exit status 2 with the
    error otherwise. ``prog`` names the command in usage and errors."""
    parser = build_parser(prog=prog)
    args = parser.parse_args(argv)
    try:
        run(args)
    except ReportError as exc:
        parser.exit(2, f"{parser.prog}: error: {exc}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
