"""``eventcap run --help``: what a user can set, for the pipeline the given overrides compose.

The config groups a user chooses from (the chosen option marked), the pipeline's nodes in the order they run with
the stage each runs, where its settings live (the key) and the group that picks its stage, and the top-level
settings with their meaning (from conf/config.yaml's comments). Not the composed config: that is ``--cfg job``.
Groups that only tools read (``stage``: the stages' own defaults, ``benchmark``: ``eventcap benchmark``'s presets,
``hydra``) and the ``stages/<x>`` groups of nodes the pipeline does not run are left out.
"""

from __future__ import annotations

import re
import textwrap
from pathlib import Path
from typing import Any

#: Config groups a run is composed from, in the order shown, with what each chooses.
USER_GROUPS = (("pipeline", "the DAG of nodes"),
               ("source", "where the recording comes from"),
               ("template", "the actor's body model"),
               ("executor", "where batches run"),
               ("experiment", "presets (e.g. experiment=quick: a short capture)"))
WIDTH = 110


def _options(loader, group: str, chosen: str | None) -> str:
    opts = loader.get_group_options(group)
    return " | ".join(f"*{o}" if o == chosen else o for o in opts)


def _config_file(loader, group: str, name: str) -> str:
    """Where config ``group/name`` comes from: the project's conf/..., or an installed package's file."""
    for source in loader.get_sources():
        if source.is_config(f"{group}/{name}"):
            if source.provider == "main":
                return f"conf/{group}/{name}.yaml"
            return f"{source.path}/{group}/{name}.yaml, from {source.provider}"
    return f"conf/{group}/{name}.yaml"


def _top_level_settings(config_yaml: Path) -> list[tuple[str, str, str]]:
    """(key, value, comment) of conf/config.yaml's top-level settings (not its defaults list, stages or hydra)."""
    rows = []
    for line in config_yaml.read_text().splitlines():
        m = re.match(r"^([a-z_]+):\s*([^#]*?)\s*(?:#\s*(.*))?$", line)
        if m and m.group(1) not in ("defaults", "stages", "hydra"):
            rows.append((m.group(1), m.group(2), m.group(3) or ""))
    return rows


def _wrap(text: str, indent: int, hang: int = 2) -> list[str]:
    return textwrap.wrap(text, WIDTH, initial_indent=" " * indent, subsequent_indent=" " * (indent + hang))


def run_help(overrides: list[str], cdir: str | Path) -> str:
    """The text of ``eventcap run [overrides] --help``. Raises what composing the overrides raises."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import OmegaConf

    from eventcap.core.pipeline import build_pipeline
    from eventcap.core.registry import load_registry

    cdir = Path(cdir)
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(cdir), version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides, return_hydra_config=True)
        loader = GlobalHydra.instance().config_loader()
        choices = dict(cfg.hydra.runtime.choices)
        data: dict[str, Any] = OmegaConf.to_container(cfg, resolve=False)
        data.pop("hydra", None)
        nodes = build_pipeline(OmegaConf.to_container(OmegaConf.create(data), resolve=True), load_registry())
        stage_groups = set(loader.list_groups("stages"))
        out = ["usage: eventcap run [GROUP=OPTION | KEY=VALUE ...] [--cfg job] [-m]",
               "Runs a pipeline on a recording (by default a synthetic capture, with its ground truth) into",
               "runs/<name>/<timestamp>/. Keys of the source may be given bare: duration_s=1 means source.duration_s=1.",
               "", "Config groups (GROUP=OPTION; * marks the chosen one):"]
        for group, what in USER_GROUPS:
            out += _wrap(f"{group:<11} {what}: {_options(loader, group, choices.get(group))}", 2, 12)
        pipeline = choices.get("pipeline") or "?"
        out += [""] + textwrap.wrap(f"Pipeline {pipeline} ({_config_file(loader, 'pipeline', pipeline)}): its nodes "
                                    "in the order they run, the stage each runs, where its settings live "
                                    "(KEY.<setting>=VALUE) and the group that picks its stage:", WIDTH,
                                    break_on_hyphens=False, break_long_words=False)
        rows = []
        for node in nodes:
            group = node.config_path.replace(".", "/")
            picks = (f"{group}={_options(loader, group, choices.get(group))}" if
                     group in USER_GROUPS_NAMES or group.partition("/")[2] in stage_groups else "")
            rows.append((node.name, node.spec.name, node.config_path, picks))
        rows.insert(0, ("node", "stage", "settings", "stage picked by"))
        w = [max(len(r[i]) for r in rows) for i in range(3)]
        indent = 2 + w[0] + 2 + w[1] + 2 + w[2] + 2
        for n, s, k, p in rows:  # the last column wrapped under itself
            lines = textwrap.wrap(p, max(20, WIDTH - indent), subsequent_indent="  ") or [""]
            out.append(f"  {n:<{w[0]}}  {s:<{w[1]}}  {k:<{w[2]}}  {lines[0]}".rstrip())
            out += [" " * indent + line for line in lines[1:]]
        if choices.get("source") == "recording":
            from eventcap.apps.compose import FRAMELESS_PIPELINE, REAL_DETECTOR, ground_truth_detect_nodes

            for name in ground_truth_detect_nodes(data):
                out.append(f"On a file without ground truth the run takes stages/{name}={REAL_DETECTOR} by itself, "
                           f"unless stages/{name}=... is given.")
            if "pipeline" not in {o.partition("=")[0].lstrip("+~") for o in overrides}:
                out.append(f"On a file without intensity frames it takes pipeline={FRAMELESS_PIPELINE} by itself.")
        example = next((n.spec.name for n in nodes if n.name == "solve"), nodes[-1].spec.name if nodes else "")
        out.append(f"A stage's settings, their defaults and meaning: eventcap stages STAGE (e.g. eventcap stages "
                   f"{example}).")
    out += ["", "Top-level settings (conf/config.yaml):"]
    resolved = OmegaConf.to_container(OmegaConf.create(data), resolve=True)
    for key, value, comment in _top_level_settings(cdir / "config.yaml"):
        value = resolved.get(key, value)
        if isinstance(value, dict):
            comment += f"; its keys: eventcap run --cfg job --package {key}"
        shown = f"{key}.*" if isinstance(value, dict) else \
            f"{key}={OmegaConf.to_yaml(OmegaConf.create({'v': value})).partition(':')[2].strip()}"
        out += _wrap(f"{shown:<24} {comment}", 2, 25)
    out += ["", "More:",
            "  eventcap run [overrides] --cfg job      the composed config, every key and value",
            "  eventcap run -m KEY=A,B ...             a sweep; eventcap report runs/<name>/multirun_<ts>/ tabulates it",
            "  eventcap run --hydra-help               Hydra's own flags",
            "Examples:",
            "  eventcap run experiment=quick",
            "  eventcap run source=recording source.path=rec.aedat4 template.height_m=1.75",
            "  eventcap run pipeline=paper stages/solve=batch"]
    return "\n".join(out)


USER_GROUPS_NAMES = {g for g, _ in USER_GROUPS}
