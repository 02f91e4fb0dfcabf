"""The report's figures: PNG files drawn on matplotlib's Agg canvas (no pyplot state, no
display needed). Every figure names under its plot the command that made its data, and why
its numbers are indicative where they are; each structure keeps one colour in every figure."""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

from reports.document import num
from reports.inputs import (
    INDICATIVE,
    MIN_FIT_SIZES,
    SET_ORDER,
    Bench,
    bench_indicative,
    count,
    dicts,
    median,
    not_fitted,
    preferred_order,
    scaling_fits,
    structure_order,
)


def _colour(name: str, names: list[str]) -> str:
    """A structure's colour: its place in the report's structure order, so that it is the
    same in every figure; names outside the order follow, in the order of ``names``."""
    from matplotlib import colormaps

    palette = colormaps["tab10"].colors
    known = structure_order()
    order = preferred_order(names, known)
    index = known.index(name) if name in known else len(known) + order.index(name)
    return palette[index % len(palette)]


def _new_figure(width: float, height: float, ncols: int = 1):
    """A figure of ``width`` x ``height`` inches with ``ncols`` axes side by side."""
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
            med = median(rate)
            if med is None:
                continue
            xs.append(j + (i - (n - 1) / 2) * width)
            ys.append(med)
            lo.append(med - (median(rate.get("min")) or med) if isinstance(rate, dict) else 0)
            hi.append((median(rate.get("max")) or med) - med if isinstance(rate, dict) else 0)
        if xs:
            ax.bar(xs, ys, width, color=_colour(name, names), label=name,
                   yerr=[lo, hi], capsize=2, error_kw={"elinewidth": 0.8})
    labelled = False
    for j, s in enumerate(sets):
        rate = median(embree.get(s, {}).get("mrays_per_s"))
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
    """One bar per structure with a value (``errors``: min..max whiskers), each labelled."""
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
    """Build time (left) and camera-ray rate (right) against the triangle count, log-log,
    with the fitted power laws dotted and Embree's rate in black."""
    recs = {r["structure"]: r for r in b.of("scaling") if isinstance(r.get("structure"), str)}
    names = [n for n in b.structures if n in recs] + [n for n in recs if n not in b.structures]
    fig, (ax_b, ax_t) = _new_figure(11.0, 4.4, ncols=2)
    embree_pts, fitted, sizes = {}, False, 0
    for name in names:
        r = recs[name]
        rows = sorted((row for row in dicts(r.get("rows")) if count(row.get("triangles"))),
                      key=lambda row: row["triangles"])
        colour = _colour(name, names)
        n = [row["triangles"] for row in rows]
        build = [median(row.get("build_seconds")) for row in rows]
        rate = [median(row.get("mrays_per_s")) for row in rows]
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
            if median(row.get("embree_mrays_per_s")):
                embree_pts[row["triangles"]] = median(row["embree_mrays_per_s"])
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
                  f"exponents {not_fitted(sizes)}", title_fontsize=7.5)
    _save(fig, file, b.command, note=bench_indicative(b))


def fig_cost_model(b: Bench, file: Path) -> None:
    """Measured against predicted time per ray, one point per structure and ray set."""
    recs = b.of("cost_model")
    names = [str(r.get("structure", "?")) for r in recs]
    fig, (ax,) = _new_figure(5.6, 4.8)
    markers = dict(zip(SET_ORDER, "o^sDv", strict=True))
    lo, hi = math.inf, 0.0
    for r in recs:
        for p in dicts(r.get("points")):
            rays, seconds = count(p.get("rays")), median(p.get("seconds"))
            predicted = median(p.get("predicted_seconds"))
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
                                          for p in dicts(r.get("points")))]
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
    """Error against run time, one panel per metric, one line per series of points."""
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


def fig_inverse(record: dict, file: Path, command: str, note: str = "") -> None:
    """The loss and parameter curves of a worked inverse problem
    (:func:`benchmarks.inverse.draw`, the drawing its ``--plot`` makes), with the command
    under it."""
    from matplotlib.figure import Figure

    from benchmarks.inverse import draw, figure_size

    width, height = figure_size(record)
    fig = Figure(figsize=(width, height + 0.6))
    draw(record, fig)
    _save(fig, file, command, note=note)
