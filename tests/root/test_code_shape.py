"""The library's shape stays readable: no function over 60 lines (the CLI's argument
tables and the numba kernels' loop nests aside), no public function
with more than 8 keyword arguments outside an options object, docstrings at most 15 %
of the library's non-blank lines (the history lives in docs/), and imports of our own
modules at the top of modules (the graph drawn from imports is the real one), except in
the CLI's command dispatch and in _precompile's per-process groups.

Run as a script to see the figures: ``python tests/root/test_code_shape.py [-v] [FILES]``.
"""

from __future__ import annotations

import ast
import sys
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
LIBRARY = ("prism3d", "capture", "reconstruct", "atr", "datasets")
MAX_FUNCTION_LINES = 60
#: Files whose functions may be longer, and why: the CLI declares each command's flags in
#: one table; a numba kernel is one loop nest compiled whole (a call out of it costs).
LONG_FUNCTIONS_ALLOWED = ("prism3d/cli.py", "_kernels.py")
MAX_KEYWORDS = 8
MAX_DOC_SHARE = 0.15
#: Where imports of our own modules may sit inside functions, and why: ``prism3d --help``
#: loads no command; each precompile group's process loads only the kernels it warms up.
LAZY_IMPORTS_ALLOWED = ("prism3d/cli.py", "prism3d/_precompile.py")


@dataclass
class Shape:
    lines: int = 0
    doc_lines: int = 0
    long: list[tuple[int, str]] = field(default_factory=list)  # (length, where)
    keywords: list[tuple[int, str]] = field(default_factory=list)  # (count, where)


def _docstring_node(node: ast.AST) -> ast.Expr | None:
    if not isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
        return None
    body = node.body
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
            and isinstance(body[0].value.value, str):
        return body[0]
    return None


def _is_field_doc(stmt: ast.stmt, prev: ast.stmt | None) -> bool:
    """A string statement right after an annotated field: an attribute docstring."""
    return isinstance(prev, ast.AnnAssign) and isinstance(stmt, ast.Expr) \
        and isinstance(stmt.value, ast.Constant) and isinstance(stmt.value.value, str)


def measure(paths: list[Path], shape: Shape | None = None) -> Shape:
    """Line, docstring, function-length and keyword figures of Python files."""
    s = shape or Shape()
    for p in paths:
        src = p.read_text(encoding="utf-8")
        lines = src.splitlines()
        s.lines += sum(1 for line in lines if line.strip())
        tree = ast.parse(src)
        rel = p.relative_to(ROOT) if p.is_relative_to(ROOT) else p
        for node in ast.walk(tree):
            docs = [_docstring_node(node)]
            if isinstance(node, ast.ClassDef):
                docs += [b for a, b in zip([None, *node.body], node.body) if _is_field_doc(b, a)]
            for d in docs:
                if d is not None:
                    s.doc_lines += sum(1 for line in lines[d.lineno - 1:d.end_lineno] if line.strip())
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES and not str(rel).endswith(LONG_FUNCTIONS_ALLOWED):
                    s.long.append((n, f"{rel}:{node.lineno} {node.name}"))
                nk = len(node.args.kwonlyargs) + len(node.args.defaults)
                if not node.name.startswith("_") and nk > MAX_KEYWORDS:
                    s.keywords.append((nk, f"{rel}:{node.lineno} {node.name}"))
    return s


def library_files() -> list[Path]:
    return sorted(p for d in LIBRARY for p in (ROOT / d).rglob("*.py") if "__pycache__" not in p.parts)


def test_no_function_over_60_lines() -> None:
    s = measure(library_files())
    over = sorted(x for x in s.long if x[0] > MAX_FUNCTION_LINES)
    assert not over, f"functions over {MAX_FUNCTION_LINES} lines: {over}"


def test_public_functions_take_an_options_object_beyond_8_keywords() -> None:
    s = measure(library_files())
    assert not s.keywords, f"public functions with more than {MAX_KEYWORDS} keyword arguments: {s.keywords}"


def test_docstrings_at_most_15_percent() -> None:
    s = measure(library_files())
    assert s.lines > 10_000  # the whole library was measured
    assert s.doc_lines / s.lines <= MAX_DOC_SHARE, f"docstrings {s.doc_lines}/{s.lines} lines"


def function_level_imports(paths: list[Path]) -> list[str]:
    """``file:line module`` of every import of a prism3d module inside a function body."""
    out = []
    for p in paths:
        tree = ast.parse(p.read_text(encoding="utf-8"))
        rel = p.relative_to(ROOT) if p.is_relative_to(ROOT) else p
        for fn in ast.walk(tree):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for n in ast.walk(fn):
                mods = [n.module or ""] if isinstance(n, ast.ImportFrom) and n.level == 0 else \
                    [a.name for a in n.names] if isinstance(n, ast.Import) else []
                out += [f"{rel}:{n.lineno} {m}" for m in mods if m == "prism3d" or m.startswith("prism3d.")]
    return sorted(set(out))


def test_own_imports_at_the_top_of_modules() -> None:
    files = [p for p in library_files() if str(p.relative_to(ROOT)) not in LAZY_IMPORTS_ALLOWED]
    inside = function_level_imports(files)
    assert not inside, f"imports of our own modules inside functions: {inside}"


def test_measure_counts_what_it_says(tmp_path: Path) -> None:
    """The gauge itself: a known file gives known figures."""
    body = "\n".join(f"    x{i} = {i}" for i in range(101))  # a 103-line function
    src = (f'"""Module."""\n\n\ndef f(*, {", ".join(f"a{i}=0" for i in range(9))}):\n'
           f'    """One line."""\n{body}\n')
    p = tmp_path / "m.py"
    p.write_text(src)
    s = measure([p])
    assert s.doc_lines == 2 and s.lines == 1 + 1 + 1 + 101  # module doc, def, doc, body
    assert [n for n, _ in s.long] == [103]
    assert [n for n, _ in s.keywords] == [9]
    q = tmp_path / "lazy.py"
    q.write_text("import prism3d.io\n\n\ndef f():\n    from prism3d.io.ply import read_ply\n    import os\n"
                 "    def g():\n        import prism3d.checks\n")
    assert function_level_imports([q]) == [f"{q}:5 prism3d.io.ply", f"{q}:8 prism3d.checks"]


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if a != "-v"]
    files = [Path(a).resolve() for a in args] or library_files()
    s = measure(files)
    print(f"docstrings {s.doc_lines}/{s.lines} = {s.doc_lines / max(s.lines, 1):.3f}")
    print(f"functions > {MAX_FUNCTION_LINES} lines: {len(s.long)}; "
          f"public with > {MAX_KEYWORDS} keywords: {len(s.keywords)}")
    if "-v" in sys.argv:
        for n, where in sorted(s.long, reverse=True):
            print(f"  {n:4d} lines  {where}")
        for n, where in sorted(s.keywords, reverse=True):
            print(f"  {n:4d} kw     {where}")
