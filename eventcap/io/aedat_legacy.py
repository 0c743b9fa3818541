"""Legacy AEDAT files, decoded by us: 2.0 (jAER: DVS128, DAVIS, DHP19) and 3.1 (cAER / DV before AEDAT4).

No package on PyPI decodes these correctly (checked: tonic and aermanager transpose x/y, miss the x flip, invert
polarity, keep invalid and special events and ignore the 3.1 timestamp overflow; evlib, aerpy and bimvee fail), so this module follows the formats' specifications:

AEDAT 2.0 (big-endian ``int32 address, int32 timestamp µs`` after ``#`` header lines; the chip from the
``# AEChip:`` line):

- DVS128: bit 0 polarity (0 = ON, as jAER reads it), bits 1-7 x, bits 8-14 y, bit 15 external (special) event;
- DAVIS240/346/...: bit 31 set = APS or IMU sample, bit 10 set (with bit 31 clear) = external (special) event,
  otherwise a polarity event with bit 11 = ON, bits 12-21 x, bits 22-30 y.

jAER's DAVIS extractor mirrors the x address of DVS events (``x = width - 1 - x_address``, not that of APS
samples) and counts y from the bottom: both are undone here into the project's top-left origin
(``y = height - 1 - y_address``). Special events and IMU samples are left out. APS samples (bit 31, readout type
in bits 10-11: 0 reset read, 1 signal read, 10-bit ADC value in bits 0-9) are assembled into global-shutter
frames: a run of reset reads of every pixel followed by a run of signal reads of every pixel gives one frame,
intensity ``(reset - signal) / 1023`` clipped to [0, 1], exposure from the last reset read to the first signal
read; samples in any other arrangement (rolling shutter, regions of interest, a frame cut by the end of the
file) are left out and counted in a note. The 32-bit timestamp
wraps after 71.6 min; that is unwrapped like any 32-bit time column. DHP19's recordings are AEDAT 2.0 of the chip
class ``MultiDavis346BCameraChip``: four DAVIS346 cameras in one stream, the camera index in address bits 0-3
(as DHP19's own loader reads it); the first camera in the file is read (``Aedat2Source(path, camera=k)`` picks
another) and the events of the others are left out and counted in a note. The x mirror and bottom-up y of jAER's
DAVIS extractor are assumed for this chip class too (not checked against a DHP19 file: none was at hand).

AEDAT 3.1 (little-endian packets after ``#!END-HEADER``; each a 28-byte header ``type, source (int16), size,
ts offset, ts overflow, capacity, number, valid (int32)`` and ``capacity × size`` bytes of events):

- polarity events (type 1, 8 bytes): ``uint32 data`` (bit 0 valid, bit 1 ON, bits 2-16 y, bits 17-31 x, origin
  top-left) and an ``int32`` timestamp; the full time is ``overflow << 31 | timestamp`` (the packet's overflow
  counter carries the timestamp-wrap special events); invalid events (valid bit 0, e.g. removed by a filter) are
  left out;
- frame events (type 2): a 36-byte header (info, frame start/end, exposure start/end, size x/y, position x/y)
  then ``uint16`` pixels, row-major from the top-left; read when they cover the whole sensor;
- other packet types (special, IMU, ...) are skipped. With several event sources in one file the lowest source
  id is read (and the others named in the log).

The sensor size comes from the chip / source name in the header (DVS128, DAVIS240, DAVIS346, ...).
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from eventcap.io.checks import RawChunk
from eventcap.io.recording import RecordingError, logger
from eventcap.io.registry import ReaderSpec
from eventcap.io.source import DEFAULT_CHUNK_EVENTS, FrameData, RowLocator, Source, file_size, numbered_chunks

MAGIC = b"#!AER-DAT"
_MAX_HEADER_BYTES = 1 << 24
_PACKET_HEADER = np.dtype([("type", "<i2"), ("source", "<i2"), ("size", "<i4"), ("ts_offset", "<i4"),
                           ("ts_overflow", "<i4"), ("capacity", "<i4"), ("number", "<i4"), ("valid", "<i4")])
_AEDAT2_RECORD = np.dtype([("a", ">u4"), ("t", ">u4")])
_POLARITY31 = np.dtype([("data", "<u4"), ("t", "<i4")])
_FRAME31_HEADER = np.dtype([("info", "<u4"), ("frame_start", "<i4"), ("frame_end", "<i4"), ("exposure_start", "<i4"),
                            ("exposure_end", "<i4"), ("size_x", "<i4"), ("size_y", "<i4"), ("pos_x", "<i4"),
                            ("pos_y", "<i4")])

#: Chip / source names → (address layout of AEDAT 2.0, width, height); matched case-insensitively, first wins.
SENSORS = (
    (r"dvs128|tmpdiff128", "dvs128", 128, 128),
    (r"davis? ?346|dvs ?346", "davis", 346, 260),  # "DAVI346": the chip name iniVation's aedat4to2 writes
    (r"davis ?240|sbret10|davis ?fx2", "davis", 240, 180),
    (r"davis ?640|davis ?rgb", "davis", 640, 480),
    (r"davis ?208", "davis", 208, 192),
    (r"davis ?128", "davis", 128, 128),
    (r"dvxplorer ?lite", "davis", 320, 240),
    (r"dvxplorer", "davis", 640, 480),
)


def sensor_of(name: str) -> tuple[str, int, int] | None:
    """(layout, width, height) of a chip / source name from a header, or ``None`` when it is not known."""
    for pattern, layout, w, h in SENSORS:
        if re.search(pattern, name, re.IGNORECASE):
            return layout, w, h
    return None


def read_legacy_header(path: Path) -> tuple[str, list[str], int]:
    """(version "2.0" / "3.1" / ..., header lines without the leading ``#``, header length in bytes)."""
    lines: list[str] = []
    length = 0
    version = None
    with open(path, "rb") as f:
        while length < _MAX_HEADER_BYTES:
            line = f.readline(1 << 16)
            if not line.startswith(b"#"):
                break
            length += len(line)
            text = line[1:].decode("latin-1").rstrip("\r\n")
            if version is None:
                if not line.startswith(MAGIC):
                    raise RecordingError(path, f"the first line {line[:40]!r} is not an AEDAT version line "
                                               f"('#!AER-DAT2.0' or '#!AER-DAT3.1')", "file header")
                version = line[len(MAGIC):].strip().decode("ascii", "replace")
            lines.append(text)
            if version.startswith("3") and line.startswith(b"#!END-HEADER"):
                return version, lines, length
            if not line.endswith(b"\n"):
                break
    if version is None:
        raise RecordingError(path, "no AEDAT version line", "file header")
    if version.startswith("3"):
        raise RecordingError(path, "no '#!END-HEADER' line: truncated or corrupted header", "file header")
    return version, lines, length


class Aedat2Source(Source):
    """An AEDAT 2.0 file written by jAER (DVS128 or DAVIS chips): polarity events."""

    format = "aedat2"

    def __init__(self, path: Path, time_unit: str | None = None, camera: int | None = None):
        super().__init__(path, time_unit)
        if time_unit not in (None, "us"):
            raise RecordingError(path, f"AEDAT 2.0 stores µs; time_unit={time_unit!r} does not apply")
        self._camera = camera
        version, lines, self._header_length = read_legacy_header(path)
        if version != "2.0":
            raise RecordingError(path, f"AEDAT version {version!r}: expected 2.0", "file header")
        chip = next((ln.split(":", 1)[1].strip() for ln in lines if ln.strip().lower().startswith("aechip:")), None)
        self.chip = chip
        self._n_records = (file_size(path) - self._header_length) // 8
        if chip is None:
            # jAER files from before the AEChip line are DVS128 recordings; their addresses are 16-bit.
            sample = self._records(0, min(self._n_records, 100_000))["a"]
            if len(sample) and int(sample.max()) >= 1 << 16:
                raise RecordingError(path, "the header names no chip (no '# AEChip:' line) and the addresses are "
                                           "32-bit: cannot tell the address layout", "file header")
            self._layout, self.width, self.height = "dvs128", 128, 128
            self.chip = "DVS128 (assumed)"
            self._assumed = "the header names no chip (no '# AEChip:' line): decoded as DVS128 (16-bit addresses)"
        else:
            found = sensor_of(chip.rsplit(".", 1)[-1])
            if found is None:
                raise RecordingError(path, f"unsupported chip {chip!r}: expected DVS128 or a DAVIS (240, 346, 640, "
                                           f"208, 128)", "file header")
            self._layout, self.width, self.height = found
            self._assumed = None
        self._multi = chip is not None and "multi" in chip.lower()

    def _records(self, a: int, b: int) -> np.ndarray:
        if b <= a:
            return np.empty(0, _AEDAT2_RECORD)
        return np.memmap(self.path, dtype=_AEDAT2_RECORD, mode="r", offset=self._header_length + 8 * a,
                         shape=(b - a,))

    def chunks(self, chunk_events: int = DEFAULT_CHUNK_EVENTS, with_frames: bool = False) -> Iterator[RawChunk]:
        self.notes.clear()
        if self._assumed:
            self.notes.append(self._assumed)
        extra = (file_size(self.path) - self._header_length) % 8
        if extra:
            self.notes.append(f"the file ends with a partial 8-byte event ({extra} byte(s), truncated file?): ignored")
        counts = {"aps": 0, "imu": 0, "special": 0, "cameras": {}}
        rows = RowLocator()
        aps: list[tuple[np.ndarray, np.ndarray]] = []

        def columns():
            for a0 in range(0, self._n_records, chunk_events):
                rec = self._records(a0, min(self._n_records, a0 + chunk_events))
                addr, t = np.asarray(rec["a"]).astype(np.uint32), np.asarray(rec["t"]).astype(np.uint32)
                x, y, p, keep = self._decode(addr, a0, counts)
                if with_frames and self._layout == "davis":
                    s = ((addr >> 31) == 1) & (((addr >> 10) & 3) < 2)
                    if s.any():
                        aps.append((addr[s], t[s]))
                idx = np.flatnonzero(keep)
                if len(idx):
                    rows.add(row_of[0], f"record {a0 + int(idx[0])} of the data")
                    row_of[0] += len(idx)
                    yield t[idx], x[idx], y[idx], p[idx]

        row_of = [0]
        yield from numbered_chunks(columns(), chunk_events, rows)
        if with_frames:
            self._frames = self._assemble_frames(aps)
            used = 0 if self._frames is None else len(self._frames[0]) * 2 * self.width * self.height
            left = counts["aps"] - used
            if left:
                self.notes.append(f"{left} APS samples are not in complete global-shutter frames (rolling shutter, a "
                                  f"region of interest, or a frame cut short): left out")
        others = {c: n for c, n in counts["cameras"].items() if c != self._camera}
        if others:
            self.notes.append(f"{self.chip} records several cameras: read camera {self._camera}; left out "
                              f"{sum(others.values())} events of camera(s) {', '.join(map(str, sorted(others)))}")
        if counts["special"] or counts["imu"]:
            logger.info("%s: left out %d special (external input) events and %d IMU samples", self.path,
                        counts["special"], counts["imu"])

    def _assemble_frames(self, aps: list[tuple[np.ndarray, np.ndarray]]) -> tuple | None:
        """(images float32 (N, H, W), exposure begin, end) from the APS samples in file order, or ``None``."""
        if not aps:
            return None
        a = np.concatenate([s[0] for s in aps])
        t = np.concatenate([s[1] for s in aps]).astype(np.int64)
        t = t + (np.cumsum(np.diff(t, prepend=t[0]) < -(2**31)) << 32)  # the 32-bit counter's wraps
        kind = ((a >> 10) & 1).astype(np.int8)  # 0 reset read, 1 signal read
        w, h = self.width, self.height
        n = w * h
        starts = np.flatnonzero(np.diff(kind, prepend=-1))
        ends = np.append(starts[1:], len(a))
        images, begin, end = [], [], []
        for k in range(len(starts) - 1):
            r0, r1, s0, s1 = starts[k], ends[k], starts[k + 1], ends[k + 1]
            if kind[r0] != 0 or r1 - r0 != n or s1 - s0 != n:
                continue
            reset = np.full((h, w), -1, np.int64)
            signal = np.full((h, w), -1, np.int64)
            for out, lo, hi in ((reset, r0, r1), (signal, s0, s1)):
                xa, ya = (a[lo:hi] >> 12) & 0x3FF, (a[lo:hi] >> 22) & 0x1FF
                if xa.max() >= w or ya.max() >= h:
                    break
                out[h - 1 - ya.astype(np.int64), xa.astype(np.int64)] = a[lo:hi] & 0x3FF
            if (reset < 0).any() or (signal < 0).any():
                continue  # not every pixel read once: not a full frame
            images.append((np.clip(reset - signal, 0, 1023) / np.float32(1023)).astype(np.float32))
            begin.append(int(t[r1 - 1]))
            end.append(int(t[s0]))
        if not images:
            return None
        return np.stack(images), np.array(begin, np.int64), np.array(end, np.int64)

    def frames(self) -> FrameData | None:
        if self._layout != "davis":
            return None
        if not hasattr(self, "_frames"):
            for _ in self.chunks(with_frames=True):
                pass
        if self._frames is None:
            return None
        images, begin, end = self._frames
        if np.any(end < begin):
            i = int(np.argmax(end < begin))
            raise RecordingError(self.path, f"APS frame {i}: the signal read ({end[i]} µs) precedes the end of the "
                                            f"reset read ({begin[i]} µs)")
        exposure = end - begin
        if not exposure.any():
            # Every sample of a frame at one time stamp (as iniVation's aedat4to2 writes them): not an exposure.
            self.notes.append("the APS samples of each frame carry a single time stamp: exposure times not recorded")
            exposure = None
        return FrameData(images, begin + (end - begin) // 2, exposure, lambda i: f"APS frame {i}")

    def _decode(self, a: np.ndarray, a0: int, counts: dict):
        w, h = self.width, self.height
        if self._layout == "dvs128":
            special = (a >> 15) & 1 == 1
            wide = a >= 1 << 16
            if wide.any():
                i = int(np.argmax(wide))
                raise RecordingError(self.path, f"address 0x{int(a[i]):08x} has bits above 16 set: not a DVS128 "
                                                f"address", f"record {a0 + i} of the data")
            keep = ~special
            xa, ya = (a >> 1) & 0x7F, (a >> 8) & 0x7F
            p = 1 - (a & 1)
        else:
            sample = (a >> 31) == 1
            kind = (a >> 10) & 3
            special = ~sample & ((a >> 10) & 1 == 1)
            counts["imu"] += int(np.sum(sample & (kind == 3)))
            counts["aps"] += int(np.sum(sample & (kind != 3)))
            keep = ~sample & ~special
            if self._multi:  # the camera index in bits 0-3 (DHP19)
                cam = (a & 0xF).astype(np.int64)
                ids, n = np.unique(cam[keep], return_counts=True)
                for c, k in zip(ids.tolist(), n.tolist()):
                    counts["cameras"][c] = counts["cameras"].get(c, 0) + k
                if self._camera is None and len(ids):
                    self._camera = int(cam[keep][0])
                keep &= cam == (self._camera if self._camera is not None else -1)
            xa, ya = (a >> 12) & 0x3FF, (a >> 22) & 0x1FF
            p = (a >> 11) & 1
        counts["special"] += int(np.sum(special))
        out = keep & ((xa >= w) | (ya >= h))
        if out.any():
            i = int(np.argmax(out))
            raise RecordingError(self.path, f"event address x={int(xa[i])}, y={int(ya[i])} lies outside the "
                                            f"{self.chip} sensor ({w} × {h})", f"record {a0 + i} of the data")
        x = (w - 1 - xa.astype(np.int64)) * keep
        y = (h - 1 - ya.astype(np.int64)) * keep
        return x, y, p.astype(np.int8), keep


class Aedat31Source(Source):
    """An AEDAT 3.1 file (cAER / DV legacy): polarity events and full-sensor frames of one event source."""

    format = "aedat3"

    def __init__(self, path: Path, time_unit: str | None = None):
        super().__init__(path, time_unit)
        if time_unit not in (None, "us"):
            raise RecordingError(path, f"AEDAT 3.1 stores µs; time_unit={time_unit!r} does not apply")
        version, lines, self._header_length = read_legacy_header(path)
        if version != "3.1":
            raise RecordingError(path, f"AEDAT version {version!r} is not supported: expected 2.0 or 3.1 (convert "
                                       f"3.0 files with DV)", "file header")
        self.sources: dict[int, str] = {}
        for ln in lines:
            m = re.match(r"\s*-?\s*source\s+(\d+)\s*:\s*(.*)$", ln, re.IGNORECASE)
            if m:
                self.sources[int(m.group(1))] = m.group(2).strip()
        self._size = file_size(path)
        self._source_id: int | None = None
        self._frames: list[tuple] | None = None
        # The packet table: (offset of the events, header) for every complete packet; one pass over the headers.
        self._packets, self._tail_note = self._scan()
        ids = sorted({int(h["source"]) for _, h in self._packets if int(h["type"]) in (1, 2)})
        if ids:
            self._source_id = ids[0]
            if len(ids) > 1:
                logger.info("%s: event sources %s; reading source %d", path, ids, ids[0])
        name = self.sources.get(self._source_id if self._source_id is not None else -1) \
            or (next(iter(self.sources.values())) if len(self.sources) == 1 else None)
        self.chip = name
        found = sensor_of(name) if name else None
        if found is not None:
            _, self.width, self.height = found

    def _scan(self) -> tuple[list[tuple[int, np.void]], str | None]:
        out: list[tuple[int, np.void]] = []
        pos = self._header_length
        k = 0
        with open(self.path, "rb") as f:
            while pos < self._size:
                if self._size - pos < 28:
                    return out, (f"the file ends inside the header of packet {k} ({self._size - pos} byte(s), "
                                 f"truncated): kept the {k} complete packets before it")
                f.seek(pos)
                h = np.frombuffer(f.read(28), _PACKET_HEADER)[0]
                size, number, capacity, valid = (int(h[n]) for n in ("size", "number", "capacity", "valid"))
                where = f"packet {k} (byte {pos})"
                if not (0 <= int(h["type"]) < 256) or size <= 0 or not 0 <= int(h["ts_offset"]) <= size - 4 \
                        or int(h["ts_overflow"]) < 0 or not 0 <= valid <= number <= capacity:
                    raise RecordingError(self.path, f"corrupted packet header: type {int(h['type'])}, event size "
                                                    f"{size}, timestamp offset {int(h['ts_offset'])}, overflow "
                                                    f"{int(h['ts_overflow'])}, capacity {capacity}, number {number}, "
                                                    f"valid {valid}", where)
                if int(h["type"]) == 1 and (size != 8 or int(h["ts_offset"]) != 4):
                    raise RecordingError(self.path, f"polarity packet with {size}-byte events (timestamp at "
                                                    f"{int(h['ts_offset'])}): expected 8 (at 4)", where)
                if int(h["type"]) == 2 and size < _FRAME31_HEADER.itemsize:
                    raise RecordingError(self.path, f"frame packet with {size}-byte events: shorter than the "
                                                    f"{_FRAME31_HEADER.itemsize}-byte frame header", where)
                end = pos + 28 + capacity * size
                if end > self._size:  # checked before anything of the packet is read or allocated
                    return out, (f"the file ends inside packet {k} (truncated, or a corrupted packet size): it "
                                 f"declares {capacity:,} events of {size} bytes at byte {pos}, {self._size - pos - 28:,} "
                                 f"bytes follow; kept the {k} complete packets before it")
                out.append((pos + 28, h))
                pos = end
                k += 1
        return out, None

    def chunks(self, chunk_events: int = DEFAULT_CHUNK_EVENTS, with_frames: bool = False) -> Iterator[RawChunk]:
        self.notes.clear()
        if self._tail_note:
            self.notes.append(self._tail_note)
        frames: list[tuple] = []
        rows = RowLocator()
        row_of = [0]

        def columns():
            with open(self.path, "rb") as f:
                for k, (offset, h) in enumerate(self._packets):
                    if int(h["source"]) != self._source_id:
                        continue
                    kind, number = int(h["type"]), int(h["number"])
                    if kind == 1 and number:
                        f.seek(offset)
                        ev = np.frombuffer(f.read(8 * number), _POLARITY31)
                        data = ev["data"]
                        valid = (data & 1) == 1
                        if not valid.all():
                            data, ts = data[valid], ev["t"][valid]
                        else:
                            ts = ev["t"]
                        if not len(data):
                            continue
                        if np.any(ts < 0):
                            i = int(np.argmax(ts < 0))
                            raise RecordingError(self.path, f"negative timestamp {int(ts[i])} (a 31-bit counter)",
                                                 f"packet {k}, event {i}")
                        t = (np.int64(int(h["ts_overflow"])) << 31) | ts.astype(np.int64)
                        rows.add(row_of[0], f"packet {k}")
                        row_of[0] += len(data)
                        yield t, (data >> 17) & 0x7FFF, (data >> 2) & 0x7FFF, ((data >> 1) & 1).astype(np.int8)
                    elif kind == 2 and with_frames and number:
                        self._read_frames(f, offset, h, k, frames)

        yield from numbered_chunks(columns(), chunk_events, rows)
        if with_frames:
            self._frames = frames

    def _read_frames(self, f, offset: int, h, k: int, frames: list) -> None:
        size, overflow = int(h["size"]), np.int64(int(h["ts_overflow"])) << 31
        for i in range(int(h["number"])):
            f.seek(offset + i * size)
            blob = f.read(size)
            fh = np.frombuffer(blob[:_FRAME31_HEADER.itemsize], _FRAME31_HEADER)[0]
            if not int(fh["info"]) & 1:
                continue
            channels = (int(fh["info"]) >> 1) & 7
            sx, sy, px, py = (int(fh[n]) for n in ("size_x", "size_y", "pos_x", "pos_y"))
            where = f"frame {i} of packet {k}"
            if channels not in (1, 3, 4) or sx <= 0 or sy <= 0 or \
                    _FRAME31_HEADER.itemsize + 2 * sx * sy * channels > size:
                raise RecordingError(self.path, f"corrupted frame header: {channels} channel(s), {sx} × {sy} pixels "
                                                f"in a {size}-byte event", where)
            times = [int(fh[n]) for n in ("exposure_start", "exposure_end")]
            if min(times) < 0 or times[1] < times[0]:
                raise RecordingError(self.path, f"exposure {times[0]}..{times[1]} µs is not an interval of 31-bit "
                                                f"times", where)
            pixels = np.frombuffer(blob, "<u2", sx * sy * channels, _FRAME31_HEADER.itemsize)
            pixels = pixels.reshape(sy, sx, channels) if channels > 1 else pixels.reshape(sy, sx)
            frames.append((pixels, overflow | times[0], overflow | times[1], (px, py), where))

    def frames(self) -> FrameData | None:
        if self._frames is None:
            for _ in self.chunks(with_frames=True):
                pass
        if not self._frames:
            return None
        frames = self._frames
        for pixels, _, _, (px, py), where in frames:
            if (px, py) != (0, 0) or (self.width is not None and pixels.shape[:2] != (self.height, self.width)):
                raise RecordingError(self.path, f"frame of {pixels.shape[1]} × {pixels.shape[0]} pixels at ({px}, "
                                                f"{py}): only full-sensor frames are supported", where)
        shapes = {p.shape for p, *_ in frames}
        if len(shapes) != 1:
            raise RecordingError(self.path, f"frames have different pixel layouts: {sorted(shapes)}")
        begin = np.array([b for _, b, _, _, _ in frames], np.int64)
        end = np.array([e for _, _, e, _, _ in frames], np.int64)
        return FrameData(np.stack([p for p, *_ in frames]), begin + (end - begin) // 2, end - begin,
                         lambda i: frames[i][4])


# ------------------------------------------------------------------------------------------------ writing (tests)
def write_aedat2(path: Path, events: np.ndarray, chip: str = "eu.seebetter.ini.chips.davis.DAVIS240C",
                 specials_every: int = 0, aps_samples: int = 0, frames=None) -> None:
    """Write ``EVENT_DTYPE`` events (file time µs, < 2^32) as jAER would: AEDAT 2.0, big-endian, x mirrored, y
    bottom-up. For tests and fixtures: ``specials_every`` inserts an external-input event after every n-th event,
    ``aps_samples`` appends stray APS samples (both left out by the reader), ``frames`` = ``(images (N, H, W) of
    10-bit values, reset_t_us, signal_t_us)`` writes global-shutter APS frames (reset reads, then signal reads)
    among the events by time."""
    layout, w, h = sensor_of(chip.rsplit(".", 1)[-1])
    xa = (w - 1 - events["x"].astype(np.uint32))
    ya = (h - 1 - events["y"].astype(np.uint32))
    on = (events["p"] > 0).astype(np.uint32)
    if layout == "dvs128":
        a = (ya << 8) | (xa << 1) | (1 - on)
        special = np.uint32(1 << 15)
    else:
        a = (ya << 22) | (xa << 12) | (on << 11)
        special = np.uint32(1 << 10)
    rec = np.empty(len(events), _AEDAT2_RECORD)
    rec["a"], rec["t"] = a, events["t"].astype(np.uint32)
    if specials_every:
        extra = np.empty(len(events) // specials_every, _AEDAT2_RECORD)
        extra["a"], extra["t"] = special, rec["t"][specials_every - 1::specials_every][:len(extra)]
        rec = np.insert(rec, np.arange(1, len(extra) + 1) * specials_every, extra)
    if frames is not None:
        images, t_reset, t_signal = frames
        n, h, w = images.shape
        rows, cols = np.mgrid[0:h, 0:w]
        xy = ((h - 1 - rows.ravel()).astype(np.uint32) << 22) | (cols.ravel().astype(np.uint32) << 12)
        parts = []
        for i in range(n):
            for kind, t, adc in ((0, t_reset[i], np.full(h * w, 1023, np.uint32)),
                                 (1, t_signal[i], 1023 - images[i].ravel().astype(np.uint32))):
                block = np.empty(h * w, _AEDAT2_RECORD)
                block["a"] = np.uint32(1 << 31) | xy | np.uint32(kind << 10) | adc
                block["t"] = int(t)
                parts.append(block)
        aps = np.concatenate(parts)
        order = np.argsort(np.concatenate([rec["t"].astype(np.int64), aps["t"].astype(np.int64)]), kind="stable")
        rec = np.concatenate([rec, aps])[order]
    if aps_samples:
        aps = np.empty(aps_samples, _AEDAT2_RECORD)
        aps["a"] = np.uint32(1 << 31) | (np.arange(aps_samples, dtype=np.uint32) % w << 12) | np.uint32(1 << 10)
        aps["t"] = rec["t"][-1]
        rec = np.concatenate([rec, aps])
    header = (b"#!AER-DAT2.0\r\n# This is a raw AE data file - do not edit\r\n"
              b"# Data format is int32 address, int32 timestamp (8 bytes total), repeated for each event\r\n"
              b"# Timestamps tick is 1 us\r\n# AEChip: " + chip.encode() + b"\r\n")
    # numpy's concatenate / insert may return native byte order: back to big-endian before writing.
    Path(path).write_bytes(header + rec.astype(_AEDAT2_RECORD).tobytes())


def write_aedat31(path: Path, events: np.ndarray, source: str = "DAVIS346B", packet_events: int = 4096,
                  frames=None, invalid_every: int = 0) -> None:
    """Write ``EVENT_DTYPE`` events (file time µs ≥ 0, sorted) as AEDAT 3.1 polarity packets of one source,
    with the timestamp overflow in the packet headers (a packet never spans an overflow); ``frames`` is
    ``(images uint16 (N, H, W), exposure_begin_us, exposure_end_us)`` written as frame packets before the events
    of their time; ``invalid_every`` marks every n-th event invalid (left out by the reader). For tests."""
    t = events["t"].astype(np.int64)
    data = (events["x"].astype(np.uint32) << 17) | (events["y"].astype(np.uint32) << 2) \
        | ((events["p"] > 0).astype(np.uint32) << 1) | np.uint32(1)
    if invalid_every:
        data[invalid_every - 1::invalid_every] &= ~np.uint32(1)
    parts = [b"#!AER-DAT3.1\r\n#Format: RAW\r\n#Source 1: " + source.encode() + b"\r\n"
             b"#Start-Time: 2020-01-01 00:00:00 (TZ+0000)\r\n#!END-HEADER\r\n"]
    packets: list[tuple[int, bytes]] = []
    over = t >> 31
    bounds = np.flatnonzero(np.diff(over)) + 1
    for seg in np.split(np.arange(len(t)), bounds):
        for a in range(0, len(seg), packet_events):
            idx = seg[a:a + packet_events]
            ev = np.empty(len(idx), _POLARITY31)
            ev["data"], ev["t"] = data[idx], (t[idx] & 0x7FFFFFFF)
            head = np.array([(1, 1, 8, 4, int(over[idx[0]]), len(idx), len(idx), len(idx))], _PACKET_HEADER)
            packets.append((int(t[idx[0]]), head.tobytes() + ev.tobytes()))
    if frames is not None:
        images, begin, end = frames
        n, hh, ww = images.shape
        for i in range(n):
            fh = np.zeros(1, _FRAME31_HEADER)
            b, e = int(begin[i]), int(end[i])
            fh[0] = (1 | (1 << 1), b & 0x7FFFFFFF, e & 0x7FFFFFFF, b & 0x7FFFFFFF, e & 0x7FFFFFFF, ww, hh, 0, 0)
            body = fh.tobytes() + np.ascontiguousarray(images[i], "<u2").tobytes()
            head = np.array([(2, 1, len(body), 12, b >> 31, 1, 1, 1)], _PACKET_HEADER)
            packets.append((b, head.tobytes() + body))
    packets.sort(key=lambda p: p[0])
    Path(path).write_bytes(b"".join(parts + [p for _, p in packets]))


def detect_version(head: bytes, path) -> str:
    """The format of a file starting with ``#!AER-DAT``: aedat2 or aedat3 by its version; others refused."""
    version = head[9:16].split(b"\r")[0].split(b"\n")[0].strip().decode("ascii", "replace")
    if version == "2.0":
        return "aedat2"
    if version == "3.1":
        return "aedat3"
    raise RecordingError(path, f"AEDAT version {version} is not supported (AEDAT 2.0, 3.1 and 4.0 are): convert it "
                               f"with DV or jAER", "file header")


READERS = [
    ReaderSpec(name="aedat2", description="jAER AEDAT 2.0 (DVS128, DAVIS240/346, DHP19): events, APS frames",
               extensions=(".aedat",), magic=(b"#!AER-DAT",), magic_name="an AEDAT", detect=
               "eventcap.io.aedat_legacy:detect_version", source="eventcap.io.aedat_legacy:Aedat2Source",
               wraps_us=(2**32,), extras="APS frames (global shutter)", library="our decoder (numpy)"),
    ReaderSpec(name="aedat3", description="cAER / DV legacy AEDAT 3.1: events, frames with exposure",
               extensions=(".aedat",), magic=(b"#!AER-DAT",), magic_name="an AEDAT",
               detect="eventcap.io.aedat_legacy:detect_version", source="eventcap.io.aedat_legacy:Aedat31Source",
               wraps_us=(2**31, 2**32), extras="frames + exposure", library="our decoder (numpy)"),
]
