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

The pieces: ``reports.document`` (the document model, Markdown and HTML, number
formatting), ``reports.inputs`` (reading and recognising the results, the commands that
made them, what a run supports), ``reports.figures`` (the PNG figures),
``reports.sections`` (the report's sections) and ``reports.reading`` (the numbers read in
words); this module puts them together (:func:`generate`) and holds the command line.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from reports.document import IMAGE_TYPES, PNG_SIGNATURE, Doc, ReportError, join_words, num
from reports.inputs import (
    BENCH_COMMAND,
    INDICATIVE,
    MIN_FIT_SIZES,
    REPORT_COMMAND,
    STABILITY_COMMAND,
    WORK_PRECISION_COMMAND,
    Bench,
    Inputs,
    bench_command,
    bench_indicative,
    classify,
    load_inputs,
)
from reports.reading import places, reading_bench, reading_stability
from reports.scenes import scene_runs, section_scenes
from reports.sections import (
    parse_image,
    section_cost_model,
    section_heatmaps,
    section_inverse,
    section_machine,
    section_renders,
    section_scaling,
    section_stability,
    section_structures,
    section_trimesh_interface,
    section_turntable,
    section_work_precision,
)

#: The report's entry points, and the names other code imports from here (the pieces live
#: in the modules beside this one).
__all__ = ["PNG_SIGNATURE", "WORK_PRECISION_COMMAND", "Bench", "ReportError", "bench_command",
           "bench_indicative", "build_parser", "classify", "generate", "main", "num",
           "parse_image", "places", "reading_bench", "run"]


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
    kinds = {"bench": "benchmark suite", "scene": "benchmark suite on a scene",
             "stability": "stability suite",
             "work_precision": "work–precision records", "inverse": "worked inverse problems"}
    # Inputs named relative to the report (beside it, as a study writes them): a path of
    # the machine that made it means nothing to a reader.
    doc.para("Generated from " + join_words(f"`{os.path.relpath(p, out)}` ({kinds[k]})"
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
    if inputs.scenes:
        doc.para(f"**Across scenes.** The section \"The structures across scenes\" compares "
                 f"the structures on {len(scene_runs(inputs))} scenes and checks four claims "
                 "of the literature against them.")
    if not inputs.bench and not inputs.scenes:
        doc.para("No benchmark results were given: the structures, scaling and cost-model "
                 f"sections come from `{BENCH_COMMAND}`.")
    if not inputs.stability:
        doc.para(f"No stability results were given: `{STABILITY_COMMAND}` produces them.")

    multi = len(inputs.bench) > 1
    for i, b in enumerate(inputs.bench, 1):
        prefix = f"bench{i}-" if multi else ""  # figures of several runs side by side
        section_structures(doc, b, out, prefix)
        section_heatmaps(doc, b, out, prefix)
        section_scaling(doc, b, out, prefix)
        section_cost_model(doc, b, out, prefix)
        section_turntable(doc, b)
        section_trimesh_interface(doc, b)
    section_scenes(doc, inputs, out)
    section_work_precision(doc, inputs, out)
    section_inverse(doc, inputs, out)
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
