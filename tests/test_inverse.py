"""The worked inverse problem through ``jrt.refit`` (``python -m benchmarks.inverse``),
small: the 19k camel, moved by 5 % of its diagonal and scaled by 1.05, found again from a
32x24 depth image by gradient descent on the translation and the scale (the glass
camel's Cauchy coefficients, the other worked problem, take a minute and are in
``docs/gradients.md``). In a process of its own, as a user runs it: optax imports absl,
whose logging would outlive the test's captured output in this process."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

if importlib.util.find_spec("optax") is None:  # (not imported here: see above)
    pytest.skip("optax is not installed (pip install -e '.[dev]')", allow_module_level=True)

ROOT = Path(__file__).resolve().parents[1]


def test_a_moved_camel_is_found_from_its_depth_image(tmp_path):
    out = tmp_path / "inverse.json"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]))
    run = subprocess.run(
        [sys.executable, "-m", "benchmarks.inverse", "--problem", "depth", "--width", "32",
         "--height", "24", "--steps", "150", "--json", str(out)],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    (result,) = json.loads(out.read_text())["problems"]
    assert result["problem"] == "depth"
    assert result["losses"][-1] < 0.1 * result["losses"][0]
    assert result["translation_error_over_diagonal"] < 0.01
    assert result["scale_error"] < 0.01
    assert np.isfinite(result["values"]).all()
    assert "translation" in run.stdout
