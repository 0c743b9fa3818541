"""Every artifact type is importable from eventcap.artifacts and listed with its fields on docs/artifacts.md, which is
made from the dataclasses (``python -m eventcap.artifacts.reference > docs/artifacts.md``)."""

from __future__ import annotations

import ast

import eventcap.artifacts as artifacts
from eventcap.artifacts.reference import markdown, section
from helpers.paths import ROOT


def test_the_page_is_made_from_the_dataclasses():
    page = (ROOT / "docs" / "artifacts.md").read_text()
    assert page == markdown(), ("docs/artifacts.md differs from the artifact dataclasses: run "
                                "python -m eventcap.artifacts.reference > docs/artifacts.md")


def test_every_artifact_class_of_the_code_is_exported_and_on_the_page():
    declared = set()
    for base in ("eventcap", "plugins"):
        for p in (ROOT / base).rglob("*.py"):
            for node in ast.walk(ast.parse(p.read_text())):
                if isinstance(node, ast.ClassDef) and any(getattr(b, "id", None) == "Artifact" for b in node.bases):
                    declared.add(node.name)
    exported = {t.__name__ for t in artifacts.TYPES}
    assert declared == exported, f"not in eventcap.artifacts.TYPES: {sorted(declared - exported)}"
    assert all(getattr(artifacts, name).__name__ == name for name in exported)
    assert set(artifacts.__all__) >= exported | {"Artifact", "array", "attr", "Batch"}
    page = (ROOT / "docs" / "artifacts.md").read_text()
    assert all(f"\n## {name}\n" in page for name in exported)


def test_every_port_of_every_installed_stage_has_an_exported_type():
    from eventcap.core.registry import load_registry

    types = set(artifacts.TYPES)
    missing = [f"{spec.name}.{port}: {p.type.__name__}" for spec in load_registry().specs()
               for port, p in {**spec.inputs, **spec.outputs}.items() if p.type not in types]
    assert not missing, missing


def test_a_section_lists_every_field_with_its_declaration():
    lines = section(artifacts.PoseSequence)
    assert lines[0] == "## PoseSequence"
    rows = {line.split("|")[1].strip(" `"): line for line in lines if line.startswith("| `")}
    assert set(rows) == {"t_us", "poses", "sigma_mm", "status", "iterations", "energies"}
    assert "| array | `float64[f, 33]` | rad, m; nan: not estimated (a gap) |" in rows["poses"]
    assert "optional" in rows["sigma_mm"] and "| attr | `int` |" in rows["iterations"]
    rec = {line.split("|")[1].strip(" `"): line for line in section(artifacts.Recording) if line.startswith("| `")}
    assert "[FrameStack](#framestack) or None" in rec["frames"] and " or None" not in rec["camera"]
