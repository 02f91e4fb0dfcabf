"""The report's section "The structures across scenes": the benchmark suite on each scene of
the scene suite (``jrt.scenes``; ``jrt bench --scene NAME``, ``jrt study`` runs them all),
side by side, and the literature's claims checked against the numbers.

A benchmark run made with ``--scene NAME`` (its ``parameters.scene``) is a *scene run*:
:func:`reports.inputs.load_inputs` keeps it apart from the headline runs, whose sections
are the report's others. This section reads the scene runs and the headline run on the
camel (the study's ``bench.json``), one row per scene:

- the trace rate relative to Embree (same rays, same process) per structure: the geometric
  mean over the ray sets, and per set for camera and incoherent rays; steps and triangle
  tests per ray; build time, memory and SAH cost;
- a ranking per scene (by that geometric mean);
- Havran and Purgathofer's cost model (time per ray ~ C_0 + C_TS steps + C_IT tests)
  fitted per structure across every scene and ray set (:func:`benchmarks.common.cost_model`),
  and how well each structure's SAH cost orders the scenes' incoherent trace times
  (Spearman's rank correlation: the SAH assumes rays spread evenly over the scene, as the
  incoherent set's are);
- four claims of the literature, each stated with the numbers that support or contradict
  it: Havran's SAH kd-tree as the best CPU scheme (Havran 2000); the uniform grid's failure
  on the "teapot in a stadium" (Haines 1988); the BVH as the structure with the least
  memory (Wald, Boulos & Shirley 2007; Vinkler et al. 2016); the SAH cost as a predictor of
  the trace time (Aila, Karras & Laine 2013, who found it a fair but imperfect one).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from benchmarks.common import cost_model
from jrt.scenes import DESCRIPTIONS, SCENES, parse_label
from reports.document import Doc, join_words, num
from reports.figures import _colour, _new_figure, _save
from reports.inputs import (
    INDICATIVE,
    Bench,
    Inputs,
    bench_indicative,
    build_mib,
    geomean,
    median,
    scene_size,
    trace_counter,
)

#: The command of one scene's run (the study passes its sizes as well).
SCENE_COMMAND = "jrt bench --scene NAME"
#: A rank correlation at least this large counts as the SAH cost predicting the order.
GOOD_CORRELATION = 0.7


def scene_of(b: Bench) -> str:
    """The scene a run measured: its ``--scene``, or the camel for a run on the camel."""
    scene = b.params.get("scene")
    if isinstance(scene, str):
        return scene
    mesh = str(b.params.get("mesh", ""))
    return (parse_label(mesh) or (mesh,))[0]


def scene_runs(inputs: Inputs) -> list[Bench]:
    """The runs of the cross-scene section, one per scene in the suite's order: the scene
    runs, and the first headline run on the camel when no scene run measured it."""
    runs = {}
    for b in inputs.scenes:
        runs.setdefault(scene_of(b), b)
    camel = next((b for b in inputs.bench if scene_of(b) == "camel"), None)
    if camel is not None:
        runs.setdefault("camel", camel)
    order = list(SCENES) + sorted(n for n in runs if n not in SCENES)
    return [runs[n] for n in order if n in runs]


def geomean_ratio(b: Bench, name: str) -> float | None:
    """The geometric mean over the run's ray sets of ``name``'s rate relative to Embree."""
    return geomean(median(b.traces.get((name, s), {}).get("ratio_to_embree")) for s in b.sets)


def _structures(runs: list[Bench]) -> list[str]:
    names = []
    for b in runs:
        names += [n for n in b.structures if n != "brute" and n not in names]
    return names


def _per_ray(rec: dict) -> float | None:
    seconds, rays = median(rec.get("seconds")), rec.get("rays")
    return seconds / rays if seconds and isinstance(rays, int) and rays > 0 else None


def spearman(xs, ys) -> float | None:
    """Spearman's rank correlation of two lists (average ranks for ties); None for fewer
    than three pairs or a constant list."""
    if len(xs) < 3:
        return None

    def ranks(v):
        v = np.asarray(v, float)
        order = np.argsort(v, kind="stable")
        r = np.empty(len(v))
        r[order] = np.arange(len(v))
        for value in np.unique(v):  # ties share their mean rank
            r[v == value] = r[v == value].mean()
        return r

    rx, ry = ranks(xs), ranks(ys)
    if rx.std() == 0 or ry.std() == 0:
        return None
    return float(np.corrcoef(rx, ry)[0, 1])


def _label(b: Bench) -> str:
    scene = scene_of(b)
    small = scene_size(b.params) == "small"
    return f"{scene} (small)" if small and scene in SCENES else scene


def section_scenes(doc: Doc, inputs: Inputs, out: Path) -> bool:
    """The section (False, and nothing written, without a scene run)."""
    if not inputs.scenes:
        return False
    runs = scene_runs(inputs)
    names = _structures(runs)
    quick = [b for b in runs if bench_indicative(b)]
    doc.heading(2, "The structures across scenes")
    doc.para(
        "The benchmark suite on each scene of the scene suite (`jrt.scenes`), one run per "
        f"scene (`{SCENE_COMMAND}`; `jrt study` runs them all), Embree in the same process "
        "on the same rays: "
        + join_words(f"**{_label(b)}**, {b.params.get('triangles', 0):,} triangles "
                     f"({DESCRIPTIONS.get(scene_of(b), 'a mesh of your own')})" for b in runs)
        + ". The rates are relative to Embree's, which removes most of the host's speed from "
        "the comparison; the commands of the runs are listed at the end of the section."
        + (f" **{INDICATIVE}**: " + join_words(f"{_label(b)} ({bench_indicative(b)})"
                                               for b in quick) + "." if quick else ""))
    _ratio_table(doc, runs, names)
    f = out / "figures" / "scenes.png"
    fig_scenes(runs, names, f)
    doc.figure(f, f"figures/{f.name}",
               "Trace rate relative to Embree per scene and structure: the geometric mean "
               f"over the ray sets (log scale). Data: `{SCENE_COMMAND}` per scene.")
    _detail_table(doc, runs, names)
    doc.para(_correctness(runs))
    doc.heading(3, "Ranking per scene")
    doc.bullets(_ranking(b, names) for b in runs)
    _cost_models(doc, runs, names)
    doc.heading(3, "The literature's claims")
    doc.bullets([_havran(runs), _stadium(runs), _memory(runs, names), _sah(runs, names)])
    doc.para("Runs: " + join_words(f"{_label(b)}: `{b.command}`" for b in runs) + ".")
    return True


def _ratio_table(doc: Doc, runs: list[Bench], names: list[str]) -> None:
    rows = []
    for b in runs:
        ratios = {n: geomean_ratio(b, n) for n in names}
        known = {n: r for n, r in ratios.items() if r is not None}
        best = max(known, key=known.get) if known else "—"
        rows.append([_label(b), f"{b.params.get('triangles', 0):,}",
                     *[f"{num(ratios[n])}x" if ratios[n] is not None else "—" for n in names],
                     best])
    doc.table(["scene", "triangles", *names, "fastest"], rows,
              "Trace rate relative to Embree, geometric mean over the ray sets (camera, "
              "shadow, reflected, refracted, incoherent).")


def _detail_table(doc: Doc, runs: list[Bench], names: list[str]) -> None:
    rows = []
    for b in runs:
        builds = b.builds
        for n in names:
            build, cam, inc = builds.get(n, {}), b.traces.get((n, "camera"), {}), \
                b.traces.get((n, "incoherent"), {})

            def rate(rec):
                r, x = median(rec.get("mrays_per_s")), median(rec.get("ratio_to_embree"))
                return f"{num(r)} ({num(x)}x)" if r is not None and x is not None else "—"

            rows.append([_label(b), n, num(median(build.get("seconds"))),
                         num(build_mib(build)), num(build.get("sah_cost")), rate(cam),
                         rate(inc), num(trace_counter(inc, "steps")),
                         f"{num(trace_counter(inc, 'tests'))} / {_whole(_worst(inc))}"])
    doc.table(["scene", "structure", "build (s)", "memory (MiB)", "SAH cost",
               "camera Mrays/s (x Embree)", "incoherent Mrays/s (x Embree)",
               "incoherent steps/ray", "incoherent tests/ray (mean / worst)"], rows,
              "Per scene and structure: the median build, the structure's arrays, its SAH "
              "cost as the builder computes it (comparable between scenes for one structure, "
              "not between structures), and two of the ray sets.")


def _correctness(runs: list[Bench]) -> str:
    """Each scene's hits against brute force, and the float64 oracle's verdict where they
    differ."""
    clean, other = [], []
    for b in runs:
        checks = [r for r in b.of("correctness") if r.get("structure") != "brute"]
        if not checks:
            continue
        bad = sum(r.get("mismatches") or 0 for r in checks)
        rays = sum(r.get("rays") or 0 for r in checks)
        if not bad:
            clean.append(_label(b))
            continue
        judged = [r["oracle"] for r in checks if isinstance(r.get("oracle"), dict)]
        text = f"{_label(b)}: {bad:,} of {rays:,} checked rays differ"
        if judged:
            text += (f"; on {sum(o['rays'] for o in judged):,} of them the float64 oracle "
                     f"sides with the structure {sum(o['structure_right'] for o in judged):,} "
                     f"times and with brute force {sum(o['brute_right'] for o in judged):,} "
                     "times")
        other.append(text)
    parts = []
    if clean:
        parts.append("every structure returns brute force's hits bit for bit on "
                     + join_words(clean))
    return ("**Against brute force** (same kernel, each run's checked rays): "
            + "; ".join(parts + other) + "." + (
                " Brute force tests every triangle for every ray: a float32 kernel evaluated "
                "on a triangle a few ulps wide, seen from far away, can report a false hit "
                "there, which the structures' boxes cull (see the scene suite's page, "
                "docs/scenes.md)." if other else ""))


def _whole(x) -> str:
    """A count: 5,000, not 5000 or 5.00e+03 (``—`` where unknown)."""
    return f"{x:,.0f}" if isinstance(x, int | float) and math.isfinite(x) else "—"


def _worst(rec: dict) -> float | None:
    """The most triangle tests any ray of a trace record made."""
    tests = (rec.get("counters") or {}).get("tests") if isinstance(rec, dict) else None
    return median(tests.get("max")) if isinstance(tests, dict) else None


def _ranking(b: Bench, names: list[str]) -> str:
    ratios = {n: geomean_ratio(b, n) for n in names}
    known = sorted(((r, n) for n, r in ratios.items() if r is not None), reverse=True)
    return f"{_label(b)}: " + " > ".join(f"{n} {num(r)}x" for r, n in known)


def _cost_models(doc: Doc, runs: list[Bench], names: list[str]) -> None:
    doc.heading(3, "Cost model and SAH across scenes")
    rows = []
    for n in names:
        traces = [t for b in runs for (s, _), t in b.traces.items() if s == n
                  and trace_counter(t, "steps") is not None and _per_ray(t)]
        fit = cost_model(n, traces) if len(traces) >= 3 else None
        rho = _sah_correlation(runs, n)
        rows.append([n, len(traces), num(fit and fit["c_ts_ns"]), num(fit and fit["c_it_ns"]),
                     num(fit and fit["c_ray_ns"]), num(fit and fit["residual"]),
                     num(rho) if rho is not None else "—"])
    doc.para("Havran and Purgathofer's model (time per ray ~ C_0 + C_TS x steps + C_IT x "
             "tests) fitted per structure over every scene and ray set at once (non-negative "
             "least squares of relative errors, as the suite fits one scene): a small residual "
             "means that steps and tests explain the time on every scene, a large one that "
             "something else (memory traffic, lanes idling) does. The last column is Spearman's "
             "rank correlation, across the scenes, of the structure's SAH cost with its "
             "incoherent rays' time per ray (1: the SAH orders the scenes as the clock does).")
    doc.table(["structure", "points", "C_TS (ns)", "C_IT (ns)", "C_0 (ns)", "residual",
               "SAH vs time (Spearman)"], rows)


def _sah_correlation(runs: list[Bench], name: str) -> float | None:
    pairs = []
    for b in runs:
        sah = b.builds.get(name, {}).get("sah_cost")
        per_ray = _per_ray(b.traces.get((name, "incoherent"), {}))
        if isinstance(sah, int | float) and per_ray:
            pairs.append((sah, per_ray))
    return spearman(*zip(*pairs, strict=True)) if len(pairs) >= 3 else None


def _havran(runs: list[Bench]) -> str:
    fastest = {}
    for b in runs:
        ratios = {n: geomean_ratio(b, n) for n in _structures([b])}
        ratios = {n: r for n, r in ratios.items() if r is not None}
        if ratios:
            fastest[_label(b)] = max(ratios, key=ratios.get)
    kd = [s for s, n in fastest.items() if n == "kdtree"]
    claim = ("**Havran's SAH kd-tree as the best CPU scheme** (Havran 2000, 12 schemes on "
             "30 scenes): ")
    if not fastest or not any("kdtree" in b.structures for b in runs):
        return claim + "not measured (no kd-tree run)."
    shares = []
    for b in runs:
        kr, br = geomean_ratio(b, "kdtree"), geomean_ratio(b, "bvh")
        if kr and br:
            shares.append(kr / br)
    steps = [(trace_counter(b.traces.get(("kdtree", "incoherent"), {}), "steps"),
              trace_counter(b.traces.get(("bvh", "incoherent"), {}), "steps")) for b in runs]
    steps = [(k, v) for k, v in steps if k and v]
    others = sorted({n for n in fastest.values() if n != "kdtree"})
    verdict = (f"agrees on {len(kd)} of {len(fastest)} scenes" if len(kd) * 2 >= len(fastest)
               else f"disagrees: the kd-tree is the fastest on {len(kd)} of {len(fastest)} "
                    f"scenes" + (f" ({join_words(kd)})" if kd else "")
               + f", {join_words(others)} on the others")
    text = claim + verdict
    if shares:
        text += (f". Across the scenes the kd-tree traces at {num(min(shares))}x to "
                 f"{num(max(shares))}x the BVH's rate (median {num(float(np.median(shares)))}x)")
    if steps:
        text += (f"; its incoherent rays take {num(float(np.median([k for k, _ in steps])))} "
                 f"steps per ray (median over the scenes) against the 4-wide BVH's "
                 f"{num(float(np.median([v for _, v in steps])))}. Havran timed scalar C++ "
                 "traversals, where a kd-tree step is a few instructions; in jrt's engine every "
                 "step, of any structure, is one iteration of a loop over all the lanes, so the "
                 "number of steps per ray weighs more than what one step costs")
    return text + "."


def _stadium(runs: list[Bench]) -> str:
    claim = ("**The uniform grid fails on the teapot in a stadium** (Haines 1988; a small "
             "detailed object in a large sparse scene): ")
    by = {scene_of(b): b for b in runs}
    stadium, camel = by.get("stadium"), by.get("camel")
    if stadium is None or not {"grid", "bvh"} <= set(stadium.structures):
        return claim + "not measured (no stadium run with the grid and the BVH)."

    def relative(b, name):  # incoherent rate relative to the BVH's, and the worst ray's tests
        g, v = (b.traces.get((n, "incoherent"), {}) for n in (name, "bvh"))
        rg, rv = median(g.get("mrays_per_s")), median(v.get("mrays_per_s"))
        worst = (g.get("counters") or {}).get("tests") or {}
        return (rg / rv if rg and rv else None), median(worst.get("max"))

    on_stadium, worst = relative(stadium, "grid")
    if on_stadium is None:
        return claim + "not measured (no incoherent rays)."
    text = (f"on the stadium the grid traces incoherent rays at {num(on_stadium)}x the BVH's "
            f"rate, and its worst ray tests {_whole(worst)} triangles")
    if "octree" in stadium.structures:
        octree, octree_worst = relative(stadium, "octree")
        if octree is not None:
            # Alike: the octree loses on the stadium as the grid does, against its own rate
            # on the camel alone (or, without a camel run, within 2x of the grid's).
            on_camel = (relative(camel, "octree")[0] if camel is not None
                        and {"octree", "bvh"} <= set(camel.structures) else None)
            alike = (octree < 0.5 * on_camel if on_camel else octree < 2 * on_stadium)
            text += (f"; the octree {'fares alike' if alike else 'does not'}: "
                     f"{num(octree)}x, {_whole(octree_worst)} tests")
            if not alike:
                text += (" (its default depth follows the scene's size over its median "
                         "triangle's, so its cells reach the camel's triangles)")
    if camel is not None and {"grid", "bvh"} <= set(camel.structures):
        on_camel, camel_worst = relative(camel, "grid")
        if on_camel:
            text += (f". On the camel alone the grid runs at {num(on_camel)}x the BVH's rate "
                     f"(worst ray {_whole(camel_worst)} tests)")
            agrees = on_stadium < 0.5 * on_camel
            return claim + ("agrees: " if agrees else "disagrees: ") + text + (
                ". The camel sits in the few cells sized for the whole stadium, and a ray "
                "through them tests all its triangles there; the engine's lanes wait for "
                "that ray, so the few such rays set the rate." if agrees else
                ". The grid's resolution follows the triangle count, which keeps its cells "
                "small enough here.")
    return claim + text + " (no camel run to compare with)."


def _memory(runs: list[Bench], names: list[str]) -> str:
    claim = "**The BVH uses the least memory** (Wald, Boulos & Shirley 2007; Vinkler et al. 2016): "
    least, bvh_wins = {}, []
    for b in runs:
        mib = {n: build_mib(b.builds.get(n, {})) for n in names}
        mib = {n: m for n, m in mib.items() if m is not None}
        if mib:
            least[_label(b)] = min(mib, key=mib.get), mib
    if not least or "bvh" not in names:
        return claim + "not measured."
    bvh_wins = [s for s, (n, _) in least.items() if n == "bvh"]
    exceptions = [f"{s}: {n} {num(m[n])} MiB against the BVH's {num(m.get('bvh'))}"
                  for s, (n, m) in least.items() if n != "bvh" and "bvh" in m]
    verdict = ("agrees on every scene" if len(bvh_wins) == len(least) else
               f"{'agrees' if len(bvh_wins) * 2 >= len(least) else 'disagrees'}: the BVH is "
               f"the smallest on {len(bvh_wins)} of {len(least)} scenes")
    return claim + verdict + (f" (elsewhere: {'; '.join(exceptions)})" if exceptions else "") + (
        ". Its node count is bounded by the triangle count (no triangle is referenced twice), "
        "where the spatial structures reference a triangle once per cell it crosses.")


def _sah(runs: list[Bench], names: list[str]) -> str:
    claim = ("**The SAH cost predicts the trace time** (MacDonald & Booth 1990; Aila, Karras "
             "& Laine 2013 found the correlation fair but imperfect): ")
    rhos = {n: _sah_correlation(runs, n) for n in names}
    rhos = {n: r for n, r in rhos.items() if r is not None}
    if not rhos:
        return claim + "not measured (fewer than three scenes with a structure's SAH cost)."
    good = [n for n, r in rhos.items() if r >= GOOD_CORRELATION]
    verdict = ("agrees" if len(good) * 2 >= len(rhos) else "disagrees")
    return (claim + f"{verdict}: across the scenes, the rank correlation of each structure's "
            "SAH cost with its incoherent time per ray is "
            + join_words(f"{num(r)} ({n})" for n, r in rhos.items())
            + f"; {len(good)} of {len(rhos)} reach {GOOD_CORRELATION}. The SAH counts the "
            "expected steps and tests of rays spread evenly over the scene's box; it leaves "
            "out what a step costs on each structure, and rays that start inside the scene "
            "or stop at the first hit.")


def fig_scenes(runs: list[Bench], names: list[str], file: Path) -> None:
    """Grouped bars: per scene, each structure's geometric-mean ratio to Embree."""
    fig, (ax,) = _new_figure(max(7.0, 1.1 * len(runs) + 2.5), 4.4)
    n = max(1, len(names))
    width = 0.8 / n
    for i, name in enumerate(names):
        xs, ys = [], []
        for j, b in enumerate(runs):
            r = geomean_ratio(b, name)
            if r is not None:
                xs.append(j + (i - (n - 1) / 2) * width)
                ys.append(r)
        if xs:
            ax.bar(xs, ys, width, color=_colour(name, names), label=name)
    ax.axhline(1.0, color="k", linestyle="--", linewidth=1.2, label="Embree")
    ax.set_yscale("log")
    ax.set_xticks(range(len(runs)), [_label(b).replace(" (", "\n(") for b in runs])
    ax.set_ylabel("rate / Embree's (geometric mean over ray sets)")
    ax.set_title("The structures across scenes")
    ax.grid(axis="y", which="both", alpha=0.3)
    ax.legend(fontsize=8, ncol=min(n + 1, 6), loc="upper center", bbox_to_anchor=(0.5, -0.18),
              frameon=False)
    notes = [bench_indicative(b) for b in runs if bench_indicative(b)]
    _save(fig, file, f"{SCENE_COMMAND} per scene", note=notes[0] if notes else "")
