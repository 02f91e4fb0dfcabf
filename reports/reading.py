"""The report's reading of the numbers in words: the fastest structure per ray set and
over all sets, ratios to Embree, build times and memory, agreement with brute force, the
fitted scaling exponents, Havran's kd-tree claim against the measured steps and tests per
ray, and where each kernel, structure and offset of the stability suite breaks.

Orders are stated only where the spread of the repeats separates them: one structure is
ahead of another when the min..max of their warm calls (or builds) do not overlap, and
structures that overlap are called tied within the run's spread."""

from __future__ import annotations

import math

from reports.document import join_words, num, plural
from reports.inputs import (
    KERNEL_ORDER,
    Bench,
    build_mib,
    count,
    dicts,
    geomean,
    median,
    not_fitted,
    preferred_order,
    scaling_fits,
    stability_rows,
    trace_counter,
)

#: How the reading names structures whose spreads overlap.
TIED = "tied within the run's spread"


def _interval(values) -> tuple[float, float] | None:
    """min..max of two or more timings; None with fewer (no spread to order by)."""
    xs = [float(v) for v in values if isinstance(v, int | float) and not isinstance(v, bool)
          and math.isfinite(v) and v > 0] if isinstance(values, list) else []
    return (min(xs), max(xs)) if len(xs) >= 2 else None


def rate_spread(rec: dict) -> tuple[float, float] | None:
    """min..max Mrays/s of a trace's warm calls: from its per-call times (``repeats``) and
    ray count, else its rate's recorded min and max; None with one call."""
    times, rays = _interval(rec.get("repeats")), count(rec.get("rays"))
    if times and rays:
        return rays / times[1] / 1e6, rays / times[0] / 1e6
    rate = rec.get("mrays_per_s")
    lo, hi = (median(rate.get(k)) for k in ("min", "max")) if isinstance(rate, dict) else (
        None, None)
    return (lo, hi) if lo and hi and lo < hi else None


def build_spread(rec: dict) -> tuple[float, float] | None:
    """min..max seconds of a structure's builds (``repeats``, else ``seconds``' min, max)."""
    times = _interval(rec.get("repeats"))
    if times:
        return times
    s = rec.get("seconds")
    lo, hi = (median(s.get(k)) for k in ("min", "max")) if isinstance(s, dict) else (None,
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
    """A place as ``3``, or a shared one as ``3–5``."""
    return str(rank[0]) if rank[0] == rank[1] else f"{rank[0]}–{rank[1]}"


def _ranking(b: Bench) -> dict[str, tuple[float, tuple[float, float] | None]]:
    """Per structure, fastest first: the geometric mean over the ray sets of its median
    Mrays/s, and the geometric means of its per-set min and max (None where a set has no
    spread): an interval that holds the geometric mean of any choice of one warm call per
    set."""
    out = {}
    for n in b.structures:
        recs = [b.traces[n, s] for s in b.sets if (n, s) in b.traces
                and median(b.traces[n, s].get("mrays_per_s"))]
        if not recs:
            continue
        spreads = [rate_spread(r) for r in recs]
        out[n] = (geomean(median(r.get("mrays_per_s")) for r in recs),
                  None if None in spreads else (geomean(lo for lo, _ in spreads),
                                                geomean(hi for _, hi in spreads)))
    return dict(sorted(out.items(), key=lambda x: -x[1][0]))


def _mean_counter(b: Bench, name: str, counter: str) -> float | None:
    """A structure's engine counter per ray, averaged over the ray sets that recorded it."""
    values = [trace_counter(b.traces.get((name, s)), counter) for s in b.sets]
    values = [v for v in values if v is not None]
    return sum(values) / len(values) if values else None


def _ordinal(k: int) -> str:
    """1st, 2nd, 3rd, 4th, 11th, 21st, ..."""
    return f"{k}{'th' if 10 <= k % 100 < 20 else {1: 'st', 2: 'nd', 3: 'rd'}.get(k % 10, 'th')}"


def _calls(b: Bench) -> int | None:
    """Warm calls per structure and set (the parameters, else the shortest repeats list)."""
    n = b.params.get("repeats")
    return n if count(n) else min((len(t["repeats"]) for t in b.of("trace")
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
    vs = (f"{num(ratio)}x Embree's {num(median(b.embree.get(s, {}).get('mrays_per_s')))}"
          if ratio is not None else "")
    if len(first) == len(rated) > 1:
        return (f"{s}: all {len(rated)} {TIED} ("
                + ", ".join(f"{n} {num(v)}" for n, (v, _) in rated.items()) + " Mrays/s)")
    if len(first) == 1:
        text = f"{s}: **{top}** {num(rated[top][0])} Mrays/s" + (f" ({vs})" if vs else "")
    else:
        text = (f"{s}: {join_words(f'{n} {num(rated[n][0])}' for n in first)} Mrays/s {TIED} for "
                "the fastest" + (f" ({top} {vs})" if vs else ""))
    if len(rated) == 1:
        return text
    if len(last) == 1:
        return text + (f", slowest {slow} {num(rated[slow][0])} "
                       f"({num(rated[top][0] / rated[slow][0])}x slower)")
    return text + f", slowest {join_words(last)} {TIED}"


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
        rated = {n: (median(traces[n, s].get("mrays_per_s")), rate_spread(traces[n, s]))
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
            parts.append(f"{n} {num(g)} ({place}" + (f", tied with {join_words(tied)}" if tied
                                                     else "") + ")")
        items.append(f"Over the {plural(len(sets), 'ray set')} (geometric mean of Mrays/s; "
                     "places from the geometric means of each set's min and max, shared where "
                     f"they overlap): " + ", ".join(parts) + ".")
    ratios = [(t.get("ratio_to_embree"), n, s) for (n, s), t in traces.items()
              if isinstance(t.get("ratio_to_embree"), int | float)]
    if ratios:
        best, worst = max(ratios), min(ratios)
        items.append(f"Against Embree on the same rays (medians): from {num(worst[0])}x "
                     f"({worst[1]}, {worst[2]}) to {num(best[0])}x ({best[1]}, {best[2]}).")
    builds = {n: (median(r.get("seconds")), build_spread(r)) for n, r in b.builds.items()}
    builds = {n: v for n, v in builds.items() if v[0]}
    mem = {n: build_mib(r) for n, r in b.builds.items() if build_mib(r)}
    if builds:
        first, last = _ends(builds, higher=False)
        if len(builds) == 1:
            text = f"Build: {first[0]} ({num(builds[first[0]][0])} s)"
        elif len(first) == len(builds):
            text = f"Build: all {len(builds)} {TIED} of the builds"
        else:
            text = "Build: " + ", ".join(
                f"{word} {n} ({num(builds[n][0])} s)" if len(group) == 1 else
                f"{word} {join_words(f'{m} ({num(builds[m][0])} s)' for m in group)} {TIED}"
                for word, group, n in (("fastest", first, first[0]),
                                       ("slowest", last, last[-1])))
        if mem:  # bytes are exact: no spread to separate
            small, big = min(mem, key=mem.get), max(mem, key=mem.get)
            text += f"; memory from {num(mem[small])} MiB ({small}) to {num(mem[big])} MiB ({big})"
        items.append(text + ".")
    checks = b.of("correctness")
    if checks:
        bad = [r for r in checks if r.get("mismatches")]
        total = sum(count(r.get("rays")) for r in checks)
        if bad:
            judged = [r["oracle"] for r in bad if isinstance(r.get("oracle"), dict)]
            items.append("Against brute force: mismatches in " + ", ".join(
                f"{r.get('structure')}/{r.get('set')} ({r['mismatches']} of {r.get('rays')})"
                for r in bad) + "." + (
                f" The float64 oracle judged {sum(count(o.get('rays')) for o in judged):,} of "
                f"them: the structure right on "
                f"{sum(count(o.get('structure_right')) for o in judged):,}, brute force on "
                f"{sum(count(o.get('brute_right')) for o in judged):,} (brute force tests every "
                "triangle for every ray, and a float32 kernel on a triangle a few ulps wide "
                "seen from far away can report a false hit)." if judged else ""))
        else:
            items.append(f"Every structure returned brute force's hits bit for bit "
                         f"(0 mismatches in {total:,} checked rays).")
    scaling = b.of("scaling")
    n = sorted({row["triangles"] for r in scaling for row in dicts(r.get("rows"))
                if count(row.get("triangles"))})
    if n:
        fits = [(r.get("structure", "?"), *scaling_fits(r)) for r in scaling]
        span = f"Scaling over {n[0]:,}–{n[-1]:,} triangles ({plural(len(n), 'size')})"
        if all(be is None and te is None for _, be, te, _ in fits):
            items.append(f"{span}: exponents {not_fitted(len(n))}.")
        else:
            def exps(i):
                return ", ".join(f"{f[0]} N^{f[i]:.2f}" if f[i] is not None else
                                 f"{f[0]} {not_fitted(f[3])}" for f in fits)
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
                f"{len(names)}" + (f", {TIED} with {join_words(tied)}" if tied else "")
                + f" ({num(kd_rate)} Mrays/s, geometric mean over the ray sets, against "
                f"{num(rate)} for the {other}: {num(rate / kd_rate)}x).")
    else:
        verdict, other = "", next(n for n in names if n != "kdtree")
        text = (f"This run neither confirms nor contradicts it on "
                f"{subject[0].lower() + subject[1:]}: the kd-tree ({num(kd_rate)} Mrays/s, "
                f"geometric mean over the ray sets) is {TIED} with {join_words(tied)} for the "
                "first place (their warm calls' min–max overlap).")
    steps = {n: _mean_counter(b, n, "steps") for n in (other, "kdtree")}
    tests = {n: _mean_counter(b, n, "tests") for n in (other, "kdtree")}
    if None in steps.values() or None in tests.values():
        return lead + text + " No traversal counters were recorded to say why."
    s_kd, t_kd, s_o, t_o = steps["kdtree"], tests["kdtree"], steps[other], tests[other]
    text += (f" Per ray, averaged over the sets, the kd-tree takes {num(s_kd)} traversal "
             f"steps and {num(t_kd)} triangle tests, the {other} {num(s_o)} and {num(t_o)}")
    cam = [b.traces.get((n, "camera")) for n in ("kdtree", other)]
    if all(cam):
        kd_cam, other_cam = ((num(trace_counter(c, "steps")), num(trace_counter(c, "tests")))
                             for c in cam)
        text += (f" (camera rays: {kd_cam[0]} / {kd_cam[1]} against {other_cam[0]} / "
                 f"{other_cam[1]})")
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
        for r in stability_rows(body):
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

    for kernel in preferred_order(by_kernel, KERNEL_ORDER):
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
    mism = [(c, r) for c, body in data["cases"].items() for r in stability_rows(body)
            if isinstance(r.get("mismatches_vs_brute"), int) and r.get("structure") != "brute"]
    if mism:
        bad = [f"{r.get('kernel')}/{r.get('structure')} in case {c} ({r['mismatches_vs_brute']})"
               for c, r in mism if r["mismatches_vs_brute"]]
        items.append("Structures against brute force with the same kernel: " + (
            "mismatches " + ", ".join(bad) if bad else
            f"0 mismatches in {plural(len(mism), 'kernel x structure run')}") + ".")
    offsets: dict = {}
    for case, body in data["cases"].items():
        for r in stability_rows(body):
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
    nan = sum(r.get("nan", 0) for body in data["cases"].values() for r in stability_rows(body)
              if isinstance(r.get("nan"), int) and not isinstance(r.get("nan"), bool))
    items.append(f"NaN in any output, all cases: {nan}.")
    return items
