"""Which reader a path needs: by content (magic bytes, Prophesee header) first, extension second."""

from __future__ import annotations

import json
import os
from pathlib import Path

from eventcap.io.aedat4 import MAGIC as AEDAT4_MAGIC
from eventcap.io.arrays import NPY_MAGIC, ZIP_MAGICS
from eventcap.io.hdf5 import MAGIC as HDF5_MAGIC
from eventcap.io.prophesee import header_kind, read_header
from eventcap.io.recording import RecordingError
from eventcap.io.rpg import EVENTS
from eventcap.io.source import check_regular, regular_sibling

#: Formats :func:`eventcap.io.read_recording` accepts as ``format=``.
READ_FORMATS = ("aedat4", "aedat2", "aedat3", "hdf5", "rpg", "evt2", "evt3", "dat", "npy", "npz")

_EXTENSIONS = {".aedat4": "aedat4", ".h5": "hdf5", ".hdf5": "hdf5", ".hdf": "hdf5", ".raw": "evt", ".dat": "dat",
               ".npy": "npy", ".npz": "npz", ".txt": "rpg", ".csv": "rpg"}


#: Formats whose files start with a signature: what a file with their extension but not their signature lacks.
_MAGICS = {"aedat4": ("an AEDAT4", AEDAT4_MAGIC), "hdf5": ("an HDF5", HDF5_MAGIC), "npy": ("a NumPy .npy", NPY_MAGIC),
           "npz": ("a NumPy .npz (zip)", ZIP_MAGICS[0])}


def detect_format(path) -> str:
    """The format name of ``path`` (one of ``READ_FORMATS``, or ``"evt"`` for a RAW file whose header names no
    version); raises :class:`RecordingError` for missing, empty or unrecognised files."""
    path = Path(path)
    check_regular(path)
    if path.is_dir():
        if regular_sibling(path / EVENTS):
            return "rpg"
        for meta in ("zarr.json", ".zgroup"):
            if os.path.lexists(path / meta):
                raise RecordingError(path / meta, project_recording_problem(path) or "a zarr folder that is not a "
                                     "recording in the project's format")
        raise RecordingError(path, f"a folder without {EVENTS}: expected the rpg layout (events.txt, images.txt, …) "
                                   f"or a recording in the project's format (zarr.json)")
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(64)
    except OSError as exc:
        raise RecordingError(path, f"cannot read the file: {exc.strerror or exc}") from exc
    if size == 0:
        raise RecordingError(path, "the file is empty (0 bytes)")
    if head.startswith(AEDAT4_MAGIC):
        return "aedat4"
    if head.startswith(b"#!AER-DAT"):
        version = head[9:16].split(b"\r")[0].split(b"\n")[0].strip().decode("ascii", "replace")
        if version == "2.0":
            return "aedat2"
        if version == "3.1":
            return "aedat3"
        raise RecordingError(path, f"AEDAT version {version} is not supported (AEDAT 2.0, 3.1 and 4.0 are): convert "
                                   f"it with DV or jAER", "file header")
    if head.startswith(HDF5_MAGIC):
        return "hdf5"
    if head.startswith(NPY_MAGIC):
        return "npy"
    if head.startswith(ZIP_MAGICS):
        return "npz"
    ext = _EXTENSIONS.get(path.suffix.lower())
    if head.startswith(b"%"):
        kind = header_kind(read_header(path)[0])
        if kind is not None:
            return kind
        if ext in ("evt", "dat"):
            return ext
    elif ext is not None and ext not in ("aedat4", "hdf5", "npy", "npz"):
        return ext
    if ext in _MAGICS:  # the extension promises a format whose signature the file lacks: say that, not "unknown"
        name, magic = _MAGICS[ext]
        raise RecordingError(path, f"not {name} file: a {path.suffix} file starts with {magic!r}, this one with "
                                   f"{head[:16]!r} (a different or damaged file, or a wrong extension)", "file header")
    expected = ", ".join(sorted(_EXTENSIONS))
    raise RecordingError(path, f"unrecognised format: first bytes {head[:16]!r}, extension {path.suffix!r} "
                               f"(expected {expected}, an rpg folder, or format=…)")


def project_recording_problem(path) -> str | None:
    """Why the folder ``path`` with a ``zarr.json`` is not a readable recording in the project's format (a sentence),
    or None when its root metadata says it is one. Reads at most 1 MB of the metadata file, which must be regular."""
    meta = Path(path) / "zarr.json"
    check_regular(meta, folder=False)
    with open(meta, "rb") as f:
        raw = f.read(1 << 20)
    try:
        doc = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        return f"not valid JSON ({exc}): the zarr group's metadata is damaged"
    if not isinstance(doc, dict) or doc.get("node_type") != "group":
        return "not a zarr group's metadata (no \"node_type\": \"group\")"
    attrs = doc.get("attributes")
    if not isinstance(attrs, dict) or attrs.get("artifact") != "Recording":
        found = attrs.get("artifact") if isinstance(attrs, dict) else None
        return (f"a zarr group of a {found}, not a Recording" if found else
                "a zarr group without the project's attributes (artifact: Recording): not a recording in the "
                "project's format")
    return None
