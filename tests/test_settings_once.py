"""Every setting is stated once: a stage's config dataclass (its spec.py) is the one source of its defaults.

- The YAML of a stage variant (conf/stages/<node>/<variant>.yaml, conf/source/*.yaml, conf/template/*.yaml) states
  only what differs from those defaults.
- No library code of a stage (its plugin package, and the energy library the solves share) gives a default of its
  own to a setting of the same name that differs from the config's: tests and benchmarks that call the library
  directly then run the pipeline's settings, not others that drifted.
"""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import yaml

from eventcap.core.registry import load_registry

ROOT = Path(__file__).resolve().parents[1]


def _defaults(spec) -> dict:
    out = {}
    for f in dataclasses.fields(spec.config):
        if f.default is not dataclasses.MISSING:
            out[f.name] = f.default
        elif f.default_factory is not dataclasses.MISSING:
            out[f.name] = f.default_factory()
    return out


def _stage_of(path: Path, data: dict) -> tuple[str, dict]:
    """The stage a variant file configures and its own keys (following `defaults: [<sibling>]`)."""
    node = data["stages"]["detect"] if "stages" in data else data
    if "stage" in node:
        return node["stage"], node
    first = data["defaults"][0]
    base = path.parent / f"{first}.yaml" if not first.startswith("/") else ROOT / "conf" / f"{first.split('@')[0].lstrip('/')}.yaml"
    return _stage_of(base, yaml.safe_load(base.read_text()))[0], node


def test_stage_yaml_states_only_what_differs_from_the_spec():
    reg = load_registry()
    restated = []
    files = [*(ROOT / "conf" / "stages").glob("*/*.yaml"), *(ROOT / "conf" / "source").glob("*.yaml"),
             *(ROOT / "conf" / "template").glob("*.yaml")]
    for path in sorted(files):
        data = yaml.safe_load(path.read_text()) or {}
        stage, node = _stage_of(path, data)
        d = _defaults(reg.get(stage))
        for key, value in node.items():
            if key in ("stage", "defaults"):
                continue
            assert key in d, f"{path.relative_to(ROOT)}: {key!r} is no key of stage {stage!r}"
            if value == d[key] or (isinstance(d[key], tuple) and list(d[key]) == value):
                restated.append(f"{path.relative_to(ROOT)}: {key}: {value!r} (the spec's default)")
    assert not restated, "YAML restates defaults:\n" + "\n".join(restated)


def _literal(node: ast.AST, constants: dict):
    try:
        return ast.literal_eval(node)
    except ValueError:
        if isinstance(node, ast.Name) and node.id in constants:
            return constants[node.id]
        raise


def _library_defaults(path: Path):
    """(qualified place, name, default) of every dataclass field and keyword default with a literal value (or a
    module constant) in one source file."""
    tree = ast.parse(path.read_text())
    constants = {}
    for st in tree.body:
        if isinstance(st, ast.Assign) and len(st.targets) == 1 and isinstance(st.targets[0], ast.Name):
            try:
                constants[st.targets[0].id] = ast.literal_eval(st.value)
            except ValueError:
                pass
    for node in ast.walk(tree):
        pairs = []
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            a = node.args
            pos = (a.posonlyargs + a.args)[len(a.posonlyargs) + len(a.args) - len(a.defaults):]
            pairs = list(zip(pos, a.defaults)) + [(x, d) for x, d in zip(a.kwonlyargs, a.kw_defaults) if d]
            pairs = [(x.arg, d) for x, d in pairs]
        elif isinstance(node, ast.ClassDef):
            pairs = [(st.target.id, st.value) for st in node.body if isinstance(st, ast.AnnAssign)
                     and st.value is not None and isinstance(st.target, ast.Name)]
        for name, d in pairs:
            try:
                yield f"{path.relative_to(ROOT)}:{node.lineno} {node.name}", name, _literal(d, constants)
            except ValueError:
                continue


def _same_kind(a, b) -> bool:
    """Two defaults of one setting: the same kind of value (a name reused for another thing, e.g. a direction sign
    1 against the tracker's 'both', or None for 'not given', is another setting)."""
    num = (int, float)
    if isinstance(a, bool) or isinstance(b, bool):
        return isinstance(a, bool) and isinstance(b, bool)
    return (isinstance(a, num) and isinstance(b, num)) or type(a) is type(b) or (
        isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)))


def test_no_setting_has_a_second_default_that_differs():
    reg = load_registry()
    energy = sorted((ROOT / "eventcap" / "energy").glob("*.py"))
    found = []
    for spec in reg.specs():
        package = ROOT / "plugins" / spec.run.split(".")[0]
        if not package.is_dir():
            continue
        d = _defaults(spec)
        files = [p for p in sorted(package.glob("*.py")) if p.name != "spec.py"]
        if spec.kind in ("solve", "refine"):
            files += energy
        for path in files:
            for where, name, value in _library_defaults(path):
                if name in d and _same_kind(value, d[name]) and value != d[name] \
                        and not (isinstance(d[name], tuple) and list(d[name]) == value):
                    found.append(f"{where}: {name}={value!r}, but stage {spec.name!r} states {d[name]!r}")
    assert not found, "settings stated twice with different values:\n" + "\n".join(sorted(set(found)))
