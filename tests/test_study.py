"""``jrt study``: the chain from results to the report (the suites themselves have their own
tests; here their JSON is reused with --skip, so the test stays fast)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from jrt.cli import main

ROOT = Path(__file__).resolve().parents[1]


def test_study_reports_the_results_it_finds(tmp_path, capsys):
    shutil.copy(ROOT / "reports" / "camel" / "bench.json", tmp_path / "bench.json")
    assert main(["study", "-o", str(tmp_path),
                 "--skip", "bench,stability,work_precision,renders"]) == 0
    printed = capsys.readouterr().out
    assert "bench: skipped" in printed and "done" in printed
    readme = (tmp_path / "README.md").read_text()
    assert "bench.json" in readme
    for link in readme.split("](")[1:]:
        target = link.split(")")[0]
        if target.endswith(".png"):
            assert (tmp_path / target).is_file(), target
    assert (tmp_path / "index.html").is_file()


def test_study_rejects_an_unknown_step(tmp_path):
    with pytest.raises(SystemExit, match="unknown step"):
        main(["study", "-o", str(tmp_path), "--skip", "benchmark"])


def test_study_with_nothing_to_report_says_so(tmp_path):
    with pytest.raises(SystemExit, match="no results"):
        main(["study", "-o", str(tmp_path), "--skip", "bench,stability,work_precision,renders"])
