"""Which reader a path needs: by content (signatures, headers) first, extension second, as the registered readers
declare them (:mod:`eventcap.io.registry`)."""

from __future__ import annotations

import json
import os
from pathlib import Path

from eventcap.io.recording import RecordingError
from eventcap.io.registry import readers
from eventcap.io.source import check_regular


def __getattr__(name: str):
    if name == "READ_FORMATS":  # the formats format= takes, from the registry (kept for callers of the old constant)
        return tuple(readers().names())
    raise AttributeError(name)


def detect_format(path) -> str:
    """The format name of ``path`` (a registered reader's); raises :class:`RecordingError` for missing, empty or
    unrecognised files, naming what a file with its extension should start with when it does not."""
    path = Path(path)
    check_regular(path)
    registry = readers()
    if path.is_dir():
        for spec in registry.specs():
            if spec.folder and spec.detect and spec.load("detect")(None, path):
                return spec.name
        for meta in ("zarr.json", ".zgroup"):
            if os.path.lexists(path / meta):
                raise RecordingError(path / meta, project_recording_problem(path) or "a zarr folder that is not a "
                                     "recording in the project's format")
        folders = [f"{s.name} ({s.description})" for s in registry.specs() if s.folder]
        raise RecordingError(path, f"a folder that no reader takes: expected {'; '.join(folders) or 'no folder'}, "
                                   f"or a recording in the project's format (zarr.json)")
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(64)
    except OSError as exc:
        raise RecordingError(path, f"cannot read the file: {exc.strerror or exc}") from exc
    if size == 0:
        raise RecordingError(path, "the file is empty (0 bytes)")
    # 1. a signature at the start of the file (its reader's detect hook may refine it: a version)
    for spec in registry.specs():
        if spec.magic and head.startswith(spec.magic):
            found = spec.load("detect")(head, path) if spec.detect else spec.name
            if found:
                return found
    # 2. content tests of readers without a signature (a Prophesee '%' header)
    tried = set()
    for spec in registry.specs():
        if spec.detect and not spec.magic and not spec.folder and spec.detect not in tried:
            tried.add(spec.detect)
            found = spec.load("detect")(head, path)
            if found:
                return found
    # 3. the extension
    by_ext = registry.by_extension(path.suffix)
    signed = [s for s in by_ext if s.magic]
    if signed:  # the extension promises a format whose signature the file lacks: say that, not "unknown"
        s = signed[0]
        raise RecordingError(path, f"not {s.magic_name} file: a {path.suffix} file starts with {s.magic[0]!r}, this "
                                   f"one with {head[:16]!r} (a different or damaged file, or a wrong extension)",
                             "file header")
    if len(by_ext) == 1:
        return by_ext[0].name
    if len(by_ext) > 1:
        raise RecordingError(path, f"a {path.suffix} file is {' or '.join(s.name for s in by_ext)} and its content "
                                   f"does not say which: pass format=", "file header")
    expected = ", ".join(registry.extensions())
    raise RecordingError(path, f"unrecognised format: first bytes {head[:16]!r}, extension {path.suffix!r} "
                               f"(expected {expected}, a folder of a reader, or format=…)")


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
