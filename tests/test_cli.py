"""The ``jrt`` command line as one program: every command's help is plain text and names
``jrt COMMAND``, the delegated commands' errors do too, and ``jrt study`` writes into
``./study`` unless the published study is asked for explicitly (nothing runs here: the
output folder is resolved, or refused, before any step)."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from benchmarks import study
from jrt.cli import main

ROOT = Path(__file__).resolve().parents[1]
COMMANDS = ("trace", "render", "bench", "study", "report")
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
