"""The report's sections: each appends its headings, paragraphs, tables and figures to the
document (the structures side by side, per-pixel cost, scaling, the cost model, batched
renders, error against run time, the stability suite's tables, renders given with
``--image``, the machine and library versions). Every section names the command that made
its data, and marks a quick run's numbers as indicative."""

from __future__ import annotations

import datetime
import json
import platform
import shutil
from pathlib import Path

from reports.document import (
    IMAGE_TYPES,
    PNG_SIGNATURE,
    Doc,
    ReportError,
    join_words,
    num,
    plural,
    seconds_text,
)
from reports.figures import (
    fig_bars,
    fig_cost_model,
    fig_heatmaps,
    fig_inverse,
    fig_rates,
    fig_scaling,
    fig_work_precision,
)
from reports.inputs import (
    INDICATIVE,
    INVERSE_COMMAND,
    MIN_FIT_SIZES,
    REPORT_COMMAND,
    WORK_PRECISION_COMMAND,
    Bench,
    Inputs,
    bench_indicative,
    build_mib,
    count,
    dicts,
    median,
    not_fitted,
    scaling_fits,
    stability_command,
    stability_indicative,
    stability_rows,
    structure_order,
    trace_counter,
)

#: Metrics of a work–precision record: (key, aliases, axis label, higher is better).
METRICS = (("psnr", ("psnr", "PSNR"), "PSNR (dB)", True),
           ("ssim", ("ssim", "SSIM"), "SSIM", True),
           ("delta_e", ("delta_e", "deltaE", "delta_e_2000", "ciede2000", "mean_delta_e"),
            "mean CIEDE2000 ΔE", False))
#: Rows of one stability table shown before the rest is left to the JSON.
MAX_ROWS = 40
#: Columns of one stability table (labels and the core counts first; the rest is in the JSON).
MAX_COLUMNS = 16


# ============================================================================================
# Marks of a quick run's numbers
# ============================================================================================


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


# ============================================================================================
# Benchmark runs
# ============================================================================================


def section_structures(doc: Doc, b: Bench, out: Path, prefix: str) -> None:
    """The run's parameters, the tables of build, memory, rate, counters, tree shape and
    correctness per structure, other peers, and the bar charts."""
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
        + (f"; ray sets: {join_words(set_desc)}" if set_desc else "")
        + (f"; {p['repeats']} warm calls per structure and set (median, min, max)"
           if p.get("repeats") else "")
        + (f", fewer where they took {p['trace_budget_seconds']:g} s (at least one)"
           if p.get("repeats") and p.get("trace_budget_seconds") and any(
               isinstance(t.get("repeats"), list) and len(t["repeats"]) < p["repeats"]
               for t in traces.values()) else "")
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
            f"{num(median(embree[s].get('mrays_per_s')))} (1)" if s in embree else "–"
            for s in sets])
    for name in names:
        bld = builds.get(name, {})
        row = [name, num(median(bld.get("seconds"))), num(build_mib(bld)), num(bld.get("sah_cost"))]
        for s in sets:
            t = traces.get((name, s))
            row.append(f"{num(median(t.get('mrays_per_s')))} ({num(t.get('ratio_to_embree'))})"
                       if t else "–")
        rows.append(row)
    doc.table(header, rows, "build: median of the builds; Mrays/s: median of the warm calls; "
                            "x Embree: the ratio to Embree's median rate on the same rays")

    rows = []
    for name in names:
        row = [name]
        for s in sets:
            t = traces.get((name, s))
            row.append(f"{num(trace_counter(t, 'steps'))} / {num(trace_counter(t, 'tests'))} / "
                       f"{num(trace_counter(t, 'leaves'))}" if t and t.get("counters") else "–")
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
                         f"{num(median(bld.get('seconds', {}).get('min')))}–"
                         f"{num(median(bld.get('seconds', {}).get('max')))}"
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
                    num(median(r.get("mrays_per_s"))), num(r.get("ratio_to_embree")),
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
    values = {n: median(builds[n].get("seconds")) for n in names if n in builds}
    if any(v is not None for v in values.values()):
        err = {n: (median(builds[n]["seconds"].get("min")) or values[n],
                   median(builds[n]["seconds"].get("max")) or values[n])
               for n in values if isinstance(builds[n].get("seconds"), dict)
               and values[n] is not None}
        f = out / "figures" / f"{prefix}build.png"
        fig_bars(b, f, values, err if len(err) == len([v for v in values.values() if v])
                 else None, "build time (s)", "Build time (median, min–max)")
        doc.figure(f, f"figures/{f.name}", _marked(
                   f"Build time per structure (median of the builds, whiskers min–max). "
                   f"Data: `{b.command}`.", mark))
    values = {n: build_mib(builds[n]) for n in names if n in builds}
    if any(v is not None for v in values.values()):
        f = out / "figures" / f"{prefix}memory.png"
        fig_bars(b, f, values, None, "memory (MiB)", "Memory of the structure's arrays")
        doc.figure(f, f"figures/{f.name}", _marked(
                   f"Memory per structure (bytes of its arrays, MiB). Data: `{b.command}`.",
                   mark))


def section_heatmaps(doc: Doc, b: Bench, out: Path, prefix: str) -> bool:
    """Per-pixel steps and tests of the camera rays (False where the run has none)."""
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
    """Build time and rate against the triangle count, with fitted exponents (False where
    the run has no scaling records)."""
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
        for row in sorted(dicts(r.get("rows")), key=lambda row: count(row.get("triangles"))):
            rows.append([r.get("structure"), row.get("mesh"), num(row.get("triangles")),
                         num(median(row.get("build_seconds"))), num(row.get("ns_per_n_log2_n")),
                         num(median(row.get("mrays_per_s"))), num(row.get("ratio_to_embree"))])
    doc.table(["structure", "mesh", "triangles", "build (s)", "ns per N log2 N", "Mrays/s",
               "x Embree"], rows)
    fits = [(r.get("structure"), *scaling_fits(r)) for r in recs]
    doc.table(["structure", "build time ~ N^", "trace time ~ N^"],
              [[name, *(num(k) if k is not None else not_fitted(sizes) for k in (be, te))]
               for name, be, te, sizes in fits])
    f = out / "figures" / f"{prefix}scaling.png"
    fig_scaling(b, f)
    legend = ("fitted exponents in the legend" if any(
        k is not None for fit in fits for k in fit[1:3]) else
        f"no exponent fitted ({plural(max(fit[3] for fit in fits), 'size')}; "
        f"{MIN_FIT_SIZES} needed)")
    doc.figure(f, f"figures/{f.name}", _marked(
               f"Build time and camera Mrays/s against N (log-log), {legend}, Embree's rate "
               f"on the same rays in black. Data: `{b.command}`.", bench_indicative(b)))
    return True


def section_cost_model(doc: Doc, b: Bench, out: Path, prefix: str) -> bool:
    """The fitted cost model per structure (False where the run has no fit)."""
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
    if any(dicts(r.get("points")) for r in recs):
        f = out / "figures" / f"{prefix}cost-model.png"
        fig_cost_model(b, f)
        doc.figure(f, f"figures/{f.name}", _marked(
                   "Measured against predicted nanoseconds per ray, one point per structure "
                   f"and ray set; on the dotted line the model is exact. Data: `{b.command}`.",
                   bench_indicative(b)))
    return True


def section_turntable(doc: Doc, b: Bench) -> bool:
    """Batched renders against a loop of single renders (False where the run has none)."""
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


def section_trimesh_interface(doc: Doc, b: Bench) -> bool:
    """trimesh's ray interface through jrt, Embree and trimesh (False where none ran)."""
    recs = b.of("trimesh_interface")
    if not recs:
        return False
    doc.heading(3, "trimesh's ray interface" + (f": {b.label}" if b.label else ""))
    doc.para(_section_mark(b)
             + "What a trimesh user calls: `intersects_location` (every hit of each ray, "
             "trimesh's default) on rays through the mesh's bounding sphere and "
             "`contains_points` on points drawn in its bounding box, through "
             "`jrt.trimesh.RayMeshIntersector` (BVH, watertight kernel, all cores), "
             "trimesh's Embree intersector (`ray_pyembree`, one thread, as trimesh calls it) "
             "and trimesh's own (`ray_triangle`, float64 NumPy, on a subset: it is slow). "
             "Items are rays or points per second; *x jrt* is jrt's rate over the engine's. "
             "Agreement: the rays whose hit count (or the points whose answer) equals "
             f"trimesh's own, and Embree's, answer. Data: `{b.command}`.")
    rows = []
    for r in recs:
        agree = ""
        if r.get("engine") == "jrt":
            parts = [f"{num(r.get(key))} of {num(r.get(of))} with {peer}"
                     for key, of, peer in (("agree_with_trimesh", "trimesh_items", "trimesh"),
                                           ("agree_with_embree", "items", "Embree"))
                     if r.get(key) is not None]
            agree = "; ".join(parts) or "not compared (neither peer installed)"
        rows.append([r.get("mesh"), num(r.get("triangles")), f"`{r.get('query')}`",
                     r.get("engine"), num(r.get("items")), num(r.get("per_second")),
                     num(r.get("jrt_speedup")), agree])
    doc.table(["mesh", "triangles", "call", "engine", "items", "per second", "x jrt",
               "agreement"], rows)
    return True


# ============================================================================================
# Work–precision
# ============================================================================================


def _wp_points(inputs: Inputs) -> list[dict]:
    """Work–precision records as {study, method, seconds, psnr, ssim, delta_e, command}."""
    points = []
    for path, r, command in inputs.work_precision:
        seconds = median(r.get("seconds"))
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
            p[key] = median(value)
        points.append(p)
    return points


def section_work_precision(doc: Doc, inputs: Inputs, out: Path) -> None:
    """One table and one diagram per study of the work–precision points (or which command
    makes them, where there are none)."""
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


def _inverse_error(problem: dict) -> str:
    """Each parameter's error as the problem records it, in per cent to two digits."""
    if "relative_error" in problem:
        return ", ".join(f"{name} {error * 100:.2g} %" for name, error in
                         zip(problem["parameters"], problem["relative_error"], strict=False))
    if "translation_error_over_diagonal" in problem:
        return (f"translation {problem['translation_error_over_diagonal'] * 100:.2g} % of "
                f"the diagonal, scale {problem.get('scale_error', float('nan')) * 100:.2g} %")
    return ""


def section_inverse(doc: Doc, inputs: Inputs, out: Path) -> None:
    """The worked inverse problems (``benchmarks.inverse``): parameters recovered from a
    target image by gradient descent through the differentiable queries and renderer, a
    table of start, truth and found values and the loss and parameter curves."""
    doc.heading(2, "Gradients: worked inverse problems")
    if not inputs.inverse:
        doc.para("No inverse-problem results in these inputs. "
                 f"`{INVERSE_COMMAND} --json inverse.json` produces them (the glass camel's "
                 "Cauchy coefficients from a render, a moved camel from a depth image); pass "
                 "the JSON to the report to draw them.")
        return
    doc.para("Parameters recovered from a target image by gradient descent (Adam, optax) "
             "on the derivatives of jrt's queries and renderer: the derivative of the image "
             "with the hit triangles held fixed (`docs/gradients.md`). **glass**: the glass "
             "camel's Cauchy coefficients (A, B) from a render with BK7's, starting from "
             "fused silica's; **depth**: the 19k camel's translation and scale from a depth "
             "image, through `jrt.refit` of its BVH.")
    for i, (path, data) in enumerate(inputs.inverse, 1):
        command = data.get("command") or INVERSE_COMMAND
        note = inputs.indicative.get(path, "")
        rows = []
        for p in data["problems"]:
            rows.append([p["problem"], ", ".join(p["parameters"]),
                         ", ".join(f"{v:.6g}" for v in p["start"]),
                         ", ".join(f"{v:.6g}" for v in p["truth"]),
                         ", ".join(f"{v:.6g}" for v in p["found"]), _inverse_error(p),
                         str(len(p["losses"]) - 1), seconds_text(p.get("seconds"))])
        doc.table(["problem", "parameters", "start", "truth", "found", "error",
                   "steps", "time"], rows)
        suffix = f"-{i}" if len(inputs.inverse) > 1 else ""
        f = out / "figures" / f"inverse{suffix}.png"
        fig_inverse(data, f, command, note=note)
        doc.figure(f, f"figures/{f.name}", _marked(
            f"Loss and parameters against the Adam step ({data.get('width')}x"
            f"{data.get('height')} pixels, {data.get('date', 'date not recorded')}). "
            f"Data: `{command}`.", note))


# ============================================================================================
# Stability
# ============================================================================================

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




def stability_overview(data: dict) -> tuple[list[str], list[list[str]]]:
    """Cracks / false hits / NaN per kernel x structure and case, summed over each case's
    records (cases whose records count cracks)."""
    cases = [c for c, body in data["cases"].items()
             if any("cracks" in r for r in stability_rows(body))]
    pairs, cells = [], {}
    for c in cases:
        for r in stability_rows(data["cases"][c]):
            if "cracks" not in r:
                continue
            pair = (str(r.get("kernel")), str(r.get("structure")))
            if pair not in pairs:
                pairs.append(pair)
            acc = cells.setdefault((pair, c), [0, 0, 0])
            for i, k in enumerate(("cracks", "false_hits", "nan")):
                v = r.get(k)
                acc[i] += v if isinstance(v, int | float) and not isinstance(v, bool) else 0
    order = structure_order()
    pairs.sort(key=lambda p: (p[0], order.index(p[1]) if p[1] in order else 99))
    header = ["kernel", "structure"] + [f"case {c}: cracks / false / NaN" for c in cases]
    rows = [[k, s] + [" / ".join(num(v) for v in cells[(k, s), c]) if ((k, s), c) in cells
                      else "–" for c in cases] for k, s in pairs]
    return header, rows


def section_stability(doc: Doc, path: Path, data: dict, many: bool) -> None:
    """The stability run's overview, then per case its findings and its records' tables."""
    doc.heading(2, "Numerical stability" + (f": `{path.name}`" if many else ""))
    command = stability_command(data, path)
    env = data.get("environment") or {}
    doc.para((_mark("a quick run (`--quick`, small sizes)") + " " if stability_indicative(data)
              else "The study's standard sizes (`--size standard`, a tenth to a quarter of the "
              "full sweep's rays; case 5 at three scales and three shifts). "
              if data.get("size") == "standard" else "")
             + f"Every case runs over kernel x structure pairs against an oracle: "
             f"{data.get('oracle', 'see the suite')}. "
             + (f"{len(data['cases'])} cases in {seconds_text(data.get('seconds'))}"
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
                    + (f" ({seconds_text(body['seconds'])})" if body.get("seconds") is not None
                       else ""))
        if body.get("findings"):
            doc.quote(str(body["findings"]))
        records = stability_rows(body)
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


# ============================================================================================
# Machine, renders
# ============================================================================================


def section_machine(doc: Doc, inputs: Inputs) -> None:
    """The machines and library versions of the runs, and of this report."""
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
                ["build threads", m.get("build_threads")],
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
    """The ``--image`` renders, copied into ``out/renders`` (ReportError for a file the
    report cannot embed)."""
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
