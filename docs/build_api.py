"""Generate docs/api.md, the API reference, from the docstrings of the jaxatt package.

    python docs/build_api.py            # write docs/api.md
    python docs/build_api.py --check    # exit 1 if docs/api.md is not what the docstrings give
    python docs/build_api.py --stdout   # print instead of writing

Every importable public module of ``jaxatt`` (no leading underscore; ``jaxatt.__main__`` and ``jaxatt.cli``'s
internals excluded) is listed with the first paragraph of its docstring, then each public name: those in the
module's ``__all__`` in that order, or else the functions and classes defined in the module (not imported),
sorted. For a callable: its signature and the first paragraph of its docstring; for a NamedTuple: its fields;
for another class: its public methods; for a constant: its type and a short repr. The output is deterministic
(sorted modules, no dates or memory addresses), so the file can be checked in CI. A module that fails to
import is listed under "Not importable" with the error's first line.
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import pkgutil
import re
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
OUT = HERE / "api.md"
SKIP = {"jaxatt.__main__"}
_ADDR = re.compile(r" at 0x[0-9a-fA-F]+")
_ANNOT = re.compile(r"(: |-> )'([^']*)'")  # stringified annotations (from __future__ import annotations)
_ROLE = re.compile(r":(?:func|class|mod|data|meth|attr):`~?([^`]+)`")


def rst_to_md(text: str) -> str:
    """Sphinx roles and ``literals`` as Markdown code spans."""
    return _ROLE.sub(r"`\1`", text).replace("``", "`")


def first_paragraph(doc: str | None) -> str:
    if not doc:
        return ""
    para = []
    for line in inspect.cleandoc(doc).splitlines():
        if not line.strip():
            if para:
                break
            continue
        para.append(line.strip())
    return rst_to_md(" ".join(para))


def _clean(s: str) -> str:
    return _ADDR.sub("", s)


def signature(obj) -> str:
    try:
        return _ANNOT.sub(r"\1\2", _clean(str(inspect.signature(obj))))
    except (TypeError, ValueError):
        return "(...)"


def _is_namedtuple(obj) -> bool:
    return inspect.isclass(obj) and issubclass(obj, tuple) and hasattr(obj, "_fields")


def module_names(package: str = "jaxatt") -> list:
    pkg = importlib.import_module(package)
    names = [package]
    for info in pkgutil.walk_packages(pkg.__path__, prefix=package + "."):
        leaf = info.name.rsplit(".", 1)[-1]
        if leaf.startswith("_") or info.name in SKIP:
            continue
        names.append(info.name)
    return sorted(set(names), key=lambda n: (n != package, n))


def public_names(mod) -> list:
    names = getattr(mod, "__all__", None)
    if names is not None:
        return [n for n in names if hasattr(mod, n)]
    out = []
    for n, obj in vars(mod).items():
        if n.startswith("_"):
            continue
        if (inspect.isfunction(obj) or inspect.isclass(obj)) and getattr(obj, "__module__", None) == mod.__name__:
            out.append(n)
    return sorted(out)


def _anchor(title: str) -> str:
    return re.sub(r"[^a-z0-9 _-]", "", title.lower()).replace(" ", "-")


def document_object(name: str, obj) -> list:
    lines = []
    if _is_namedtuple(obj):
        lines.append(f"#### `{name}` (NamedTuple)")
        doc = first_paragraph(obj.__doc__)
        if doc and not doc.startswith(f"{name}("):
            lines.append(doc)
        defaults = getattr(obj, "_field_defaults", {})
        fields = ", ".join(
            f"`{f}`" + (f" = `{_clean(repr(defaults[f]))}`" if f in defaults else "") for f in obj._fields
        )
        lines.append(f"Fields: {fields}.")
        methods = [
            m
            for m, v in vars(obj).items()
            if not m.startswith("_") and (inspect.isfunction(v) or isinstance(v, property))
        ]
        if methods:
            lines.append("Methods / properties: " + ", ".join(f"`{m}`" for m in sorted(methods)) + ".")
    elif inspect.isclass(obj):
        lines.append(f"#### `{name}{signature(obj)}` (class)")
        doc = first_paragraph(obj.__doc__)
        if doc:
            lines.append(doc)
        for m, v in sorted(vars(obj).items()):
            if m.startswith("_") or not (inspect.isfunction(v) or isinstance(v, (staticmethod, classmethod))):
                continue
            fn = v.__func__ if isinstance(v, (staticmethod, classmethod)) else v
            d = first_paragraph(fn.__doc__)
            lines.append(f"- `{m}{signature(fn)}`" + (f": {d}" if d else ""))
    elif callable(obj):
        lines.append(f"#### `{name}{signature(obj)}`")
        doc = first_paragraph(getattr(obj, "__doc__", None))
        if doc:
            lines.append(doc)
    elif inspect.ismodule(obj):
        lines.append(f"#### `{name}` (module `{obj.__name__}`)")
    else:
        r = _clean(repr(obj))
        if len(r) > 100:
            r = r[:97] + "..."
        lines.append(f"#### `{name}` ({type(obj).__name__})")
        lines.append(f"`{r}`")
    return lines


def build() -> str:
    import jaxatt

    mods, failed = [], []
    for name in module_names():
        try:
            mods.append(importlib.import_module(name))
        except Exception as e:  # a module under construction must not break the reference
            msg = str(e).strip().splitlines()[0] if str(e).strip() else ""
            failed.append((name, f"{type(e).__name__}: {msg}"))
    out = [
        "# API reference",
        "",
        f"Generated by `docs/build_api.py` from the docstrings of jaxatt {jaxatt.__version__}: do not edit by "
        "hand; run `python docs/build_api.py` after changing a docstring. Each entry shows the signature and "
        "the first paragraph of the docstring; the full text is in the source (or `help(...)`). Conventions "
        "and concepts: [concepts.md](concepts.md).",
        "",
        "## Modules",
        "",
    ]
    for m in mods:
        summary = first_paragraph(m.__doc__)
        summary = summary if len(summary) <= 140 else summary[:137] + "..."
        out.append(f"- [`{m.__name__}`](#{_anchor(m.__name__)}): {summary}")
    out.append("")
    for m in mods:
        out += [f"## {m.__name__}", ""]
        doc = first_paragraph(m.__doc__)
        if doc:
            out += [doc, ""]
        names = public_names(m)
        if not names and hasattr(m, "__path__"):
            subs = sorted(
                n for n, v in vars(m).items() if inspect.ismodule(v) and v.__name__.startswith(m.__name__ + ".")
            )
            alias = sorted(
                (n, v)
                for n, v in vars(m).items()
                if not n.startswith("_") and not inspect.ismodule(v) and (inspect.isclass(v) or inspect.isfunction(v))
            )
            if subs:
                out += [
                    "Submodules: "
                    + ", ".join(f"[`{m.__name__}.{n}`](#{_anchor(m.__name__ + '.' + n)})" for n in subs)
                    + ".",
                    "",
                ]
            if alias:
                out += [
                    "Shortcuts: "
                    + ", ".join(f"`{m.__name__}.{n}` = `{v.__module__}.{v.__qualname__}`" for n, v in alias)
                    + ".",
                    "",
                ]
            continue
        if not names:
            out += ["(no public names)", ""]
        for n in names:
            out += document_object(n, getattr(m, n))
            out.append("")
    if failed:
        out += ["## Not importable", "", "These modules failed to import when this file was generated:", ""]
        out += [f"- `{n}`: {e}" for n, e in failed]
        out.append("")
    return "\n".join(out).rstrip() + "\n"


README = HERE.parent / "README.md"
BEGIN, END = "<!-- observers table: python docs/build_api.py -->", "<!-- end of observers table -->"


def readme_with_observers() -> str:
    """README.md with the block between the markers replaced by the registry's table."""
    from jaxatt.observers import registry

    text = README.read_text(encoding="utf-8")
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    return f"{head}{BEGIN}\n{registry.markdown_table()}\n{END}{tail}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Generate docs/api.md from jaxatt's docstrings.")
    ap.add_argument("--check", action="store_true", help="exit 1 if docs/api.md is out of date")
    ap.add_argument("--stdout", action="store_true", help="print the reference instead of writing it")
    args = ap.parse_args(argv)
    readme = readme_with_observers()
    text = build()
    if args.stdout:
        sys.stdout.write(text)
        return 0
    if args.check:
        if not OUT.exists() or OUT.read_text(encoding="utf-8") != text:
            print("docs/api.md is out of date: run python docs/build_api.py", file=sys.stderr)
            return 1
        if README.read_text(encoding="utf-8") != readme:
            print("README.md's observers table is out of date: run python docs/build_api.py", file=sys.stderr)
            return 1
        return 0
    OUT.write_text(text, encoding="utf-8")
    README.write_text(readme, encoding="utf-8")
    print(f"wrote {OUT} ({len(text.splitlines())} lines)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
