"""The layers: accel (NumPy only) <- jrt (JAX) <- benchmarks <- reports, the command line on
top through entry points. A lower package never imports a higher one and accel never
imports JAX (the import-linter contracts in pyproject.toml), and no package reaches into
another's private names (``from jrt.kernels import _name``, ``jrt.kernels._name``,
``import jrt._module``): what one package uses of another is that package's public API."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: The four top packages, lowest first (pyproject.toml's [tool.importlinter]).
PACKAGES = ("accel", "jrt", "benchmarks", "reports")


def _private(name: str) -> bool:
    """``_name`` is private; ``__name__`` (a dunder) is not."""
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _is_module(dotted: str) -> bool:
    """Whether a dotted name under one of the packages is a module or a package (a file
    or a folder of the source), rather than a name defined in one."""
    path = ROOT.joinpath(*dotted.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def _sources():
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            yield package, path


def private_uses(package: str, source: str, where: str) -> list[str]:
    """``WHERE:LINE name`` for each private name of another top package that a module of
    ``package`` (its ``source``) imports or reaches as an attribute of an imported
    module."""
    tree = ast.parse(source, filename=where)
    found = []
    # Local names bound to modules of other packages: "jrt" for ``import jrt``,
    # "k" for ``import jrt.kernels as k`` or ``from jrt import kernels as k``.
    modules: dict[str, str] = {}

    def other(dotted: str) -> bool:
        top = dotted.split(".")[0]
        return top in PACKAGES and top != package

    def report(node, dotted: str) -> None:
        found.append(f"{where}:{node.lineno} {dotted}")

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if not other(alias.name):
                    continue
                if any(map(_private, alias.name.split("."))):
                    report(node, alias.name)
                if alias.asname:
                    modules[alias.asname] = alias.name
                else:
                    top = alias.name.split(".")[0]
                    modules[top] = top
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if not other(node.module):
                continue
            for alias in node.names:
                dotted = f"{node.module}.{alias.name}"
                if any(map(_private, dotted.split("."))):
                    report(node, dotted)
                elif _is_module(dotted):
                    modules[alias.asname or alias.name] = dotted
    for node in ast.walk(tree):
        # The outermost attribute chain on a module name: jrt.kernels._gamma.
        if isinstance(node, ast.Attribute) and not isinstance(getattr(node, "parent", None),
                                                              ast.Attribute):
            chain = []
            part = node
            while isinstance(part, ast.Attribute):
                chain.append(part.attr)
                part = part.value
            if isinstance(part, ast.Name) and part.id in modules:
                names = chain[::-1]
                dotted = ".".join([modules[part.id], *names])
                if any(map(_private, names)):
                    report(node, dotted)
        for child in ast.iter_child_nodes(node):
            child.parent = node
    return sorted(found, key=lambda use: (int(use.split(":")[-1].split()[0]), use))


def test_private_uses_are_found():
    """The checker itself, on a module of each kind of private use (and public ones)."""
    sample = ("import jrt\nimport jrt._xla\nimport jrt.kernels as k\n"
              "from jrt.kernels import _gamma, gamma\nfrom jrt import kernels\n"
              "from benchmarks.common import _own\n"
              "x = jrt.kernels._gamma(1) + k._gamma + kernels._eps + jrt.__version__\n"
              "y = gamma._private + k.gamma + _own\n")
    found = private_uses("benchmarks", sample, "sample.py")
    assert found == ["sample.py:2 jrt._xla", "sample.py:4 jrt.kernels._gamma",
                     "sample.py:7 jrt.kernels._eps", "sample.py:7 jrt.kernels._gamma",
                     "sample.py:7 jrt.kernels._gamma"], found


def test_no_private_names_across_packages():
    found = [use for package, path in _sources()
             for use in private_uses(package, path.read_text(encoding="utf-8"),
                                     str(path.relative_to(ROOT)))]
    assert not found, ("private names of another package (use its public API, or make "
                       "the name public where it is defined):\n  " + "\n  ".join(found))


def dynamic_imports_upward(package: str, source: str, where: str) -> list[str]:
    """``WHERE:LINE module`` for each ``importlib.import_module(...)`` or ``__import__(...)``
    in a module of ``package`` whose module name (a string, or an f-string's leading text)
    is in a higher package: an import that import-linter cannot see."""
    level = PACKAGES.index(package)
    found = []
    for node in ast.walk(ast.parse(source, filename=where)):
        if not (isinstance(node, ast.Call) and node.args):
            continue
        func = node.func
        name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
        if name not in ("import_module", "__import__"):
            continue
        arg = node.args[0]
        if isinstance(arg, ast.JoinedStr) and arg.values:
            arg = arg.values[0]
        if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
            top = arg.value.split(".")[0]
            if top in PACKAGES and PACKAGES.index(top) > level:
                found.append(f"{where}:{node.lineno} {arg.value}")
    return found


def test_dynamic_imports_are_found():
    sample = ("import importlib\nimportlib.import_module('reports.report')\n"
              "__import__(f'benchmarks.{name}')\nimportlib.import_module('jrt.kernels')\n"
              "importlib.import_module(f'accel.{name}')\n")
    assert dynamic_imports_upward("jrt", sample, "s.py") == [
        "s.py:2 reports.report", "s.py:3 benchmarks."]


def test_no_dynamic_imports_of_a_higher_package():
    """The command line reaches the commands above the library through entry points
    (jrt.cli.COMMAND_GROUP), never by importing them by name."""
    found = [use for package, path in _sources()
             for use in dynamic_imports_upward(package, path.read_text(encoding="utf-8"),
                                               str(path.relative_to(ROOT)))]
    assert not found, "a lower package imports a higher one by name:\n  " + "\n  ".join(found)


def test_import_contracts_are_kept(monkeypatch, capsys):
    """pyproject.toml's [tool.importlinter] contracts: the layers, and accel without JAX."""
    cli = pytest.importorskip(
        "importlinter.cli", reason="import-linter is not installed (pip install -e '.[dev]')")
    monkeypatch.chdir(ROOT)
    status = cli.lint_imports(config_filename=str(ROOT / "pyproject.toml"), no_cache=True,
                              no_logo=True)
    printed = capsys.readouterr().out
    assert status == 0, printed
    assert "0 broken" in printed and "layers" in printed, printed
