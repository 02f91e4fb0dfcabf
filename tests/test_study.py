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
                 "--skip", "bench,scenes,stability,work_precision,inverse,renders"]) == 0
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
        main(["study", "-o", str(tmp_path), "--skip",
              "bench,scenes,stability,work_precision,inverse,renders"])


def test_study_rejects_an_unknown_structure(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["study", "-o", str(tmp_path), "--structures", "bvh,octtree"])
    assert "unknown structure(s) ['octtree']" in capsys.readouterr().err


def test_quick_study_end_to_end(quick_study, quick_study_structures):
    """``jrt study --quick`` (``conftest.quick_study``), the whole chain as a user runs it
    (a process of its own, as the command would be): every step's JSON, the renders, the
    report and its figures, each checked against its own schema or format. One structure
    (and brute force) keeps it to a few minutes of CI; every structure has its own tests in
    the suites'. ``test_work_precision.py`` checks its work-precision JSON further."""
    import json

    import accel
    from benchmarks.schema import validate
    from benchmarks.stability import CASES
    from reports.report import PNG_SIGNATURE

    out, printed = quick_study
    print(printed[-2000:])
    for step in ("bench", "scenes", "stability", "work_precision", "inverse", "renders"):
        assert f"[study] {step}: " in printed and f"{step}: skipped" not in printed
    bench = json.loads((out / "bench.json").read_text())
    stadium = json.loads((out / "scenes" / "stadium.json").read_text())
    assert sorted(p.name for p in (out / "scenes").iterdir()) == ["stadium.json"]
    assert (stadium["parameters"]["scene"], stadium["parameters"]["mesh"]) == (
        "stadium", "stadium-small")
    for run in (bench, stadium):
        validate(run)
        benched = {r.get("structure") for r in run["records"]}
        # Of the engine's structures, exactly those asked for (brute force runs anyway).
        assert benched & set(accel.names(engine=True)) == set(quick_study_structures), benched
    stability = json.loads((out / "stability.json").read_text())
    assert stability["size"] == "quick"
    assert sorted(map(int, stability["cases"])) == list(CASES)
    assert not [c for c, body in stability["cases"].items() if "error" in body]
    assert json.loads((out / "work_precision.json").read_text())["records"]
    readme = (out / "README.md").read_text()
    for section in ("## The structures side by side", "### Per-pixel cost",
                    "### trimesh's ray interface",
                    "## The structures across scenes", "### The literature's claims",
                    "## Error against run time", "## Gradients: worked inverse problems",
                    "## Numerical stability", "## Renders"):
        assert section in readme, section
    links = [link.split(")")[0] for link in readme.split("](")[1:]]
    pngs = [link for link in links if link.endswith(".png")]
    assert sorted(p for p in pngs if p.startswith("renders/")) == [
        "renders/camel.png", "renders/glass-camel-closeup.png", "renders/glass-camel.png",
        "renders/mirror-camel.png"]
    for link in pngs:
        assert (out / link).read_bytes()[:8] == PNG_SIGNATURE, link
    page = (out / "index.html").read_text()
    assert page.count("data:image/png;base64,") == len(pngs)


def test_study_scenes_are_checked_and_in_the_suites_order(tmp_path, capsys):
    from reports import study

    parser = study.build_parser()
    args = parser.parse_args(["--scenes", "room,stadium"])
    assert args.scenes == ["stadium", "room"]
    for bad in ("camel", "stadum"):
        with pytest.raises(SystemExit):
            parser.parse_args(["--scenes", bad])
        assert "allowed: bunny, teapot, fandisk, stadium, herd, room, slivers" in (
            capsys.readouterr().err)


def test_full_study_runs_the_slivers_with_fewer_rays():
    """The options the scenes step gives the benchmark suite, as its parser reads them:
    every generated scene at its study size, the full slivers with the fewer rays of
    FULL_SCENE_RAYS (the later option wins), the suite's extra parts off."""
    from benchmarks.suite import build_parser
    from reports.study import OTHER_SCENES, scene_options

    parser = build_parser()
    for name in OTHER_SCENES:
        for size, scene_size in (("default", "small"), ("full", "full")):
            args = parser.parse_args(["--scene", name, *scene_options(name, size)])
            assert args.scene_size == scene_size
            assert (args.scaling, args.turntable_frames, args.trimesh_rays,
                    args.interface_rays) == (0, 0, 0, 0)
            fewer = size == "full" and name == "slivers"
            assert (args.rays, args.camera_size) == ((8192, 128) if fewer else
                                                     (65536, 256) if size == "default"
                                                     else (131072, 512))


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="needs /proc (Linux)")
def test_study_releases_each_steps_compiled_programs():
    """Each compiled program holds mappings of its machine code; a full study in one
    process compiled enough of them to reach the kernel's limit (vm.max_map_count) and
    died in its stability step. After a step the study drops them: the mappings fall back
    to what they were before the programs were compiled."""
    import jax
    import jax.numpy as jnp

    from jrt import clear_caches as release_programs  # what the study calls after a step

    def mappings():
        with open("/proc/self/maps") as fh:
            return sum(1 for _ in fh)

    jax.jit(lambda x: x + 1)(jnp.ones(3)).block_until_ready()  # the backend is up
    release_programs()
    before = mappings()
    # Functions that stay alive, as the library's module-level ones do.
    programs = [jax.jit(lambda x, i=i: jnp.sin(x) * i + jnp.cumsum(x) ** 2)
                for i in range(12)]
    for i, fn in enumerate(programs):
        fn(jnp.ones(100 + i)).block_until_ready()  # a shape of its own: a compile each
    compiled = mappings()
    release_programs()
    assert compiled - before >= 12  # the programs took mappings
    assert mappings() - before < (compiled - before) / 4
