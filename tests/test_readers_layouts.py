"""Array and text layouts: (N, 4) / (4, N), C / Fortran order, named column orders (``columns=``, a csv header),
time units, a bottom-up y axis; the sensor size inferred despite a few outliers; random bytes after an EVT3 header;
a corrupt compressed AEDAT4 packet; the options through the recording source and ``eventcap convert``."""

from __future__ import annotations

import numpy as np
import pytest

from eventcap.events import make_events
from eventcap.io import RecordingError, iter_event_chunks, read_recording, write_events

W, H = 64, 48


def events(n=4000, seed=0):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.choice(np.arange(1_000, 2_000_000), n, replace=False))  # distinct, increasing
    return make_events(t, rng.integers(0, W, n), rng.integers(0, H, n), rng.choice([-1, 1], n))


def expected(ev):
    out = ev.copy()
    out["t"] -= out["t"][0]
    return out


def as_columns(ev, order):
    cols = {"t": ev["t"].astype(np.int64), "x": ev["x"].astype(np.int64), "y": ev["y"].astype(np.int64),
            "p": (ev["p"] > 0).astype(np.int64)}
    return np.stack([cols[c] for c in order], axis=1)


@pytest.mark.parametrize("transpose", [False, True], ids=["N4", "4N"])
@pytest.mark.parametrize("fortran", [False, True], ids=["C", "F"])
@pytest.mark.parametrize("order", ["txyp", "xytp", "ptxy"])
def test_npy_layouts_and_column_orders(tmp_path, transpose, fortran, order):
    ev = events()
    arr = as_columns(ev, order)
    arr = arr.T if transpose else arr
    arr = np.asfortranarray(arr) if fortran else np.ascontiguousarray(arr)
    p = tmp_path / "e.npy"
    np.save(p, arr)
    kwargs = {"columns": ",".join(order)} if order == "ptxy" else {}
    r = read_recording(p, width=W, height=H, **kwargs)
    np.testing.assert_array_equal(r.events, expected(ev))
    assert any("(4, N)" in s for s in r.repairs) == transpose
    chunks = iter_event_chunks(p, chunk_events=1000, width=W, height=H, **kwargs)
    np.testing.assert_array_equal(np.concatenate(list(chunks)), r.events)


def test_unnamed_columns_without_a_time_ordered_candidate_are_refused_and_bad_names_too(tmp_path):
    ev = events()
    p = tmp_path / "e.npy"
    np.save(p, as_columns(ev, "ptxy"))
    with pytest.raises(RecordingError, match="no time-ordered column 0 or 2"):
        read_recording(p, width=W, height=H)
    with pytest.raises(ValueError, match=r"columns='p,t,x': expected 4 names that name t, x, y, p once each"):
        read_recording(p, width=W, height=H, columns="p,t,x")
    with pytest.raises(ValueError, match="columns=.* applies to array and text files"):
        read_recording(tmp_path / "e.npy", format="evt3", columns="t,x,y,p")


def test_truncated_column_major_npy_is_refused_but_event_major_keeps_complete_events(tmp_path):
    ev = events(100)
    for arr, ok in ((np.asfortranarray(as_columns(ev, "txyp")), False), (as_columns(ev, "txyp"), True),
                    (np.asfortranarray(as_columns(ev, "txyp").T), True)):
        p = tmp_path / "t.npy"
        np.save(p, arr)
        p.write_bytes(p.read_bytes()[:-12])
        if ok:
            r = read_recording(p, width=W, height=H)
            assert len(r.events) == 99 and any("only 99 complete ones are stored: kept those" in s for s in r.repairs)
        else:
            with pytest.raises(RecordingError, match="stored column by column .* no event is complete"):
                read_recording(p, width=W, height=H)


def test_npz_events_array_in_4_by_n(tmp_path):
    ev = events()
    p = tmp_path / "e.npz"
    np.savez(p, events=as_columns(ev, "xytp").T, width=W, height=H)
    r = read_recording(p, columns=["x", "y", "t", "p"])
    np.testing.assert_array_equal(r.events, expected(ev))


def test_csv_with_a_header_guessed_order_and_time_unit(tmp_path):
    ev = events(500)
    rows = as_columns(ev, "xytp")
    named = tmp_path / "named.csv"
    named.write_text("x,y,t,p\n" + "".join(f"{x},{y},{t / 1000:.3f},{p}\n" for x, y, t, p in rows))
    r = read_recording(named, width=W, height=H, time_unit="ms")
    np.testing.assert_array_equal(r.events, expected(ev))
    assert r.format == "rpg" and r.repairs == ()
    plain = tmp_path / "plain.txt"  # x y t p without names: the time-ordered third column is found (noted)
    plain.write_text("".join(f"{x} {y} {t} {p}\n" for x, y, t, p in rows))
    r = read_recording(plain, width=W, height=H, time_unit="us")
    np.testing.assert_array_equal(r.events, expected(ev))
    assert any("read as (x, y, t, p) (column 2 is time-ordered)" in s for s in r.repairs)
    chunks = iter_event_chunks(named, chunk_events=64, width=W, height=H, time_unit="ms")
    np.testing.assert_array_equal(np.concatenate(list(chunks)), expected(ev))


def test_y_up_flips_events_in_reading_and_streaming(tmp_path):
    ev = events()
    up = ev.copy()
    up["y"] = H - 1 - ev["y"]
    p = tmp_path / "up.npz"
    np.savez(p, t=up["t"], x=up["x"], y=up["y"], p=up["p"], width=W, height=H)
    r = read_recording(p, y_up=True)
    np.testing.assert_array_equal(r.events, expected(ev))
    np.testing.assert_array_equal(np.concatenate(list(iter_event_chunks(p, 999, y_up=True))), expected(ev))
    assert read_recording(p).events["y"][0] == up["y"][0]


def test_inferred_sensor_size_ignores_a_few_far_outliers_and_says_so(tmp_path):
    ev = events(20_000)
    ev["x"][[500, 9000]] = [60_000, 41_000]  # two corrupted coordinates
    p = tmp_path / "o.npz"
    np.savez(p, t=ev["t"], x=ev["x"], y=ev["y"], p=ev["p"])
    r = read_recording(p)
    assert (r.width, r.height) == (W, H) and len(r.events) == 19_998
    assert any("inferred 64 × 48" in s and "ignored and dropped 2 outlier event(s): 2 event(s) with x up to 60000 "
               "(beyond x = 63 of the others)" in s for s in r.repairs)
    # eventcap convert has written them already when it finds them: it refuses and says how to crop them.
    from eventcap.io.convert import convert_recording

    with pytest.raises(RecordingError, match=r"2 event\(s\) are outliers \(2 event\(s\) with x up to 60000 \(beyond "
                                             r"x = 63 of the others\)\): corrupted events, .* crop them with --roi 0 0 "
                                             r"64 48"):
        convert_recording(p, tmp_path / "o.zarr", chunk_events=3000)
    assert not (tmp_path / "o.zarr").exists()
    assert convert_recording(p, tmp_path / "o.zarr", roi=(0, 0, 64, 48))["events"] == 19_998
    # Many events far out: not outliers, and not a plausible sensor either (issue 38): refused with the count,
    # unless the user says how big the sensor is.
    ev["x"][:100] = 60_000
    np.savez(p, t=ev["t"], x=ev["x"], y=ev["y"], p=ev["p"])
    with pytest.raises(RecordingError, match=r"102 of 20,000 events \(0.51 %\) lie outside every known event sensor"):
        read_recording(p)
    assert read_recording(p, width=60_001, height=H).width == 60_001


def test_random_bytes_after_an_evt3_header_are_rejected(tmp_path):
    rng = np.random.default_rng(0)
    p = tmp_path / "r.raw"
    p.write_bytes(b"% evt 3.0\n% end\n" + rng.integers(0, 256, 20_000, dtype=np.uint8).tobytes())
    with pytest.raises(RecordingError, match=r"data: not EVT3 data: 3\d{3} of the first 10000 words \(3\d %\) have "
                                             r"event types EVT3 does not define"):
        read_recording(p)
    ok = tmp_path / "ok.raw"
    ev = events()
    write_events(ok, ev, width=W, height=H, format="evt3", t_offset_us=0)
    np.testing.assert_array_equal(read_recording(ok).events, expected(ev))


def test_corrupt_compressed_aedat4_packet_is_skipped_and_reported(tmp_path):
    ev = events(20_000)
    p = tmp_path / "m.aedat4"
    write_events(p, iter([ev[i:i + 2000] for i in range(0, len(ev), 2000)]), width=W, height=H, format="aedat4",
                 t_offset_us=0)
    raw = bytearray(p.read_bytes())
    pos = 18 + int.from_bytes(raw[14:18], "little")  # magic, IO header length, IO header
    for _ in range(2):  # to packet 2: stream id, size, payload
        pos += 8 + int.from_bytes(raw[pos + 4:pos + 8], "little")
    raw[pos + 8:pos + 16] = bytes(8)  # packet 2's LZ4 frame header
    p.write_bytes(bytes(raw))
    r = read_recording(p)
    keep = np.ones(len(ev), bool)
    keep[4000:6000] = False
    np.testing.assert_array_equal(r.events, expected(ev[keep]))
    assert r.repairs == ("skipped 1 corrupted compressed packet(s) whose data does not decompress, their events are "
                         "missing: packet 2 (LZ4 error: ERROR_frameType_unknown)",)


def test_options_through_the_recording_source_and_convert(tmp_path):
    from eventcap.artifacts.recording import Recording
    from eventcap.apps.cli import main
    from eventcap.core.config import build_config
    from eventcap.core.registry import load_registry
    from eventcap.core.stage import StageContext

    ev = events()
    up = ev.copy()
    up["y"] = H - 1 - ev["y"]
    arr = as_columns(up, "xytp").T.astype(np.float64)
    arr[2] /= 1000.0  # milliseconds
    p = tmp_path / "e.npy"
    np.save(p, np.asfortranarray(arr))
    spec = load_registry().get("recording")
    cfg = build_config(spec, {"path": str(p), "width": W, "height": H, "time_unit": "ms", "columns": ["x", "y", "t", "p"],
                              "y_up": True}, "source")
    out = spec.load_run()({}, cfg, StageContext(node="source", stage="recording"))
    got = out["recording"].events.events
    np.testing.assert_array_equal(got, expected(ev))
    z = tmp_path / "e.zarr"
    assert main(["convert", str(p), str(z), "--width", str(W), "--height", str(H), "--time-unit", "ms",
                 "--columns", "x,y,t,p", "--y-up"]) == 0
    import zarr

    back = Recording.from_zarr(zarr.open_group(str(z), mode="r"))
    np.testing.assert_array_equal(back.events.events, got)
