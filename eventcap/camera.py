"""The event camera's geometry: pinhole + OpenCV distortion, projection in numpy and CasADi, calibration I/O.

Conventions (the project's, everywhere):

- World: metres, y up; the synthetic actor stands on y = 0 facing +z.
- Camera axes as in OpenCV: x right, y down, z forward. ``x_cam = R @ x_world + t``.
- Pixels: origin top-left; pixel ``(x, y)`` covers ``[x - 0.5, x + 0.5] × [y - 0.5, y + 0.5]``, so integer
  coordinates are pixel centres (the OpenCV convention).
- Distortion ``dist = (k1, k2, p1, p2, k3)`` in OpenCV / rpg order, applied to normalised coordinates
  ``(x/z, y/z)`` before the intrinsics.
"""

from __future__ import annotations

import math
import os
import re
import stat
from dataclasses import dataclass
from typing import ClassVar
from pathlib import Path

import numpy as np

from eventcap.artifact import Artifact, array, attr

#: Public calibration of a DAVIS240C (rpg Event Camera Dataset), order fx fy cx cy k1 k2 p1 p2 k3.
DAVIS240C_CALIBRATION = (199.092, 198.829, 132.192, 110.713, -0.3684, 0.1509, -0.0003, -0.0008, 0.0)

#: Default synthetic placement: ~4 m in front of the actor (who faces +z), lens at chest height, looking
#: slightly down, so that a box x ±1.1 m, y 0..2.6 m, z -0.6..0.9 m (jumping jacks with a 0.3 m jump, kicks)
#: projects inside 240×180 (rows ~22..173 with distortion).
DEFAULT_EYE_M = (0.0, 1.3, 4.0)
DEFAULT_TARGET_M = (0.0, 1.0, 0.0)


def _as_float_array(value, shape: tuple[int, ...], name: str) -> np.ndarray:
    arr = np.array(value, dtype=np.float64)
    if arr.shape != shape:
        raise ValueError(f"Camera.{name}: expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"Camera.{name}: expected finite values, got {arr.tolist()}")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class Camera(Artifact):
    """A calibrated camera: image size (pixels), intrinsics (pixels), distortion and world→camera extrinsics.

    ``dist`` is (5,) = k1 k2 p1 p2 k3; ``R`` (3,3) rotation and ``t`` (3,) metres map world to camera
    coordinates, ``x_cam = R x_world + t``. Arrays are stored read-only; equality is identity (use
    :meth:`to_dict` to compare values).
    """

    schema_version: ClassVar[int] = 1
    width: int = attr(units="px")
    height: int = attr(units="px")
    fx: float = attr(units="px")
    fy: float = attr(units="px")
    cx: float = attr(units="px")
    cy: float = attr(units="px")
    dist: np.ndarray = array("float64", (5,), doc="k1 k2 p1 p2 k3", default_factory=lambda: np.zeros(5))
    R: np.ndarray = array("float64", (3, 3), doc="world -> camera rotation", default_factory=lambda: np.eye(3))
    t: np.ndarray = array("float64", (3,), units="m", default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or value <= 0:
                raise ValueError(f"Camera.{name}: expected a positive integer number of pixels, got {value!r}")
            object.__setattr__(self, name, int(value))
        for name in ("fx", "fy", "cx", "cy"):
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise ValueError(f"Camera.{name}: expected a finite number, got {value!r}")
            object.__setattr__(self, name, value)
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"Camera focal lengths must be positive pixels, got fx={self.fx}, fy={self.fy}")
        object.__setattr__(self, "dist", _as_float_array(self.dist, (5,), "dist"))
        R = _as_float_array(self.R, (3, 3), "R")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise ValueError(f"Camera.R: expected a rotation matrix (orthonormal, det +1), got {R.tolist()}")
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", _as_float_array(self.t, (3,), "t"))
        Artifact.validate(self)

    # ----------------------------------------------------------------------------------------- properties
    @property
    def K(self) -> np.ndarray:
        """(3,3) intrinsic matrix in pixels."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0.0))

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates, metres."""
        return -self.R.T @ self.t

    @property
    def max_valid_radius(self) -> float:
        """Normalised radius up to which the radial distortion is monotonic (``inf`` if it always is).

        Beyond it the OpenCV polynomial folds back, so far-off points would land inside the image; the
        renderer drops triangles with a vertex beyond this radius.
        """
        k1, k2, _, _, k3 = self.dist
        # d/dr [r (1 + k1 r² + k2 r⁴ + k3 r⁶)] = 1 + 3 k1 s + 5 k2 s² + 7 k3 s³ with s = r².
        coeffs = np.trim_zeros(np.array([7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0]), "f")
        if coeffs.size <= 1:
            return math.inf
        roots = np.roots(coeffs)
        s = [r.real for r in roots if abs(r.imag) < 1e-12 and r.real > 0]
        return math.sqrt(min(s)) if s else math.inf

    def with_pose(self, R, t) -> Camera:
        """The same intrinsics with other extrinsics."""
        return Camera(self.width, self.height, self.fx, self.fy, self.cx, self.cy, self.dist, R, t)

    def without_distortion(self) -> Camera:
        """The same camera with ``dist = 0`` (an ideal pinhole)."""
        return Camera(self.width, self.height, self.fx, self.fy, self.cx, self.cy, np.zeros(5), self.R, self.t)

    def to_dict(self) -> dict:
        """Plain-JSON form (lists of floats); :meth:`from_dict` inverts it."""
        return {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy, "cx": self.cx,
                "cy": self.cy, "dist": self.dist.tolist(), "R": self.R.tolist(), "t": self.t.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> Camera:
        return cls(**{k: d[k] for k in ("width", "height", "fx", "fy", "cx", "cy", "dist", "R", "t")})

    # ----------------------------------------------------------------------------------------- numpy
    def to_camera(self, points) -> np.ndarray:
        """World points (...,3) metres → camera coordinates (...,3) metres."""
        p = _check_points(points)
        return p @ self.R.T + self.t

    def depth(self, points) -> np.ndarray:
        """Camera z (...,) in metres of world points (...,3); positive in front of the camera."""
        p = _check_points(points)
        return p @ self.R[2] + self.t[2]

    def distort(self, normalised) -> np.ndarray:
        """Apply the lens distortion to normalised coordinates (...,2) ``(x/z, y/z)``."""
        xy = np.asarray(normalised, dtype=np.float64)
        x, y = xy[..., 0], xy[..., 1]
        k1, k2, p1, p2, k3 = self.dist
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return np.stack([xd, yd], axis=-1)

    def project(self, points) -> np.ndarray:
        """World points (...,3) metres → pixels (...,2) with distortion; NaN for points with z ≤ 0.

        Matches ``cv2.projectPoints`` (same distortion model) for points in front of the camera.
        """
        pc = self.to_camera(points)
        z = pc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            normalised = pc[..., :2] / np.where(z > 0, z, np.nan)[..., None]
        xd = self.distort(normalised)
        return np.stack([self.fx * xd[..., 0] + self.cx, self.fy * xd[..., 1] + self.cy], axis=-1)

    def undistort_points(self, pixels, iterations: int = 20) -> np.ndarray:
        """Pixels (...,2) → normalised coordinates (...,2) ``(x/z, y/z)`` of their rays (inverse distortion).

        Gauss–Newton on the distortion polynomial, started at the distorted coordinates; converges to
        ~1e-12 inside the image for real lenses. Rays in world coordinates: ``R.T @ [x, y, 1]``.
        """
        uv = np.asarray(pixels, dtype=np.float64)
        if uv.ndim == 0 or uv.shape[-1] != 2:
            raise ValueError(f"undistort_points: expected pixels of shape (..., 2), got {uv.shape}")
        target = np.stack([(uv[..., 0] - self.cx) / self.fx, (uv[..., 1] - self.cy) / self.fy], axis=-1)
        if not self.has_distortion:
            return target
        k1, k2, p1, p2, k3 = self.dist
        xy = target.copy()
        for _ in range(iterations):
            x, y = xy[..., 0], xy[..., 1]
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
            residual = self.distort(xy) - target
            # Jacobian of distort() w.r.t. (x, y).
            j00 = radial + 2 * x * x * dradial + 2 * p1 * y + 6 * p2 * x
            j01 = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
            j10 = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
            j11 = radial + 2 * y * y * dradial + 6 * p1 * y + 2 * p2 * x
            det = j00 * j11 - j01 * j10
            xy = xy - np.stack([(j11 * residual[..., 0] - j01 * residual[..., 1]) / det,
                                (-j10 * residual[..., 0] + j00 * residual[..., 1]) / det], axis=-1)
        return xy

    def backproject(self, pixels, depth) -> np.ndarray:
        """Pixels (...,2) and camera depths z (...,) metres → world points (...,3)."""
        xy = self.undistort_points(pixels)
        z = np.asarray(depth, dtype=np.float64)
        pc = np.concatenate([xy * z[..., None], z[..., None]], axis=-1)
        return (pc - self.t) @ self.R

    # ----------------------------------------------------------------------------------------- CasADi
    def project_sym(self, points):
        """CasADi projection π: points 3×n (SX, MX, DM or a numpy (3,) / (3,n) array, metres) → pixels 2×n.

        Same model as :meth:`project` (no NaN guard: the caller keeps points in front of the camera).
        """
        import casadi as ca

        if isinstance(points, (ca.SX, ca.MX, ca.DM)):
            P = points
        else:
            arr = np.asarray(points, dtype=np.float64)
            if arr.ndim == 1:
                arr = arr[:, None]
            if arr.ndim != 2:
                raise ValueError(f"project_sym: expected a 3×n matrix of points, got shape {arr.shape}")
            P = ca.DM(arr)
        if P.size1() != 3:
            raise ValueError(f"project_sym: expected a 3×n matrix (one point per column), got "
                             f"{P.size1()}×{P.size2()}")
        n = P.size2()
        Pc = ca.mtimes(ca.DM(self.R), P) + ca.repmat(ca.DM(self.t), 1, n)
        x = Pc[0, :] / Pc[2, :]
        y = Pc[1, :] / Pc[2, :]
        if self.has_distortion:
            k1, k2, p1, p2, k3 = (float(v) for v in self.dist)
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            x, y = (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                    y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)
        return ca.vertcat(self.fx * x + self.cx, self.fy * y + self.cy)


def _check_points(points) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim == 0 or p.shape[-1] != 3:
        raise ValueError(f"expected points of shape (..., 3) in metres, got {p.shape}")
    return p


def look_at(eye, target, up=(0.0, 1.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """World→camera ``(R (3,3), t (3,))`` of a camera at ``eye`` looking at ``target`` (metres, world).

    The image's "up" (−y of the OpenCV camera) is as close to ``up`` as possible.
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    for name, v in (("eye", eye), ("target", target), ("up", up)):
        if v.shape != (3,):
            raise ValueError(f"look_at: expected {name} of shape (3,), got {v.shape}")
    forward = target - eye
    if np.linalg.norm(forward) < 1e-12:
        raise ValueError(f"look_at: eye and target coincide ({eye.tolist()})")
    z = forward / np.linalg.norm(forward)
    x = np.cross(-up, z)  # right-handed: x = y × z with y pointing down
    if np.linalg.norm(x) < 1e-9:
        raise ValueError(f"look_at: up {up.tolist()} is parallel to the viewing direction {z.tolist()}")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ eye


def level_rotation(pitch_deg: float = 0.0, roll_deg: float = 0.0) -> np.ndarray:
    """World→camera rotation of a camera at the world's origin looking along -z, for a y-up world: with both angles
    0 the camera is level (image up = world up, image right = world x). ``pitch_deg`` tilts the optical axis (negative:
    looking down); ``roll_deg`` turns the camera about its axis (positive: the world's up appears turned clockwise
    in the image, image up (0, -1) towards image right). :func:`tilt_from_up` inverts it."""
    p, r = math.radians(float(pitch_deg)), math.radians(float(roll_deg))
    if not (math.isfinite(p) and math.isfinite(r)) or abs(p) >= math.pi / 2:
        raise ValueError(f"level_rotation: expected finite angles with |pitch| < 90 degrees, got pitch {pitch_deg!r}, "
                         f"roll {roll_deg!r}")
    R, _ = look_at((0.0, 0.0, 0.0), (0.0, math.sin(p), -math.cos(p)))
    c, s = math.cos(r), math.sin(r)
    roll = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return roll @ R


def tilt_from_up(up_camera) -> tuple[float, float]:
    """(pitch_deg, roll_deg) of :func:`level_rotation` under which the world's up is ``up_camera`` (a direction in
    camera axes: x right, y down, z forward; normalised here)."""
    u = np.asarray(up_camera, dtype=np.float64)
    n = float(np.linalg.norm(u))
    if u.shape != (3,) or not (n > 0 and math.isfinite(n)):
        raise ValueError(f"tilt_from_up: expected a non-zero direction (3,), got {u.tolist()}")
    u = u / n
    pitch = math.degrees(math.asin(float(np.clip(u[2], -1.0, 1.0))))
    roll = math.degrees(math.atan2(u[0], -u[1]))
    return pitch, roll


def seen_length(n_a: np.ndarray, n_b: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(K,) the length ℓ of segments seen at the normalised image points n_a, n_b (K, 2), lying along the
    directions v (K, 3, camera axes), with their middles at depth z (K,): the points z_a (n_a, 1) and z_b (n_b, 1)
    with z_a (n_a, 1) - z_b (n_b, 1) = ℓ v / ‖v‖ (least squares, exact for consistent data; perspective included:
    an off-axis segment along the line of sight still projects shorter than its image-plane part)."""
    ra = np.concatenate([n_a, np.ones((len(n_a), 1))], axis=1)
    rb = np.concatenate([n_b, np.ones((len(n_b), 1))], axis=1)
    u = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    A = np.stack([ra, -u], axis=2)  # (K, 3, 2): [r_a, -u] (z_a, ℓ) = r_b with z_b = 1
    AtA = np.einsum("kij,kil->kjl", A, A)
    Atb = np.einsum("kij,ki->kj", A, rb)
    det = AtA[:, 0, 0] * AtA[:, 1, 1] - AtA[:, 0, 1] * AtA[:, 1, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        za = (AtA[:, 1, 1] * Atb[:, 0] - AtA[:, 0, 1] * Atb[:, 1]) / det
        ell = (AtA[:, 0, 0] * Atb[:, 1] - AtA[:, 1, 0] * Atb[:, 0]) / det
        return ell * z / (0.5 * (za + 1.0))


def davis240c_default(distortion: bool = True, eye=DEFAULT_EYE_M, target=DEFAULT_TARGET_M) -> Camera:
    """A DAVIS240C (240×180, rpg calibration) placed for the synthetic capture (see ``DEFAULT_EYE_M``)."""
    fx, fy, cx, cy, *dist = DAVIS240C_CALIBRATION
    R, t = look_at(eye, target)
    return Camera(240, 180, fx, fy, cx, cy, np.array(dist) if distortion else np.zeros(5), R, t)


#: A calibration file is a line of numbers (and comments): anything larger is not one, and is not read.
MAX_CALIBRATION_BYTES = 64 * 1024


def check_rpg_calibration(path, key: str) -> None:
    """Refuse, before anything runs, a calibration setting whose file is not an rpg calib.txt (ValueError naming
    ``key``); reads at most MAX_CALIBRATION_BYTES, and nothing of a file that is not regular or is larger."""
    try:
        read_rpg_calibration(path, 1, 1)
    except ValueError as exc:
        raise ValueError(f"{key}: {exc}") from None


def _shown_token(tok: str) -> str:
    """A token of a file that failed to parse, quoted in a message only when it could be a mistyped number (a file
    given by mistake, such as a password file, never has its content repeated in a log)."""
    return f": {tok!r}" if re.fullmatch(r"[\w.+-]{1,16}", tok) else f" ({len(tok)} characters)"


def read_rpg_calibration(path, width: int, height: int, R=None, t=None) -> Camera:
    """Read an rpg Event Camera Dataset ``calib.txt``: one line ``fx fy cx cy k1 k2 p1 p2 k3`` (or ``fx fy cx cy``).

    Blank lines and ``#`` comments are ignored. Extrinsics default to the identity (camera = world frame). A path
    that is not a regular file, or a file larger than MAX_CALIBRATION_BYTES, is refused without being read; an error
    quotes the file's content only where it could be a mistyped number.
    """
    path = Path(path)
    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):
            raise ValueError(f"{path}: not a calibration file: {'a folder' if stat.S_ISDIR(st.st_mode) else 'not a regular file'}"
                             f" (expected an rpg calib.txt: one line 'fx fy cx cy [k1 k2 p1 p2 k3]')")
        if st.st_size > MAX_CALIBRATION_BYTES:
            raise ValueError(f"{path}: not a calibration file: {st.st_size:,} bytes (an rpg calib.txt is one line of "
                             f"numbers, at most {MAX_CALIBRATION_BYTES // 1024} KiB with comments); not read")
        with open(path, "rb") as fh:
            raw = fh.read(MAX_CALIBRATION_BYTES + 1)
        text = raw.decode("utf-8")
    except OSError as exc:
        raise ValueError(f"{path}: cannot read calibration file ({exc.strerror or exc})") from exc
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a calibration file: not text (an rpg calib.txt is one line of numbers)") from None
    lines = [(i + 1, ln.split("#", 1)[0].strip()) for i, ln in enumerate(text.splitlines())]
    lines = [(i, ln) for i, ln in lines if ln]
    if len(lines) != 1:
        raise ValueError(f"{path}: expected exactly one calibration line 'fx fy cx cy [k1 k2 p1 p2 k3]', "
                         f"found {len(lines)} non-empty lines")
    lineno, line = lines[0]
    tokens = line.replace(",", " ").split()
    if len(tokens) not in (4, 9):
        raise ValueError(f"{path}:{lineno}: expected 4 numbers (fx fy cx cy) or 9 (fx fy cx cy k1 k2 p1 p2 k3), "
                         f"got {len(tokens)} value(s)")
    values = []
    for k, tok in enumerate(tokens):
        try:
            v = float(tok)
        except ValueError:
            raise ValueError(f"{path}:{lineno}: value {k + 1} is not a number{_shown_token(tok)}") from None
        if not math.isfinite(v):
            raise ValueError(f"{path}:{lineno}: value {k + 1} is not finite{_shown_token(tok)}")
        values.append(v)
    fx, fy, cx, cy = values[:4]
    dist = np.array(values[4:]) if len(values) == 9 else np.zeros(5)
    return Camera(width, height, fx, fy, cx, cy, dist, np.eye(3) if R is None else R,
                  np.zeros(3) if t is None else t)
