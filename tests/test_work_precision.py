"""The work–precision study (``benchmarks.work_precision``) on the glass camel.

Its JSON is the quick study's (``conftest.quick_study``: ``jrt study --quick``, whose
work-precision step runs ``benchmarks.work_precision --quick``: the 19k camel at 64x48
pixels, every study's quick points and a depth-10, 32-sample reference): the records carry
what ``reports.report`` needs, the depth and samples studies get closer to the reference,
the reference is not a record (and a point identical to it would have a null PSNR, not an
infinite one), and the report generator draws the file. (The study runs once per test
session; this file is run last, when the study has finished.)
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

import jrt  # noqa: F401  (XLA flags before JAX starts)
from benchmarks import work_precision as wp
from reports.report import classify, generate

#: The quick study's size (``wp.SIZES``).
WIDTH, HEIGHT = wp.SIZES[1]
STUDIES = {"Whitted depth", "wavelength samples", "pruning threshold",
           "exact tree vs sampled branches", "Fresnel exact vs Schlick", "kernel"}


@pytest.fixture(scope="module")
def result(quick_study):
    path = quick_study[0] / "work_precision.json"
    return path, json.loads(path.read_text())


def test_records_have_what_the_report_needs(result):
    path, doc = result
    assert classify(doc) == "work_precision"
    assert doc["kind"] == "work_precision"
    assert {"platform", "cpu_count", "jax"} <= set(doc["machine"])
    assert doc["parameters"]["width"] == WIDTH and doc["parameters"]["mesh"] == "camel-19k"
    assert any("float64" in n for n in doc["notes"])
    records = doc["records"]
    assert {r["study"] for r in records} == STUDIES
    assert {r["series"] for r in records
            if r["study"] == "exact tree vs sampled branches"} == {"tree", "sampled"}
    for r in records:
        assert r["kind"] == "work_precision"
        assert isinstance(r["method"], str) and r["method"]
        assert isinstance(r["series"], str) and r["series"]
        assert r["seconds"] > 0 and r["compile_seconds"] >= 0
        assert r["command"].startswith(wp.PROG) and "--quick" in r["command"]
        assert r["psnr"] is None or (math.isfinite(r["psnr"]) and r["psnr"] > 0)
        assert 0 < r["ssim"] <= 1 and r["delta_e"] >= 0
    # strict JSON: no Infinity or NaN anywhere
    json.loads(path.read_text(), parse_constant=lambda c: pytest.fail(f"{c} in the JSON"))


def _study(doc, name):
    return [r for r in doc["records"] if r["study"] == name]


@pytest.mark.parametrize("study", ["Whitted depth", "wavelength samples"])
def test_error_decreases_toward_the_reference(result, study):
    pts = _study(result[1], study)
    assert len(pts) >= 2
    first, last = pts[0], pts[-1]
    assert last["psnr"] > first["psnr"]
    assert last["ssim"] > first["ssim"]
    assert last["delta_e"] < first["delta_e"]


def test_reference_is_not_a_record(result):
    doc = result[1]
    ref = doc["reference"]
    assert ref["max_depth"] == 10 and ref["samples"] == 32 and ref["threshold"] == 0.0
    assert ref["fresnel"] == "exact" and ref["kernel"] == "watertight" and ref["seconds"] > 0
    same = {"max_depth": 10, "samples": 32, "threshold": 0.0, "fresnel": "exact",
            "kernel": "watertight", "mode": "tree"}
    assert not any(all(r["settings"][k] == v for k, v in same.items())
                   for r in doc["records"])
    assert not any(r.get("identical") for r in doc["records"])


def test_identical_image_has_null_psnr():
    rng = np.random.default_rng(0)
    image = rng.random((12, 16, 3)).astype(np.float32)
    m = wp.metrics(image, image)
    assert m["identical"] and m["psnr"] is None
    assert m["ssim"] == pytest.approx(1.0) and m["delta_e"] == pytest.approx(0.0, abs=1e-9)
    other = wp.metrics(np.clip(image + 0.05, 0, 1), image)
    assert not other["identical"] and math.isfinite(other["psnr"]) and other["delta_e"] > 0


def test_report_draws_the_file(result, tmp_path):
    path, doc = result
    written = generate([path], tmp_path / "report")
    assert written is not None
    readme = (tmp_path / "report" / "README.md").read_text()
    assert "## Error against run time" in readme
    for study in STUDIES:
        assert f"### {study}" in readme
    figures = sorted((tmp_path / "report" / "figures").glob("work-precision-*.png"))
    assert len(figures) == len(STUDIES)
    assert doc["records"][0]["method"] in readme
