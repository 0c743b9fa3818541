"""`eventcap preview FILE` (issue 35 item 7, issue 38 item 8): any format the readers take, a line saying what was
read (format, sensor size, events, duration, frames), and by default the recording's most active moment."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from eventcap.apps.cli import main
from eventcap.events import make_events
from eventcap.imaging.viz import most_active_time

W, H = 240, 180
BURST_US = 200_000  # a bar sweeps the sensor in the 10 ms around this time
REAL_DAVIS346 = Path(__file__).resolve().parent / "data" / "real" / "davis346_lab_aps.aedat4"  # tests/data/real/SOURCE.md
SHARED_DAVIS346 = Path("/work/shared/data/real/davis346_lab_aps.aedat4")


def burst_events(seed: int = 0) -> np.ndarray:
    """0.3 s of sparse noise (2,000 events) and a sweeping bar of about 3,000 events within 10 ms around BURST_US."""
    rng = np.random.default_rng(seed)
    t_noise = rng.integers(0, 300_000, 2000)
    t_bar = rng.integers(BURST_US - 5000, BURST_US + 5000, 3000)
    x_bar = np.clip(((t_bar - (BURST_US - 5000)) / 10_000 * (W - 1)).astype(int) + rng.integers(-2, 3, 3000),
                    0, W - 1)
    t = np.concatenate([t_noise, t_bar])
    x = np.concatenate([rng.integers(0, W, 2000), x_bar])
    y = np.concatenate([rng.integers(0, H, 2000), rng.integers(20, 160, 3000)])
    ev = make_events(t + 1000, x, y, rng.choice([-1, 1], 5000))
    return np.unique(ev)  # sorted by t (the dtype's first field), without exact duplicates


def write_in(fmt: str, folder: Path, ev: np.ndarray) -> Path:
    from eventcap.io import write_events
    from eventcap.io.aedat_legacy import write_aedat2, write_aedat31

    if fmt == "aedat2":
        path = folder / "rec.aedat"
        write_aedat2(path, ev)
    elif fmt == "aedat3":
        path = folder / "rec31.aedat"
        write_aedat31(path, ev, source="DAVIS240C")
    elif fmt in ("csv", "npy"):
        cols = np.stack([ev["t"], ev["x"], ev["y"], (ev["p"] > 0)], axis=1).astype(np.int64)
        path = folder / f"rec.{fmt}"
        np.savetxt(path, cols, fmt="%d", delimiter=",", header="t,x,y,p", comments="") if fmt == "csv" \
            else np.save(path, cols)
    else:
        ext = {"aedat4": ".aedat4", "evt2": ".raw", "evt3": ".raw", "dat": ".dat", "hdf5": ".h5", "npz": ".npz",
               "rpg": ""}[fmt]
        path = folder / f"rec_{fmt}{ext}"
        write_events(path, ev, width=W, height=H, format=fmt)
    return path


def preview(capsys, *args) -> tuple[int, str, str]:
    code = main(["preview", *map(str, args)])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_most_active_time_finds_the_burst():
    t, count = most_active_time(burst_events(), 20_000)
    assert abs(t - (BURST_US + 1000)) <= 5000 and count >= 2900


@pytest.mark.parametrize("fmt", ["aedat4", "aedat2", "aedat3", "hdf5", "evt2", "evt3", "dat", "npy", "npz", "csv",
                                 "rpg"])
def test_preview_reads_every_format_and_shows_the_most_active_moment(fmt, tmp_path, capsys):
    ev = burst_events()
    path = write_in(fmt, tmp_path, ev)
    extra = ["--width", W, "--height", H] if fmt in ("npy", "csv", "rpg", "evt2", "evt3", "dat") else []
    extra += ["--time-unit", "us"] if fmt == "csv" else []  # text columns are read as seconds by default
    out_png = tmp_path / "p.png"
    code, out, err = preview(capsys, path, "--out", out_png, *extra)
    assert code == 0, err
    m = re.search(r"read \S+: (\w+); (\d+) x (\d+) px, ([\d,]+) events over ([\d.]+) s", out)
    assert m, out
    assert m.group(1) == {"evt2": "evt2", "evt3": "evt3", "csv": "rpg"}.get(fmt, fmt)
    assert (int(m.group(2)), int(m.group(3))) == (W, H)
    assert int(m.group(4).replace(",", "")) == ev.size
    assert float(m.group(5)) == pytest.approx((int(ev["t"][-1]) - int(ev["t"][0])) / 1e6, abs=1e-3)
    assert "no intensity frames (an event-only recording)" in out
    shown = float(re.search(r"showing t = ([\d.]+) s, the most active moment", out).group(1))
    assert abs(shown - BURST_US / 1e6) < 0.007  # times count from the first event (at 1 ms here)
    img = cv2.imread(str(out_png))
    assert img.shape == (2 * H, 2 * 2 * W, 3)  # image from the events | events
    events_panel = img[:, 2 * W:]
    assert (events_panel != 255).any(axis=2).sum() > 2 * 2000  # the bar's events are drawn


def test_preview_refuses_what_it_cannot_read_naming_the_file(tmp_path, capsys):
    bad = tmp_path / "noise.aedat4"
    bad.write_bytes(b"\x00" * 100)
    code, out, err = preview(capsys, bad)
    assert code == 2 and str(bad) in err and "No group found" not in err
    code, out, err = preview(capsys, tmp_path / "missing.h5")
    assert code == 2 and f"{tmp_path / 'missing.h5'}: no such file or folder" in err


def test_preview_of_the_real_davis346_recording(tmp_path, capsys):
    path = REAL_DAVIS346 if REAL_DAVIS346.is_file() else SHARED_DAVIS346
    if not path.is_file():
        pytest.skip(f"the DAVIS346 sample is not here ({REAL_DAVIS346} nor {SHARED_DAVIS346})")
    code, out, err = preview(capsys, path, "--out", tmp_path / "d.png")
    assert code == 0, err
    assert "aedat4; 346 x 260 px, 117,667 events over 0.130 s" in out and "3 intensity frames" in out
    assert "UNCALIBRATED" in out
    assert "showing t = 0.018 s, the most active moment (22,129 events in 20 ms" in out
    assert cv2.imread(str(tmp_path / "d.png")).shape == (2 * 260, 2 * 2 * 346, 3)  # frame | events


def grid_times(rng, seconds: float = 2.0, frame_us: float = 1e6 / 30, steps: int = 12, per_step: int = 40):
    """Timestamps as a video-to-events converter makes them: each 33 ms frame interval cut into ``steps`` steps,
    tens of events at each step (fewer later in the interval)."""
    t = []
    for k in range(int(seconds * 1e6 / frame_us)):
        for j in range(steps):
            n = max(1, int(per_step * 3 / (j + 1)) + int(rng.integers(0, 5)))
            t.append(np.full(n, int(round(k * frame_us + j * frame_us / steps))))
    return np.sort(np.concatenate(t))


def test_timestamps_on_a_grid_are_named_sensor_timing_is_not():
    from eventcap.io.checks import timing_note

    rng = np.random.default_rng(3)
    grid = grid_times(rng)
    note = timing_note(grid)
    assert note is not None and "lie on a grid" in note and "median step 2.8 ms" in note
    assert "a motion at 1 ms between is the prior's" in note
    # a sensor: Poisson arrivals at 8 per ms, distinct microseconds
    sensor = np.sort(rng.integers(0, 2_000_000, 16_000))
    assert timing_note(sensor) is None
    # a vectorising sensor (EVT3): 25 events share each timestamp, a timestamp every 20 µs
    vectors = np.repeat(np.arange(0, 2_000_000, 20), 25)
    assert timing_note(vectors) is None
    # bursts: a limb's flick fires 3,000 events within 5 ms every 50 ms, each at its own time
    bursts = np.sort(np.concatenate([b * 50_000 + rng.integers(0, 5000, 3000) for b in range(40)]))
    assert timing_note(bursts) is None
    # a grid at 1 ms (a sensor's output binned per ms) is as fine as the motion: not named
    assert timing_note(np.repeat(np.arange(0, 2_000_000, 1000), 25)) is None


def test_preview_names_a_recording_on_a_timestamp_grid(tmp_path, capsys):
    rng = np.random.default_rng(4)
    t = grid_times(rng)
    x, y = rng.integers(0, 128, t.size), rng.integers(0, 128, t.size)
    path = tmp_path / "converted.csv"
    np.savetxt(path, np.column_stack([t / 1e6, x, y, rng.integers(0, 2, t.size)]), fmt=["%.6f", "%d", "%d", "%d"],
               delimiter=",")
    code, out, err = preview(capsys, path, "--columns", "t,x,y,p", "--time-unit", "s", "--width", "128", "--height",
                             "128", "--out", tmp_path / "c.png")
    assert code == 0, err
    assert "note: the events' timestamps lie on a grid" in out and "made from video frames by a converter" in out
