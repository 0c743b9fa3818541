"""docs/conventions.md says what the code does: its joint table, pose-vector table and event-dtype table are checked
against eventcap.body.skeleton and eventcap.events, row by row."""

from __future__ import annotations

import re

import numpy as np
import pytest

from eventcap.body import skeleton as sk
from eventcap.events import EVENT_DTYPE
from helpers.paths import ROOT

DOC = ROOT / "docs" / "conventions.md"


def table_after(text: str, header: str) -> list[list[str]]:
    """The rows (cells, backticks stripped) of the Markdown table whose header line is ``header``."""
    lines = text.splitlines()
    start = lines.index(header)
    rows = []
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip().strip("`") for c in line.strip().strip("|").split("|")])
    return rows


@pytest.fixture(scope="module")
def doc() -> str:
    return DOC.read_text(encoding="utf-8")


def test_the_table_reader_reads_cells_and_stops_at_the_tables_end():
    text = "x\n| a | b |\n|---|---|\n| `1` | two |\n| 3 | 4 |\n\nafter\n"
    assert table_after(text, "| a | b |") == [["1", "two"], ["3", "4"]]


def test_the_joint_table_is_the_codes_joint_order_and_tree(doc):
    rows = table_after(doc, "| index | joint | parent |")
    assert [int(r[0]) for r in rows] == list(range(sk.NUM_JOINTS))
    assert tuple(r[1] for r in rows) == sk.JOINT_NAMES
    parents = [-1 if r[2] == "—" else sk.JOINT_INDEX[r[2]] for r in rows]
    assert parents == sk.PARENTS.tolist()


def test_the_pose_table_is_the_codes_layout_names_joints_and_limits(doc):
    rows = table_after(doc, "| index | parameter | joint | range |")
    assert [int(r[0]) for r in rows] == list(range(sk.NUM_POSE_PARAMS))
    assert tuple(r[1] for r in rows) == sk.DOF_NAMES + sk.ROOT_ROTATION_NAMES + sk.ROOT_TRANSLATION_NAMES
    assert [sk.JOINT_INDEX[r[2]] for r in rows[:27]] == sk.DOF_JOINT.tolist()
    assert {r[2] for r in rows[27:]} == {"pelvis"}
    lo, hi = sk.pose_bounds()
    for i, r in enumerate(rows):
        m = re.fullmatch(r"\[(-?[\d.]+), (-?[\d.]+)\] rad", r[3])
        if i < 27:
            assert m and (float(m[1]), float(m[2])) == (lo[i], hi[i]), r
        else:
            assert m is None and np.isinf(lo[i]) and r[3] == f"unbounded, {'rad' if i < 30 else 'm'}", r
    # the slices the prose names
    assert (sk.THETA_SLICE, sk.ROOT_ROTATION_SLICE, sk.ROOT_TRANSLATION_SLICE) == \
        (slice(0, 27), slice(27, 30), slice(30, 33))
    assert "`S[0:27]`" in doc and "`S[27:30]`" in doc and "`S[30:33]`" in doc


def test_the_event_table_is_the_event_dtype(doc):
    rows = table_after(doc, "| field | dtype | meaning |")
    assert [(r[0], np.dtype(r[1])) for r in rows] == [(n, EVENT_DTYPE[n]) for n in EVENT_DTYPE.names]
