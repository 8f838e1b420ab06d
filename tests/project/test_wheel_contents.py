"""A built wheel carries what the package opens at run time (issue 28, item 7).

The package's own data files are opened through ``importlib.resources`` only (never a path
relative to ``__file__`` or to the repository), so the wheel works without the source tree.
The cheap check reads the code: every ``importlib.resources.files(PKG)`` resource exists and
is declared as package data in pyproject.toml. The slow check builds the wheel and compares
its file list with the package's files in git.
"""
from __future__ import annotations

import ast
import fnmatch
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "bayes_talk"


def resources_opened(tree: ast.AST) -> list[tuple[str, str]]:
    """(package, resource) of every ``importlib.resources.files("pkg").joinpath("name")``
    and ``files("pkg") / "name"`` with literal arguments."""
    def is_files_call(node) -> str | None:
        if (isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant)
                and ((isinstance(node.func, ast.Attribute) and node.func.attr == "files")
                     or (isinstance(node.func, ast.Name) and node.func.id == "files"))):
            return node.args[0].value
        return None

    found = []
    for node in ast.walk(tree):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "joinpath"
                and (pkg := is_files_call(node.func.value)) and node.args
                and isinstance(node.args[0], ast.Constant)):
            found.append((pkg, node.args[0].value))
        if (isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div) and (pkg := is_files_call(node.left))
                and isinstance(node.right, ast.Constant)):
            found.append((pkg, node.right.value))
    return found


def module_trees() -> dict[str, ast.AST]:
    return {str(p.relative_to(ROOT)): ast.parse(p.read_text(encoding="utf-8")) for p in PACKAGE.rglob("*.py")}


def package_data_globs() -> dict[str, list[str]]:
    conf = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    return conf["tool"]["setuptools"].get("package-data", {})


def declared(pkg: str, resource: str, globs: dict[str, list[str]]) -> bool:
    """Whether ``pkg``'s ``resource`` matches a package-data glob of ``pkg`` or of a parent
    package (setuptools' globs are relative to the package that declares them)."""
    parts = pkg.split(".")
    for i in range(len(parts), 0, -1):
        owner = ".".join(parts[:i])
        rel = "/".join([*parts[i:], resource])
        if any(fnmatch.fnmatch(rel, g) for g in globs.get(owner, [])):
            return True
    return False


def test_every_resource_the_code_opens_exists_and_is_package_data():
    globs = package_data_globs()
    opened = [(mod, pkg, res) for mod, tree in module_trees().items() for pkg, res in resources_opened(tree)]
    assert opened, "no importlib.resources use found: the scan is broken (corpus build reads sentences.txt)"
    assert ("bayes_talk.data", "sentences.txt") in {(p, r) for _, p, r in opened}
    for mod, pkg, res in opened:
        path = ROOT.joinpath(*pkg.split("."), res)
        assert path.is_file(), f"{mod}: opens {pkg}/{res}, which is not in the repository"
        assert declared(pkg, res, globs), f"{mod}: opens {pkg}/{res}, not declared in [tool.setuptools.package-data]"


def test_resource_scan_and_declaration_check_can_fail():
    tree = ast.parse('import importlib.resources as r\n'
                     'r.files("bayes_talk.data").joinpath("voices.json").read_text()\n'
                     'from importlib.resources import files\n(files("bayes_talk") / "fonts/a.ttf").read_bytes()\n')
    assert resources_opened(tree) == [("bayes_talk.data", "voices.json"), ("bayes_talk", "fonts/a.ttf")]
    globs = {"bayes_talk": ["data/*.txt", "data/*.json"]}
    assert declared("bayes_talk.data", "voices.json", globs)
    assert declared("bayes_talk.data", "sentences.txt", globs)
    assert not declared("bayes_talk", "fonts/a.ttf", globs)
    assert not declared("bayes_talk.data", "voices.npz", globs)


def test_no_module_finds_files_relative_to_its_source():
    """``__file__`` (of the package itself) would point into site-packages, where only the
    declared package data is; ``torch.__file__`` and the like are other packages' business."""
    offenders = [mod for mod, tree in module_trees().items()
                 if any(isinstance(n, ast.Name) and n.id == "__file__" for n in ast.walk(tree))]
    assert offenders == []


@pytest.mark.slow
def test_built_wheel_holds_every_package_file_in_git(tmp_path):
    """``pip wheel`` (no dependencies, no build isolation: setuptools and wheel come from the
    dev extra) then the wheel's bayes_talk/ files equal git's (nothing left out, nothing
    extra such as __pycache__ or numba caches) and the entry point is there."""
    pytest.importorskip("setuptools")
    pytest.importorskip("wheel")
    listed = subprocess.run(["git", "ls-files", "bayes_talk"], cwd=ROOT, capture_output=True, text=True, check=False)
    if listed.returncode != 0:
        pytest.skip(f"not a git checkout: {listed.stderr.strip()}")
    # built from a copy of the tracked files: setuptools' in-tree build/ keeps files of earlier
    # builds, and an untracked file of the working tree is not part of the package
    src = tmp_path / "src"
    for rel in ["pyproject.toml", "README.md", *listed.stdout.split()]:
        (src / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / rel, src / rel)
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--quiet",
                           "--disable-pip-version-check", "-w", str(tmp_path / "dist"), str(src)],
                          capture_output=True, text=True, check=False, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (wheel,) = (tmp_path / "dist").glob("bayes_talk-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert sorted(n for n in names if n.startswith("bayes_talk/")) == sorted(listed.stdout.split())
    entry = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
    assert "bayes-talk = bayes_talk.app.cli:main" in zipfile.ZipFile(wheel).read(entry).decode()
