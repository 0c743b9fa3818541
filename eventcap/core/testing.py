"""Conformance tests every stage inherits (ours and third parties'), in the manner of Hydra's launcher test suite.

    import numpy as np
    from eventcap.artifacts import PoseSequence
    from eventcap.core.testing import StageConformance

    class TestPostSmooth(StageConformance):
        stage_name = "post_smooth"              # the stage, by its registered name (required)
        sensitive = ("sigma_ms", 20.0)          # a result-affecting setting and another value for it (required
                                                # while the stage has such settings: the key must change with it)

        def make_inputs(self):                  # a tiny, seeded input for every input port (required)
            t = np.arange(0, 41_000, 1_000, dtype=np.int64)
            poses = np.random.default_rng(0).normal(0.0, 0.1, (t.size, 33))
            return {"poses": [PoseSequence(t_us=t, poses=poses)]}   # an all_batches port: a list of batches

Optional: ``config_overrides`` (settings every test runs with, e.g. a file the stage needs), ``insensitive`` (a
setting declared ``affects_result=False`` and another value: the key must not change). A per-batch stage runs on
batch 0 of the first ``BatchPlan`` among its inputs. Helpers for tests of what the stage computes:
``run_once(**changes)`` (on ``make_inputs()``), ``run_on(inputs, **changes)``, ``config(**changes)``, ``spec()``.

The suite checks discovery through the registry, config round trip and rejection of unknown keys, renamed keys,
cache-key stability and sensitivity, the output schema (declared types, zarr round trip) and determinism (two runs
on the same input give equal outputs). Add tests of what the stage computes beside it.
"""

from __future__ import annotations

from typing import Any, ClassVar

from eventcap.artifacts import Artifact, Batch, BatchPlan
from eventcap.core.cache import make_key
from eventcap.core.config import ConfigError, build_config, config_to_dict
from eventcap.params import leaves, nest
from eventcap.core.registry import load_registry
from eventcap.core.stage import StageContext, StageSpec


class StageConformance:
    """Subclass in a pytest module (its name starting with ``Test``); set ``stage_name`` and ``sensitive`` and
    implement ``make_inputs`` (module doc)."""

    stage_name: ClassVar[str] = ""
    config_overrides: ClassVar[dict[str, Any]] = {}
    sensitive: ClassVar[tuple[str, Any] | None] = None
    insensitive: ClassVar[tuple[str, Any] | None] = None

    def make_inputs(self) -> dict[str, Any]:
        raise NotImplementedError("return a tiny seeded input for each input port of the stage")

    # -- helpers ------------------------------------------------------------------------------------------------
    def spec(self) -> StageSpec:
        assert self.stage_name, "set stage_name on the conformance test class"
        return load_registry().get(self.stage_name)

    def config(self, **changes: Any):
        """The stage's config with the class's overrides and these changes (keys may be dotted: terms.sil.weight)."""
        return build_config(self.spec(), nest(self.config_overrides, changes), f"stages.{self.stage_name}")

    def batch(self, inputs: dict[str, Any]) -> Batch | None:
        if not self.spec().per_batch:
            return None
        plans = [v for v in inputs.values() if isinstance(v, BatchPlan)]
        return plans[0].batch(0) if plans else Batch(0, 0, 40_000, 0)

    def run_once(self, **changes: Any) -> dict[str, Artifact]:
        """The stage's outputs on :meth:`make_inputs`, with the class's config and these changes."""
        return self.run_on(self.make_inputs(), **changes)

    def run_on(self, inputs: dict[str, Any], **changes: Any) -> dict[str, Artifact]:
        """The stage's outputs on these inputs (for tests of what it computes), with the config and changes."""
        spec = self.spec()
        ctx = StageContext(node=f"conformance_{spec.name}", stage=spec.name, batch=self.batch(inputs))
        return dict(spec.load_run()(inputs, self.config(**changes), ctx))

    def key(self, **changes: Any) -> str:
        from eventcap.core.runner import base_doc

        spec = self.spec()
        return make_key({**base_doc(spec, self.config(**changes), f"stages.{spec.name}"), "inputs": {}})

    # -- the suite ------------------------------------------------------------------------------------------------
    def test_discovery(self):
        spec = self.spec()
        assert spec.name == self.stage_name
        assert spec.kind and spec.description and isinstance(spec.version, int)
        assert callable(spec.load_run())

    def test_config_roundtrip(self):
        spec = self.spec()
        cfg = self.config()
        again = build_config(spec, config_to_dict(cfg), "roundtrip")
        assert config_to_dict(again) == config_to_dict(cfg)
        for key, f in leaves(spec.config):
            assert f.metadata.get("help"), f"config field {key} has no help text"

    def test_renamed_keys_name_their_new_key(self):
        spec = self.spec()
        for old, new in spec.renamed.items():
            try:
                self.config(**{old: 1})
            except ConfigError as exc:
                assert f".{new}" in str(exc), str(exc)
            else:
                raise AssertionError(f"the renamed setting {old!r} was accepted")

    def test_unknown_config_key_rejected(self):
        try:
            self.config(no_such_key_xyz=1)
        except ConfigError as exc:
            assert "no_such_key_xyz" in str(exc)
        else:
            raise AssertionError("an unknown config key was accepted")

    def test_cache_key_stable(self):
        assert self.key() == self.key()
        if self.insensitive is not None:
            name, value = self.insensitive
            assert name not in self.spec().result_fields()
            assert self.key(**{name: value}) == self.key()

    def test_cache_key_sensitive(self):
        if self.sensitive is None:
            fields = self.spec().result_fields()
            assert not fields, (f"set sensitive = (setting, another value) on {type(self).__name__}: stage "
                                f"{self.stage_name!r} has settings that change its result: {', '.join(fields)}")
            return
        name, value = self.sensitive
        assert name in self.spec().result_fields()
        assert self.key(**{name: value}) != self.key()

    def test_output_schema(self, tmp_path):
        import zarr

        spec = self.spec()
        outputs = self.run_once()
        assert set(outputs) == set(spec.outputs)
        group = zarr.open_group(str(tmp_path / "out.zarr"), mode="w")
        for port, value in outputs.items():
            assert isinstance(value, spec.outputs[port].type)
            value.write_zarr(group, port)
            back = spec.outputs[port].type.from_zarr(zarr.open_group(str(tmp_path / "out.zarr"), mode="r")[port])
            assert back.equals(value), f"output {port} does not survive a zarr round trip"

    def test_determinism(self):
        a, b = self.run_once(), self.run_once()
        for port in a:
            assert a[port].equals(b[port]), f"output {port} differs between two runs on the same input"
