"""The benchmark suite's quick run (``jrt bench --quick``) against its schema.

The run is the quick study's bench step (``conftest.quick_study``: ``jrt study --quick``,
once per test session, whose first step is ``python -m benchmarks --quick`` with two
structures on the 19k camel, Embree, trimesh, the scaling to the 69k camel and the
turntable). Its JSON is checked against ``benchmarks.schema`` (and by ``jsonschema`` where
installed), then for facts the schema does not state: every structure and set present,
ratios to Embree equal to the recorded rates' quotient, zero mismatches against brute
force, repetition lists of the requested lengths. A user's own mesh file (``--mesh PATH``)
is checked on its own: how it loads and the scaling ladder of its subdivisions.
"""

from __future__ import annotations

import copy
import json

import jax
import numpy as np
import pytest
import trimesh

from benchmarks import peers, suite
from benchmarks.schema import SCHEMA, validate

SETS = ["camera", "shadow", "reflected", "refracted", "incoherent"]


@pytest.fixture(scope="module")
def results(quick_study):
    return json.loads((quick_study[0] / "bench.json").read_text())


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
    # Fewer timed calls only where they reached the trace budget.
    broken = copy.deepcopy(results)
    assert broken["parameters"]["trace_budget_seconds"] == suite.TRACE_BUDGET_SECONDS
    broken["records"][i]["repeats"] = [suite.TRACE_BUDGET_SECONDS / 2]
    with pytest.raises(ValueError, match=rf"^\$\.records\[{i}\]\.repeats: expected 2 repeats"):
        validate(broken)
    broken["records"][i]["repeats"] = [suite.TRACE_BUDGET_SECONDS]
    validate(broken)


def test_time_calls_stops_at_its_budget(monkeypatch):
    """Each call takes 4 s of a stand-in clock: a budget of 10 s allows three calls (4, 8,
    12 s), none allows all five, and a call longer than the budget is still timed once."""
    from benchmarks import common

    clock = iter(range(0, 4000, 4))  # each reading 4 s after the one before
    monkeypatch.setattr(common.time, "perf_counter", lambda: next(clock))
    assert common.time_calls(lambda: None, 5, budget=10.0) == [4, 4, 4]
    assert common.time_calls(lambda: None, 5) == [4] * 5
    assert common.time_calls(lambda: None, 5, budget=1.0) == [4]


def test_machine_and_parameters(results, quick_study_structures):
    machine, params = results["machine"], results["parameters"]
    assert machine["cores"] >= 1 and machine["cpu"]
    assert machine["versions"]["jax"] == jax.__version__
    assert machine["device"]["platform"] == jax.default_backend()
    assert machine["device"]["count"] == len(jax.local_devices())
    commit = machine["git_commit"]
    assert commit is None or (len(commit) == 40 and int(commit, 16) >= 0)
    assert params["quick"] is True and params["structures"] == quick_study_structures
    assert params["camera_rays"] == params["rays"] == 64 * 64
    assert [s["name"] for s in params["sets"]] == SETS  # jrt.optics is there


def test_every_structure_and_set_present(results, quick_study_structures):
    for kind in ("build", "scaling", "cost_model"):
        benched = sorted(r["structure"] for r in _records(results, kind))
        assert benched == sorted(quick_study_structures)
    for kind in ("trace", "correctness"):
        pairs = sorted((r["structure"], r["set"]) for r in _records(results, kind))
        assert pairs == sorted((s, t) for s in quick_study_structures for t in SETS)
    assert sorted(r["set"] for r in _records(results, "peer", peer="embree")) == sorted(SETS)
    for peer in ("trimesh", "open3d", "mitsuba"):
        assert _records(results, "peer", peer=peer), peer
    # trimesh's intersector runs where rtree is installed, and is "not installed" elsewhere.
    import importlib.util

    statuses = {r["status"] for r in _records(results, "peer", peer="trimesh")}
    assert statuses == ({"ok"} if importlib.util.find_spec("rtree") else {"not installed"})


def test_heatmaps_average_the_camera_counters(results, quick_study_structures):
    """The per-pixel maps hold the same counters as the camera trace's summary: over
    whole blocks their mean is the mean per ray, their max at most the max."""
    camera = results["parameters"]["camera"]
    for name in quick_study_structures:
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
    assert rec["frames"] == suite.DEFAULTS["quick"]["turntable_frames"]
    assert rec["batch_devices"] == len(jax.local_devices())
    best = max(rec["loop_images_per_s"], rec["loop_same_capacities_images_per_s"])
    assert rec["ratio"] == pytest.approx(rec["batched_images_per_s"] / best)
    assert rec["peak_radiance"] > 0
    # Float32 rounding of the shading compiled for another shape (tests/test_batch.py's
    # LOOP_TOLERANCE): 1.9e-6 of the peak on an AVX2 host.
    assert rec["max_abs_difference"] <= 1e-5 * rec["peak_radiance"]


def test_trimesh_interface_through_jrt_embree_and_trimesh(results):
    """trimesh's ray interface on the run's mesh and the icosphere: jrt's intersector
    answers every ray and point as trimesh's own float64 intersector does on its subset
    and as Embree's on all of them, and each speedup is the rates' quotient."""
    recs = _records(results, "trimesh_interface")
    meshes = {r["mesh"] for r in recs}
    assert meshes == {results["parameters"]["mesh"], "sphere"}
    for mesh in meshes:
        for query in ("intersects_location", "contains_points"):
            mine = _records(results, "trimesh_interface", mesh=mesh, query=query)
            by = {r["engine"]: r for r in mine}
            assert set(by) == {"jrt", "embree", "trimesh"}
            jrt_rec = by["jrt"]
            assert jrt_rec["items"] == suite.DEFAULTS["quick"]["interface_rays"]
            assert jrt_rec["agree_with_trimesh"] == jrt_rec["trimesh_items"] > 0
            assert jrt_rec["agree_with_embree"] == jrt_rec["items"]
            assert jrt_rec["found"] > 0
            for r in mine:
                assert r["jrt_speedup"] == pytest.approx(jrt_rec["per_second"]
                                                         / r["per_second"])


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
        main, other = r["rows"]  # --quick: the 19k camel and the 69k camel
        assert main["from_main_run"] and not other["from_main_run"]
        assert (main["mesh"], other["mesh"]) == ("camel-19k", "camel")
        assert other["triangles"] > 3 * main["triangles"]
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


@pytest.fixture(scope="module")
def tiny_mesh(tmp_path_factory):
    """A user's own mesh file: a sphere and a box beside it."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    box = trimesh.creation.box(extents=(0.6, 0.6, 0.6))
    box.apply_translation((1.4, 0.3, 0.2))
    path = tmp_path_factory.mktemp("bench") / "tiny.off"
    trimesh.util.concatenate([sphere, box]).export(path)
    return path


def test_a_users_mesh_loads_and_scales_by_subdivision(tiny_mesh):
    """``--mesh PATH``: the file is the benchmarked mesh (the camels are not), and its
    scaling ladder is itself then its 4x, 16x and 64x subdivisions, as many as asked."""
    args = suite.build_parser().parse_args(["--quick", "--mesh", str(tiny_mesh)])
    params = suite._resolve(args)
    assert params["mesh"] == str(tiny_mesh)
    mesh = suite._load(params["mesh"])
    loaded = trimesh.load(tiny_mesh, process=False)
    assert len(mesh.faces) == len(loaded.faces) and len(mesh.vertices) == len(loaded.vertices)
    ladder = suite.scaling_ladder(mesh, "tiny", params["scaling"])
    assert [label for label, _ in ladder] == ["tiny", "tiny x4"]
    assert ladder[0][1]() is mesh
    finer = ladder[1][1]()
    assert len(finer.faces) == 4 * len(mesh.faces)
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    assert (finer.vertices >= lo - 1e-6).all() and (finer.vertices <= hi + 1e-6).all()
    assert [label for label, _ in suite.scaling_ladder(mesh, "tiny", 4)] == [
        "tiny", "tiny x4", "tiny x16", "tiny x64"]
    assert [label for label, _ in suite.scaling_ladder(None, "camel-19k", 3)] == [
        "camel-19k", "camel", "camel x4"]
    with pytest.raises(suite.BenchError, match="nowhere.obj"):
        suite._load(str(tiny_mesh.parent / "nowhere.obj"))


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


def test_json_writer_keeps_number_arrays_on_one_line(results, quick_study_structures):
    """benchmarks.common.dumps: the same JSON as json.dumps, each heat-map row and list of
    repeats on one line."""
    from benchmarks.common import dumps

    text = dumps(results)
    assert json.loads(text) == json.loads(json.dumps(results))
    (hm,) = _records(results, "heatmap", structure=quick_study_structures[0])
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
