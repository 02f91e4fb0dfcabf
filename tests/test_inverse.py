"""The worked inverse problem through ``jrt.refit`` (``python -m benchmarks.inverse``),
small: the 19k camel, moved by 5 % of its diagonal and scaled by 1.05, found again from a
32x24 depth image by gradient descent on the translation and the scale. Its JSON is the
quick study's (``conftest.quick_study``: ``jrt study --quick`` runs
``benchmarks.inverse --quick``, in a process of its own, as a user runs it; optax imports
absl, whose logging would outlive a test's captured output in the test process). The
glass camel's Cauchy coefficients, the other worked problem, take a minute and are in
``docs/gradients.md`` and the published report."""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest

if importlib.util.find_spec("optax") is None:  # (not imported here: see above)
    pytest.skip("optax is not installed (pip install -e '.[dev]')", allow_module_level=True)


def test_a_moved_camel_is_found_from_its_depth_image(quick_study):
    folder, printed = quick_study
    record = json.loads((folder / "inverse.json").read_text())
    assert record["kind"] == "inverse" and record["quick"] is True
    assert "--quick" in record["command"]
    assert (record["width"], record["height"], record["steps"]) == (32, 24, 150)
    (result,) = record["problems"]
    assert result["problem"] == "depth"
    assert len(result["losses"]) == len(result["values"]) == 151
    assert result["losses"][-1] < 0.1 * result["losses"][0]
    assert result["translation_error_over_diagonal"] < 0.01
    assert result["scale_error"] < 0.01
    assert np.isfinite(result["values"]).all()
    assert "depth: loss" in printed and "translation" in printed
