"""The ``jrt`` command line as one program: every command's help is plain text and names
``jrt COMMAND``, the registered commands' errors do too (the commands that the packages
above the library register as entry points, and what ``jrt`` says when one is missing),
``jrt render --turntable`` without a scene turns the default one, and ``jrt study`` writes
into ``./study`` unless the published study is asked for explicitly (nothing runs there:
the output folder is resolved, or refused, before any step)."""

from __future__ import annotations

import importlib.metadata
import inspect
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from jrt import cli
from jrt.cli import main
from reports import study

ROOT = Path(__file__).resolve().parents[1]
COMMANDS = ("trace", "render", "bench", "stability", "study", "report")
#: The commands registered by pyproject.toml's [project.entry-points."jrt.commands"].
REGISTERED = {"bench": "benchmarks.suite:main", "stability": "benchmarks.stability:main",
              "study": "reports.study:main", "report": "reports.report:main"}
#: reStructuredText markup that has no place in a terminal's help.
RST = re.compile(r"``|:(?:func|class|data|meth|mod|attr):`")


def _help(capsys, *argv) -> str:
    with pytest.raises(SystemExit) as done:
        main([*argv, "--help"])
    assert done.value.code == 0
    return capsys.readouterr().out


@pytest.mark.parametrize("command", (None,) + COMMANDS)
def test_help_is_plain_text_and_names_the_jrt_command(capsys, command):
    text = _help(capsys, *([command] if command else []))
    prog = "jrt" if command is None else f"jrt {command}"
    assert text.startswith(f"usage: {prog} "), text[:200]
    assert "python -m" not in text.split("\n\n")[0]  # the usage block
    assert not RST.search(text), RST.search(text).group(0)


@pytest.mark.parametrize("argv, prog", [
    (["bench", "--structures", "quadtree"], "jrt bench"),
    (["report", "results.json"], "jrt report"),  # -o is required
    (["study", "--full", "--quick"], "jrt study"),
])
def test_delegated_option_errors_name_the_jrt_command(capsys, argv, prog):
    with pytest.raises(SystemExit) as done:
        main(argv)
    assert done.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith(f"usage: {prog} ") and f"\n{prog}: error: " in err, err
    assert "python -m" not in err


def test_the_study_commands_are_registered_entry_points():
    """The installed entry points are pyproject.toml's, each a main(argv, prog=...)."""
    registered = cli.registered_commands()
    assert {name: ep.value for name, ep in registered.items()} == REGISTERED
    assert tuple(registered) == cli.STUDY_COMMANDS
    for name, entry_point in registered.items():
        parameters = inspect.signature(entry_point.load()).parameters
        assert list(parameters)[:1] == ["argv"] and "prog" in parameters, (name, parameters)


def test_help_lists_every_command_without_importing_the_upper_packages():
    """``jrt --help`` (in a process of its own): a line of help for each registered command,
    taken from its module's docstring, and none of benchmarks or reports imported."""
    code = ("import sys\nfrom jrt.cli import main\ntry:\n    main(['--help'])\n"
            "except SystemExit as done:\n    assert done.code == 0\n"
            "print('imported:', sorted(m for m in sys.modules "
            "if m.split('.')[0] in ('benchmarks', 'reports')))")
    run = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    printed = " ".join(run.stdout.split())
    assert "imported: []" in printed
    for name, line in [
            ("bench", "the benchmark suite: every structure on the camel, side by side with "
                      "Embree, as JSON"),
            ("stability", "numerical stability on stiff and extreme cases"),
            ("study", "the whole study of the camel in one command"),
            ("report", "the report generator: JSON results in, DIR/README.md")]:
        assert f" {name} {line}" in printed, (name, printed)
        assert f"(options: jrt {name} --help)" in printed


def _entry_points(*registered):
    """A stand-in for importlib.metadata.entry_points: these jrt.commands entry points."""
    def entry_points(group):
        return [importlib.metadata.EntryPoint(name, value, group) for name, value in registered
                if group == cli.COMMAND_GROUP]
    return entry_points


def test_a_command_that_is_not_installed_says_so(monkeypatch, capsys):
    monkeypatch.setattr(cli.importlib.metadata, "entry_points",
                        _entry_points(("report", REGISTERED["report"])))
    assert main(["bench", "--quick"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("jrt bench: error: not installed here") and "jrt.commands" in err
    assert "registered: report" in err and "pip install -e ." in err
    text = _help(capsys)
    assert re.search(r"bench\s+not installed here", text) and "report" in text


def test_a_command_whose_module_is_missing_says_so(monkeypatch, capsys):
    monkeypatch.setattr(cli.importlib.metadata, "entry_points",
                        _entry_points(("bench", "no_such_package.suite:main")))
    assert main(["bench"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("jrt bench: error: registered as no_such_package.suite:main")
    assert "No module named 'no_such_package'" in err
    assert re.search(r"bench\s+not available: no_such_package.suite is not installed",
                     _help(capsys))


def test_render_turntable_without_a_scene_turns_the_default_scene(tmp_path, monkeypatch,
                                                                  capsys):
    """``jrt render --turntable N`` alone turns the scene of what ``jrt render`` alone
    renders (the camel): the same frames as ``--scene camel``, into camel-turntable/."""
    import imageio.v3 as iio

    monkeypatch.chdir(tmp_path)
    small = ["--width", "24", "--height", "18"]
    assert main(["render", "--turntable", "2", *small]) == 0, capsys.readouterr().err
    assert "camel turntable: 2 images 24x18" in capsys.readouterr().out
    out = tmp_path / "camel-turntable"
    assert sorted(p.name for p in out.iterdir()) == [
        "frame_000.png", "frame_001.png", "turntable.gif"]
    frames = [iio.imread(out / f"frame_00{i}.png") for i in range(2)]
    assert frames[0].shape == (18, 24, 3) and not np.array_equal(*frames)
    assert iio.imread(out / "turntable.gif").shape[:3] == (2, 18, 24)
    assert main(["render", "--scene", "camel", "--turntable", "2", "-o", "named", *small]) == 0
    for i, frame in enumerate(frames):
        assert np.array_equal(frame, iio.imread(tmp_path / "named" / f"frame_00{i}.png"))


def test_render_sweep_without_a_scene_varies_the_default_scene(capsys):
    """The sweep's material is looked up in the default scene (checked before rendering)."""
    assert main(["render", "--sweep", "glass.B=0:0.02:2"]) == 2
    assert "scene 'camel' has no material 'glass'; its materials: sand, floor" in (
        capsys.readouterr().err)


@pytest.mark.parametrize("option", [["--turntable", "2"], ["--sweep", "sand.albedo=0:1:2"]])
def test_render_batches_of_a_mesh_are_refused(capsys, option):
    assert main(["render", "bunny", *option]) == 2
    err = capsys.readouterr().err
    assert f"jrt render: error: {option[0]} applies to scene renders" in err
    assert "not to a mesh (bunny)" in err and "--scene NAME|FILE" in err


def test_study_step_errors_name_the_jrt_command(tmp_path):
    with pytest.raises(SystemExit, match=r"^jrt study: error: unknown step"):
        main(["study", "-o", str(tmp_path / "s"), "--skip", "benchmark"])
    assert not (tmp_path / "s").exists()


def _folder(argv):
    parser = study.build_parser("jrt study")
    args = parser.parse_args(argv)
    return study.output_folder(args, parser), args


@pytest.mark.parametrize("argv", [[], ["--quick"], ["--full"]])
def test_study_writes_into_study_in_the_working_directory_by_default(
        tmp_path, monkeypatch, argv):
    monkeypatch.chdir(tmp_path)
    out, _ = _folder(argv)
    assert out.resolve() == tmp_path.resolve() / "study"
    assert not out.exists()  # resolving the folder writes nothing


def test_the_published_folder_is_the_repository_reports_camel():
    assert study.PUBLISHED == ROOT / "reports" / "camel"
    assert (ROOT / "reports" / "camel" / "README.md").is_file()


def test_publish_means_reports_camel_at_full_size():
    out, args = _folder(["--publish"])
    assert out.resolve() == study.PUBLISHED and args.full and not args.quick
    out, args = _folder(["--publish", "-o", str(ROOT / "reports" / "camel")])
    assert out.resolve() == study.PUBLISHED and args.full


@pytest.mark.parametrize("argv", [[], ["--quick"], ["--skip", "stability"]])
def test_a_smaller_study_into_reports_camel_is_refused_without_force(
        capsys, tmp_path, monkeypatch, argv):
    monkeypatch.chdir(ROOT)
    with pytest.raises(SystemExit) as done:
        _folder(["-o", "reports/camel", *argv])
    assert done.value.code == 2
    err = capsys.readouterr().err
    assert "reports/camel holds the published study" in err and "--publish" in err
    assert "--force" in err
    out, _ = _folder(["-o", "reports/camel", "--force", *argv])
    assert out.resolve() == study.PUBLISHED.resolve()
    out, args = _folder(["-o", "reports/camel", "--full"])
    assert out.resolve() == study.PUBLISHED.resolve() and args.full


@pytest.mark.parametrize("argv, said", [
    (["--publish", "--quick"], "cannot be --quick"),
    (["--publish", "-o", "elsewhere"], "not both"),
])
def test_publish_refuses_a_quick_run_or_another_folder(capsys, argv, said):
    with pytest.raises(SystemExit) as done:
        _folder(argv)
    assert done.value.code == 2
    assert said in capsys.readouterr().err


def test_a_quick_study_aimed_at_reports_camel_writes_nothing(capsys):
    """Through the command: refused before any step, every tracked file of the published
    study untouched (same names, sizes and modification times)."""
    def listing():
        return {p: (p.stat().st_size, p.stat().st_mtime_ns)
                for p in study.PUBLISHED.rglob("*") if p.is_file()}

    before = listing()
    with pytest.raises(SystemExit) as done:
        main(["study", "--quick", "-o", str(study.PUBLISHED)])
    assert done.value.code == 2
    assert "holds the published study" in capsys.readouterr().err
    assert listing() == before


@pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(),
                    reason="needs git and the repository")
def test_git_ignores_the_default_study_folder():
    for path in ("study/bench.json", "study/figures/x.png"):
        ignored = subprocess.run(["git", "check-ignore", "-q", path], cwd=ROOT)
        assert ignored.returncode == 0, path
    tracked = subprocess.run(["git", "check-ignore", "-q", "reports/camel/bench.json"],
                             cwd=ROOT)
    assert tracked.returncode == 1


def test_render_and_trace_take_a_generated_scene_by_name(tmp_path, monkeypatch, capsys):
    """A generated scene of the scene suite is a mesh name like the shipped ones: ``jrt
    render room-small`` renders the small room and writes room-small.png; ``jrt trace``
    reads it the same way (rays from the room's middle hit its walls)."""
    from skimage import io

    from jrt.scenes import scene_mesh

    monkeypatch.chdir(tmp_path)
    assert main(["render", "room-small", "--width", "24", "--height", "18",
                 "--no-shadows"]) == 0, capsys.readouterr().err
    printed = capsys.readouterr().out
    room = scene_mesh("room", size="small")
    assert f"room (small): {len(room.vertices):,} vertices, {len(room.faces):,} triangles" \
        in printed and "-> room-small.png" in printed
    image = io.imread(tmp_path / "room-small.png")
    assert image.shape[:2] == (18, 24)
    # Rays from the room's middle toward each wall all hit it.
    origins = np.tile(room.vertices.mean(axis=0), (6, 1)).astype(np.float32)
    directions = np.concatenate([np.eye(3), -np.eye(3)]).astype(np.float32)
    np.savez(tmp_path / "rays.npz", origins=origins, directions=directions)
    assert main(["trace", "room-small", str(tmp_path / "rays.npz"), "-o",
                 str(tmp_path / "hits.npz")]) == 0, capsys.readouterr().err
    assert (np.load(tmp_path / "hits.npz")["triangle"] >= 0).all()
