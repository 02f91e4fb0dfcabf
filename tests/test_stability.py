"""The numerical-stability suite (the package ``benchmarks/stability/``) at CI sizes.

Every case that should pass runs here, small: the suite's own case functions with small
parameters, and assertions on their records. What is known not to hold yet is an xfail
with its reason (nearly coplanar stacks of layers make structures disagree with brute
force through the tie window).
Sizes: the 19k-triangle camel where the case allows, the 69k camel for its slivers, a
few hundred rays per case, two or three structures per test except case 1 (all six).
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import accel
import jrt
from benchmarks import stability

KERNELS = tuple(jrt.KERNELS)
ROOT = Path(__file__).resolve().parents[1]


def _by(records, **match):
    return [r for r in records if all(r.get(k) == v for k, v in match.items())]


def test_kernels_run_in_float64_for_the_oracle():
    assert stability.float64_kernels_ok()


def test_oracle_agrees_with_jrt_brute_force_on_clean_rays():
    """The suite's float64 brute force against jrt's float32 brute force, away from edges."""
    rng = np.random.default_rng(0)
    tris = rng.uniform(-1, 1, (200, 3, 3)).astype(np.float32)
    v = tris.reshape(-1, 3)
    f = np.arange(len(v)).reshape(-1, 3)
    o = rng.uniform(-2, 2, (300, 3)).astype(np.float32)
    d = tris[rng.integers(0, 200, 300)].mean(axis=1) - o  # aimed at centroids: all hit
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    t64, _ = stability.oracle(tris, o, d)
    hits = stability.trace(accel.build("brute", v, f), o, d, "watertight")
    cmp = stability.compare(hits, t64, 1e-4, geometry=(tris, o, d))
    assert cmp["crack"].sum() == 0 and cmp["false"].sum() == 0
    assert np.isfinite(t64).sum() == 300


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_brute_hits_keeps_the_k_nearest_pairs_of_t_and_row(dtype):
    """The suite's all-hits brute force (case 1's k nearest hits, the oracle's among them)
    against NumPy's sort of every (t, row) pair. The kernel is a stand-in whose t are small
    integers, exact in any program: many rays have more hits than k, many equal t (ties
    within a chunk of triangles and across chunks) and some rays none."""
    import jax.numpy as jnp

    rng = np.random.default_rng(3)
    n_tris, n_rays, k = 150, 300, 16
    tris = np.zeros((n_tris, 3, 3), dtype)
    tris[:, 0, 0] = rng.integers(1, 12, n_tris)  # the t this triangle gives
    tris[:, 0, 1] = rng.uniform(0, 1, n_tris)  # hit by rays whose origin's y is above
    o = np.zeros((n_rays, 3), dtype)
    o[:, 1] = rng.uniform(-0.1, 1, n_rays)
    o[:, 2] = rng.integers(0, 3, n_rays)  # added to t
    d = np.tile(np.asarray([0, 0, 1], dtype), (n_rays, 1))

    def kernel(origin, direction, v0, v1, v2):  # (brute_hits pads with zero triangles)
        hit = (v0[..., 1] <= origin[..., 1]) & (v0[..., 0] > 0)
        t = jnp.where(hit, v0[..., 0] + origin[..., 2], jnp.inf)
        return t, jnp.zeros_like(t), jnp.zeros_like(t)

    t, rows = stability.brute_hits(tris, o, d, kernel, k=k, dtype=dtype, tri_chunk=32)
    t_all = np.where(tris[None, :, 0, 1] <= o[:, None, 1],
                     tris[None, :, 0, 0].astype(np.float64) + o[:, None, 2], np.inf)
    for ray in range(n_rays):
        order = np.lexsort((np.arange(n_tris), t_all[ray]))[:k]
        want_t = t_all[ray, order]
        np.testing.assert_array_equal(t[ray], want_t)
        np.testing.assert_array_equal(rows[ray], np.where(np.isfinite(want_t), order, -1))
    hits = np.isfinite(t_all).sum(axis=1)
    assert (hits > k).sum() > 100 and (hits == 0).sum() > 5
    assert (t[:, 1:] == t[:, :-1]).sum() > 1000  # ties


# --- Cases 1 to 6 at the quick size: the quick study's record ------------------------------


@pytest.fixture(scope="module")
def quick_cases(quick_study):
    """The case bodies of the quick study's ``stability.json`` (``jrt stability --size
    quick``, run once per test session by ``conftest.quick_study``), by case number."""
    import json

    doc = json.loads((quick_study[0] / "stability.json").read_text())
    assert doc["size"] == "quick"
    cases = {int(c): body for c, body in doc["cases"].items()}
    assert not [c for c, body in cases.items() if "error" in body]
    return cases


def _pairs(records):
    return {(r["kernel"], r["structure"]) for r in records}


def test_case1_watertight_has_no_cracks_under_any_structure(quick_cases):
    out = quick_cases[1]
    records = out["records"]
    assert _pairs(records) == {("watertight", s) for s in accel.names(engine=True)} | {
        (k, "brute") for k in KERNELS}
    assert out["parameters"]["rays"] > 400 and out["parameters"]["mesh"] == "camel-19k"
    for r in _by(records, kernel="watertight"):
        assert r["cracks"] == 0, r
        assert r["false_hits"] == 0, r
        assert r["parity_errors"] == 0, r
        assert r["mismatches_vs_brute"] == 0, r
    for r in records:
        assert r["nan"] == 0, r
    # The other two kernels leak through edges and vertices: the test discriminates.
    assert sum(r["cracks"] for r in records if r["kernel"] != "watertight") > 0
    assert "watertight: zero cracks" in out["findings"]


# --- Case 2 -----------------------------------------------------------------------------------

def test_case2_grazing_rays(quick_cases):
    out = quick_cases[2]
    assert _pairs(out["records"]) >= {(k, "brute") for k in KERNELS} | {("watertight", "bvh")}
    for r in out["records"]:
        assert r["nan"] == 0, r
        assert r["mismatches_vs_brute"] in (0, None), r
        for row in r["sweep"]:
            if row["mesh"] == "axis-aligned" and row["angle"] == "in-plane":
                # Exactly in the plane: no kernel may hit (the oracle has no hit either).
                assert row["false_hits"] == row["borderline_hits"] == 0, (r["kernel"], row)
    for r in _by(out["records"], kernel="watertight"):
        for row in r["sweep"]:
            if row["angle"] in ("90-1e-1", "90-1e-2", "90-1e-3"):
                assert row["cracks"] == 0 and row["false_hits"] == 0, (r["structure"], row)


# --- Case 3 -----------------------------------------------------------------------------------

def test_case3_slivers_and_degenerate_triangles(quick_cases):
    out = quick_cases[3]
    assert _pairs(out["records"]) >= {(k, "brute") for k in KERNELS} | {("watertight", "bvh")}
    assert out["parameters"]["mesh"] == "camel" and out["parameters"]["slivers"] == 273
    slivers = _by(out["records"], ray_set="slivers")
    for r in _by(slivers, kernel="watertight"):
        assert r["cracks"] == 0 and r["false_hits"] == 0, r
    # The libigl-like fixed threshold passes through the slivers: the baseline fails here.
    assert _by(slivers, kernel="libigl_like_f64")[0]["cracks_on_slivers"] > 0
    for r in out["records"]:
        assert r["nan"] == 0, r
    assert out["synthetic"]
    for row in out["synthetic"]:
        for kernel, cell in row.items():
            if not isinstance(cell, dict):
                continue
            assert cell["nan"] == 0, (row["family"], kernel)
            if row["family"].startswith("zero-area"):
                assert cell["hits"] == 0, (row["family"], kernel)
            if row["family"].startswith("tiny") and kernel != "libigl_like":
                assert cell["misses"] == 0, (row["family"], kernel)


# --- Cases 4 and 5 ----------------------------------------------------------------------------

def test_case4_offsets_prevent_self_intersection(quick_cases):
    out = quick_cases[4]
    assert _pairs(out["records"]) >= {("watertight", "bvh"), ("moller_trumbore", "brute")}
    for r in out["records"]:
        assert r["hits"] > 50
        assert r["nan"] == 0
        assert r["self_hits"]["pbrt"] == 0, r["self_hits"]
        assert r["totals"]["pbrt"]["wrong"] == 0, r["totals"]
    # Without an offset Möller–Trumbore re-hits its own triangle: the test discriminates.
    assert _by(out["records"], kernel="moller_trumbore")[0]["self_hits"]["none"] > 0


def test_case5_pbrt_offset_has_no_self_hits_across_scale_and_offset(quick_cases):
    out = quick_cases[5]
    params = out["parameters"]
    assert {1e-6, 1e6} <= set(params["scales"]) and {1.0, 1e7} <= set(params["shifts"])
    (r,) = _by(out["records"], kernel="watertight", structure="brute")
    assert r["self_hits"]["pbrt"] == 0, r["self_hits"]
    assert r["nan"] == 0
    assert len(r["sweep"]) == len(params["scales"]) + len(params["shifts"])
    # A fixed epsilon fails somewhere in the sweep (at scale 1e6 at least).
    assert r["self_hits"]["fixed"] > 0
    rand = out["random_triangles"]
    assert rand["triangles"] >= 190
    # The renderer's kernel: pbrt's offset bounds the error of the point, and watertight
    # requires t above its own error bound, so no re-hit (pbrt-v4's reintersect test).
    assert rand["table"]["pbrt"]["watertight"]["self_hits"] == 0
    assert all(cell["nan"] == 0 for cell in rand["table"]["pbrt"].values())


def test_case5_builds_anywhere_record():
    """The sweep's per-structure record: the octree moved by 1e5 builds within 2x the memory
    at the origin, with no crack on the aimed rays and brute force's hits; at 1e7 (no bits
    left for the shape) the build still succeeds and is reported apart."""
    out = stability.case5(mesh="camel-19k", rays=64, scales=(1.0,), shifts=(1e5, 1e7),
                          pairs=[("watertight", "brute"), ("watertight", "octree")],
                          random_triangles=0, methods=("none",), aimed=256)
    (octree,) = [r for r in out["records"] if r.get("check") == "builds anywhere"]
    assert octree["structure"] == "octree" and octree["configs"] == 2
    assert octree["build_failures"] == 0
    assert octree["worst_memory_x_origin"] <= 2.0
    assert octree["aimed_misses"] == 0 and octree["mismatches_vs_brute"] == 0
    (beyond,) = octree["beyond"]
    assert beyond["shift"] == 1e7 and "build_error" not in beyond
    # Brute force itself finds no crack up to 1e5 either (the kernel is watertight there).
    (brute,) = [r for r in out["records"] if r["structure"] == "brute"]
    assert brute["cracks"] == 0 and all(row["aimed_rays"] > 200 for row in brute["sweep"]
                                        if row["shift"] <= stability.ANYWHERE_UP_TO)
    assert "build as at the origin" in out["findings"]


# --- Case 6 -----------------------------------------------------------------------------------

def test_case6_axis_parallel_rays_on_planes(quick_cases):
    out = quick_cases[6]
    assert _pairs(out["records"]) >= {(k, "brute") for k in KERNELS} | {
        ("watertight", s) for s in ("kdtree", "octree", "grid")}
    for r in out["records"]:
        assert r["nan"] == 0, r
        assert r["mismatches_vs_brute"] == 0, r
        if r["kernel"] == "watertight":
            assert r["cracks"] == 0 and r["false_hits"] == 0, r
    assert all(r["own_plane_values"] > 0 for r in out["records"] if r["structure"] != "brute")


# --- Case 7 -----------------------------------------------------------------------------------

def test_case7_interface_optics():
    checks = stability.optics_checks()
    bad = [c for c in checks if not c["ok"]]
    assert not bad, bad
    tir = [c for c in checks if c["check"].startswith("TIR")]
    assert len(tir) == 12 and all(not c["tir_below"] and c["tir_above"] for c in tir)


def test_case7_glass_camel_traps_light_without_leaks(quick_cases):
    (g,) = [r for r in quick_cases[7]["records"] if r["check"].startswith("glass camel")]
    assert (g["kernel"], g["structure"]) == ("watertight", "bvh")
    assert g["rays"] == quick_cases[7]["parameters"]["rays"] >= 8
    assert g["leaks"] == 0 and g["wrong_side"] == 0 and g["nan"] == 0, g
    assert g["bounces_max"] >= 3 and g["tir_share"] > 0


# --- Case 8 -----------------------------------------------------------------------------------

def test_case8_boundaries_reject_bad_inputs():
    checks = stability.boundary_checks()
    bad = [c for c in checks if c["ok"] is False]
    assert not bad, bad
    mesh = [c for c in checks if c["check"] == "mesh vertices"]
    assert len(mesh) == 4 and all("MeshError" in c["outcome"] for c in mesh)


def test_case8_closest_hit_rejects_nan_and_infinite_rays():
    """Every bad ray alone (NaN / inf origin or direction, zero direction) is a ValueError
    naming the ray, under brute force and the BVH; the suite records them as rejected."""
    m = stability.load("camel-19k")
    o, d, _ = stability.bad_rays()
    for kind in ("brute", "bvh"):
        s = stability.build(kind, m.vertices, m.faces, key="camel-19k")
        for i in range(len(o)):
            with pytest.raises(ValueError, match="ray 0"):
                jrt.closest_hit(s, o[i:i + 1], d[i:i + 1])
    out = stability.nan_ray_outcomes("camel-19k", [("watertight", "brute"),
                                                   ("watertight", "bvh")])
    assert all(r["rejected"] and r["nan"] == 0 and r["hits"] == 0 for r in out), out


# --- Case 9 -----------------------------------------------------------------------------------

def test_case9_stack_overflow_is_reported(quick_cases):
    """A deep chain of layers (a BVH deeper than 8): an 8-entry stack overflows
    (StackOverflowError, in a subprocess so that a traversal that runs to its iteration
    budget cannot hang the suite), the default 64 answers."""
    (res,) = [r for r in quick_cases[9]["records"] if r["check"].startswith("deep chain")]
    assert res["structure"] == "bvh" and "error" not in res, res
    assert res["depth"] > 8
    assert res["sizes"]["8"]["outcome"] == "StackOverflowError"
    assert res["sizes"]["64"]["outcome"] == "ok"


@pytest.mark.xfail(reason="the tie window (2^-20 t, lowest face wins) is not transitive: on "
                          "a stack of nearly coplanar layers the winner depends on the "
                          "visiting order, and the structures disagree with brute force "
                          "(benchmarks/stability/deep_trees.py, case 9)", strict=False)
def test_case9_stacked_layers_agree_with_brute_force():
    out = stability.stacked_layers([("watertight", "brute"), ("watertight", "bvh")], n=1000)
    assert all(r["same_as_brute"] for r in out), out


def test_every_size_names_only_arguments_of_its_case():
    """--size quick and standard (jrt study's default) call each case function with
    arguments it takes, and never with larger sizes than the full sweep's defaults."""
    import inspect

    for case, fn in stability.CASE_FUNCTIONS.items():
        signature = inspect.signature(fn)
        for params in (stability.quick_params(case, None),
                       stability.standard_params(case, None)):
            signature.bind(**params)
            for name in ("per_family", "per_angle", "per_triangle", "incoherent_rays", "rays"):
                if name in params:
                    assert params[name] <= signature.parameters[name].default, (case, name)
    with pytest.raises(ValueError, match="allowed quick, standard, full"):
        stability.run(cases=(8,), size="medium")


def test_structure_lists_come_from_the_registry(capsys):
    """A structure registered after import is in the default pairs, in the quick size's
    pairs and in the command's help."""
    accel.register(dataclasses.replace(accel.kind("bvh"), name="bvh_copy"))
    try:
        assert ("watertight", "bvh_copy") in stability.combos(("watertight",))
        quick = stability.quick_params(1, None)["pairs"]
        # Every kernel on brute force, then watertight on every structure the engine steps.
        assert [s for k, s in quick if k == "watertight"] == ["brute", "bvh", "kdtree",
                                                             "octree", "bsp", "grid",
                                                             "bvh_copy"]
        assert {s for k, s in quick if k != "watertight"} == {"brute"}
        with pytest.raises(SystemExit) as exit_:
            stability.main(["--help"], prog="jrt stability")
        assert exit_.value.code == 0
        usage = capsys.readouterr().out
        assert usage.startswith("usage: jrt stability") and "bvh_copy" in usage
    finally:
        accel.unregister("bvh_copy")
    assert "bvh_copy" not in {s for _, s in stability.combos()}


def test_the_package_runs_as_a_module():
    """``python -m benchmarks.stability`` parses its options under its own name."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]))
    proc = subprocess.run([sys.executable, "-m", "benchmarks.stability", "--cases", "10"],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    assert "python -m benchmarks.stability: error: --cases: unknown [10]" in proc.stderr
