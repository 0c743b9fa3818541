"""The rpg Event Camera Dataset text layout (Mueggler et al. 2017): a folder of text files and PNG frames.

::

    events.txt       one event per line: t x y p   (t in seconds, p in {0, 1} or {-1, 1})
    images.txt       one frame per line: t path     (path relative to the folder, e.g. images/frame_00000000.png)
    images/          the frames (8- or 16-bit PNG)
    calib.txt        fx fy cx cy k1 k2 p1 p2 k3     (read with eventcap.camera.read_rpg_calibration)
    groundtruth.txt  t px py pz qx qy qz qw         (optional; becomes ground_truth {"t_us", "pose"})

A path to a folder reads all of it; a path to a text file reads that file as events (and, if it is called
``events.txt``, the other files beside it). Other text event files (``.txt``, ``.csv``) read the same way:
fields separated by spaces or commas; the column order is ``columns=`` if given, else a first line of names
(``x,y,t,p``), else t x y p — or x y t p when only the third column is time-ordered (noted). The sensor size comes from the frames, else the caller, else the
events (noted). Frame exposure is not recorded by the layout (``exposure_us`` is ``None``). Blank lines and
``#`` comments are skipped; an incomplete last line without a newline (a truncated file) is dropped and noted;
any other malformed line is an error naming its line number.
"""

from __future__ import annotations

import itertools
import os
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from eventcap.camera import Camera, read_rpg_calibration
from eventcap.io.checks import RawChunk, times_to_us
from eventcap.io.recording import RecordingError
from eventcap.io.registry import ReaderSpec
from eventcap.io.source import (
    DEFAULT_CHUNK_EVENTS,
    FrameData,
    Source,
    check_fits_in_memory,
    native_call,
)

EVENTS, IMAGES, CALIB, GROUND_TRUTH = "events.txt", "images.txt", "calib.txt", "groundtruth.txt"


def _data_line(line: str) -> bool:
    s = line.strip()
    return bool(s) and not s.startswith("#")


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _parse_line(line: str, n_fields: int) -> str | None:
    """Why ``line`` is not ``n_fields`` numbers, or ``None`` if it is."""
    fields = line.split("#", 1)[0].split()
    if len(fields) != n_fields:
        return f"expected {n_fields} numbers, got {len(fields)}"
    for k, tok in enumerate(fields):
        try:
            float(tok)
        except ValueError:
            return f"field {k + 1} is not a number: {tok!r}"
    return None


class RpgSource(Source):
    """A folder in the rpg layout (or a single events text file)."""

    format = "rpg"

    def __init__(self, path: Path, time_unit: str | None = None, columns: tuple[str, ...] | None = None):
        super().__init__(path, time_unit)
        self.columns = columns
        self._order: tuple[int, int, int, int] | None = None  # column indices of t, x, y, p, once known
        self._header_line: int | None = None  # line number of a line of column names
        if path.is_dir():
            self.folder, self.events_path = path, path / EVENTS
            if not self.events_path.is_file():
                raise RecordingError(path, f"no {EVENTS} in the folder (found {sorted(os.listdir(path))[:20]})")
        else:
            self.folder, self.events_path = path.parent, path
        self._siblings = path.is_dir() or path.name == EVENTS
        self._read_column_names()
        self._images = self._read_images_txt() if self._siblings else None
        if self._images:
            first = self._read_image(0)
            self.height, self.width = int(first.shape[0]), int(first.shape[1])

    # ------------------------------------------------------------------------------------------------ events
    def _read_column_names(self) -> None:
        """The column order from ``columns=`` or from a first data line of names (a csv header)."""
        from eventcap.io.source import columns_of_2d

        first, lineno = None, 0
        try:
            with open(self.events_path, encoding="utf-8", errors="replace") as f:
                for lineno, line in enumerate(f, 1):
                    if _data_line(line):
                        first = line
                        break
                    if lineno > 1000:
                        break
        except OSError as exc:
            raise RecordingError(self.events_path, f"cannot read the file: {exc}") from exc
        names = None
        if first is not None and _parse_line(first.replace(",", " "), 4) is not None:
            tokens = [t.strip().strip('"') for t in first.replace(",", " ").split()]
            if len(tokens) == 4 and not any(_is_number(t) for t in tokens):
                names = tokens
                self._header_line = lineno
        declared = self.columns or names
        if declared is not None:
            try:
                self._order = columns_of_2d(self.events_path, np.empty((0, 4)), declared)[0]
            except RecordingError as exc:
                raise RecordingError(self.events_path, exc.what, f"{self.events_path.name} line {lineno}"
                                     if names and not self.columns else "columns=") from None

    def _columns_of(self, block: np.ndarray) -> tuple[int, int, int, int]:
        if self._order is None:
            from eventcap.io.source import columns_of_2d

            self._order = (0, 1, 2, 3)
            if len(block) >= 3:
                try:
                    order, note = columns_of_2d(self.events_path, block[:100_000])
                except RecordingError:
                    order, note = (0, 1, 2, 3), None  # the layout's own t x y p; disorder is repaired later
                self._order = order
                if order != (0, 1, 2, 3) and note:
                    self.notes.append(f"{self.events_path.name}: {note}")
        return self._order

    def _line_of_row(self, row: int) -> str:
        """"events.txt line L" of data row ``row`` (scans the file; only used for error messages)."""
        with open(self.events_path, errors="replace") as f:
            k = -1
            for lineno, line in enumerate(f, 1):
                if _data_line(line) and lineno != self._header_line:
                    k += 1
                    if k == row:
                        return f"{self.events_path.name} line {lineno}"
        return f"{self.events_path.name} event {row}"

    def chunks(self, chunk_events: int = DEFAULT_CHUNK_EVENTS, with_frames: bool = False) -> Iterator[RawChunk]:
        self.notes[:] = [n for n in self.notes if not n.startswith(EVENTS)]
        size = self.events_path.stat().st_size
        ends_with_newline = True
        if size:
            with open(self.events_path, "rb") as f:
                f.seek(size - 1)
                ends_with_newline = f.read(1) in (b"\n", b"\r")
        row = 0
        first_line = 1
        with native_call(self.events_path, "text reader", "file"), \
                open(self.events_path, encoding="utf-8", errors="strict", newline=None) as f:

            def read_block():
                try:
                    return list(itertools.islice(f, chunk_events))
                except UnicodeDecodeError as exc:
                    raise RecordingError(self.events_path, f"not UTF-8 text ({exc.reason})",
                                         f"{self.events_path.name} after line {first_line - 1}") from exc

            lines = read_block()
            while lines:
                lines = [ln.replace(",", " ") for ln in lines]
                if self._header_line is not None and 0 <= self._header_line - first_line < len(lines):
                    lines[self._header_line - first_line] = "# column names\n"
                following = read_block()  # one block ahead, to know which block holds the file's last line
                try:
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore", UserWarning)  # a block of comments only is fine
                        block = np.loadtxt(lines, dtype=np.float64, ndmin=2, comments="#")
                except ValueError:
                    block = self._parse_slowly(lines, first_line, not following and not ends_with_newline)
                if block.size and block.shape[1] != 4:
                    bad = next(i for i, ln in enumerate(lines) if _data_line(ln))
                    raise RecordingError(self.events_path, f"expected 4 numbers t x y p, got {block.shape[1]}",
                                         f"{self.events_path.name} line {first_line + bad}")
                if len(block):
                    ct, cx, cy, cp = self._columns_of(block)
                    yield RawChunk(block[:, ct], block[:, cx], block[:, cy], block[:, cp], row, self._line_of_row)
                    row += len(block)
                first_line += len(lines)
                lines = following

    def _parse_slowly(self, lines: list[str], first_line: int, may_be_truncated: bool) -> np.ndarray:
        """Find the malformed line of a block: the truncated last line is dropped (noted), any other is an error."""
        data = [(i, ln) for i, ln in enumerate(lines) if _data_line(ln)]
        for k, (i, ln) in enumerate(data):
            why = _parse_line(ln, 4)
            if why is None:
                continue
            lineno = first_line + i
            if k == len(data) - 1 and may_be_truncated:
                self.notes.append(f"{EVENTS}: the last line ({lineno}) is incomplete ({why}; truncated file?): "
                                  f"dropped")
                kept = [ln for _, ln in data[:-1]]
                return np.loadtxt(kept, dtype=np.float64, ndmin=2) if kept else np.empty((0, 4))
            raise RecordingError(self.events_path, f"{why} (expected 't x y p'): {ln.strip()[:80]!r}",
                                 f"{self.events_path.name} line {lineno}")
        raise RecordingError(self.events_path, "cannot parse the lines as numbers t x y p",
                             f"{self.events_path.name} lines {first_line}..{first_line + len(lines) - 1}")

    # ------------------------------------------------------------------------------------------------ frames
    def _read_images_txt(self) -> list[tuple[float, str, int]] | None:
        path = self.folder / IMAGES
        if not path.is_file():
            return None
        out = []
        with native_call(path, "text reader", "file"):
            text = path.read_text(encoding="utf-8")
        for lineno, line in enumerate(text.splitlines(), 1):
            if not _data_line(line):
                continue
            fields = line.split("#", 1)[0].split()
            try:
                if len(fields) != 2:
                    raise ValueError(f"expected 2 fields 't path', got {len(fields)}")
                t = float(fields[0])
                if not np.isfinite(t):
                    raise ValueError(f"time {fields[0]!r} is not finite")
            except ValueError as exc:
                raise RecordingError(path, f"{exc}: {line.strip()[:80]!r}", f"line {lineno}") from None
            out.append((t, fields[1], lineno))
        return out or None

    def _read_image(self, i: int) -> np.ndarray:
        import cv2

        _, rel, lineno = self._images[i]
        where = f"{IMAGES} line {lineno}"
        image_path = self.folder / rel
        if not image_path.is_file():
            raise RecordingError(self.folder / IMAGES, f"image file {rel!r} does not exist", where)
        image = cv2.imread(str(image_path), cv2.IMREAD_UNCHANGED)
        if image is None or image.ndim not in (2, 3) or image.size == 0:
            raise RecordingError(image_path, "cannot decode the image (corrupted or not an image)", where)
        if image.ndim == 3:
            code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
            image = cv2.cvtColor(image, code)
        return image

    def frames(self) -> FrameData | None:
        if not self._images:
            return None
        first = self._read_image(0)
        check_fits_in_memory(self.folder / IMAGES, len(self._images) * first.nbytes, "the frames")
        images = np.empty((len(self._images), *first.shape), dtype=first.dtype)
        images[0] = first
        for i in range(1, len(self._images)):
            image = self._read_image(i)
            if image.shape != first.shape or image.dtype != first.dtype:
                raise RecordingError(self.folder / IMAGES, f"image {self._images[i][1]!r} is {image.shape} "
                                                           f"{image.dtype}, the first is {first.shape} {first.dtype}",
                                     f"line {self._images[i][2]}")
            images[i] = image
        lines = [im[2] for im in self._images]
        locate = lambda i: f"{IMAGES} line {lines[i]}"
        t = times_to_us(self.folder / IMAGES, np.array([im[0] for im in self._images]), self.time_unit or "s",
                           "frame time", locate)
        return FrameData(images, t, None, locate)

    def calibration(self, width: int, height: int) -> Camera | None:
        path = self.folder / CALIB
        if not (self._siblings and path.is_file()):
            return None
        try:
            return read_rpg_calibration(path, width, height)
        except ValueError as exc:
            raise RecordingError(path, str(exc).removeprefix(f"{path}: ")) from exc

    def ground_truth(self) -> dict[str, np.ndarray] | None:
        path = self.folder / GROUND_TRUTH
        if not (self._siblings and path.is_file()):
            return None
        with native_call(path, "text reader", "file"):
            lines = path.read_text(encoding="utf-8").splitlines()
        for lineno, line in enumerate(lines, 1):
            why = _parse_line(line, 8) if _data_line(line) else None
            if why:
                raise RecordingError(path, f"{why} (expected 't px py pz qx qy qz qw')", f"line {lineno}")
        data = np.loadtxt([ln for ln in lines if _data_line(ln)], dtype=np.float64, ndmin=2).reshape(-1, 8)
        if not np.all(np.isfinite(data)):
            raise RecordingError(path, "non-finite values")
        t = times_to_us(path, data[:, 0], self.time_unit or "s", "time", lambda i: f"data line {i + 1}")
        return {"t_us": t, "pose": data[:, 1:]}


def write_rpg(folder: Path, events: Iterator[np.ndarray], frames=None, calibration=None,
              ground_truth=None) -> None:
    """Write the rpg layout into ``folder`` (which must not exist yet): events as exact decimal seconds.

    ``events``: ``EVENT_DTYPE`` chunks in file time (µs ≥ 0); ``frames``: (images float32 (N,H,W) in [0, 1],
    t_us, exposure ignored), written as 8-bit PNGs; ``calibration``: a :class:`Camera`; ``ground_truth``:
    ``{"t_us": (N,), "pose": (N, 7)}`` (file time), written as ``groundtruth.txt``.
    """
    if ground_truth and (set(ground_truth) != {"t_us", "pose"} or np.shape(ground_truth["pose"])[1:] != (7,)):
        raise ValueError(f"the rpg layout stores ground truth as t_us (N,) and pose (N, 7), got "
                         f"{ {k: np.shape(v) for k, v in ground_truth.items()} }")
    import cv2

    folder.mkdir(parents=True)
    with open(folder / EVENTS, "w") as f:
        for chunk in events:
            t = chunk["t"].astype(np.int64)
            if len(t) and t.min() < 0:
                raise ValueError(f"the rpg layout stores times as seconds ≥ 0: got t = {int(t.min())} µs")
            secs, micro = np.divmod(t, 1_000_000)
            p01 = (chunk["p"] > 0).astype(np.int64)
            rows = np.stack([secs, micro, chunk["x"].astype(np.int64), chunk["y"].astype(np.int64), p01], axis=1)
            f.write("".join(f"{s}.{m:06d} {x} {y} {p}\n" for s, m, x, y, p in rows.tolist()))
    if frames is not None:
        images, t_us, _ = frames
        (folder / "images").mkdir()
        with open(folder / IMAGES, "w") as f:
            for i, (image, t) in enumerate(zip(images, np.asarray(t_us, dtype=np.int64))):
                rel = f"images/frame_{i:08d}.png"
                if not cv2.imwrite(str(folder / rel), np.clip(np.rint(image * 255.0), 0, 255).astype(np.uint8)):
                    raise OSError(f"cannot write {folder / rel}")
                secs, micro = divmod(int(t), 1_000_000)
                f.write(f"{secs}.{micro:06d} {rel}\n")
    if calibration is not None:
        c = calibration
        values = [c.fx, c.fy, c.cx, c.cy, *c.dist]
        (folder / CALIB).write_text(" ".join(repr(float(v)) for v in values) + "\n")
    if ground_truth:
        with open(folder / GROUND_TRUTH, "w") as f:
            for t, pose in zip(np.asarray(ground_truth["t_us"], dtype=np.int64), np.asarray(ground_truth["pose"])):
                secs, micro = divmod(int(t), 1_000_000)
                f.write(f"{secs}.{micro:06d} " + " ".join(repr(float(v)) for v in pose) + "\n")


def detect_folder(head, path) -> str | None:
    """An rpg dataset folder is one with events.txt (a regular file) in it."""
    from eventcap.io.source import regular_sibling

    return "rpg" if head is None and regular_sibling(Path(path) / EVENTS) else None


READERS = [ReaderSpec(
    name="rpg", description="text columns (csv/txt) or an rpg Event Camera Dataset folder (events.txt, images.txt, "
                        "calib.txt)", extensions=(".txt", ".csv"), source="eventcap.io.rpg:RpgSource", columns=True,
    folder=True, detect="eventcap.io.rpg:detect_folder", declares_size=False, extras="frames, calib.txt, ground truth",
    library="numpy, OpenCV")]
