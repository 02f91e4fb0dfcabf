"""The worked inverse problem through ``jrt.refit`` (``benchmarks.inverse``), small: the
19k camel, moved by 5 % of its diagonal and scaled by 1.05, found again from a 32x24 depth
image by gradient descent on the translation and the scale (the glass camel's Cauchy
coefficients, the other worked problem, take a minute and are in ``docs/gradients.md``)."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

pytest.importorskip("optax")

from benchmarks import inverse  # noqa: E402


def test_a_moved_camel_is_found_from_its_depth_image():
    args = argparse.Namespace(width=32, height=24, steps=150, rate=0.02, depth=3)
    result = inverse.depth_problem(args)
    assert result["losses"][-1] < 0.1 * result["losses"][0]
    assert result["translation_error_over_diagonal"] < 0.01
    assert result["scale_error"] < 0.01
    assert np.isfinite(result["values"]).all()
