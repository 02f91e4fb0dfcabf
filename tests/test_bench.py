"""The benchmark suite's smoke run (``python -m benchmarks --quick``) against its schema.

The suite runs once, in this process, as ``python -m benchmarks --quick`` would, on a tiny
mesh (a sphere and a box beside it, and its 4x subdivision for the scaling) with two
structures, so that it stays within a minute: each structure compiles four queries
(closest hit and any-hit, with and without counters) whatever the mesh. Its JSON is
checked against ``benchmarks.schema`` (and by ``jsonschema`` where installed), then for
facts the schema does not state: every structure and set present, ratios to Embree equal
to the recorded rates' quotient, zero mismatches against brute force, repetition lists
of the requested lengths.
"""

from __future__ import annotations

import copy
import json
import runpy
import sys

import jax
import numpy as np
import pytest
import trimesh

from benchmarks import peers, suite
from benchmarks.schema import SCHEMA, validate

STRUCTURES = ["bvh", "kdtree"]
SETS = ["camera", "shadow", "reflected", "refracted", "incoherent"]


@pytest.fixture(scope="module")
def tiny_mesh(tmp_path_factory):
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    box = trimesh.creation.box(extents=(0.6, 0.6, 0.6))
    box.apply_translation((1.4, 0.3, 0.2))
    path = tmp_path_factory.mktemp("bench") / "tiny.off"
    trimesh.util.concatenate([sphere, box]).export(path)
    return path


@pytest.fixture(scope="module")
def results(tiny_mesh, tmp_path_factory):
    out = tmp_path_factory.mktemp("bench") / "bench.json"
    argv = ["python -m benchmarks", "--quick", "--mesh", str(tiny_mesh), "--structures",
            ",".join(STRUCTURES), "--trimesh-rays", "8", "--turntable-frames",
            "2",
            "--no-progress", "-o", str(out)]
    saved = sys.argv
    sys.argv = argv
    try:
        runpy.run_module("benchmarks", run_name="__main__", alter_sys=False)
    finally:
        sys.argv = saved
    return json.loads(out.read_text())


def _records(results, kind, **match):
    return [r for r in results["records"]
            if r["kind"] == kind and all(r.get(k) == v for k, v in match.items())]


def test_results_fit_the_schema(results):
    validate(results)
    jsonschema = pytest.importorskip("jsonschema")
    jsonschema.Draft202012Validator.check_schema(SCHEMA)
    jsonschema.Draft202012Validator(SCHEMA).validate(results)


def test_validate_names_the_first_problem(results):
    broken = copy.deepcopy(results)
    i = next(i for i, r in enumerate(broken["records"]) if r["kind"] == "trace")
    broken["records"][i]["seconds"]["median"] = -1.0
    with pytest.raises(ValueError, match=rf"^\$\.records\[{i}\]\.seconds\.median: "):
        validate(broken)
    broken = copy.deepcopy(results)
    del broken["machine"]["cpu"]
    with pytest.raises(ValueError, match=r"^\$\.machine\.cpu: required"):
        validate(broken)
    broken = copy.deepcopy(results)
    broken["records"][i]["repeats"].append(1.0)
    with pytest.raises(ValueError, match=rf"^\$\.records\[{i}\]\.repeats: expected 2 repeats"):
        validate(broken)


def test_machine_and_parameters(results):
    machine, params = results["machine"], results["parameters"]
    assert machine["cores"] >= 1 and machine["cpu"]
    assert machine["versions"]["jax"] == jax.__version__
    assert machine["device"]["platform"] == jax.default_backend()
    assert machine["device"]["count"] == len(jax.local_devices())
    commit = machine["git_commit"]
    assert commit is None or (len(commit) == 40 and int(commit, 16) >= 0)
    assert params["quick"] is True and params["structures"] == STRUCTURES
    assert params["camera_rays"] == params["rays"] == 64 * 64
    assert [s["name"] for s in params["sets"]] == SETS  # jrt.optics is there


def test_every_structure_and_set_present(results):
    for kind in ("build", "scaling", "cost_model"):
        assert sorted(r["structure"] for r in _records(results, kind)) == sorted(STRUCTURES)
    for kind in ("trace", "correctness"):
        pairs = sorted((r["structure"], r["set"]) for r in _records(results, kind))
        assert pairs == sorted((s, t) for s in STRUCTURES for t in SETS)
    assert sorted(r["set"] for r in _records(results, "peer", peer="embree")) == sorted(SETS)
    for peer in ("trimesh", "open3d", "mitsuba"):
        assert _records(results, "peer", peer=peer), peer
    # trimesh's intersector runs where rtree is installed, and is "not installed" elsewhere.
    import importlib.util

    statuses = {r["status"] for r in _records(results, "peer", peer="trimesh")}
    assert statuses == ({"ok"} if importlib.util.find_spec("rtree") else {"not installed"})


def test_heatmaps_average_the_camera_counters(results):
    """The per-pixel maps hold the same counters as the camera trace's summary: over
    whole blocks their mean is the mean per ray, their max at most the max."""
    camera = results["parameters"]["camera"]
    for name in STRUCTURES:
        (hm,) = _records(results, "heatmap", structure=name)
        (trace,) = _records(results, "trace", structure=name, set="camera")
        assert hm["width"] * hm["block"] == camera["width"]
        assert hm["height"] * hm["block"] == camera["height"]
        for key in ("steps", "tests"):
            cells = np.asarray(hm[key])
            assert cells.shape == (hm["height"], hm["width"])
            assert cells.mean() == pytest.approx(trace["counters"][key]["mean"], rel=1e-3)
            assert cells.max() <= trace["counters"][key]["max"]
            assert cells.min() >= 0 and cells.max() > 0


def test_turntable_batched_against_the_loop(results):
    """The glass camel's turntable: the batch equals the loop of single renders, and the
    ratio is the batch's rate over the faster loop's."""
    (rec,) = _records(results, "turntable")
    assert rec["frames"] == 2 and rec["batch_devices"] == len(jax.local_devices())
    best = max(rec["loop_images_per_s"], rec["loop_same_capacities_images_per_s"])
    assert rec["ratio"] == pytest.approx(rec["batched_images_per_s"] / best)
    assert rec["peak_radiance"] > 0
    # Float32 rounding of the shading compiled for another shape (tests/test_batch.py's
    # LOOP_TOLERANCE): 1.9e-6 of the peak on an AVX2 host.
    assert rec["max_abs_difference"] <= 1e-5 * rec["peak_radiance"]


def test_rates_and_ratios_agree(results):
    embree = {r["set"]: r for r in _records(results, "peer", peer="embree")}
    for r in _records(results, "trace") + _records(results, "peer", status="ok"):
        times = r["repeats"]
        assert r["seconds"]["median"] == pytest.approx(float(np.median(times)), rel=1e-12)
        assert r["mrays_per_s"]["median"] == pytest.approx(
            r["rays"] / np.median(times) / 1e6, rel=1e-12)
        assert r["mrays_per_s"]["min"] <= r["mrays_per_s"]["median"] <= r["mrays_per_s"]["max"]
        ours, theirs = r["mrays_per_s"]["median"], embree[r["set"]]["mrays_per_s"]["median"]
        assert r["ratio_to_embree"] == pytest.approx(ours / theirs, rel=1e-9), r
    for r in _records(results, "trace"):
        assert r["embree_mrays_per_s"] == embree[r["set"]]["mrays_per_s"]["median"]
        assert r["query"] == ("occluded" if r["set"] == "shadow" else "closest")
        assert 0 <= r["hits"] <= r["rays"]
        assert r["first_call_seconds"] >= r["compile_seconds"] >= 0
        for counter in r["counters"].values():
            assert 0 <= counter["mean"] <= counter["max"] and counter["p95"] <= counter["max"]
    for r in _records(results, "scaling"):
        for row in r["rows"]:
            assert row["ratio_to_embree"] == pytest.approx(
                row["mrays_per_s"]["median"] / row["embree_mrays_per_s"], rel=1e-9)


def test_no_mismatch_against_brute_force(results):
    for r in _records(results, "correctness"):
        assert r["mismatches"] == 0, r
        assert r["rays"] == results["parameters"]["brute_rays"]
        assert set(r["mismatches_by_field"]) == (
            {"occluded"} if r["query"] == "occluded" else {"t", "triangle", "u", "v"})


def test_repetition_lists_have_the_requested_length(results):
    params = results["parameters"]
    assert params["builds"] == 2 and params["repeats"] == 2  # --quick
    for r in _records(results, "build"):
        assert len(r["repeats"]) == params["builds"]
    for r in _records(results, "trace") + _records(results, "peer", peer="embree"):
        assert len(r["repeats"]) == params["repeats"]
    for r in _records(results, "scaling"):
        main, other = r["rows"]  # --quick: the mesh and its 4x subdivision
        assert main["from_main_run"] and not other["from_main_run"]
        assert other["triangles"] == 4 * main["triangles"]
        assert len(main["build_repeats"]) == params["builds"]
        assert len(main["trace_repeats"]) == params["repeats"]
        assert len(other["build_repeats"]) == params["scaling_builds"]
        assert len(other["trace_repeats"]) == params["scaling_repeats"]
        # Two sizes: no power law is fitted through them (written as null).
        assert r["build_exponent"] is None and r["trace_exponent"] is None


def test_cost_model_predicts_its_points(results):
    for r in _records(results, "cost_model"):
        assert len(r["points"]) == len(SETS)
        for point in r["points"]:
            model = r["c_ts_ns"] * point["steps_mean"] + r["c_it_ns"] * point["tests_mean"]
            model = point["rays"] * (model + r["c_ray_ns"]) * 1e-9
            assert point["predicted_seconds"] == pytest.approx(model, rel=1e-9)
        assert r["residual"] >= 0


def test_absent_device_is_named(capsys):
    present = {d.platform for d in jax.devices()}
    if "gpu" in present or "cuda" in present:
        pytest.skip("this machine has a GPU")
    with pytest.raises(SystemExit) as exc:
        suite.main(["--device", "gpu", "-o", "unused.json"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "no gpu device" in err and "cpu" in err


def test_parser_is_reusable():
    parent = suite.build_parser(add_help=False)
    parser = __import__("argparse").ArgumentParser(prog="jrt bench", parents=[parent])
    args = parser.parse_args(["--quick", "--structures", "grid,bvh"])
    assert args.quick and args.structures == ["grid", "bvh"] and args.output == "out/bench.json"


def test_jrt_bench_hands_its_options_to_the_suite(capsys):
    """``jrt bench`` is the suite's command line: its help and its option errors."""
    from jrt.cli import main

    with pytest.raises(SystemExit) as done:
        main(["bench", "--help"])
    assert done.value.code == 0
    printed = capsys.readouterr().out
    assert printed.startswith("usage: jrt bench ") and "--quick" in printed
    assert f"default {suite.DEFAULT_OUTPUT}" in printed
    with pytest.raises(SystemExit) as done:
        main(["bench", "--structures", "quadtree"])
    assert done.value.code == 2
    err = capsys.readouterr().err
    assert "jrt bench: error: " in err and "quadtree" in err and "python -m" not in err


def test_trimesh_peer_without_rtree_says_not_installed(monkeypatch):
    """trimesh's ray intersector needs rtree: without it the peer's record says so and how
    to install it (a record the schema accepts), instead of a failure."""
    import importlib.util

    from benchmarks.schema import STATUSES

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(peers.importlib.util, "find_spec",
                        lambda name, *a: None if name == "rtree" else find_spec(name, *a))
    said = []
    (row,) = peers.trimesh_rows(None, {}, {}, count=8, seed=0, log=said.append)
    assert row["peer"] == "trimesh" and row["status"] == "not installed"
    assert row["status"] in STATUSES and "pip install rtree" in row["note"]
    assert said and "pip install rtree" in said[0]


def test_json_writer_keeps_number_arrays_on_one_line(results):
    """benchmarks.common.dumps: the same JSON as json.dumps, each heat-map row and list of
    repeats on one line."""
    from benchmarks.common import dumps

    text = dumps(results)
    assert json.loads(text) == json.loads(json.dumps(results))
    (hm,) = _records(results, "heatmap", structure=STRUCTURES[0])
    assert len(text.splitlines()) < len(json.dumps(results, indent=2).splitlines()) / 4
    assert json.dumps(hm["steps"][0]) in text  # "[a, b, ...]" on one line


def test_interleaved_times_calls_each_peer_once_a_round_in_turn():
    """The benchmarks' timing rounds (benchmarks.common.interleaved_times): every label
    gets one time per round, and the calls alternate (a, b, a, b, ...), never a block of
    one peer followed by a block of the other."""
    from benchmarks.common import interleaved_times

    calls = []
    times = interleaved_times({"a": lambda: calls.append("a"),
                               "b": lambda: calls.append("b")}, 3)
    assert calls == ["a", "b"] * 3
    assert list(times) == ["a", "b"]
    assert all(len(v) == 3 and all(t >= 0 for t in v) for v in times.values())
