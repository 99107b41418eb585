"""The layer order of ../DESIGN.md, enforced on every import in the library, module
level or inside functions: capture <- reconstruct <- atr <- datasets (a layer imports
only the layers to its left); the root package's shared modules import no layer; only
the entry points (cli, demo, _precompile) wire layers together, and nothing imports them.
Inside a layer, its sub-packages keep their own order (:data:`SUBPACKAGES`), and every
library module is tied to the import graph.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
#: layers in import order: each may import those before it
LAYERS = ("capture", "reconstruct", "atr", "datasets")
#: root modules that wire the layers together (nothing in the library imports them)
ENTRY_POINTS = ("prism3d.cli", "prism3d.demo", "prism3d._precompile")
#: a layer's sub-packages -> the sibling sub-packages each may import (its own always)
SUBPACKAGES = {
    "prism3d.reconstruct": {"stereo": set(), "scan": {"stereo"}, "survey": {"stereo"}},
    "prism3d.datasets": {"models": set(), "database": {"models"}, "simulation": {"models", "database"},
                         "jobs": {"models", "database", "simulation"}, "evaluation": {"models"}},
}
#: folder on disk -> import prefix
FOLDERS = {"prism3d": "prism3d", **{layer: f"prism3d.{layer}" for layer in LAYERS}}


def _module_name(folder: str, path: Path) -> str:
    rel = path.relative_to(ROOT / folder).with_suffix("")
    parts = [p for p in rel.parts if p != "__init__"]
    return ".".join([FOLDERS[folder], *parts])


def _imports(module: str, path: Path) -> list[tuple[int, str]]:
    """(line, imported prism3d module) of every import statement in a file."""
    is_pkg = path.name == "__init__.py"
    package = module if is_pkg else module.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names if a.name.startswith("prism3d")]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.startswith("prism3d"):
                out.append((node.lineno, target))
                # `from package import module` imports the module too
                out += [(node.lineno, f"{target}.{a.name}") for a in node.names]
    return out


def _layer(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in LAYERS else "root"


def violations(files: dict[str, Path]) -> list[str]:
    """Every import that breaks the layer order, as 'file:line module -> target (why)'."""
    rank = {layer: i for i, layer in enumerate(LAYERS)}
    bad = []
    for module, path in files.items():
        src_layer = _layer(module)
        seen = set()  # one report per import statement
        for line, target in _imports(module, path):
            if line in seen:
                continue
            where = f"{path.relative_to(ROOT) if path.is_relative_to(ROOT) else path}:{line} {module} -> {target}"
            if any(target == e or target.startswith(e + ".") for e in ENTRY_POINTS):
                if module not in ENTRY_POINTS:
                    bad.append(f"{where} (library code imports an entry point)")
                    seen.add(line)
                continue
            dst_layer = _layer(target)
            if dst_layer == "root" or module in ENTRY_POINTS:
                continue
            if src_layer == "root":
                bad.append(f"{where} (a shared root module imports a layer)")
                seen.add(line)
            elif rank[dst_layer] > rank[src_layer]:
                bad.append(f"{where} ({src_layer} imports {dst_layer}, to its right)")
                seen.add(line)
    return bad


def _subpackage(module: str) -> tuple[str, str] | None:
    for pkg, subs in SUBPACKAGES.items():
        rest = module[len(pkg) + 1:].split(".")[0] if module.startswith(pkg + ".") else ""
        if rest in subs:
            return pkg, rest
    return None


def subpackage_violations(files: dict[str, Path]) -> list[str]:
    """Imports between a layer's sub-packages against :data:`SUBPACKAGES`."""
    bad = []
    for module, path in files.items():
        src = _subpackage(module)
        if src is None:
            continue
        seen = set()  # one report per import statement
        for line, target in _imports(module, path):
            dst = _subpackage(target)
            if line not in seen and dst and dst[0] == src[0] and dst[1] != src[1] \
                    and dst[1] not in SUBPACKAGES[src[0]][src[1]]:
                seen.add(line)
                bad.append(f"{path.relative_to(ROOT) if path.is_relative_to(ROOT) else path}:{line} "
                           f"{module} -> {target} ({src[1]} imports {dst[1]})")
    return sorted(set(bad))


def untied(files: dict[str, Path]) -> list[str]:
    """Library modules (packages' ``__init__`` aside) that import none of ours and that none of
    ours import: rooms without a door in the drawn graph."""
    edges = {m: {t for _, t in _imports(m, p) if t in files and t != m} for m, p in files.items()}
    imported = set().union(*edges.values())
    return sorted(m for m, p in files.items() if p.name != "__init__.py" and not edges[m] and m not in imported)


def cycles(files: dict[str, Path]) -> list[list[str]]:
    """Groups of library modules that import each other, directly or around a loop
    (Tarjan's strongly connected components over every import, function level included)."""
    graph = {m: sorted({t for _, t in _imports(m, p) if t in files and t != m}) for m, p in files.items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while not group or group[-1] != v:
                group.append(stack.pop())
            if len(group) > 1:
                found.append(sorted(group))

    for v in graph:
        if v not in index:
            visit(v)
    return found


def library_modules(root: Path = ROOT) -> dict[str, Path]:
    return {_module_name(folder, p): p for folder in FOLDERS for p in sorted((root / folder).rglob("*.py"))
            if "__pycache__" not in p.parts}


def test_library_follows_the_layer_order() -> None:
    files = library_modules()
    assert len(files) > 60 and "prism3d.reconstruct.stereo.match" in files  # the whole library was read
    assert violations(files) == []


def test_sub_packages_keep_their_order(tmp_path: Path) -> None:
    """reconstruct's scan and survey build on stereo; neither imports the other (and the
    check catches a planted stereo -> survey import, relative or absolute)."""
    assert subpackage_violations(library_modules()) == []
    bad, ok = tmp_path / "bad.py", tmp_path / "ok.py"
    bad.write_text("from prism3d.reconstruct.survey import run\nfrom ..scan import stitch\n")
    ok.write_text("from prism3d.reconstruct.stereo import match\nfrom . import pair\n")
    found = subpackage_violations({"prism3d.reconstruct.stereo.bad": bad, "prism3d.reconstruct.survey.ok": ok})
    assert len(found) == 2 and "(stereo imports survey)" in found[0] and "(stereo imports scan)" in found[1], found


def test_every_library_module_is_tied_to_the_graph() -> None:
    assert untied(library_modules()) == []


def test_no_import_cycles_between_modules() -> None:
    """A function-level import can hide a cycle from Python; not from this test."""
    assert cycles(library_modules()) == []


def private_imports(files: dict[str, Path]) -> list[str]:
    """``from other_module import _name`` of a private function or class (a package's
    private *modules*, like ``_match_kernels``, may be imported by their package)."""
    bad = []
    for module, path in files.items():
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not isinstance(node, ast.ImportFrom):
                continue
            base = package.split(".")
            target = ".".join(base[: len(base) - node.level + 1] + ([node.module] if node.module else [])) \
                if node.level else (node.module or "")
            if not target.startswith("prism3d") or target == module:
                continue
            for a in node.names:
                if a.name.startswith("_") and not a.name.startswith("__") and f"{target}.{a.name}" not in files:
                    bad.append(f"{path.relative_to(ROOT) if path.is_relative_to(ROOT) else path}:{node.lineno} "
                               f"imports {target}.{a.name}")
    return bad


def test_private_helpers_stay_in_their_module() -> None:
    """A helper another module needs is public (named without ``_``) or moves."""
    assert private_imports(library_modules()) == []


def test_a_planted_violation_is_caught(tmp_path: Path) -> None:
    """The check itself: a capture module importing atr, a root module importing a layer,
    a library module importing the CLI -- inside a function, relative and absolute."""
    cap = tmp_path / "capture_bad.py"
    cap.write_text("def f():\n    from ..atr import chips\n    return chips\n")
    root_mod = tmp_path / "root_bad.py"
    root_mod.write_text("import prism3d.reconstruct.stereo.match\n")
    cli_user = tmp_path / "cli_user.py"
    cli_user.write_text("from prism3d.cli import main\n")
    ok = tmp_path / "ok.py"
    ok.write_text("from prism3d.capture.rig import StereoRig\nfrom . import match\n")
    found = violations({"prism3d.capture.bad": cap, "prism3d.io.bad": root_mod,
                        "prism3d.atr.uses_cli": cli_user, "prism3d.reconstruct.ok": ok})
    assert len(found) == 3, found
    assert "capture imports atr" in found[0]
    assert "shared root module imports a layer" in found[1]
    assert "imports an entry point" in found[2]
    a, b = tmp_path / "a.py", tmp_path / "b.py"
    a.write_text("def f():\n    from prism3d.atr import b\n")
    b.write_text("from . import a\n")
    assert cycles({"prism3d.atr.a": a, "prism3d.atr.b": b, "prism3d.reconstruct.ok": ok}) == [
        ["prism3d.atr.a", "prism3d.atr.b"]]
    (tmp_path / "_kern.py").write_text("")
    b.write_text("from prism3d.atr.a import _helper\nfrom . import _kern\n")
    found = private_imports({"prism3d.atr.a": a, "prism3d.atr.b": b, "prism3d.atr._kern": tmp_path / "_kern.py"})
    assert len(found) == 1 and found[0].endswith("imports prism3d.atr.a._helper"), found
