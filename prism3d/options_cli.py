"""Command-line options drawn from the options dataclasses: each default lives once, in
its dataclass field, and an option's help is the field's docstring.

The fields are read from the dataclass's source (``ast``), not by importing its module,
so building the parser stays instant (``prism3d --help`` loads no command). An option
left off the command line is absent from the parsed namespace, and the dataclass's own
default applies.
"""

from __future__ import annotations

import argparse
import ast
import functools
import importlib.util
import re
from pathlib import Path
from typing import Any

__all__ = ["field_option", "given_fields"]

#: A dataclass as (module, class name), e.g. ("prism3d.reconstruct.survey.model", "SurveyOptions").
Where = tuple[str, str]
#: The fields each dataclass has flags for (a command's other arguments may share a field's
#: name without setting it: `stitch --mesh FILE` is no StitchOptions.mesh).
_DECLARED: dict[Where, set[str]] = {}


#: A field whose default is no literal (a factory): no flag can show it.
_NOT_LITERAL = object()


@functools.cache
def _module_tree(module: str) -> ast.Module:
    """The parsed source of ``module``, found without running any package's ``__init__``
    below the top two levels (``prism3d.datasets`` imports the built-in targets)."""
    parts = module.split(".")
    spec = importlib.util.find_spec(".".join(parts[:2]))
    if spec is None or (spec.origin is None and not spec.submodule_search_locations):
        raise RuntimeError(f"options: no source for {module}")
    if not spec.submodule_search_locations:  # prism3d.<module>
        path = Path(str(spec.origin))
    else:
        base = Path(next(iter(spec.submodule_search_locations))).joinpath(*parts[2:])
        path = base / "__init__.py" if base.is_dir() else base.with_suffix(".py")
    return ast.parse(path.read_text(encoding="utf-8"))


def _constant(module: str, name: str) -> Any:
    """The literal a module-level constant ``name`` of ``module`` holds, following
    ``from M import name``; _NOT_LITERAL when it holds none."""
    tree = _module_tree(module)
    for st in tree.body:
        if isinstance(st, ast.Assign) and any(isinstance(t, ast.Name) and t.id == name for t in st.targets):
            return _literal(module, st.value)
        if isinstance(st, ast.ImportFrom) and st.level == 0 and st.module and \
                any((a.asname or a.name) == name for a in st.names):
            real = next(a.name for a in st.names if (a.asname or a.name) == name)
            return _constant(st.module, real)
    return _NOT_LITERAL


def _literal(module: str, node: ast.expr) -> Any:
    if isinstance(node, ast.Name):
        return _constant(module, node.id)
    try:
        return ast.literal_eval(node)
    except ValueError:
        return _NOT_LITERAL


@functools.cache
def _fields(where: Where) -> dict[str, tuple[Any, str]]:
    """Field name -> (default, docstring on one line) of the dataclass ``where``, read from
    its source (a default is a literal or a module constant holding one, here or imported)."""
    module, name = where
    tree = _module_tree(module)
    node = next((n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == name), None)
    if node is None:
        raise RuntimeError(f"options: no class {name} in {module}")
    out: dict[str, tuple[Any, str]] = {}
    for st, nxt in zip(node.body, [*node.body[1:], None], strict=True):
        if not (isinstance(st, ast.AnnAssign) and isinstance(st.target, ast.Name) and st.value is not None):
            continue
        doc = nxt.value.value if isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant) \
            and isinstance(nxt.value.value, str) else ""
        out[st.target.id] = (_literal(module, st.value), " ".join(doc.split()))
    return out


def _plain(doc: str) -> str:
    """A docstring as terminal help: Sphinx roles and literals as plain words, and a None
    default described as the default."""
    doc = re.sub(r":\w+:`~?(?:[\w.]*\.)?([^`.]+)`", r"\1", doc)
    doc = doc.replace("``", "")
    return re.sub(r"\bNone: ", "default: ", doc)


def _shown(value: Any) -> str:
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, (tuple, list)):
        return " ".join(str(v) for v in value)
    return f"{value:g}" if isinstance(value, float) else str(value)


def field_option(p: argparse.ArgumentParser, where: Where, name: str, *flags: str, note: str = "",
                 **kw: Any) -> None:
    """Add ``flags`` setting the field ``name`` of the dataclass ``where``: help from the
    field's docstring with its default appended (a None default is explained by the
    docstring itself) and then ``note`` (what the flag means elsewhere in the command), no
    argparse default (the dataclass's applies); ``kw`` as for ``add_argument`` (type,
    choices, nargs, action, metavar)."""
    default, doc = _fields(where)[name]
    if default is _NOT_LITERAL:
        raise RuntimeError(f"options: {where[1]}.{name} has no literal default to show")
    if not doc:
        raise RuntimeError(f"options: {where[1]}.{name} has no docstring to show as help")
    text = _plain(doc) if default is None or default == () else f"{_plain(doc)} (default: {_shown(default)})"
    text = f"{text}; {note}" if note else text
    p.add_argument(*flags, dest=name, default=argparse.SUPPRESS, help=text.replace("%", "%%"), **kw)
    _DECLARED.setdefault(where, set()).add(name)


def given_fields(args: argparse.Namespace, where: Where) -> dict[str, Any]:
    """The fields of the dataclass ``where`` given on the command line (by their
    :func:`field_option` flags), by name."""
    return {k: getattr(args, k) for k in _DECLARED.get(where, ()) if hasattr(args, k)}
