"""Typed artifacts: schema validation with expected-vs-actual errors, zarr round trips, read-only arrays."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pytest
import zarr

from eventcap.artifacts import Artifact, ArtifactError, BatchPlan, Metrics, array, attr
from eventcap.events import EVENT_DTYPE, make_events


@dataclass(frozen=True, eq=False)
class Frames(Artifact):
    schema_version: ClassVar[int] = 2
    images: np.ndarray = array("uint8", ("n", "height", "width"), units="DN")
    t_us: np.ndarray = array("int64", ("n",), units="us")
    height: int = attr(units="px")
    width: int = attr(units="px")


@dataclass(frozen=True, eq=False)
class Capture(Artifact):
    events: np.ndarray = array(EVENT_DTYPE, ("n_events",))
    frames: Frames | None = None
    gain: np.ndarray = array("float32", (3,), optional=True)
    name: str = attr(default="")


def frames(n=3, h=4, w=5, **kw):
    return Frames(images=np.zeros((n, h, w), np.uint8), t_us=np.arange(n, dtype=np.int64), height=h, width=w, **kw)


def test_smoke_and_read_only():
    f = frames()
    assert f.images.shape == (3, 4, 5)
    with pytest.raises(ValueError):
        f.images[0, 0, 0] = 1


def test_exception_wrong_dtype():
    with pytest.raises(ArtifactError, match=r"Frames.t_us: expected dtype <i8, got <f8"):
        Frames(images=np.zeros((3, 4, 5), np.uint8), t_us=np.zeros(3), height=4, width=5)


def test_exception_dim_mismatch_names_both_fields():
    with pytest.raises(ArtifactError, match=r"Frames.t_us: dim 'n' is 3 in images but 4 here"):
        Frames(images=np.zeros((3, 4, 5), np.uint8), t_us=np.zeros(4, np.int64), height=4, width=5)


def test_exception_dim_must_equal_attribute():
    with pytest.raises(ArtifactError, match=r"axis 1 \('height'\) must equal Frames.height = 7"):
        Frames(images=np.zeros((3, 4, 5), np.uint8), t_us=np.zeros(3, np.int64), height=7, width=5)


def test_exception_fixed_size_and_ndim():
    ev = make_events([0], [1], [2], [1])
    with pytest.raises(ArtifactError, match=r"Capture.gain: axis 0 must have size 3, got shape \(4,\)"):
        Capture(events=ev, gain=np.zeros(4, np.float32))
    with pytest.raises(ArtifactError, match=r"expected 1 dims"):
        Capture(events=ev, gain=np.zeros((3, 1), np.float32))


def test_exception_non_finite_values_rejected():
    ev = make_events([0], [1], [2], [1])
    with pytest.raises(ArtifactError, match=r"non-finite value at index \(1,\)"):
        Capture(events=ev, gain=np.array([0, np.nan, 1], np.float32))


def test_zarr_roundtrip_structured_nested_optional(tmp_path):
    rng = np.random.default_rng(0)
    ev = make_events(np.sort(rng.integers(0, 10**6, 100)), rng.integers(0, 240, 100), rng.integers(0, 180, 100),
                     rng.choice([-1, 1], 100))
    cap = Capture(events=ev, frames=frames(), name="x")
    g = zarr.open_group(str(tmp_path / "a.zarr"), mode="w")
    cap.to_zarr(g.create_group("cap"))
    back = Capture.from_zarr(zarr.open_group(str(tmp_path / "a.zarr"), mode="r")["cap"])
    assert back.equals(cap)
    assert back.gain is None and back.frames.t_us.dtype == np.int64
    assert back.events.dtype == EVENT_DTYPE and np.array_equal(back.events, ev)


def test_zarr_schema_version_mismatch_is_an_error(tmp_path):
    g = zarr.open_group(str(tmp_path / "a.zarr"), mode="w")
    frames().to_zarr(g.create_group("f"))
    g["f"].attrs["schema_version"] = 1
    with pytest.raises(ArtifactError, match="schema version 1 on disk, this code reads version 2"):
        Frames.from_zarr(zarr.open_group(str(tmp_path / "a.zarr"), mode="r")["f"])


def test_zarr_wrong_type_and_missing_array(tmp_path):
    g = zarr.open_group(str(tmp_path / "a.zarr"), mode="w")
    Metrics(values={"a": 1}).to_zarr(g.create_group("m"))
    frames().to_zarr(g.create_group("f"))
    del g["f"]["t_us"]
    r = zarr.open_group(str(tmp_path / "a.zarr"), mode="r")
    with pytest.raises(ArtifactError, match="expected a Frames artifact, found 'Metrics'"):
        Frames.from_zarr(r["m"])
    with pytest.raises(ArtifactError, match=r"array 't_us' missing \(expected <i8\[n\] \(us\)\)"):
        Frames.from_zarr(r["f"])


def test_batch_plan_between_frames_and_validation():
    plan = BatchPlan.between_frames(np.array([0, 40_000, 80_000, 120_000]))
    assert len(plan) == 3
    b = plan.batch(2)
    assert (b.index, b.t0_us, b.t1_us, b.frame0) == (2, 80_000, 120_000, 2)
    with pytest.raises(ArtifactError, match="batch 0 ends"):
        BatchPlan(t0_us=np.array([5]), t1_us=np.array([5]), frame0=np.array([0]))


def test_make_events_checks_columns():
    with pytest.raises(ValueError, match=r"event column 'x': expected shape \(2,\), got \(3,\)"):
        make_events([0, 1], [0, 1, 2], [0, 0], [1, -1])
