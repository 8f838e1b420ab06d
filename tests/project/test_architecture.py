"""The package's import graph (issue 11; docs/architecture.md).

Every ``bayes_talk`` module's imports are read from its source with :mod:`ast` (module
level, inside functions and under ``if TYPE_CHECKING:`` alike: a lazy or type-only import
is still an arrow). The tests fail on (issue 26, item 5: modules cut by cohesion, not by
line count)

* an import cycle among ``bayes_talk`` modules, type-only imports included (two modules
  that need each other's names are one idea: merge them, or move the shared part down);
* a *backward arrow*: a module importing one of a later layer in :data:`LAYERS`,
  unless the arrow is listed in :data:`ALLOWED` with a reason;
* a private name (one leading underscore) imported from another ``bayes_talk`` module, or
  read as an attribute of an imported ``bayes_talk`` module: a name used across modules is
  part of its module's interface and is spelled without the underscore;
* a module over :data:`MAX_LINES` lines whose docstring does not say why ("... above ~N
  lines because ...").

The layer order, defined here once and explained in docs/architecture.md, is the flow of
data: raw data → features → corpus → alignment → models → synthesis → estimators →
evaluation → command line. A module may import its own layer and the layers before it.
"""
from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[2] / "bayes_talk"

#: (layer, module prefixes), in data-flow order. A module belongs to the layer of its
#: longest matching prefix (``bayes_talk`` itself matches only the package root); every
#: module must match one, so a new top-level module must be placed here.
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    # low-level utilities: no knowledge of faces, speech or models; the package root is a
    # façade whose exports are imported lazily (bayes_talk/__init__.py) so it sits here
    ("base", ("bayes_talk", "bayes_talk.base", "bayes_talk.gp")),
    # raw data: phone set, utterance container, label files, speech synthesis, face
    # geometry and coarticulation
    ("data", ("bayes_talk.data",)),
    # features of one utterance: audio front end, MFCC, Procrustes/PCA/warp/AAM
    ("features", ("bayes_talk.features",)),
    # a stored corpus: renders synthetic faces (needs the warp), extracts and saves the
    # features of every utterance, loads them back (needs the AAM); tracking real video
    ("corpus", ("bayes_talk.corpus",)),
    # phone labels from audio: forced alignment and recognition, trained on a corpus
    ("alignment", ("bayes_talk.alignment",)),
    # generative models and their MAP fit (never inference for new audio)
    ("models", ("bayes_talk.models",)),
    # the papers' synthesis given a fitted model: initialisers, objectives, Algorithms 1-2,
    # the whole-utterance density and its joint MAP, the result type
    ("synthesis", ("bayes_talk.synthesis",)),
    # posterior methods behind one interface: the method table, the samplers, diagnostics
    ("posterior", ("bayes_talk.posterior",)),
    # the predictive's calibration: fitted on held-out training utterances, applied to results
    ("calibration", ("bayes_talk.calibration",)),
    # fit / predict / predict_dist / save / load: our systems and the published baselines
    ("estimators", ("bayes_talk.estimators",)),
    # protocols, metrics, reports
    ("evaluation", ("bayes_talk.evaluation",)),
    # what a user runs: train / synth directories, the command line, the demo
    ("application", ("bayes_talk.pipeline", "bayes_talk.app")),
]

#: arrows tolerated for now, backward or closing a cycle: (importer, imported) -> reason.
#: Keep it empty.
ALLOWED: dict[tuple[str, str], str] = {
}


def module_name(path: Path) -> str:
    """Dotted module name of a file under :data:`PACKAGE`."""
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def all_modules() -> dict[str, Path]:
    """Every module of the package: dotted name -> file."""
    return {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def from_module(node: ast.ImportFrom, package: str) -> str:
    """The absolute module of ``from MODULE import ...`` in ``package`` (relative imports resolved)."""
    if not node.level:
        return node.module or ""
    base = package.split(".")
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports_of(name: str, path: Path, modules: set[str]) -> set[str]:
    """The ``bayes_talk`` modules ``name`` imports (``from pkg import sub`` counts as ``pkg.sub``
    when ``sub`` is a module; otherwise as ``pkg``), type-only imports included."""
    is_pkg = path.name == "__init__.py"
    package = name if is_pkg else name.rpartition(".")[0]
    out: set[str] = set()
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            mod = from_module(node, package)
            targets = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in modules else mod for a in node.names]
        else:
            continue
        for t in targets:
            if t == "bayes_talk" or t.startswith("bayes_talk."):
                while t not in modules and "." in t:  # e.g. `import bayes_talk.x.y as z` of an attribute
                    t = t.rpartition(".")[0]
                if t != name:
                    out.add(t)
    return out


def layer_of(name: str) -> int:
    """Index in :data:`LAYERS` of the longest prefix matching ``name``."""
    best, best_len = None, -1
    for i, (_, prefixes) in enumerate(LAYERS):
        for p in prefixes:
            below = name.startswith(p + ".") and p != "bayes_talk"  # the root names itself only
            if (name == p or below) and len(p) > best_len:
                best, best_len = i, len(p)
    if best is None:
        raise LookupError(f"module {name} is in no layer of tests/project/test_architecture.py LAYERS")
    return best


def import_graph() -> dict[str, set[str]]:
    """module -> the package modules it imports (see :func:`imports_of`)."""
    mods = all_modules()
    names = set(mods)
    return {n: imports_of(n, p, names) for n, p in mods.items()}


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def backward_arrows(graph: dict[str, set[str]]) -> list[str]:
    """``importer -> imported`` for every import of a later layer not in :data:`ALLOWED`."""
    bad = []
    for a, targets in sorted(graph.items()):
        for b in sorted(targets):
            if layer_of(b) > layer_of(a) and (a, b) not in ALLOWED:
                bad.append(f"{a} ({LAYERS[layer_of(a)][0]}) -> {b} ({LAYERS[layer_of(b)][0]})")
    return bad


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    return import_graph()


def test_every_module_has_a_layer(graph):
    missing = []
    for name in graph:
        try:
            layer_of(name)
        except LookupError:
            missing.append(name)
    assert not missing, f"modules in no layer (add them to LAYERS): {missing}"


def test_no_import_cycles(graph):
    """Cycles of imports, those under ``if TYPE_CHECKING:`` included: a type-only circle
    still means neither module can be read without the other."""
    cycles = find_cycles({a: {b for b in bs if (a, b) not in ALLOWED} for a, bs in graph.items()})
    assert not cycles, "import cycles among bayes_talk modules:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_no_backward_arrows(graph):
    bad = backward_arrows(graph)
    assert not bad, "imports against the data flow (tests/project/test_architecture.py LAYERS):\n" + "\n".join(bad)


def test_allowed_exceptions_are_still_needed(graph):
    """An ALLOWED entry whose import has gone must be removed, so the list stays honest."""
    stale = [f"{a} -> {b}" for a, b in ALLOWED if b not in graph.get(a, set())]
    assert not stale, f"ALLOWED lists arrows that no longer exist: {stale}"


def test_checker_sees_cycles_and_backward_arrows(tmp_path):
    """The checker itself: a planted cycle and a planted backward arrow are reported; an
    import under ``if TYPE_CHECKING:`` is an arrow like any other."""
    src = tmp_path / "x.py"
    src.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from bayes_talk.base.files import a\n")
    assert imports_of("bayes_talk.x", src, {"bayes_talk.base.files", "bayes_talk.x"}) == {"bayes_talk.base.files"}
    assert find_cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert find_cycles({"a": {"b"}, "b": set()}) == []
    planted = {"bayes_talk.models.x": {"bayes_talk.synthesis.y"}, "bayes_talk.synthesis.y": set()}
    assert backward_arrows(planted) == ["bayes_talk.models.x (models) -> bayes_talk.synthesis.y (synthesis)"]
    assert backward_arrows({"bayes_talk.synthesis.y": {"bayes_talk.models.x"}}) == []
    with pytest.raises(LookupError):
        layer_of("bayes_talk.somewhere_new")


def private_imports(name: str, path: Path, modules: set[str]) -> list[str]:
    """``module: name`` for every private name (``_x``, not dunder) that ``name`` takes from
    another ``bayes_talk`` module: ``from bayes_talk.m import _x``; ``m._x`` where ``m`` is
    a name bound to a ``bayes_talk`` module by an import (``bayes_talk.m._x`` after a plain
    ``import bayes_talk.m`` too); or ``C._x`` where ``C`` is a class or function imported
    from another ``bayes_talk`` module (its private members are its module's business)."""
    is_pkg = path.name == "__init__.py"
    package = name if is_pkg else name.rpartition(".")[0]
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    private = lambda n: n.startswith("_") and not n.startswith("__")
    out: list[str] = []
    bound: dict[str, str] = {}  # local name -> bayes_talk module
    names: dict[str, str] = {}  # local name -> the bayes_talk module it was imported from
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("bayes_talk") and a.asname:
                    bound[a.asname] = a.name
        elif isinstance(node, ast.ImportFrom):
            mod = from_module(node, package)
            if mod != "bayes_talk" and not mod.startswith("bayes_talk."):
                continue
            for a in node.names:
                if f"{mod}.{a.name}" in modules:
                    bound[a.asname or a.name] = f"{mod}.{a.name}"
                elif private(a.name) and mod != name:
                    out.append(f"{name}: from {mod} import {a.name}")
                elif mod != name:
                    names[a.asname or a.name] = mod
    for node in ast.walk(tree):
        if not isinstance(node, ast.Attribute) or not private(node.attr):
            continue
        if isinstance(node.value, ast.Name) and node.value.id in bound and bound[node.value.id] != name:
            out.append(f"{name}: {bound[node.value.id]}.{node.attr} (line {node.lineno})")
        elif isinstance(node.value, ast.Name) and node.value.id in names:
            out.append(f"{name}: {names[node.value.id]}.{node.value.id}.{node.attr} (line {node.lineno})")
        elif isinstance(node.value, ast.Attribute):
            dotted = ast.unparse(node.value)
            if dotted in modules and dotted != name:
                out.append(f"{name}: {dotted}.{node.attr} (line {node.lineno})")
    return out


def test_no_private_names_across_modules():
    """A name another module uses is part of its module's interface: no leading underscore."""
    mods = all_modules()
    names = set(mods)
    bad = [b for n, p in mods.items() for b in private_imports(n, p, names)]
    assert not bad, f"{len(bad)} private names used across modules (make them public or move them):\n" + "\n".join(bad)


def test_checker_sees_private_imports(tmp_path):
    """The checker itself: planted private imports (by name, by module attribute, by a dotted
    module path, by a member of an imported class) are reported, public and dunder names and
    a module's own names are not."""
    src = tmp_path / "x.py"
    src.write_text("from bayes_talk.base.files import _a, b, __version__, Thing\n"
                   "from bayes_talk.base import files as f\n"
                   "import bayes_talk.gp.linalg as la\n"
                   "import bayes_talk.gp.lapack\n"
                   "f._c; f.d; la._e; bayes_talk.gp.lapack._g; Thing._h; Thing.i; b.__doc__\n")
    mods = {"bayes_talk", "bayes_talk.base", "bayes_talk.base.files", "bayes_talk.gp", "bayes_talk.gp.linalg", "bayes_talk.gp.lapack",
            "bayes_talk.x"}
    assert sorted(private_imports("bayes_talk.x", src, mods)) == sorted([
        "bayes_talk.x: from bayes_talk.base.files import _a",
        "bayes_talk.x: bayes_talk.base.files._c (line 5)",
        "bayes_talk.x: bayes_talk.gp.linalg._e (line 5)",
        "bayes_talk.x: bayes_talk.gp.lapack._g (line 5)",
        "bayes_talk.x: bayes_talk.base.files.Thing._h (line 5)",
    ])


#: a module longer than this must say why in its docstring ("... above ~N lines because ...")
MAX_LINES = 500
_SAYS_WHY = re.compile(r"above ~\d+ lines because")


def long_modules(modules: dict[str, Path]) -> list[str]:
    """``name (N lines)`` of every module over :data:`MAX_LINES` lines whose docstring does not
    say why (:data:`_SAYS_WHY`)."""
    bad = []
    for name, path in modules.items():
        text = path.read_text(encoding="utf-8")
        n = len(text.splitlines())
        if n <= MAX_LINES:
            continue
        doc = ast.get_docstring(ast.parse(text)) or ""
        if not _SAYS_WHY.search(" ".join(doc.split())):
            bad.append(f"{name} ({n} lines)")
    return bad


def test_long_modules_say_why():
    """No module over ~500 lines (:data:`MAX_LINES`) unless its docstring says why."""
    bad = long_modules(all_modules())
    assert not bad, (f"modules over {MAX_LINES} lines whose docstring does not say why "
                     f"('above ~{MAX_LINES} lines because ...'): " + ", ".join(bad))


def test_checker_sees_a_long_module_without_a_reason(tmp_path):
    """The checker itself: a planted module of MAX_LINES + 1 lines is reported until its
    docstring says why; one of MAX_LINES lines never is."""
    body = "\n".join(f"x{i} = {i}" for i in range(MAX_LINES))
    (tmp_path / "short.py").write_text('"""Short."""\n' + "\n".join(body.splitlines()[1:]) + "\n")
    (tmp_path / "long.py").write_text('"""Long."""\n' + body + "\n")
    (tmp_path / "told.py").write_text('"""Long: above ~500 lines\nbecause it is one idea."""\n' + body + "\n")
    got = long_modules({p.stem: p for p in sorted(tmp_path.glob("*.py"))})
    assert got == [f"long ({MAX_LINES + 1} lines)"]


ARCHITECTURE_DOC = PACKAGE.parent / "docs" / "architecture.md"


def test_architecture_doc_names_every_module():
    """docs/architecture.md's module index names every module of ``bayes_talk/`` (as
    `path/relative/to/bayes_talk.py`) and no module that does not exist."""
    text = ARCHITECTURE_DOC.read_text(encoding="utf-8")
    index = text.split("## Module index", 1)
    assert len(index) == 2, "docs/architecture.md has no '## Module index' section"
    named = set(re.findall(r"^\* `([\w/]+\.py)`", index[1], flags=re.MULTILINE))
    files = {str(p.relative_to(PACKAGE)) for p in PACKAGE.rglob("*.py") if p.name != "__init__.py"}
    assert not files - named, f"modules missing from docs/architecture.md's index: {sorted(files - named)}"
    assert not named - files, f"docs/architecture.md's index names modules that do not exist: {sorted(named - files)}"


#: the largest share of the package's lines one first-level package may hold: a package
#: above it holds several ideas and is cut by idea
MAX_PACKAGE_SHARE = 0.15


def package_lines() -> dict[str, int]:
    """Lines of every first-level entry of ``bayes_talk/`` (a package, or a loose module)."""
    out: dict[str, int] = {}
    for p in PACKAGE.rglob("*.py"):
        top = p.relative_to(PACKAGE).parts[0]
        out[top] = out.get(top, 0) + len(p.read_text(encoding="utf-8").splitlines())
    return out


def test_no_first_level_package_holds_more_than_its_share():
    lines = package_lines()
    total = sum(lines.values())
    big = {k: f"{v / total:.1%}" for k, v in lines.items() if v > MAX_PACKAGE_SHARE * total}
    assert not big, f"first-level packages above {MAX_PACKAGE_SHARE:.0%} of bayes_talk's lines: {big}"


def test_only_the_facade_sits_at_the_top():
    """Every module lives in a package that names its layer; the package root holds only
    the lazy façade (``__init__.py``) and ``__main__.py``."""
    loose = sorted(p.name for p in PACKAGE.glob("*.py") if p.name not in ("__init__.py", "__main__.py"))
    assert not loose, f"loose modules at the top of bayes_talk/ (put them in the package of their layer): {loose}"


def test_first_level_packages_import_only_their_own_or_earlier_layers(graph):
    """The folders are the layers: every first-level package lies in one layer (so no
    import between two folders can run back up; :func:`test_no_backward_arrows` checks
    the arrows)."""
    spread = {}
    for name in graph:
        parts = name.split(".")
        if len(parts) < 2:
            continue
        spread.setdefault(parts[1], set()).add(LAYERS[layer_of(name)][0])
    mixed = {k: sorted(v) for k, v in spread.items() if len(v) > 1}
    assert not mixed, f"first-level packages spread over several layers: {mixed}"
