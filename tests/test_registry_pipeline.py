"""Stage discovery, unknown names with suggestions, and DAG validation errors that name the node."""

from __future__ import annotations

import ast
import subprocess
import sys

import pytest

from eventcap.core.config import ConfigError, build_config
from eventcap.core.pipeline import PipelineError, build_pipeline
from eventcap.core.registry import UnknownStageError, load_registry

from helpers.paths import ROOT
from helpers.toy import toy_env


def test_discovery_through_env_override(toy):
    reg = load_registry()
    assert {"toy_signal", "toy_smooth", "toy_scale", "toy_sum"} <= set(reg.names())
    assert reg.get("toy_smooth").per_batch and not reg.get("toy_sum").per_batch
    assert "EVENTCAP_STAGES" in reg.get("toy_sum").origin


def test_unknown_stage_did_you_mean(toy):
    with pytest.raises(UnknownStageError) as exc:
        load_registry().get("toy_smoth")
    msg = str(exc.value)
    assert "no stage named 'toy_smoth'" in msg and "did you mean 'toy_smooth'" in msg
    assert "Available: " in msg and "toy_signal" in msg


def test_broken_plugin_is_reported_not_fatal(toy, monkeypatch):
    monkeypatch.setenv("EVENTCAP_STAGES", "toy_stages:SPECS,no_such_module_xyz:SPEC")
    reg = load_registry()
    assert "toy_sum" in reg
    assert any("no_such_module_xyz" in p for p in reg.problems)


def test_stages_command_lists_without_importing_solvers():
    code = (
        "import sys; from eventcap.apps.cli import main; main(['stages']); "
        "heavy = [m for m in ('casadi', 'cv2', 'scipy.optimize', 'numba', 'zarr', 'trimesh') if m in sys.modules]; "
        "print('HEAVY', heavy)"
    )
    out = subprocess.run([sys.executable, "-c", code], env=toy_env(), capture_output=True, text=True, check=True)
    assert "toy_smooth" in out.stdout and "per-batch moving average" in out.stdout
    assert "HEAVY []" in out.stdout, out.stdout


def test_core_imports_no_plugin_module():
    offenders = []
    for path in (ROOT / "eventcap").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            for n in names:
                top = n.split(".")[0]
                if top == "plugins" or (top.startswith("eventcap_")):
                    offenders.append(f"{path.relative_to(ROOT)}: {n}")
    plugin_pkgs = {p.name for p in (ROOT / "plugins").iterdir() if (p / "__init__.py").exists()} if (ROOT / "plugins").exists() else set()
    assert all(p.startswith("eventcap_") for p in plugin_pkgs), plugin_pkgs
    assert offenders == []


# -- pipeline validation -------------------------------------------------------------------------------------------
def problems(cfg) -> list[str]:
    with pytest.raises(PipelineError) as exc:
        build_pipeline(cfg, load_registry())
    return exc.value.problems


def test_valid_pipeline_is_topologically_ordered(toy_cfg):
    nodes = build_pipeline(toy_cfg(), load_registry())
    assert [n.name for n in nodes] == ["signal", "smooth", "scale", "total"]
    assert nodes[1].plan_node == "signal" and nodes[2].plan_node == "signal" and nodes[3].plan_node is None


def test_unknown_stage_names_node(toy_cfg):
    cfg = toy_cfg(scale={"stage": "toy_scal"})
    [p] = problems(cfg)
    assert p.startswith("node 'scale' (stages.scale.stage): no stage named 'toy_scal'") and "did you mean 'toy_scale'" in p


def test_unknown_input_port_and_upstream(toy_cfg):
    cfg = toy_cfg()
    cfg["pipeline"]["nodes"]["scale"]["inputs"] = {"chunks": "smooth.chunk"}
    cfg["pipeline"]["nodes"]["total"]["inputs"] = {"chunks": "scal.chunk"}
    ps = problems(cfg)
    assert any("node 'scale': no input port named 'chunks'" in p and "did you mean 'chunk'" in p for p in ps)
    assert any("node 'total': input 'chunks' <- 'scal.chunk': no node named 'scal'" in p for p in ps)
    assert any("node 'scale': required input 'chunk' (Series) is not connected" in p for p in ps)


def test_unknown_output_port_and_type_mismatch(toy_cfg):
    cfg = toy_cfg()
    cfg["pipeline"]["nodes"]["smooth"]["inputs"] = {"series": "signal.batches", "batches": "signal.batchs"}
    ps = problems(cfg)
    assert any("node 'smooth': input 'series' expects Series, but signal.batches is a BatchPlan" in p for p in ps)
    assert any("no output port named 'batchs'" in p and "did you mean 'batches'" in p for p in ps)


def test_per_batch_into_whole_needs_all_batches(toy_cfg):
    cfg = toy_cfg(total={"stage": "toy_scale"})
    cfg["pipeline"]["nodes"]["total"]["inputs"] = {"chunk": "scale.chunk"}
    cfg["stages"]["signal2"] = {"stage": "toy_signal"}
    ok = build_pipeline(cfg, load_registry())  # per-batch -> per-batch is fine
    assert ok[-1].spec.per_batch
    cfg = toy_cfg()
    cfg["pipeline"]["nodes"]["total"]["inputs"] = {"chunks": "signal.series"}  # all_batches reads a whole output too
    nodes = {n.name: n for n in build_pipeline(cfg, load_registry())}
    assert nodes["total"].inputs["chunks"].node == "signal" and not nodes["total"].spec.per_batch


def test_cycle_is_named(toy_cfg):
    cfg = toy_cfg()
    cfg["pipeline"]["nodes"]["smooth"]["inputs"] = {"series": "signal.series", "batches": "signal.batches"}
    cfg["pipeline"]["nodes"]["scale"]["inputs"] = {"chunk": "scale2.chunk"}
    cfg["pipeline"]["nodes"]["scale2"] = {"config": "stages.scale", "inputs": {"chunk": "scale.chunk"}}
    [p] = problems(cfg)
    assert p.startswith("cycle in the pipeline: scale -> scale2 -> scale") or p.startswith(
        "cycle in the pipeline: scale2 -> scale -> scale2")


def test_missing_node_config_and_stage_key(toy_cfg):
    cfg = toy_cfg()
    del cfg["stages"]["total"]
    cfg["stages"]["scale"] = {"factor": 2.0}
    ps = problems(cfg)
    assert any("node 'total': its config 'stages.total' is missing" in p and "stages/total=<variant>" in p for p in ps)
    assert any("node 'scale': config 'stages.scale' must name its stage" in p for p in ps)


def test_config_unknown_key_and_wrong_type(toy_cfg):
    ps = problems(toy_cfg(smooth={"windw": 3}))
    assert any("stages.smooth.windw: no config key named 'windw'" in p and "did you mean 'window'" in p for p in ps)
    spec = load_registry().get("toy_smooth")
    with pytest.raises(ConfigError, match=r"stages.smooth.window: .*toy_smooth"):
        build_config(spec, {"window": "wide"}, "stages.smooth")
    assert build_config(spec, {"window": "7"}, "stages.smooth").window == 7


@pytest.mark.parametrize("pipeline", ["default", "no_refine"])
@pytest.mark.parametrize("track", ["eklt", "klt_latent", "oracle"])
def test_every_tracker_drops_into_the_shipped_pipelines(pipeline, track):
    """`stages/track=<any tracker>` composes and builds with the pipelines we ship (they wire optional inputs)."""
    from eventcap.apps.benchmark import compose_run

    cfg, _ = compose_run(ROOT / "conf", [f"pipeline={pipeline}", f"stages/track={track}"])
    node = {n.name: n for n in build_pipeline(cfg, load_registry())}["track"]
    assert node.spec.name == track
    assert "detections" in node.inputs


def test_a_packages_config_folder_is_found_through_its_entry_point(tmp_path, monkeypatch, caplog):
    from importlib.metadata import EntryPoint

    import eventcap.core.registry as registry

    (tmp_path / "myplug" / "conf" / "pipeline").mkdir(parents=True)
    for init in ("myplug/__init__.py", "myplug/conf/__init__.py", "myplug/flat.py"):
        (tmp_path / init).write_text("")
    monkeypatch.syspath_prepend(str(tmp_path))
    eps = [EntryPoint("b_good", "myplug.conf", registry.CONFIG_GROUP),
           EntryPoint("a_missing", "myplug_nowhere.conf", registry.CONFIG_GROUP),
           EntryPoint("c_module", "myplug.flat", registry.CONFIG_GROUP)]
    monkeypatch.setattr(registry, "entry_points", lambda group: eps if group == registry.CONFIG_GROUP else [])
    with caplog.at_level("WARNING"):
        found = registry.plugin_config_dirs()
    assert found == [("b_good", tmp_path / "myplug" / "conf")]
    assert ("entry point a_missing = myplug_nowhere.conf (group eventcap.configs): ModuleNotFoundError: No module "
            "named 'myplug_nowhere'; expected a package whose folder holds config groups") in caplog.text
    assert "entry point c_module = myplug.flat (group eventcap.configs): a module, not a package" in caplog.text
