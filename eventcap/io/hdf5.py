"""HDF5 event files (h5py): the common layouts in, one documented layout out.

Read (event columns found by name, case-insensitive, see ``source.COLUMN_NAMES``):

- a group ``events`` (or the root) holding 1-D datasets ``t, x, y, p`` (aliases ``ts``, ``timestamp``, ``xs``,
  ``polarity``, ...), as DSEC and many exports; a root dataset ``t_offset`` (µs) is added to the times;
- a dataset ``events``: compound with such fields, or 2-D (N, 4) whose columns are named by an attribute
  ``columns`` (e.g. ``"t,x,y,p"``) or, failing that, recognised by which column is time-ordered;
- time unit from an attribute ``units`` / ``unit`` / ``time_unit`` on the time dataset or its group, else
  integers are µs and floats seconds;
- sensor size from attributes ``width`` / ``height`` (or ``sensor_width`` / ``sensor_height``) on the root,
  the events group or dataset, else from the frames, else inferred from the events by the reader (noted);
- optional frames: a group ``frames`` (``images``/``data`` + ``t_us``/``t``/``ts``/``timestamps`` +
  optional ``exposure_us``/``exposure``), or a root dataset ``frames``/``images`` with ``<name>_t_us``,
  ``<name>_ts``, ``<name>_t`` or ``<name>_timestamps`` beside it; frame times follow the same unit rule;
- optional ``calibration`` group (attributes ``fx fy cx cy``, ``dist`` (5,) attribute or dataset) and
  ``ground_truth`` group (its datasets, as stored).

Written (:func:`write_hdf5`): root attributes ``width``, ``height``; ``events/t`` int64 µs (file time,
``units="us"``), ``events/x``, ``events/y`` uint16, ``events/p`` int8 ±1, chunked and gzip-compressed;
``frames/images`` float32 (N, H, W) in [0, 1], ``frames/t_us``, ``frames/exposure_us``; ``calibration`` and
``ground_truth`` as above.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from eventcap.camera import Camera
from eventcap.io.checks import RawChunk, parse_time_unit, times_to_us
from eventcap.io.recording import RecordingError
from eventcap.io.registry import ReaderSpec
from eventcap.io.source import (
    DEFAULT_CHUNK_EVENTS,
    FrameData,
    Source,
    check_fits_in_memory,
    columns_of_2d,
    match_columns,
    native_call,
    probe_in_child,
)

MAGIC = b"\x89HDF\r\n\x1a\n"
_WIDTH_NAMES = (("width", "height"), ("sensor_width", "sensor_height"))
_FRAME_IMAGES = ("images", "data", "frames")
_FRAME_TIMES = ("t_us", "t", "ts", "timestamps", "time")
_FRAME_EXPOSURES = ("exposure_us", "exposure", "exposures")
_WHAT = "HDF5 reader (h5py)"


def _attr_unit(*objects) -> str | None:
    for obj in objects:
        for key in ("units", "unit", "time_unit"):
            if obj is not None and key in obj.attrs:
                value = obj.attrs[key]
                try:
                    return parse_time_unit(value.item() if hasattr(value, "item") else value)
                except ValueError:
                    continue
    return None


def _child(group, names):
    """The first member of ``group`` whose name matches one of ``names`` (case-insensitive), else ``None``."""
    lower = {k.lower(): k for k in group}
    for n in names:
        if n in lower:
            return group[lower[n]]
    return None


class Hdf5Source(Source):
    """An HDF5 file in one of the layouts of the module docstring."""

    format = "hdf5"

    def __init__(self, path: Path, time_unit: str | None = None, columns: tuple[str, ...] | None = None):
        super().__init__(path, time_unit)
        self.columns = columns
        import h5py

        self._h5py = h5py
        probe_in_child(path, _WHAT, lambda: self._structure(probe=True))
        self._structure()

    def _structure(self, probe: bool = False) -> None:
        """Read the file's layout, size, time offset and frames' place (in a probe: also the first events and the
        calibration, which read more of the metadata)."""
        path, h5py = self.path, self._h5py
        with native_call(path, _WHAT, "file structure"), self._open() as f:
            self._layout = self._find_events(f)
            self._size_from_attrs(f)
            if "t_offset" in f and isinstance(f["t_offset"], h5py.Dataset) and f["t_offset"].shape in ((), (1,)):
                self.t_add_us = int(np.asarray(f["t_offset"][()]).reshape(-1)[0])
                if abs(self.t_add_us) >= 2**62:
                    raise RecordingError(path, f"t_offset {self.t_add_us} µs is out of range", "/t_offset")
            self._frames_key = self._find_frames(f)
            if self.width is None and self._frames_key is not None:
                shape = f[self._frames_key[0]].shape
                self.height, self.width = int(shape[1]), int(shape[2])
                self.notes.append(f"sensor size not in the file: taken from the frames ({self.width} × {self.height})")
        if probe:
            next(iter(self.chunks(1 << 16)), None)
            self.frames()
            self.calibration(self.width or 1, self.height or 1)
            self.ground_truth()

    def _open(self):
        return self._h5py.File(self.path, "r", locking=False)

    def _check_stored(self, ds) -> None:
        """Refuse a dataset that declares more than the file stores (checked from its metadata, before anything is
        read or allocated): a contiguous dataset whose bytes are not all in the file, or a chunked one whose chunks
        are not all written. HDF5 reads what was never written as the fill value (zeros), silently; a corrupted
        shape declares terabytes the file cannot hold."""
        h5d = self._h5py.h5d
        nbytes = int(np.prod(ds.shape, dtype=np.float64) * ds.dtype.itemsize) if ds.shape else ds.dtype.itemsize
        with native_call(self.path, _WHAT, ds.name):
            layout = ds.id.get_create_plist().get_layout()
            stored = int(ds.id.get_storage_size())
            if layout == h5d.CONTIGUOUS and nbytes and stored < nbytes:
                raise RecordingError(self.path, f"dataset {ds.name} declares shape {ds.shape} of {ds.dtype} "
                                                f"({nbytes:,} bytes) but the file stores {stored:,} bytes of it: a "
                                                f"corrupted shape, or data never written (read back as zeros)",
                                     ds.name)
            if layout == h5d.CHUNKED and ds.shape and all(ds.shape):
                expected = int(np.prod([-(-n // c) for n, c in zip(ds.shape, ds.chunks)], dtype=np.float64))
                have = int(ds.id.get_num_chunks()) if expected < 1 << 40 else 0
                if have < expected:
                    raise RecordingError(self.path, f"dataset {ds.name} declares shape {ds.shape} in {expected:,} "
                                                    f"chunks of {ds.chunks} but the file holds {have:,} of them "
                                                    f"({stored:,} bytes): a corrupted shape, or data never written "
                                                    f"(the missing chunks would read back as zeros)", ds.name)

    # ----------------------------------------------------------------------------------------------- layout
    def _find_events(self, f) -> tuple:
        h5py = self._h5py
        groups = [g for g in (f.get("events"), f) if isinstance(g, h5py.Group)]
        for g in groups:
            datasets = [k for k in g if isinstance(g[k], h5py.Dataset) and g[k].ndim == 1]
            roles = match_columns(datasets)
            if roles is None:
                continue
            names = {r: f"{g.name.rstrip('/')}/{n}" for r, n in roles.items()}
            lengths = {r: g[n].shape[0] for r, n in roles.items()}
            for n in roles.values():
                self._check_stored(g[n])
            if len(set(lengths.values())) != 1:
                raise RecordingError(self.path, f"event columns differ in length: {lengths} ({names})", g.name)
            unit = _attr_unit(g[roles["t"]], g)
            self.time_unit = self.time_unit or unit
            return ("columns", names, lengths["t"])
        ds = f.get("events")
        if isinstance(ds, h5py.Dataset):
            self._check_stored(ds)
            self.time_unit = self.time_unit or _attr_unit(ds)
            if ds.dtype.names:
                roles = match_columns(ds.dtype.names)
                if roles is None:
                    raise RecordingError(self.path, f"compound dataset has fields {list(ds.dtype.names)}: expected "
                                                    f"t, x, y, p (or aliases)", ds.name)
                return ("compound", ds.name, roles, ds.shape[0] if ds.ndim else 0)
            if ds.ndim == 2 and ds.shape[1] == 4:
                declared = self.columns or next((ds.attrs[k] for k in ("columns", "fields", "column_names")
                                                 if k in ds.attrs), None)
                with native_call(self.path, _WHAT, ds.name):
                    sample = ds[: min(ds.shape[0], 100_000)]
                cols, note = columns_of_2d(self.path, sample, declared)
                if note:
                    self.notes.append(note)
                return ("2d", ds.name, cols, ds.shape[0])
            raise RecordingError(self.path, f"dataset 'events' has shape {ds.shape} and dtype {ds.dtype}: expected "
                                            f"a compound dtype with t, x, y, p, or shape (N, 4)", ds.name)
        members = sorted(f.keys())
        raise RecordingError(self.path, f"no event data: expected a group 'events' with datasets t, x, y, p (or "
                                        f"aliases), or a dataset 'events' (compound or (N, 4)); found {members}")

    def _size_from_attrs(self, f) -> None:
        places = [f]
        layout = self._layout
        if layout[0] == "columns":
            places.append(f[layout[1]["t"]].parent)
        else:
            places.append(f[layout[1]])
        for obj in places:
            for wk, hk in _WIDTH_NAMES:
                if wk in obj.attrs and hk in obj.attrs:
                    try:
                        w, h = int(np.asarray(obj.attrs[wk]).item()), int(np.asarray(obj.attrs[hk]).item())
                    except (TypeError, ValueError) as exc:
                        raise RecordingError(self.path, f"attributes {wk}/{hk} are not integers: {exc}",
                                             obj.name) from exc
                    if not (0 < w <= 65536 and 0 < h <= 65536):
                        raise RecordingError(self.path, f"sensor size {w} × {h} is not a positive 16-bit size",
                                             f"attributes of {obj.name}")
                    self.width, self.height = w, h
                    return

    def _find_frames(self, f) -> tuple[str, str | None, str | None] | None:
        h5py = self._h5py
        g = f.get("frames")
        if isinstance(g, h5py.Group):
            images, t, exp = _child(g, _FRAME_IMAGES), _child(g, _FRAME_TIMES), _child(g, _FRAME_EXPOSURES)
            if images is not None:
                return self._frames_found(images, t, exp)
        for name in ("frames", "images", "aps"):
            images = f.get(name)
            if isinstance(images, h5py.Dataset) and images.ndim in (3, 4):
                t = _child(f, [f"{name}{s}" for s in ("_t_us", "_ts", "_t", "_timestamps", "_time")])
                exp = _child(f, [f"{name}_exposure_us", f"{name}_exposure"])
                return self._frames_found(images, t, exp)
        return None

    def _frames_found(self, images, t, exp):
        if images.ndim not in (3, 4) or not isinstance(images, self._h5py.Dataset):
            raise RecordingError(self.path, f"frames: expected a dataset (N, height, width[, channels]), got shape "
                                            f"{getattr(images, 'shape', None)}", images.name)
        if t is None:
            self.notes.append(f"frames {images.name} have no time stamps beside them: frames ignored")
            return None
        return images.name, t.name, exp.name if exp is not None else None

    # ---------------------------------------------------------------------------------------------- reading
    def chunks(self, chunk_events: int = DEFAULT_CHUNK_EVENTS, with_frames: bool = False) -> Iterator[RawChunk]:
        layout = self._layout
        with self._open() as f:
            n = layout[-1]
            for a in range(0, n, chunk_events):
                b = min(n, a + chunk_events)
                with native_call(self.path, _WHAT, f"event index {a}..{b - 1}"):
                    if layout[0] == "columns":
                        t, x, y, p = (f[layout[1][r]][a:b] for r in "txyp")
                    elif layout[0] == "compound":
                        rec = f[layout[1]][a:b]
                        t, x, y, p = (rec[layout[2][r]] for r in "txyp")
                    else:
                        block = f[layout[1]][a:b]
                        t, x, y, p = (block[:, c] for c in layout[2])
                yield RawChunk(t, x, y, p, a)

    def frames(self) -> FrameData | None:
        if self._frames_key is None:
            return None
        images_name, t_name, exp_name = self._frames_key
        with native_call(self.path, _WHAT, images_name), self._open() as f:
            ds = f[images_name]
            self._check_stored(ds)
            check_fits_in_memory(self.path, int(ds.size) * ds.dtype.itemsize, f"frames {images_name}")
            images = ds[()]
            t_ds = f[t_name]
            unit = self.time_unit or _attr_unit(t_ds)  # None: floats are seconds, integers µs
            t = times_to_us(self.path, t_ds[()], unit, t_name, lambda i: f"frame {i}")
            exposure = None
            if exp_name is not None:
                e_ds = f[exp_name]
                e_unit = _attr_unit(e_ds)
                exposure = times_to_us(self.path, e_ds[()], e_unit, exp_name, lambda i: f"frame {i}")
        return FrameData(images, t + self.t_add_us, exposure, lambda i: f"frame {i} of {images_name}")

    def calibration(self, width: int, height: int) -> Camera | None:
        with native_call(self.path, _WHAT, "calibration"), self._open() as f:
            g = f.get("calibration")
            if g is None:
                return None
            try:
                fx, fy, cx, cy = (float(np.asarray(g.attrs[k]).item()) for k in ("fx", "fy", "cx", "cy"))
            except KeyError as exc:
                raise RecordingError(self.path, f"calibration lacks attribute {exc}: expected fx, fy, cx, cy",
                                     "calibration") from exc
            dist = g.attrs["dist"] if "dist" in g.attrs else (g["dist"][()] if "dist" in g else np.zeros(5))
        try:
            return Camera(width, height, fx, fy, cx, cy, np.asarray(dist, dtype=np.float64).reshape(-1))
        except ValueError as exc:
            raise RecordingError(self.path, str(exc), "calibration") from exc

    def ground_truth(self) -> dict[str, np.ndarray] | None:
        with native_call(self.path, _WHAT, "ground_truth"), self._open() as f:
            g = f.get("ground_truth")
            if not isinstance(g, self._h5py.Group):
                return None
            out = {}
            for k in g:
                if isinstance(g[k], self._h5py.Dataset):
                    self._check_stored(g[k])
                    check_fits_in_memory(self.path, int(g[k].size) * g[k].dtype.itemsize, f"ground_truth/{k}")
                    out[k] = g[k][()]
        return out or None


def write_hdf5(path: Path, chunks: Iterator[np.ndarray], width: int, height: int, frames=None, calibration=None,
               ground_truth=None) -> None:
    """Write events (``EVENT_DTYPE`` chunks, file time µs) and optional extras in the layout of the docstring.

    ``frames`` is ``(images float32 (N,H,W), t_us file time, exposure_us or None)``; ``calibration`` a
    :class:`Camera`; ``ground_truth`` a mapping of names to arrays (``t_us`` in file time).
    """
    import h5py

    with h5py.File(path, "w") as f:
        f.attrs["width"], f.attrs["height"] = int(width), int(height)
        g = f.create_group("events")
        dtypes = {"t": np.int64, "x": np.uint16, "y": np.uint16, "p": np.int8}
        ds = {k: g.create_dataset(k, shape=(0,), maxshape=(None,), dtype=d, chunks=(1 << 16,), compression="gzip",
                                  compression_opts=1, shuffle=True) for k, d in dtypes.items()}
        ds["t"].attrs["units"] = "us"
        n = 0
        for chunk in chunks:
            m = len(chunk)
            if not m:
                continue
            for k, d in ds.items():
                d.resize((n + m,))
                d[n:] = chunk[k]
            n += m
        if frames is not None:
            images, t_us, exposure_us = frames
            fg = f.create_group("frames")
            fg.create_dataset("images", data=images, compression="gzip", compression_opts=1)
            fg["t_us"] = np.asarray(t_us, dtype=np.int64)
            fg["t_us"].attrs["units"] = "us"
            if exposure_us is not None:
                fg["exposure_us"] = np.asarray(exposure_us, dtype=np.int64)
                fg["exposure_us"].attrs["units"] = "us"
        if calibration is not None:
            cg = f.create_group("calibration")
            for k in ("fx", "fy", "cx", "cy"):
                cg.attrs[k] = float(getattr(calibration, k))
            cg["dist"] = np.asarray(calibration.dist, dtype=np.float64)
        if ground_truth:
            gg = f.create_group("ground_truth")
            for k, v in ground_truth.items():
                gg[k] = np.asarray(v)


READERS = [ReaderSpec(
    name="hdf5", description="HDF5: events/{t,x,y,p}, a compound or (N, 4) 'events' dataset; frames, calibration, "
                         "ground truth", extensions=(".h5", ".hdf5", ".hdf"), magic=(MAGIC,), magic_name="an HDF5",
    source="eventcap.io.hdf5:Hdf5Source", columns=True, declares_size=False,
    extras="frames, calibration, ground truth", library="h5py")]
