"""Readers of body-joint detections produced elsewhere (OpenPose JSON, npz, csv) and their alignment with frames.

Formats (2D keypoints in the file's *layout*: OpenPose BODY_25 (25 points) or COCO-18 (18 points); 3D joints
always in SMPL order, 24 joints, root-relative, metres unless configured otherwise):

- **openpose**: a folder of OpenPose ``--write_json`` files, one per frame (``<name>_000000000012_keypoints.json``),
  or one such file. ``people[0].pose_keypoints_2d`` is a flat list x0, y0, c0, x1, y1, c1, ... (pixels; OpenPose
  writes 0, 0, 0 for keypoints it did not find); ``people: []`` means nobody was detected (all confidences 0).
  Files are matched to the recording's intensity frames either by *order* (natural sort of the file names:
  the n-th file is the n-th frame, and there must be one file per frame) or by *number* (the last number in
  the file name, minus ``first_frame``, is the frame index; frames without a file get confidence 0).
  No 3D joints.
- **npz**: arrays ``keypoints_2d`` (n, K, 2) px and ``confidence_2d`` (n, K); optionally ``joints_3d``
  (n, 24, 3) root-relative with ``confidence_3d`` (n, 24) (default 1); and one of ``t_us`` (n,) int (matched to
  the frame within a tolerance), ``frame`` (n,) int (frame number, minus ``first_frame`` = frame index) or
  neither (row i = frame i, and the counts must agree). A file for 3D only may omit the 2D arrays.
- **csv**: a header line, then one line per frame (lines starting with ``#`` before the header are skipped).
  Columns, in any order: optional ``t_us`` or ``frame`` (as in npz); ``kp{k}_x, kp{k}_y, kp{k}_c`` for every
  keypoint k = 0..K-1 of the layout; optional ``j{j}_x, j{j}_y, j{j}_z`` for j = 0..23 (all or none) with
  optional ``j{j}_c``. Empty cells and NaN coordinates mean "not detected".

Keypoints are mapped onto the skeleton's landmarks (:data:`eventcap.body.skeleton.LANDMARK_NAMES`, BODY_25
order) by the layout's default mapping (BODY_25: identity; COCO-18: by name, leaving mid_hip and the six foot
points unmapped), changed by per-keypoint overrides. Unmapped landmarks get confidence 0; NaN coordinates
become "not detected" (position 0, confidence 0).
"""

from __future__ import annotations

import csv
import json
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eventcap.body.skeleton import LANDMARK_INDEX, LANDMARK_NAMES, NUM_JOINTS, NUM_LANDMARKS

#: Keypoint names of the OpenPose layouts, in file order.
BODY25_NAMES: tuple[str, ...] = (
    "Nose", "Neck", "RShoulder", "RElbow", "RWrist", "LShoulder", "LElbow", "LWrist", "MidHip", "RHip", "RKnee",
    "RAnkle", "LHip", "LKnee", "LAnkle", "REye", "LEye", "REar", "LEar", "LBigToe", "LSmallToe", "LHeel",
    "RBigToe", "RSmallToe", "RHeel",
)
COCO18_NAMES: tuple[str, ...] = (
    "Nose", "Neck", "RShoulder", "RElbow", "RWrist", "LShoulder", "LElbow", "LWrist", "RHip", "RKnee", "RAnkle",
    "LHip", "LKnee", "LAnkle", "REye", "LEye", "REar", "LEar",
)
LAYOUTS: dict[str, tuple[str, ...]] = {"body25": BODY25_NAMES, "coco18": COCO18_NAMES}
FORMATS = ("openpose", "npz", "csv", "auto")


def _landmark_name(openpose_name: str) -> str:
    """'RBigToe' -> 'r_big_toe', 'MidHip' -> 'mid_hip' (the skeleton's names of the BODY_25 points)."""
    snake = re.sub(r"(?<!^)([A-Z])", r"_\1", openpose_name).lower()
    return re.sub(r"^([lr])(?=_)", r"\1", snake)


# The skeleton's landmarks are the BODY_25 points under snake-case names; checked once here.
assert tuple(_landmark_name(n) for n in BODY25_NAMES) == LANDMARK_NAMES


class DetectionFileError(ValueError):
    """A detections file is missing, malformed or does not fit the recording; names the file and the frame."""

    def __init__(self, path, message: str, frame: str | int | None = None):
        where = str(path) + (f" (frame {frame})" if frame is not None else "")
        super().__init__(f"{where}: {message}")


def keypoint_mapping(layout: str, overrides: Mapping[str, str] | None = None) -> np.ndarray:
    """(25,) int64: for each landmark of LANDMARK_NAMES, the index of the file keypoint it takes (-1 = none).

    ``overrides`` maps a file keypoint (its index as a string, ``"4"``, or its layout name, ``"RWrist"``) to a
    landmark name, or to ``""`` to ignore that keypoint; other keypoints keep the layout's default.
    """
    if layout not in LAYOUTS:
        raise ValueError(f"layout: expected one of {', '.join(LAYOUTS)}, got {layout!r}")
    names = LAYOUTS[layout]
    target = {k: _landmark_name(n) for k, n in enumerate(names)}  # file keypoint -> landmark name
    for key, value in (overrides or {}).items():
        key = str(key)
        if key.isdigit() and int(key) < len(names):
            k = int(key)
        elif key in names:
            k = names.index(key)
        else:
            raise ValueError(f"mapping: unknown keypoint {key!r} of layout {layout}: expected an index 0..{len(names) - 1} "
                             f"or one of {', '.join(names)}")
        if value and value not in LANDMARK_INDEX:
            raise ValueError(f"mapping[{key!r}]: unknown landmark {value!r}; landmarks: {', '.join(LANDMARK_NAMES)}")
        target[k] = value
    out = np.full(NUM_LANDMARKS, -1, dtype=np.int64)
    for k, name in target.items():
        if not name:
            continue
        li = LANDMARK_INDEX[name]
        if out[li] >= 0:
            raise ValueError(f"mapping: landmark {name!r} is given by two keypoints of layout {layout}: "
                             f"{names[out[li]]} ({out[li]}) and {names[k]} ({k})")
        out[li] = k
    return out


@dataclass(frozen=True)
class DetectionTable:
    """Detections as a file holds them, before alignment with frames (m rows, K keypoints).

    keypoints_px (m, K, 2) and confidence (m, K), or None for a 3D-only file; joints_3d (m, 24, 3) and
    confidence_3d (m, 24) or None; at most one of t_us (m,) int64 and frame (m,) int64 (frame numbers as
    written, before ``first_frame``); labels (m,) say where each row came from (a file name or "row 7").
    """

    path: str
    labels: tuple[str, ...]
    keypoints_px: np.ndarray | None
    confidence: np.ndarray | None
    joints_3d: np.ndarray | None = None
    confidence_3d: np.ndarray | None = None
    t_us: np.ndarray | None = None
    frame: np.ndarray | None = None

    @property
    def n_rows(self) -> int:
        return len(self.labels)

    def error(self, row: int, message: str) -> DetectionFileError:
        """An error located at a row: the row's own file for OpenPose folders, else the file and the row."""
        if Path(self.path).is_dir():
            return DetectionFileError(Path(self.path) / self.labels[row], message)
        return DetectionFileError(self.path, message, self.labels[row])


def resolve_format(path, format: str) -> str:
    """The format of ``path`` (``auto``: folder or .json = openpose, .npz = npz, .csv = csv)."""
    if format not in FORMATS:
        raise ValueError(f"format: expected one of {', '.join(FORMATS)}, got {format!r}")
    p = Path(path)
    if not p.exists():
        raise DetectionFileError(p, "no such file or folder")
    if format != "auto":
        return format
    if p.is_dir() or p.suffix.lower() == ".json":
        return "openpose"
    if p.suffix.lower() in (".npz", ".csv"):
        return p.suffix.lower()[1:]
    raise DetectionFileError(p, "cannot tell the format from the name: expected a folder of OpenPose JSON files, "
                                ".json, .npz or .csv (or set format=openpose|npz|csv)")


def _natural_key(name: str):
    return [int(s) if s.isdigit() else s for s in re.split(r"(\d+)", name)]


def _last_number(path: Path) -> int | None:
    nums = re.findall(r"\d+", path.stem)
    return int(nums[-1]) if nums else None


def read_openpose(path, layout: str = "body25", match: str = "order") -> DetectionTable:
    """OpenPose ``--write_json`` output: a folder of per-frame files or one file; see the module docstring."""
    if layout not in LAYOUTS:
        raise ValueError(f"layout: expected one of {', '.join(LAYOUTS)}, got {layout!r}")
    if match not in ("order", "number"):
        raise ValueError(f"match: expected order | number, got {match!r}")
    p = Path(path)
    files = sorted(p.glob("*.json"), key=lambda f: _natural_key(f.name)) if p.is_dir() else [p]
    if not files:
        raise DetectionFileError(p, "no OpenPose .json files in this folder")
    K = len(LAYOUTS[layout])
    kp = np.zeros((len(files), K, 2))
    conf = np.zeros((len(files), K))
    numbers = []
    for i, f in enumerate(files):
        frame_label = f"{i} by order" if match == "order" else None
        if match == "number":
            num = _last_number(f)
            if num is None:
                raise DetectionFileError(f, "match=number needs a frame number in the file name, e.g. "
                                            "video_000000000012_keypoints.json (or use match=order)")
            numbers.append(num)
            frame_label = f"number {num}"
        try:
            doc = json.loads(f.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError) as exc:
            raise DetectionFileError(f, f"cannot read the file: {exc}", frame_label) from None
        except json.JSONDecodeError as exc:
            raise DetectionFileError(f, f"malformed JSON: {exc.msg} at line {exc.lineno}, column {exc.colno}",
                                     frame_label) from None
        people = doc.get("people") if isinstance(doc, dict) else None
        if not isinstance(people, list):
            raise DetectionFileError(f, "not an OpenPose keypoint file: expected an object with a 'people' list",
                                     frame_label)
        if not people:
            continue  # nobody detected in this frame
        values = people[0].get("pose_keypoints_2d") if isinstance(people[0], dict) else None
        if not isinstance(values, list):
            raise DetectionFileError(f, "people[0] has no 'pose_keypoints_2d' list", frame_label)
        if len(values) != 3 * K:
            hint = ""
            for other, names in LAYOUTS.items():
                if other != layout and len(values) == 3 * len(names):
                    hint = f" (this looks like layout {other}: set layout={other})"
            raise DetectionFileError(f, f"pose_keypoints_2d has {len(values)} values, expected {3 * K} "
                                        f"(x, y, confidence of the {K} keypoints of layout {layout}){hint}",
                                     frame_label)
        try:
            a = np.asarray(values, dtype=np.float64).reshape(K, 3)
        except (TypeError, ValueError):
            raise DetectionFileError(f, "pose_keypoints_2d holds non-numeric values", frame_label) from None
        kp[i], conf[i] = a[:, :2], a[:, 2]
    if match == "number":
        uniq, counts = np.unique(numbers, return_counts=True)
        if (counts > 1).any():
            dup = int(uniq[np.argmax(counts > 1)])
            names = [f.name for f, num in zip(files, numbers) if num == dup]
            raise DetectionFileError(p, f"two files carry frame number {dup}: {', '.join(names)}")
    return DetectionTable(path=str(p), labels=tuple(f.name for f in files), keypoints_px=kp, confidence=conf,
                          frame=np.asarray(numbers, dtype=np.int64) if match == "number" else None)


def _npz_array(z, name, path, dims: tuple, dtype_kind="f"):
    a = np.asarray(z[name])
    if a.ndim != len(dims) or any(d is not None and s != d for s, d in zip(a.shape, dims)):
        shape = "(" + ", ".join("n" if d is None else str(d) for d in dims) + ")"
        raise DetectionFileError(path, f"array {name!r} has shape {a.shape}, expected {shape}")
    if dtype_kind == "i" and a.dtype.kind not in "iu":
        raise DetectionFileError(path, f"array {name!r} must hold integers, got dtype {a.dtype}")
    if dtype_kind == "f" and a.dtype.kind not in "fiu":
        raise DetectionFileError(path, f"array {name!r} must hold numbers, got dtype {a.dtype}")
    return a.astype(np.int64 if dtype_kind == "i" else np.float64)


def read_detections_npz(path) -> DetectionTable:
    """Detections from an npz file with the arrays of the module docstring."""
    p = Path(path)
    try:
        z = np.load(p, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise DetectionFileError(p, f"not a readable npz file: {exc}") from None
    with z:
        names = set(z.files)
        kp = conf = j3 = c3 = t = fr = None
        if "keypoints_2d" in names:
            kp = _npz_array(z, "keypoints_2d", p, (None, None, 2))
            if "confidence_2d" not in names:
                raise DetectionFileError(p, "has keypoints_2d but no confidence_2d (n, K)")
            conf = _npz_array(z, "confidence_2d", p, kp.shape[:2])
        if "joints_3d" in names:
            j3 = _npz_array(z, "joints_3d", p, (None, NUM_JOINTS, 3))
            c3 = (_npz_array(z, "confidence_3d", p, (j3.shape[0], NUM_JOINTS)) if "confidence_3d" in names
                  else np.ones(j3.shape[:2]))
        if kp is None and j3 is None:
            raise DetectionFileError(p, f"holds neither keypoints_2d (n, K, 2) nor joints_3d (n, 24, 3); arrays: "
                                        f"{', '.join(sorted(names)) or 'none'}")
        m = (kp if kp is not None else j3).shape[0]
        if kp is not None and j3 is not None and j3.shape[0] != m:
            raise DetectionFileError(p, f"keypoints_2d has {m} rows but joints_3d {j3.shape[0]}")
        if "t_us" in names and "frame" in names:
            raise DetectionFileError(p, "has both t_us and frame: keep one of them")
        if "t_us" in names:
            t = _npz_array(z, "t_us", p, (m,), "i")
        if "frame" in names:
            fr = _npz_array(z, "frame", p, (m,), "i")
    return DetectionTable(path=str(p), labels=tuple(f"row {i}" for i in range(m)), keypoints_px=kp,
                          confidence=conf, joints_3d=j3, confidence_3d=c3, t_us=t, frame=fr)


def read_detections_csv(path) -> DetectionTable:
    """Detections from a csv file with the columns of the module docstring."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise DetectionFileError(p, f"cannot read the file: {exc}") from None
    lines = text.splitlines()
    start = 0
    while start < len(lines) and (not lines[start].strip() or lines[start].lstrip().startswith("#")):
        start += 1
    rows = [(start + 1 + i, r) for i, r in enumerate(csv.reader(lines[start:])) if any(c.strip() for c in r)]
    if not rows:
        raise DetectionFileError(p, "empty: expected a header line and one line per frame")
    header = [h.strip() for h in rows[0][1]]
    col = {h: i for i, h in enumerate(header)}
    if len(col) != len(header):
        dup = next(h for h in header if header.count(h) > 1)
        raise DetectionFileError(p, f"column {dup!r} appears twice in the header")
    K = 0
    while f"kp{K}_x" in col:
        K += 1
    J = sum(f"j{j}_x" in col for j in range(NUM_JOINTS))
    known = {"t_us", "frame"} | {f"kp{k}_{a}" for k in range(K) for a in "xyc"}
    known |= {f"j{j}_{a}" for j in range(NUM_JOINTS) for a in "xyzc"}
    unknown = [h for h in header if h not in known]
    if unknown:
        raise DetectionFileError(p, f"unknown column {unknown[0]!r}: expected t_us or frame, kp<k>_x/_y/_c for "
                                    f"k = 0..K-1 (consecutive) and optional j<j>_x/_y/_z/_c for j = 0..23")
    for k in range(K):
        for a in "yc":
            if f"kp{k}_{a}" not in col:
                raise DetectionFileError(p, f"column kp{k}_{a} missing (keypoint {k} has kp{k}_x)")
    if J not in (0, NUM_JOINTS) or (J and any(f"j{j}_{a}" not in col for j in range(NUM_JOINTS) for a in "yz")):
        raise DetectionFileError(p, "3D joints need all of j0_x, j0_y, j0_z ... j23_x, j23_y, j23_z (or none)")
    if K == 0 and J == 0:
        raise DetectionFileError(p, "no keypoint columns (kp0_x, kp0_y, kp0_c, ...) and no joint columns")
    if "t_us" in col and "frame" in col:
        raise DetectionFileError(p, "has both t_us and frame columns: keep one of them")
    data = rows[1:]
    m = len(data)

    def column(name: str, integer: bool = False, default: float = np.nan) -> np.ndarray:
        if name not in col:
            return np.full(m, default)
        c = col[name]
        out = np.empty(m, dtype=np.int64 if integer else np.float64)
        for i, (line, r) in enumerate(data):
            s = r[c].strip()
            try:
                if integer:
                    out[i] = int(s)
                else:
                    out[i] = float(s) if s else np.nan
            except ValueError:
                raise DetectionFileError(p, f"line {line}, column {name!r}: expected "
                                            f"{'an integer' if integer else 'a number'}, got {s!r}",
                                         f"row {i}") from None
        return out

    for i, (line, r) in enumerate(data):
        if len(r) != len(header):
            raise DetectionFileError(p, f"line {line} has {len(r)} values, the header {len(header)}", f"row {i}")
    kp = conf = j3 = c3 = None
    if K:
        kp = np.stack([np.stack([column(f"kp{k}_x"), column(f"kp{k}_y")], -1) for k in range(K)], 1)
        conf = np.nan_to_num(np.stack([column(f"kp{k}_c") for k in range(K)], 1), nan=0.0)
    if J:
        j3 = np.stack([np.stack([column(f"j{j}_{a}") for a in "xyz"], -1) for j in range(NUM_JOINTS)], 1)
        c3 = np.nan_to_num(np.stack([column(f"j{j}_c", default=1.0) for j in range(NUM_JOINTS)], 1), nan=0.0)
    return DetectionTable(path=str(p), labels=tuple(f"row {i}" for i in range(m)), keypoints_px=kp,
                          confidence=conf, joints_3d=j3, confidence_3d=c3,
                          t_us=column("t_us", integer=True) if "t_us" in col else None,
                          frame=column("frame", integer=True) if "frame" in col else None)


def read_detection_table(path, format: str = "auto", layout: str = "body25", match: str = "order") -> DetectionTable:
    """Read any supported detections file or folder (``format``: openpose | npz | csv | auto)."""
    fmt = resolve_format(path, format)
    if fmt == "openpose":
        return read_openpose(path, layout, match)
    return read_detections_npz(path) if fmt == "npz" else read_detections_csv(path)


def frame_rows(table: DetectionTable, frame_t_us: np.ndarray, first_frame: int = 0,
               time_tolerance_us: int = 500) -> np.ndarray:
    """(n,) int64: the table row of each of the recording's n frames (-1 = no detection for that frame).

    Rows carry frame times (nearest frame within ``time_tolerance_us``), frame numbers (minus ``first_frame``),
    or neither (row i is frame i; the counts must then agree).
    """
    frame_t_us = np.asarray(frame_t_us, dtype=np.int64)
    n, m = frame_t_us.size, table.n_rows
    rows = np.full(n, -1, dtype=np.int64)
    if table.t_us is None and table.frame is None:
        if m != n:
            what = "files" if table.labels and table.labels[0].endswith(".json") else "rows"
            raise DetectionFileError(table.path, f"has {m} {what} but the recording has {n} intensity frames "
                                                 f"(matched by order, the counts must agree)")
        return np.arange(n, dtype=np.int64)
    if table.t_us is not None:
        j = np.clip(np.searchsorted(frame_t_us, table.t_us), 1, max(n - 1, 1))
        cand = np.stack([j - 1, np.minimum(j, n - 1)], axis=1)
        dist = np.abs(frame_t_us[cand] - table.t_us[:, None])
        idx = cand[np.arange(m), np.argmin(dist, axis=1)]
        off = np.abs(frame_t_us[idx] - table.t_us)
        bad = off > time_tolerance_us
        if bad.any():
            i = int(np.argmax(bad))
            raise table.error(i, f"t_us = {int(table.t_us[i])} is {int(off[i])} us from the nearest intensity frame "
                                 f"({int(frame_t_us[idx[i]])} us), more than time_tolerance_us = {time_tolerance_us}")
    else:
        idx = table.frame - int(first_frame)
        bad = (idx < 0) | (idx >= n)
        if bad.any():
            i = int(np.argmax(bad))
            raise table.error(i, f"frame number {int(table.frame[i])} (minus first_frame = {first_frame}) is outside "
                                 f"the recording's {n} intensity frames (0..{n - 1})")
    for i, f in enumerate(idx):
        if rows[f] >= 0:
            raise table.error(i, f"{table.labels[rows[f]]} and {table.labels[i]} both fall on intensity frame "
                                 f"{int(f)}")
        rows[f] = i
    return rows


def _check_confidence(table: DetectionTable, conf: np.ndarray, what: str) -> None:
    bad = np.isfinite(conf) & ((conf < 0) | (conf > 1))
    if bad.any():
        i, k = (int(v) for v in np.argwhere(bad)[0])
        raise table.error(i, f"{what} {k} has confidence {conf[i, k]:g}, expected a value in [0, 1]")


def keypoints_at_frames(table: DetectionTable, rows: np.ndarray, mapping: np.ndarray,
                        layout: str) -> tuple[np.ndarray, np.ndarray]:
    """2D landmarks (n, 25, 2) px and confidences (n, 25) at the frames, via ``rows`` (frame_rows) and
    ``mapping`` (keypoint_mapping); frames without a row and unmapped or undetected landmarks: (0, 0), 0."""
    if table.keypoints_px is None:
        raise DetectionFileError(table.path, "holds no 2D keypoints")
    K = len(LAYOUTS[layout])
    if table.keypoints_px.shape[1] != K:
        got = table.keypoints_px.shape[1]
        hint = next((f" (set layout={o})" for o, names in LAYOUTS.items() if len(names) == got), "")
        raise DetectionFileError(table.path, f"has {got} keypoints per frame, layout {layout} has {K}{hint}")
    _check_confidence(table, table.confidence, "keypoint")
    n = rows.size
    kp = np.zeros((n, NUM_LANDMARKS, 2))
    conf = np.zeros((n, NUM_LANDMARKS))
    have = rows >= 0
    mapped = mapping >= 0
    src_kp = table.keypoints_px[rows[have]][:, mapping[mapped]]
    src_c = np.nan_to_num(table.confidence[rows[have]][:, mapping[mapped]], nan=0.0)
    ok = np.isfinite(src_kp).all(axis=-1) & (src_c > 0)
    kp[np.ix_(have, mapped)] = np.where(ok[..., None], src_kp, 0.0)
    conf[np.ix_(have, mapped)] = np.where(ok, src_c, 0.0)
    return kp, conf


def joints_at_frames(table: DetectionTable, rows: np.ndarray, camera_R: np.ndarray | None = None,
                     frame_3d: str = "world", unit_3d: str = "m") -> tuple[np.ndarray, np.ndarray]:
    """Root-relative 3D joints (n, 24, 3) metres in world axes and confidences (n, 24) at the frames.

    The file's joints are scaled to metres (``unit_3d`` m | mm), rotated from camera into world axes when
    ``frame_3d == "camera"`` (``camera_R`` is the world->camera rotation) and made relative to the pelvis
    (joint 0; a frame without a finite pelvis has no 3D joints). Without 3D joints in the file, or for frames without a row: zeros, confidence 0.
    """
    if frame_3d not in ("world", "camera"):
        raise ValueError(f"frame_3d: expected world | camera, got {frame_3d!r}")
    if unit_3d not in ("m", "mm"):
        raise ValueError(f"unit_3d: expected m | mm, got {unit_3d!r}")
    n = rows.size
    joints = np.zeros((n, NUM_JOINTS, 3))
    conf = np.zeros((n, NUM_JOINTS))
    if table.joints_3d is None:
        return joints, conf
    _check_confidence(table, table.confidence_3d, "joint")
    have = rows >= 0
    j = table.joints_3d[rows[have]] * (1e-3 if unit_3d == "mm" else 1.0)
    c = np.nan_to_num(table.confidence_3d[rows[have]], nan=0.0)
    if frame_3d == "camera":
        if camera_R is None:
            raise ValueError("frame_3d=camera needs the camera rotation")
        j = j @ np.asarray(camera_R, dtype=np.float64)  # v_world = R^T v_cam, as rows
    ok = np.isfinite(j).all(axis=-1)
    ok &= ok[:, :1]  # without the pelvis nothing is root-relative
    j = j - np.where(ok[:, :1, None], j[:, :1], 0.0)
    joints[have] = np.where(ok[..., None], j, 0.0)
    conf[have] = np.where(ok, c, 0.0)
    return joints, conf
