"""AEDAT 4 (iniVation DV) recordings: events and APS frames read with ``aedat``, events written with ``faery``.

``aedat`` is used for reading because it hands over events as stored (``faery``'s decoder silently clamps
out-of-order timestamps and aborts on the first out-of-sensor event), and frames with their exposure times.
Frame times: the exposure centre ``(exposure_begin_t + exposure_end_t) // 2`` (the DV frame's own ``t`` is the
same instant), exposure = ``exposure_end_t - exposure_begin_t``.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from eventcap.io.checks import RawChunk
from eventcap.io.recording import RecordingError, logger
from eventcap.io.registry import ReaderSpec
from eventcap.io.source import DEFAULT_CHUNK_EVENTS, FrameData, RowLocator, Source, native_call, numbered_chunks

MAGIC = b"#!AER-DAT4.0"
_TRUNCATED = ("failed to fill whole buffer", "UnexpectedEof", "unexpected end of file")
# Decompression failures of one packet (its checksum or frame header): the decoder has read past the packet
# and goes on with the next one, so the packet is skipped and reported.
_CORRUPT_PACKET = ("LZ4 error", "lz4", "zstd", "Zstd", "ZSTD")
_MAX_CORRUPT_PACKETS = 16


def check_ioheader(path: Path) -> tuple[int, int]:
    """Bounds- and UTF-8-check the file's IO header (a small flatbuffer) before a native decoder sees it; return
    (the byte where the packets start, the header's file_data_position: where they end, or -1).

    Both ``aedat`` and ``faery`` read this header without flatbuffer verification; a corrupted header then
    hands invalid UTF-8 or out-of-range offsets to Rust code, which aborts the interpreter. The check follows
    the flatbuffer layout of ``ioheader.fbs`` (table Ioheader {compression: int32; file_data_position: int64;
    description: string}) and only reads offsets, it decodes nothing.
    """
    with open(path, "rb") as f:
        head = f.read(len(MAGIC) + 2 + 4)
        if len(head) < len(MAGIC) + 6:
            raise RecordingError(path, "the file ends inside the AEDAT4 header (truncated)", "file header")
        length = int.from_bytes(head[-4:], "little")
        buf = f.read(min(length, 1 << 26))
    if len(buf) < length:
        raise RecordingError(path, f"the AEDAT4 header declares {length} bytes but {len(buf)} follow (truncated or "
                                   f"corrupted)", "file header")

    def u(offset: int, size: int, what: str) -> int:
        if offset < 0 or offset + size > len(buf):
            raise RecordingError(path, f"corrupted IO header: {what} at byte {offset} lies outside the header's "
                                       f"{len(buf)} bytes", "file header")
        return int.from_bytes(buf[offset:offset + size], "little", signed=False)

    table = u(0, 4, "root table offset")
    soffset = u(table, 4, "table")
    vtable = table - (soffset - (1 << 32) if soffset >= 1 << 31 else soffset)
    vt_len, table_len = u(vtable, 2, "vtable"), u(vtable + 2, 2, "vtable")
    u(vtable, vt_len, "vtable")
    u(table, table_len, "table")
    fields = [u(vtable + 4 + 2 * k, 2, "vtable entry") if 4 + 2 * k + 2 <= vt_len else 0 for k in range(3)]
    if any(fo >= table_len for fo in fields if fo) or (fields[0] and fields[0] + 4 > table_len) \
            or (fields[1] and fields[1] + 8 > table_len) or (fields[2] and fields[2] + 4 > table_len):
        raise RecordingError(path, "corrupted IO header: a field lies outside its table", "file header")
    if fields[2]:
        ref = table + fields[2]
        start = ref + u(ref, 4, "description offset")
        n = u(start, 4, "description length")
        u(start + 4, n, "description")
        try:
            buf[start + 4:start + 4 + n].decode("utf-8")
        except UnicodeDecodeError as exc:
            raise RecordingError(path, f"corrupted IO header: the stream description is not UTF-8 ({exc.reason} at "
                                       f"byte {start + 4 + exc.start} of the header)", "file header") from None
    data_position = -1
    if fields[1]:
        raw = u(table + fields[1], 8, "file_data_position")
        data_position = raw - (1 << 64) if raw >= 1 << 63 else raw
    return len(MAGIC) + 2 + 4 + length, data_position


def scan_packets(path: Path, start: int, data_position: int) -> tuple[int, str | None]:
    """Check every packet's declared size against the bytes that follow it, before a decoder allocates it: (the
    number of complete packets, a note when the last one declares more bytes than the file holds). A packet is
    a 4-byte stream id and a 4-byte size, then that many bytes; the packets end at the header's
    file_data_position (when given) or at the end of the file."""
    import os

    end = os.path.getsize(path)
    if 0 < data_position <= end:
        end = data_position
    pos, k = start, 0
    with open(path, "rb") as f:
        while pos < end:
            if end - pos < 8:
                return k, (f"the file ends inside the header of packet {k} ({end - pos} byte(s) at byte {pos}, "
                           f"truncated): kept the {k} complete packets before it")
            f.seek(pos + 4)
            size = int.from_bytes(f.read(4), "little")
            if pos + 8 + size > end:
                return k, (f"packet {k} at byte {pos} declares {size:,} bytes but {end - pos - 8:,} follow (a "
                           f"truncated file, or a corrupted packet size): kept the {k} complete packets before it")
            pos += 8 + size
            k += 1
    return k, None


class Aedat4Source(Source):
    """An AEDAT 4 file: the first event stream (and the first frame stream, if any)."""

    format = "aedat4"

    def __init__(self, path: Path, time_unit: str | None = None):
        super().__init__(path, time_unit)
        import aedat

        self._aedat = aedat
        self._complete, self._cut_note = scan_packets(path, *check_ioheader(path))
        with native_call(path, "AEDAT4 decoder (aedat)", "file header"):
            streams = aedat.Decoder(str(path)).id_to_stream()
        events = sorted(i for i, s in streams.items() if s.get("type") == "events")
        if not events:
            raise RecordingError(path, f"no event stream (streams: {streams})", "file header")
        self._event_id = events[0]
        info = streams[self._event_id]
        try:
            self.width, self.height = int(info["width"]), int(info["height"])
        except (KeyError, TypeError, ValueError):
            raise RecordingError(path, f"event stream {self._event_id} has no sensor size ({info})",
                                 "file header") from None
        if not (0 < self.width <= 65536 and 0 < self.height <= 65536):
            raise RecordingError(path, f"event stream declares a {self.width} × {self.height} sensor", "file header")
        if len(events) > 1:
            logger.info("%s: %d event streams, reading stream %d", path, len(events), self._event_id)
        frames = sorted(i for i, s in streams.items() if s.get("type") == "frame")
        self._frame_id = frames[0] if frames else None
        self._frames: list[dict] | None = None

    def _packets(self) -> Iterator[tuple[int, dict]]:
        """(packet index, packet) in file order; a file that ends inside a packet stops with a note."""
        decoder = None
        with native_call(self.path, "AEDAT4 decoder (aedat)", "file header"):
            decoder = self._aedat.Decoder(str(self.path))
        k = 0
        corrupt: list[str] = []
        while True:
            if k == self._complete:  # the packets after it declare more bytes than the file holds: never read
                self._note_corrupt(corrupt)
                if self._cut_note:
                    self.notes.append(self._cut_note)
                return
            try:
                packet = next(decoder)
            except StopIteration:
                self._note_corrupt(corrupt)
                return
            except (KeyboardInterrupt, SystemExit, GeneratorExit):
                raise
            except BaseException as exc:
                message = str(exc)
                if any(s in message for s in _TRUNCATED):
                    self._note_corrupt(corrupt)
                    self.notes.append(f"the file ends inside packet {k} (truncated, or a corrupted packet size): "
                                      f"kept the {k} complete packets before it")
                    return
                if any(s in message for s in _CORRUPT_PACKET) and len(corrupt) < _MAX_CORRUPT_PACKETS:
                    corrupt.append(f"packet {k} ({message.strip()[:80]})")
                    k += 1
                    continue
                raise RecordingError(self.path, f"AEDAT4 decoder (aedat) failed: {type(exc).__name__}: {message}",
                                     f"packet {k}") from exc
            yield k, packet
            k += 1

    def _note_corrupt(self, corrupt: list[str]) -> None:
        if corrupt:
            self.notes.append(f"skipped {len(corrupt)} corrupted compressed packet(s) whose data does not decompress, "
                              f"their events are missing: {'; '.join(corrupt[:4])}" + (" ..." if len(corrupt) > 4
                                                                                        else ""))

    def chunks(self, chunk_events: int = DEFAULT_CHUNK_EVENTS, with_frames: bool = False) -> Iterator[RawChunk]:
        self.notes.clear()
        frames: list[dict] = []
        locate = RowLocator()
        row = 0

        def columns():
            nonlocal row
            for k, packet in self._packets():
                if packet.get("stream_id") == self._event_id and "events" in packet:
                    ev = packet["events"]
                    locate.add(row, f"packet {k}")
                    row += len(ev)
                    yield ev["t"], ev["x"], ev["y"], ev["on"]
                elif with_frames and packet.get("stream_id") == self._frame_id and "frame" in packet:
                    frames.append({**packet["frame"], "packet": k})

        yield from numbered_chunks(columns(), chunk_events, locate)
        if with_frames:
            self._frames = frames

    def frames(self) -> FrameData | None:
        if self._frame_id is None:
            return None
        if self._frames is None:
            for _ in self.chunks(with_frames=True):
                pass
        if not self._frames:
            return None
        frames = self._frames
        locate = lambda i: f"frame {i} (packet {frames[i]['packet']})"
        images = []
        for i, f in enumerate(frames):
            if (f["offset_x"], f["offset_y"]) != (0, 0) or (f["width"], f["height"]) != (self.width, self.height):
                raise RecordingError(self.path, f"frame of width {f['width']} and height {f['height']} at offset "
                                                f"({f['offset_x']}, {f['offset_y']}): only full-sensor frames "
                                                f"({self.width} × {self.height}) are supported", locate(i))
            images.append(f["pixels"])
        begin = np.array([f["exposure_begin_t"] for f in frames], dtype=np.int64)
        end = np.array([f["exposure_end_t"] for f in frames], dtype=np.int64)
        far = (begin >= 2**62) | (begin <= -(2**62)) | (end >= 2**62) | (end <= -(2**62))
        if far.any():
            i = int(np.argmax(far))
            raise RecordingError(self.path, f"exposure times {begin[i]}..{end[i]} µs are out of range", locate(i))
        bad = end < begin
        if bad.any():
            i = int(np.argmax(bad))
            raise RecordingError(self.path, f"exposure ends ({end[i]} µs) before it begins ({begin[i]} µs)", locate(i))
        shapes = {im.shape for im in images}
        if len(shapes) != 1:
            raise RecordingError(self.path, f"frames have different pixel layouts: {sorted(shapes)}")
        return FrameData(np.stack(images), begin + (end - begin) // 2, end - begin, locate)


def write_aedat4(path: Path, chunks: Iterator[np.ndarray], width: int, height: int) -> None:
    """Write faery-dtype event chunks (absolute µs, sorted) as an LZ4-compressed AEDAT 4 file (events only)."""
    import faery

    a = faery.aedat
    info = a.DescriptionNode("info", "/mainloop/Recorder/outInfo/0/info/", {
        "sizeX": a.DescriptionAttribute("int", int(width)),
        "sizeY": a.DescriptionAttribute("int", int(height)),
        "source": a.DescriptionAttribute("string", "eventcap"),
    }, [])
    stream = a.DescriptionNode("0", "/mainloop/Recorder/outInfo/0/", {
        "compression": a.DescriptionAttribute("string", "LZ4"),
        "originalOutputName": a.DescriptionAttribute("string", "events"),
        "typeIdentifier": a.DescriptionAttribute("string", "EVTS"),
    }, [info])
    description = [a.DescriptionNode("outInfo", "/mainloop/Recorder/outInfo/", {}, [stream])]
    with a.Encoder(path=path, description=description, compression=a.LZ4_DEFAULT) as encoder:
        for chunk in chunks:
            if len(chunk):
                encoder.write(0, chunk)


READERS = [ReaderSpec(
    name="aedat4", description="iniVation DV AEDAT 4.0: events, frames with exposure", extensions=(".aedat4",),
    magic=(MAGIC,), magic_name="an AEDAT4", source="eventcap.io.aedat4:Aedat4Source", library="aedat (read), faery (write)",
    extras="frames + exposure")]
