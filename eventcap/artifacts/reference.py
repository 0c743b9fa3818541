"""The reference page of the artifact types, docs/artifacts.md, made from their dataclasses.

    python -m eventcap.artifacts.reference > docs/artifacts.md

``tests/test_artifacts_reference.py`` fails while the page differs from what this prints, so the page is the code's.
"""

from __future__ import annotations

import dataclasses
import inspect
import textwrap

import numpy as np

from eventcap.artifact import Artifact

from . import TYPES

HEADER = """# Artifacts: the data between stages

Every type a stage declares its ports with, and what each holds. Import them from `eventcap.artifacts`
(`from eventcap.artifacts import PoseSequence`). Each is a frozen dataclass: its arrays are checked against the
declared dtype and dimensions when it is made (a dimension named twice must have one size; one named after an
integer attribute must equal it), they are read-only, and NaN is refused unless the units say `nan`. The runner
writes each output to the cache as a zarr group and reads it back as the same type (`schema_version` is checked).
How to declare a new one: `eventcap/artifact.py`.

This page is made from the dataclasses (`python -m eventcap.artifacts.reference > docs/artifacts.md`; a test keeps
the two in step). Kinds: **array** (a numpy array: dtype[dimensions]), **attr** (a number, string, list or dict in
the group's attributes), **artifact** (another artifact, stored as a sub-group).
"""


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def _dtype(dt: np.dtype) -> str:
    if dt.names:
        return "{" + ", ".join(f"{n}: {dt.fields[n][0].name}" for n in dt.names) + "}"
    return dt.name


def _default(f: dataclasses.Field) -> str:
    if f.default is not dataclasses.MISSING:
        return "" if f.default is None else f"default {f.default!r}"
    if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        return f"default {f.default_factory()!r}" if not hasattr(f.default_factory(), "shape") else "has a default"
    return ""


def section(cls: type[Artifact]) -> list[str]:
    """The page's section of one artifact type: its summary and a table of its fields."""
    doc = inspect.cleandoc(cls.__doc__ or "").split("\n\n")[0]
    lines = [f"## {cls.__name__}", "", f"`{cls.__module__}.{cls.__name__}`, schema version {cls.schema_version}. "
             + _cell(doc), "", "| field | kind | type | units | notes |", "|---|---|---|---|---|"]
    arrays, attrs, children = cls.array_fields(), cls.attr_fields(), cls.child_fields()
    for f in dataclasses.fields(cls):
        if f.name in arrays:
            s = arrays[f.name]
            dims = ", ".join(str(d) for d in s.dims)
            notes = "; ".join(x for x in (s.doc, "optional" if s.optional else "") if x)
            lines.append(f"| `{f.name}` | array | `{_cell(_dtype(s.dtype))}[{dims}]` | {_cell(s.units)} | "
                         f"{_cell(notes)} |")
        elif f.name in attrs:
            s = attrs[f.name]
            notes = "; ".join(x for x in (s.doc, _default(f)) if x)
            lines.append(f"| `{f.name}` | attr | `{_cell(getattr(f.type, '__name__', f.type))}` | {_cell(s.units)} | "
                         f"{_cell(notes)} |")
        else:
            child, optional = children[f.name]
            lines.append(f"| `{f.name}` | artifact | [{child.__name__}](#{child.__name__.lower()})"
                         f"{' or None' if optional else ''} | | |")
    return lines + [""]


def markdown() -> str:
    """docs/artifacts.md as the dataclasses declare it."""
    lines = HEADER.splitlines() + [""]
    lines += textwrap.wrap("Types: " + ", ".join(f"[{t.__name__}](#{t.__name__.lower()})" for t in TYPES) + ".",
                           118, break_on_hyphens=False, break_long_words=False) + [""]
    for t in TYPES:
        lines += section(t)
    return "\n".join(lines).rstrip() + "\n"


if __name__ == "__main__":
    print(markdown(), end="")
