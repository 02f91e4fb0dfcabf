"""The report generator (``reports.report``) on small results made by the suites' own code.

The benchmark results are assembled from ``benchmarks.suite``'s record builders (real
builds of a tiny icosphere, ``build_record``, ``_peer_row``, ``_scaling_row``,
``cost_model``, ``machine_record``) with synthetic trace times, and checked against
``benchmarks.schema`` (running the suite itself takes a minute: ``tests/test_bench.py``
does). The stability results come from ``benchmarks.stability.run`` (case 6, its lattice
scene, two kernels under brute force and the BVH) plus case 7's optics checks. The report is
generated once into a temporary folder; the tests read its README.md back (tables against
the JSON's numbers, every linked PNG a valid image) and its index.html (every image a data
URI, no link to a local file), then check the errors for unusable inputs.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import types
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
import trimesh
from skimage import io

import accel
import jrt
from reports import report
from reports.report import PNG_SIGNATURE, ReportError, generate, num

ROOT = Path(__file__).resolve().parents[1]
STRUCTURES = ["bvh", "kdtree", "grid"]
SETS = {"camera": "closest", "shadow": "occluded", "incoherent": "closest"}
RAYS = 256
#: Synthetic warm-call times: per set (s), scaled per structure (kd-tree slowest here).
BASE = {"camera": 0.010, "shadow": 0.008, "incoherent": 0.020}
FACTOR = {"bvh": 1.0, "kdtree": 1.6, "grid": 1.25}
STEPS = {"bvh": 6.0, "kdtree": 10.0, "grid": 3.5}
TESTS = {"bvh": 0.6, "kdtree": 1.9, "grid": 4.0}
SET_SCALE = {"camera": 1.0, "shadow": 2.0, "incoherent": 2.7}


def _mesh(subdivisions: int):
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    return np.asarray(sphere.vertices, np.float32), np.asarray(sphere.faces, np.int32)


@pytest.fixture(scope="module")
def bench_results(tmp_path_factory):
    import jax

    suite = pytest.importorskip("benchmarks.suite")
    from benchmarks.build_scaling import fit_exponent
    from benchmarks.common import jsonable, summary, time_calls
    from benchmarks.peers import absent_peer, peer_row
    from benchmarks.schema import validate

    v, f = _mesh(2)
    v4, f4 = _mesh(3)
    records, traces = [], {n: [] for n in STRUCTURES}
    for name in STRUCTURES:
        structure = accel.build(name, v, f)
        times = time_calls(lambda name=name: accel.build(name, v, f), 2)
        records.append(suite.build_record(name, "tiny", len(f), times, structure))
    embree = {}
    for set_name, query in SETS.items():
        ray_set = types.SimpleNamespace(name=set_name, query=query, rays=RAYS)
        row = peer_row("embree", ray_set, [BASE[set_name] / 20, BASE[set_name] / 21],
                       None, threads=2, note="embreex robust mode")
        row["ratio_to_embree"] = 1.0
        embree[set_name] = row["mrays_per_s"]["median"]
        records.append(row)
        for name in STRUCTURES:
            t = BASE[set_name] * FACTOR[name]
            times = [t * 1.02, t * 0.98]
            rate = {"median": RAYS / t / 1e6, "min": RAYS / (t * 1.02) / 1e6,
                    "max": RAYS / (t * 0.98) / 1e6}
            counters = {key: {"mean": value[name] * SET_SCALE[set_name], "p95": 20.0,
                              "max": 40} for key, value in (("steps", STEPS), ("tests", TESTS),
                                                            ("leaves", TESTS))}
            rec = {"kind": "trace", "structure": name, "set": set_name, "query": query,
                   "rays": RAYS, "distinct_rays": RAYS, "hits": RAYS // 2,
                   "first_call_seconds": 1.0, "counters_first_call_seconds": 1.2,
                   "compile_seconds": 0.99, "repeats": times, "seconds": summary(times),
                   "mrays_per_s": rate, "embree_mrays_per_s": embree[set_name],
                   "ratio_to_embree": rate["median"] / embree[set_name], "counters": counters}
            records.append(rec)
            traces[name].append(rec)
            records.append({"kind": "correctness", "structure": name, "set": set_name,
                            "query": query, "reference": "brute", "rays": RAYS,
                            "reference_hits": RAYS // 2, "mismatches": 0,
                            "mismatches_by_field": {"t": 0, "triangle": 0},
                            "embree_rays": RAYS, "embree_disagreements": 1})
    records.append(absent_peer("open3d", "not installed", "pip install open3d"))
    records.append({"kind": "turntable", "scene": "glass-camel", "mesh": "camel-19k",
                    "frames": 8, "width": 48, "height": 36, "samples": 4, "max_depth": 3,
                    "batched_images_per_s": 11.5, "loop_images_per_s": 2.7,
                    "loop_same_capacities_images_per_s": 7.4, "ratio": 11.5 / 7.4,
                    "batch_devices": 2, "max_abs_difference": 0.0, "peak_radiance": 3.2})
    camera = suite.fitted_camera(v, 16)
    o, d = jrt.camera_rays(camera)
    for name in STRUCTURES:  # the engine's real counters, as the suite records them
        _, counts = jrt.closest_hit(accel.build(name, v, f), o, d, counters=True)
        records.append(suite.heatmap_record(name, counts, camera.width, camera.height))
    builds = {r["structure"]: r for r in records if r["kind"] == "build"}
    for name in STRUCTURES:
        cam = traces[name][0]
        big = time_calls(lambda name=name: accel.build(name, v4, f4), 1)
        rows = [suite._scaling_row("tiny", len(f), builds[name]["repeats"], cam["repeats"],
                                   RAYS, 1.0, embree["camera"], True),
                suite._scaling_row("tiny-x4", len(f4), big, [x * 1.3 for x in cam["repeats"]],
                                   RAYS, 1.1, embree["camera"] * 0.9, False)]
        counts = [r["triangles"] for r in rows]
        records.append({"kind": "scaling", "structure": name, "set": "camera", "rays": RAYS,
                        "rows": rows,
                        "build_exponent": fit_exponent(
                            counts, [r["build_seconds"]["median"] for r in rows]),
                        "trace_exponent": fit_exponent(
                            counts, [r["trace_seconds"]["median"] for r in rows])})
    for name in STRUCTURES:
        records.append(suite.cost_model(name, traces[name]))
    with mock.patch.object(suite, "git_commit", return_value=None):
        machine = suite.machine_record(jax.local_devices(), None)
    results = jsonable({
        "schema": "jrt-bench/1", "machine": machine,
        "parameters": {
            "quick": True, "mesh": "tiny", "triangles": len(f), "structures": STRUCTURES,
            "kernel": "watertight", "device": None, "camera": {"width": 16, "height": 16},
            "camera_rays": RAYS, "rays": RAYS,
            "sets": [{"name": s, "query": q, "rays": RAYS, "distinct_rays": RAYS}
                     for s, q in SETS.items()],
            "builds": 2, "repeats": 2, "brute_rays": RAYS, "trimesh_rays": 0,
            "scaling_meshes": 2, "scaling_builds": 1, "scaling_repeats": 2,
            "embree_threads": 2, "seed": 0},
        "records": records, "notes": [], "wall_seconds": 1.0})
    validate(results)
    path = tmp_path_factory.mktemp("results") / "bench.json"
    path.write_text(json.dumps(results, indent=1))
    return path, results


@pytest.fixture(scope="module")
def stability_results(tmp_path_factory):
    stability = pytest.importorskip("benchmarks.stability")
    result = stability.run(cases=(6,), quick=True, kernels=["watertight", "moller_trumbore"],
                           structures=["brute", "bvh"])
    optics = stability._json_safe(stability.optics_checks())
    result["cases"]["7"] = {"records": optics, "findings": stability._findings7(optics),
                            "parameters": {}, "seconds": 1.0,
                            "title": stability.CASE_TITLES[7]}
    path = tmp_path_factory.mktemp("results") / "stability.json"
    path.write_text(json.dumps(result, indent=1))
    return path, result


@pytest.fixture(scope="module")
def wp_results(tmp_path_factory):
    records = [{"kind": "work_precision", "study": "Whitted depth", "series": "exact tree",
                "method": f"depth {d}", "seconds": 0.5 * d, "psnr": 20.0 + 4 * d,
                "ssim": 0.7 + 0.05 * d, "delta_e": 4.0 / d} for d in (1, 2, 4)]
    records.append({"kind": "work_precision", "study": "Fresnel", "method": "schlick",
                    "seconds": {"median": 1.9}, "psnr": 35.0, "ssim": 0.97, "deltaE": 0.5,
                    "command": "jrt study --only fresnel"})
    path = tmp_path_factory.mktemp("results") / "wp.json"
    path.write_text(json.dumps({"records": records}))
    return path, records


@pytest.fixture(scope="module")
def render_png(tmp_path_factory):
    path = tmp_path_factory.mktemp("renders") / "camel.png"
    image = np.zeros((12, 16, 3), np.uint8)
    image[..., 0] = np.arange(16, dtype=np.uint8) * 15
    io.imsave(path, image, check_contrast=False)
    return path


@pytest.fixture(scope="module")
def full_report(tmp_path_factory, bench_results, stability_results, wp_results, render_png):
    out = tmp_path_factory.mktemp("report") / "camel"
    result = generate([bench_results[0], stability_results[0], wp_results[0]], out,
                      images=[f"{render_png}:The camel, `jrt render`"])
    print(f"report: {len(result['figures'])} figures in {result['seconds']:.1f} s")
    return out, result


# --- Reading the report back ----------------------------------------------------------------


def md_tables(text: str) -> list[tuple[str, list[str], list[list[str]]]]:
    """(nearest heading above, header, rows) of every Markdown table."""
    tables, heading, lines, i = [], "", text.splitlines(), 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("#"):
            heading = line.lstrip("#").strip()
        if line.startswith("|") and i + 1 < len(lines) and lines[i + 1].startswith("| ---"):
            header, rows, i = _cells(line), [], i + 2
            while i < len(lines) and lines[i].startswith("|"):
                rows.append(_cells(lines[i]))
                i += 1
            tables.append((heading, header, rows))
            continue
        i += 1
    return tables


def _cells(line: str) -> list[str]:
    return [c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", line.strip()[1:-1])]


def table(text: str, heading_start: str, column: str) -> list[dict]:
    """The rows (column -> cell) of the first table under a heading that starts with
    ``heading_start`` and has the column ``column``."""
    for heading, header, rows in md_tables(text):
        if heading.startswith(heading_start) and column in header:
            return [dict(zip(header, r, strict=True)) for r in rows]
    raise AssertionError(f"no table under {heading_start!r} with a column {column!r}")


def close(cell: str, value: float) -> bool:
    """A cell printed with 3 significant digits equals the JSON's value."""
    return float(cell.split()[0].replace(",", "")) == pytest.approx(value, rel=5e-3, abs=1e-12)


def readme(full_report) -> str:
    return (full_report[0] / "README.md").read_text()


# --- Files ----------------------------------------------------------------------------------


def test_report_files_and_figures(full_report):
    out, result = full_report
    text = readme(full_report)
    assert (out / "index.html").is_file()
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text)
    # Rates, build, memory, heat maps, scaling, cost model, two work-precision diagrams,
    # one render.
    assert len(links) == 9 == len(result["figures"])
    for link in links:
        assert not link.startswith(("/", "http")), link
        image = io.imread(out / link)
        assert image.ndim == 3 and image.shape[0] > 10 and image.shape[1] > 10, link
        assert (out / link).read_bytes()[:8] == report.PNG_SIGNATURE
    assert "renders/camel.png" in links
    for section in ("## Reading", "## The structures side by side", "### Per-pixel cost",
                    "### Scaling",
                    "### Cost model", "## Error against run time", "## Numerical stability",
                    "## Renders", "## Machine and versions"):
        assert section in text, section
    # The machine's row of the builders' threads, as accel.threads counts them here.
    from accel.threads import build_threads
    assert f"| build threads | {build_threads()} |" in text


def test_every_figure_names_its_command(full_report, bench_results):
    text = readme(full_report)
    captions = [c for c in re.findall(r"^\*(.+)\*$", text, flags=re.M)
                if "Data:" in c or "jrt render" in c]
    figures = [c for c in captions if "Data:" in c]
    assert len(figures) == 8
    bench_command = report.bench_command(bench_results[1], bench_results[0])
    assert bench_command.startswith("python -m benchmarks --quick --mesh tiny ")
    assert bench_command.endswith(f"-o {bench_results[0]}")
    assert sum(bench_command in c for c in figures) == 6
    assert any("jrt study --only fresnel" in c for c in figures)
    assert "python -m benchmarks.stability --quick --cases 6,7 -o" in text


def test_html_is_self_contained(full_report):
    out, result = full_report
    page = (out / "index.html").read_text()
    sources = re.findall(r"""\bsrc\s*=\s*["']([^"']*)["']""", page)
    assert len(sources) == len(result["figures"])
    assert all(s.startswith("data:image/png;base64,") for s in sources)
    hrefs = re.findall(r"""\bhref\s*=\s*["']([^"']*)["']""", page)
    assert all(h.startswith(("#", "http://", "https://")) for h in hrefs), hrefs
    assert "<link" not in page and "url(" not in page
    assert "figures/" not in re.sub(r"<figcaption>.*?</figcaption>", "", page)


# --- Numbers --------------------------------------------------------------------------------


def test_structure_tables_equal_the_json(full_report, bench_results):
    text = readme(full_report)
    results = bench_results[1]
    rows = {r["structure"]: r for r in table(text, "The structures side by side", "SAH cost")}
    builds = {r["structure"]: r for r in results["records"] if r["kind"] == "build"}
    traces = {(r["structure"], r["set"]): r for r in results["records"] if r["kind"] == "trace"}
    assert list(rows) == ["Embree", *STRUCTURES]
    for name in STRUCTURES:
        row, build = rows[name], builds[name]
        assert close(row["build (s)"], build["seconds"]["median"])
        assert close(row["memory (MiB)"], build["bytes"] / 2**20)
        assert close(row["SAH cost"], build["sah_cost"])
        for set_name in SETS:
            cell, t = row[f"{set_name} Mrays/s (x Embree)"], traces[name, set_name]
            rate, ratio = re.fullmatch(r"(\S+) \((\S+)\)", cell).groups()
            assert close(rate, t["mrays_per_s"]["median"])
            assert close(ratio, t["ratio_to_embree"])
    counters = {r["structure"]: r["camera: steps / tests / leaves"] for r in table(
        text, "The structures side by side", "camera: steps / tests / leaves")}
    for name in STRUCTURES:
        steps, tests, _ = counters[name].split(" / ")
        c = traces[name, "camera"]["counters"]
        assert close(steps, c["steps"]["mean"]) and close(tests, c["tests"]["mean"])


def test_scaling_and_cost_model_tables(full_report, bench_results):
    text = readme(full_report)
    records = bench_results[1]["records"]
    exps = {r["structure"]: r for r in table(text, "Scaling", "build time ~ N^")}
    costs = {r["structure"]: r for r in table(text, "Cost model", "C_TS (ns)")}
    for rec in records:
        if rec["kind"] == "scaling":  # two sizes: the run's exponents are not shown
            assert len(rec["rows"]) == 2 and rec["build_exponent"] is None
            assert exps[rec["structure"]]["build time ~ N^"] == "not fitted (2 sizes; 3 needed)"
            assert exps[rec["structure"]]["trace time ~ N^"] == "not fitted (2 sizes; 3 needed)"
        if rec["kind"] == "cost_model":
            row = costs[rec["structure"]]
            for column, key in (("C_TS (ns)", "c_ts_ns"), ("C_IT (ns)", "c_it_ns"),
                                ("C_0 (ns)", "c_ray_ns")):
                assert row[column] == "0" if rec[key] == 0 else close(row[column], rec[key])


def test_stability_tables_equal_the_json(full_report, stability_results):
    text = readme(full_report)
    data = stability_results[1]
    case6 = data["cases"]["6"]["records"]
    overview = {(r["kernel"], r["structure"]): r
                for r in table(text, "Numerical stability", "case 6: cracks / false / NaN")}
    assert set(overview) == {(r["kernel"], r["structure"]) for r in case6}
    for rec in case6:
        cracks, false, nan = overview[rec["kernel"], rec["structure"]][
            "case 6: cracks / false / NaN"].split(" / ")
        assert (int(cracks), int(false), int(nan)) == (rec["cracks"], rec["false_hits"],
                                                       rec["nan"])
    rows = table(text, "Case 6", "cracks")
    assert len(rows) == len(case6)
    for row, rec in zip(rows, case6, strict=True):
        assert (row["kernel"], row["structure"]) == (rec["kernel"], rec["structure"])
        assert int(row["cracks"]) == rec["cracks"] and int(row["NaN"]) == rec["nan"]
        assert close(row["max error (ulps)"], rec["max_error_ulps"])
    assert data["cases"]["6"]["findings"] in text
    assert data["cases"]["7"]["findings"] in text
    brewster = [r for r in data["cases"]["7"]["records"] if r.get("check") == "Brewster"]
    rows = table(text, "Case 7", "Rs")
    assert len(rows) == len(brewster)
    for row, rec in zip(rows, brewster, strict=True):
        assert row["pair"] == rec["pair"] and close(row["Rs"], rec["Rs"])


def test_work_precision_section(full_report, wp_results):
    text = readme(full_report)
    rows = table(text, "Whitted depth", "PSNR (dB)")
    assert [r["method"] for r in rows] == ["depth 1", "depth 2", "depth 4"]
    for row, rec in zip(rows, wp_results[1][:3], strict=True):
        assert close(row["run time (s)"], rec["seconds"]) and close(row["PSNR (dB)"], rec["psnr"])
        assert close(row["ΔE (CIEDE2000)"], rec["delta_e"])
    fresnel = table(text, "Fresnel", "PSNR (dB)")[0]
    assert close(fresnel["run time (s)"], 1.9) and close(fresnel["ΔE (CIEDE2000)"], 0.5)


def test_reading_follows_the_numbers(full_report, bench_results):
    text = readme(full_report)
    reading = text.split("## Reading", 1)[1].split("\n## ", 1)[0]
    # Synthetic times: the BVH is the fastest on every set, the kd-tree the slowest.
    assert "camera: **bvh**" in reading and "incoherent: **bvh**" in reading
    assert "This mesh (`tiny`) does not agree" in reading and "the kd-tree ranks 3 of 3" in reading
    assert f"the kd-tree takes {num(np.mean([STEPS['kdtree'] * SET_SCALE[s] for s in SETS]))}"\
        " traversal steps" in reading
    assert "`moller_trumbore`" in reading and "`watertight`" in reading
    assert "NaN in any output, all cases: 0." in reading
    machine = bench_results[1]["machine"]
    assert machine["cpu"] in text and f"| jax | {machine['versions']['jax']} |" in text


# --- Missing parts --------------------------------------------------------------------------


def test_bench_only_and_stability_only(tmp_path, bench_results, stability_results):
    generate([bench_results[0]], tmp_path / "bench")
    text = (tmp_path / "bench" / "README.md").read_text()
    assert "## The structures side by side" in text and "## Numerical stability" not in text
    section = text.split("## Error against run time", 1)[1].split("\n## ", 1)[0]
    assert "No work–precision records" in section
    assert f"`{report.WORK_PRECISION_COMMAND}`" in section
    assert "`python -m benchmarks.stability` produces them" in text

    generate([stability_results[0]], tmp_path / "stab")
    text = (tmp_path / "stab" / "README.md").read_text()
    assert "## Numerical stability" in text and "## The structures side by side" not in text
    assert not (tmp_path / "stab" / "figures").exists() or not list(
        (tmp_path / "stab" / "figures").glob("*.png"))
    page = (tmp_path / "stab" / "index.html").read_text()
    assert "<table>" in page and "src=" not in page


def test_stale_figures_are_removed(tmp_path, bench_results, stability_results):
    out = tmp_path / "r"
    generate([bench_results[0]], out)
    assert (out / "figures" / "rates.png").is_file()
    generate([stability_results[0]], out)
    assert not (out / "figures" / "rates.png").exists()


# --- Errors ---------------------------------------------------------------------------------


def test_errors_name_the_file(tmp_path, bench_results):
    bad = tmp_path / "bad.json"
    bad.write_text('{"records": [1, 2,')
    with pytest.raises(ReportError, match=r"bad\.json: not valid JSON .*line 1.*expected a "
                                          r"benchmark suite result"):
        generate([bad], tmp_path / "out")
    other = tmp_path / "other.json"
    other.write_text('{"mesh": "camel", "results": []}')
    with pytest.raises(ReportError, match=r"other\.json: not a jrt results file: found a JSON "
                                          r"object with top-level keys mesh, results; expected"):
        generate([other], tmp_path / "out")
    empty = tmp_path / "empty.json"
    empty.write_text("  \n")
    with pytest.raises(ReportError, match=r"empty\.json: is empty"):
        generate([empty], tmp_path / "out")
    with pytest.raises(ReportError, match=r"missing\.json: no such file"):
        generate([tmp_path / "missing.json"], tmp_path / "out")
    wp = tmp_path / "wp.json"
    wp.write_text(json.dumps([{"kind": "work_precision", "method": "x", "psnr": 3}]))
    with pytest.raises(ReportError, match=r"wp\.json: a work_precision record needs"):
        generate([wp], tmp_path / "out")
    with pytest.raises(ReportError, match=r"--image .*nope\.png: no such image file"):
        generate([bench_results[0]], tmp_path / "out", images=[str(tmp_path / "nope.png")])
    stab = tmp_path / "stab.json"
    stab.write_text(json.dumps({"cases": {"1": {"records": 3, "findings": "x"}}}))
    with pytest.raises(ReportError, match=r"stab\.json: stability case 1 is not an object "
                                          r"with a \"records\" list"):
        generate([stab], tmp_path / "out")


def test_main_exits_with_the_error(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text("not json")
    with pytest.raises(SystemExit) as exc:
        report.main([str(bad), "-o", str(tmp_path / "out")])
    assert exc.value.code == 2
    assert "bad.json: not valid JSON" in capsys.readouterr().err
    assert report.build_parser().parse_args(["a.json", "-o", "d"]).output == "d"


def test_command_line(tmp_path, bench_results):
    out = tmp_path / "cli"
    run = subprocess.run([sys.executable, "-m", "reports.report", str(bench_results[0]), "-o",
                          str(out), "--title", "tiny"], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert (out / "README.md").read_text().startswith("# tiny\n")
    assert "figures in" in run.stdout


def test_numbers_are_formatted_to_three_digits():
    assert [num(x) for x in (0.000123456, 0.0123456, 1.23456, 123.456, 12345.6, 1.5e7, 0,
                             7, None, True, "nan")] == [
        "1.23e-04", "0.0123", "1.23", "123", "12346", "1.50e+07", "0", "7", "–", "yes", "nan"]


def test_jrt_report_is_the_generator(tmp_path, capsys):
    """``jrt report`` hands its options to reports.report: a missing file is exit 2."""
    from jrt.cli import main

    with pytest.raises(SystemExit) as done:
        main(["report", str(tmp_path / "absent.json"), "-o", str(tmp_path / "out")])
    assert done.value.code == 2
    assert "absent.json" in capsys.readouterr().err


def test_heatmaps_show_each_structure(full_report, bench_results):
    """One column per structure, its caption under the mean of the recorded cells."""
    out, _ = full_report
    text = readme(full_report)
    assert "figures/heatmaps.png" in text
    image = io.imread(out / "figures" / "heatmaps.png")
    assert image.shape[1] > image.shape[0] > 200
    maps = [r for r in bench_results[1]["records"] if r["kind"] == "heatmap"]
    assert sorted(r["structure"] for r in maps) == sorted(STRUCTURES)
    section = text.split("### Per-pixel cost")[1].split("###")[0]
    for r in maps:
        cells = np.asarray(r["steps"], np.float64)
        row = next(line for line in section.splitlines() if line.startswith(f"| {r['structure']} "))
        assert row.split(" | ")[1:3] == [num(cells.mean()), num(cells.max())], row


def test_image_with_a_long_caption(render_png):
    """A caption longer than a file name may be (a render's statistics) is still parsed."""
    caption = "`jrt render --scene glass-camel`: " + "rays per level [1, 2, 3] " * 20
    assert report.parse_image(f"{render_png}:{caption}") == (render_png, caption.strip())


def test_turntable_table(full_report, bench_results):
    text = readme(full_report)
    (rec,) = [r for r in bench_results[1]["records"] if r["kind"] == "turntable"]
    row = next(line for line in text.split("### Batched renders")[1].splitlines()
               if line.startswith("| 8 |"))
    assert row.split(" | ")[4:8] == [num(rec["batched_images_per_s"]),
                                     num(rec["loop_images_per_s"]),
                                     num(rec["loop_same_capacities_images_per_s"]),
                                     num(rec["ratio"])]


# --- Quick runs: indicative marks, fits through 3 or more sizes, ranks within the spread ----

SYN_SETS = {"camera": "closest", "shadow": "occluded"}


def synthetic_bench(times: dict, builds: dict, sizes=(), quick: bool | None = True,
                    rays: int = 4096, steps=None) -> dict:
    """A benchmark result of plain dicts: ``times`` {structure: [seconds per warm call]}
    (the same calls for every set, the shadow set twice as slow), ``builds`` {structure:
    [seconds per build]}, scaling rows at ``sizes`` (triangles) with build times
    1e-7 N^1.3 and trace times 0.01 N^0.2 times a fixed jitter."""
    names = list(times)
    calls = len(next(iter(times.values())))
    params = {"mesh": "synthetic", "triangles": 1000, "structures": names,
              "kernel": "watertight", "camera_rays": rays, "rays": rays,
              "sets": [{"name": s, "query": q, "rays": rays, "distinct_rays": rays}
                       for s, q in SYN_SETS.items()],
              "builds": len(next(iter(builds.values()))), "repeats": calls}
    if quick is not None:
        params["quick"] = quick
    records = []
    for name in names:
        b = builds[name]
        records.append({"kind": "build", "structure": name, "mesh": "synthetic",
                        "triangles": 1000, "repeats": b,
                        "seconds": {"median": float(np.median(b)), "min": min(b),
                                    "max": max(b), "spread": max(b) - min(b)},
                        "bytes": 2**20})
        for k, (set_name, query) in enumerate(SYN_SETS.items()):
            t = [x * (k + 1) for x in times[name]]
            rate = {"median": rays / float(np.median(t)) / 1e6, "min": rays / max(t) / 1e6,
                    "max": rays / min(t) / 1e6}
            counters = {c: {"mean": v, "p95": v, "max": int(v) + 1}
                        for c, v in (steps or {}).get(name, {}).items()}
            records.append({"kind": "trace", "structure": name, "set": set_name,
                            "query": query, "rays": rays, "repeats": t,
                            "seconds": {"median": float(np.median(t)), "min": min(t),
                                        "max": max(t), "spread": max(t) - min(t)},
                            "mrays_per_s": rate, **({"counters": counters} if counters
                                                    else {})})
    jitter = [1.0, 1.1, 0.93, 1.05]
    for i, name in enumerate(names):
        rows = []
        for n, j in zip(sizes, jitter, strict=False):
            build = 1e-7 * n**1.3 * j * (1 + 0.1 * i)
            trace = 0.01 * n**0.2 / j
            rows.append({"mesh": f"m{n}", "triangles": n, "build_repeats": [build],
                         "build_seconds": {"median": build, "min": build, "max": build},
                         "trace_repeats": [trace],
                         "trace_seconds": {"median": trace, "min": trace, "max": trace},
                         "mrays_per_s": {"median": rays / trace / 1e6}})
        if rows:  # the exponents a run records from any two sizes: not what the report shows
            records.append({"kind": "scaling", "structure": name, "set": "camera",
                            "rays": rays, "rows": rows, "build_exponent": 9.99,
                            "trace_exponent": 9.99})
    return {"schema": "jrt-bench/1", "parameters": params, "records": records}


def _write(tmp_path, name, data) -> Path:
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps(data))
    return path


def _reading(text: str) -> str:
    return text.split("## Reading", 1)[1].split("\n## ", 1)[0]


#: Warm calls that overlap between every pair (min..max 10-14, 11-15, 12-16 ms).
OVERLAPPING = {"bvh": [0.010, 0.014], "kdtree": [0.011, 0.015], "grid": [0.012, 0.016]}
#: Warm calls whose min..max are apart: bvh fastest, then grid, then the kd-tree.
SEPARATED = {"bvh": [0.010, 0.011], "kdtree": [0.020, 0.022], "grid": [0.014, 0.015]}
STEPS_SYN = {"bvh": {"steps": 6.0, "tests": 1.0}, "kdtree": {"steps": 9.0, "tests": 0.5},
             "grid": {"steps": 4.0, "tests": 3.0}}


def test_quick_run_two_sizes_overlapping_repeats(tmp_path):
    """A quick run says it is indicative at the top and under every figure, fits no
    exponent through two sizes, and ranks nothing its repeats do not separate."""
    data = synthetic_bench(OVERLAPPING, {n: [0.10, 0.13] for n in OVERLAPPING},
                           sizes=(1000, 4000), steps=STEPS_SYN)
    generate([_write(tmp_path, "quick", data)], tmp_path / "r")
    text = (tmp_path / "r" / "README.md").read_text()
    top = text.split("## Reading", 1)[0]
    assert "Quick run: small ray sets, indicative only." in top
    assert "4,096 rays a set" in top and "`jrt study`" in top
    captions = [c for c in re.findall(r"^\*(.+)\*$", text, flags=re.M) if "Data:" in c]
    assert len(captions) == 4  # rates, build, memory, scaling
    assert all("Indicative only: quick run" in c for c in captions), captions
    assert "**Indicative only**: quick run" in text.split("## The structures side by side")[1]
    reading = _reading(text)
    assert "Scaling over 1,000–4,000 triangles (2 sizes): exponents not fitted (2 sizes; 3 "\
           "needed)." in reading
    assert not re.search(r"N\^-?\d", text), re.findall(r".{40}N\^-?\d.{10}", text)
    exps = {r["structure"]: r for r in table(text, "Scaling", "build time ~ N^")}
    assert {r["build time ~ N^"] for r in exps.values()} == {"not fitted (2 sizes; 3 needed)"}
    # Overlapping warm calls: no fastest, no slowest, no verdict on Havran.
    assert "camera: all 3 tied within the run's spread" in reading
    assert "shadow: all 3 tied within the run's spread" in reading
    assert "**" not in reading.split("**Against the literature.**")[0].replace(
        "**Numerical", "")
    assert "Build: all 3 tied within the run's spread" in reading
    assert "(1st–3rd, tied with kdtree and grid)" in reading
    assert "This run neither confirms nor contradicts it on this mesh (`synthetic`)" in reading
    assert "agrees:" not in reading and "does not agree" not in reading
    assert "decide" not in reading and "The measured reason" not in reading


def test_full_run_three_sizes_separated_repeats(tmp_path):
    """A full run is not marked, fits its exponents through three sizes (numpy.polyfit of
    the log-log points, independently) and ranks what its repeats separate."""
    data = synthetic_bench(SEPARATED, {"bvh": [0.10, 0.11], "kdtree": [0.30, 0.32],
                                       "grid": [0.05, 0.06]},
                           sizes=(1000, 4000, 16000), quick=False, rays=2**18, steps=STEPS_SYN)
    generate([_write(tmp_path, "full", data)], tmp_path / "r")
    text = (tmp_path / "r" / "README.md").read_text()
    assert "ndicative" not in text
    reading = _reading(text)
    exps = {r["structure"]: r for r in table(text, "Scaling", "build time ~ N^")}
    for rec in (r for r in data["records"] if r["kind"] == "scaling"):
        n = np.log([row["triangles"] for row in rec["rows"]])
        k_build = np.polyfit(n, np.log([row["build_seconds"]["median"]
                                        for row in rec["rows"]]), 1)[0]
        k_trace = np.polyfit(n, np.log([row["trace_seconds"]["median"]
                                        for row in rec["rows"]]), 1)[0]
        assert abs(k_build - 1.3) > 0.005  # the jitter moves the fit off the generating law
        row = exps[rec["structure"]]
        assert close(row["build time ~ N^"], k_build) and close(row["trace time ~ N^"], k_trace)
        assert f"{rec['structure']} N^{k_build:.2f}" in reading
        assert f"{rec['structure']} N^{k_trace:.2f}" in reading
    assert "9.99" not in text
    assert "fitted exponents in the legend" in text
    assert "camera: **bvh**" in reading and "slowest kdtree" in reading
    geo = {n: np.exp(np.mean(np.log([2**18 / np.median(t) / k / 1e6 for k in (1, 2)])))
           for n, t in SEPARATED.items()}
    assert (f"bvh {num(geo['bvh'])} (1st), grid {num(geo['grid'])} (2nd), kdtree "
            f"{num(geo['kdtree'])} (3rd)") in reading
    assert (f"Build: fastest grid ({num(np.median([0.05, 0.06]))} s), slowest kdtree "
            f"({num(np.median([0.30, 0.32]))} s)") in reading
    assert "does not agree on this machine: the kd-tree ranks 3 of 3 (" in reading
    assert "neither confirms" not in reading and "tied" not in reading


def _bench(data) -> report.Bench:
    return report.Bench(Path("synthetic.json"), data)


def test_havran_verdict_follows_the_spread():
    """The kd-tree apart above the others: agrees; apart below one: does not agree, its
    place spanning the structures it ties with; overlapping the leader: cannot tell."""
    builds = {n: [0.1, 0.2] for n in ("bvh", "kdtree", "grid")}
    cases = {
        "agrees: the kd-tree is the fastest here": {
            "kdtree": [0.010, 0.011], "bvh": [0.014, 0.015], "grid": [0.020, 0.022]},
        "does not agree on this machine: the kd-tree ranks 2–3 of 3, tied within the run's "
        "spread with grid": {
            "bvh": [0.010, 0.011], "kdtree": [0.014, 0.016], "grid": [0.015, 0.017]},
        "neither confirms nor contradicts": {
            "bvh": [0.010, 0.013], "kdtree": [0.012, 0.014], "grid": [0.020, 0.022]},
    }
    for expected, times in cases.items():
        _, text = report.reading_bench(_bench(synthetic_bench(times, builds,
                                                              steps=STEPS_SYN)))
        assert expected in text, text
    # One warm call each: no spread, so nothing is ranked.
    one = {n: [t[0]] for n, t in SEPARATED.items()}
    items, text = report.reading_bench(_bench(synthetic_bench(one, {n: [0.1] for n in one})))
    assert "one warm call each: no spread" in items[0] and "**" not in items[0]
    assert "neither confirms nor contradicts" in text


def test_unrecorded_quick_flag_is_derived():
    """A run that does not record ``quick``: small ray sets or fewer than three warm calls
    make it indicative, large sets with enough calls do not."""
    builds = {n: [0.1, 0.2, 0.3] for n in SEPARATED}
    three = {n: [*t, t[0]] for n, t in SEPARATED.items()}
    small = _bench(synthetic_bench(three, builds, quick=None, rays=4096))
    assert report.bench_indicative(small).startswith("small run (small ray sets, 4,096 rays")
    large = _bench(synthetic_bench(three, builds, quick=None, rays=2**18))
    assert report.bench_indicative(large) == ""
    few = _bench(synthetic_bench(SEPARATED, builds, quick=None, rays=2**18))
    assert "2 warm calls per set" in report.bench_indicative(few)


def test_places_are_the_extremes_of_every_choice_in_the_intervals():
    """places(): the best and worst rank of each name over every choice of one value per
    interval (endpoints suffice), by sorting the chosen values."""
    import itertools

    rng = np.random.default_rng(5)
    for _ in range(20):
        lo = rng.uniform(0, 10, 5)
        values = {f"s{i}": (float(lo[i]), (float(lo[i]), float(lo[i] + rng.uniform(0, 3))))
                  for i in range(5)}
        seen = {n: set() for n in values}
        for pick in itertools.product((0, 1), repeat=5):
            chosen = {n: v[1][k] for (n, v), k in zip(values.items(), pick, strict=True)}
            for rank, n in enumerate(sorted(chosen, key=chosen.get, reverse=True), 1):
                seen[n].add(rank)
        assert report.places(values) == {n: (min(r), max(r)) for n, r in seen.items()}


def test_structure_order_follows_the_registry():
    """The report lists structures in the registry's order with brute force last; a kind
    registered later joins before brute force, and a run over every engine structure needs
    no ``--structures`` in its rebuilt command."""
    import dataclasses

    from reports.inputs import structure_order

    builtin = ("bvh", "kdtree", "octree", "bsp", "grid")
    assert structure_order() == (*builtin, "brute")
    accel.register(dataclasses.replace(accel.kind("bvh"), name="bvh_copy"))
    try:
        assert structure_order() == (*builtin, "bvh_copy", "brute")
        records = [{"kind": "build", "structure": n} for n in ("brute", "grid", "bvh_copy",
                                                               "bvh")]
        assert _bench({"records": records}).structures == ["bvh", "grid", "bvh_copy", "brute"]
        every = {"parameters": {"mesh": "tiny", "structures": [*builtin, "bvh_copy"]}}
        assert "--structures" not in report.bench_command(every, Path("b.json"))
        some = {"parameters": {"mesh": "tiny", "structures": list(builtin)}}
        assert ("--structures bvh,kdtree,octree,bsp,grid -o b.json"
                in report.bench_command(some, Path("b.json")))
    finally:
        accel.unregister("bvh_copy")
    assert structure_order() == (*builtin, "brute")


# --- Worked inverse problems --------------------------------------------------------------


def _inverse_record(quick: bool) -> dict:
    """A record as ``python -m benchmarks.inverse --json`` writes it: the losses fall by
    1e4 over 10 steps and the parameters move from the start to near the truth."""
    steps = 10
    fraction = np.linspace(1.0, 0.001, steps + 1)[:, None]

    def problem(name, parameters, truth, start, **errors):
        truth, start = np.asarray(truth), np.asarray(start)
        values = truth + fraction * (start - truth)
        return {"problem": name, "parameters": parameters, "truth": truth.tolist(),
                "start": start.tolist(), "found": values[-1].tolist(),
                "losses": np.geomspace(1.0, 1e-4, steps + 1).tolist(),
                "values": values.tolist(), "seconds": 12.5, **errors}

    return {"kind": "inverse", "command": "python -m benchmarks.inverse --json inverse.json",
            "date": "2026-12-06", "width": 48, "height": 36, "steps": steps, "rate": 0.02,
            "quick": quick, "problems": [
                problem("glass", ["A", "B"], [1.50459, 0.004202], [1.44826, 0.003506],
                        relative_error=[3.7e-5, 1.7e-4]),
                problem("depth", ["tx", "ty", "tz", "scale"], [0, 0, 0, 1],
                        [0.01, -0.01, 0.01, 1.05], translation_error_over_diagonal=2.1e-3,
                        scale_error=2.3e-3)]}


@pytest.mark.parametrize("quick", [False, True])
def test_inverse_section(tmp_path, quick):
    """The table holds each problem's start, truth and found values and its error as the
    JSON has them, the figure is drawn with its command, and a quick run is marked."""
    record = _inverse_record(quick)
    path = tmp_path / "inverse.json"
    path.write_text(json.dumps(record))
    out = tmp_path / "report"
    result = generate([path], out)
    text = (out / "README.md").read_text()
    rows = table(text, "Gradients: worked inverse problems", "found")
    assert [r["problem"] for r in rows] == ["glass", "depth"]
    for row, problem in zip(rows, record["problems"], strict=True):
        found = [float(x) for x in row["found"].split(", ")]
        assert found == pytest.approx(problem["found"], rel=1e-5, abs=1e-9)
        assert row["steps"] == "10"
    assert rows[0]["error"] == "A 0.0037 %, B 0.017 %"
    assert rows[1]["error"] == "translation 0.21 % of the diagonal, scale 0.23 %"
    figure = out / "figures" / "inverse.png"
    assert figure in result["figures"] and figure.read_bytes()[:8] == PNG_SIGNATURE
    assert "worked inverse problems" in text.split("\n\n")[1]  # named among the inputs
    assert ("quick run (one problem, a small image)" in text) == quick


def test_an_inverse_record_without_its_problems_is_refused(tmp_path):
    path = tmp_path / "inverse.json"
    path.write_text(json.dumps({"kind": "inverse", "problems": [{"problem": "glass"}]}))
    with pytest.raises(ReportError, match=r"inverse.json: an inverse-problem result whose "
                       r"\"problems\" is not a list of problems"):
        generate([path], tmp_path / "report")
