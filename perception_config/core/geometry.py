"""Rigid poses and the lambda noise model.

Units follow REP 103: metres and radians. A `Pose` maps model coordinates to camera
coordinates (BOP `cam_R_m2c`, `cam_t_m2c`), camera frame as OpenCV (x right, y down, z forward).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MM = 1e-3  # metres per millimetre: BOP files are in mm
SIGMA_R = 0.35  # rad, rotation noise at lambda = 1
SIGMA_T = 0.15  # share of the object diameter, translation noise at lambda = 1
LAMBDA_MAX = 2.0  # the largest noise level anything accepts (the paper sweeps 0.1 .. 1.0)


def check_noise_lambda(value: object, what: str = "lambda") -> float:
    """`value` as a noise level in [0, LAMBDA_MAX]; ValueError naming `what` otherwise."""
    try:
        lam = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a number, got {value!r}") from None
    if not (np.isfinite(lam) and 0.0 <= lam <= LAMBDA_MAX):
        raise ValueError(f"{what} must be in [0, {LAMBDA_MAX}], got {value}")
    return lam


@dataclass(frozen=True, eq=False)
class Pose:
    """Model-to-camera rigid transform: x_cam = R @ x_model + t (t in metres).

    `==` is exact value equality of R and t (the generated dataclass `==` compared the arrays
    with `==` and raised "truth value of an array is ambiguous"); poses are not hashable."""

    R: np.ndarray
    t: np.ndarray

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Pose):
            return NotImplemented
        return bool(np.array_equal(self.R, other.R) and np.array_equal(self.t, other.t))

    __hash__ = None  # type: ignore[assignment]  # mutable arrays inside: no hash

    def __post_init__(self) -> None:
        object.__setattr__(self, "R", np.asarray(self.R, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "t", np.asarray(self.t, dtype=np.float64).reshape(3))

    @staticmethod
    def identity() -> "Pose":
        return Pose(np.eye(3), np.zeros(3))

    @staticmethod
    def from_matrix(T: np.ndarray) -> "Pose":
        T = np.asarray(T, dtype=np.float64)
        return Pose(T[:3, :3], T[:3, 3])

    def matrix(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.t
        return T

    def compose(self, other: "Pose") -> "Pose":
        """self ∘ other: apply `other` first, then `self`."""
        return Pose(self.R @ other.R, self.R @ other.t + self.t)

    def inverse(self) -> "Pose":
        return Pose(self.R.T, -self.R.T @ self.t)

    def transform(self, points: np.ndarray) -> np.ndarray:
        """Apply the pose to Nx3 points."""
        return np.asarray(points) @ self.R.T + self.t

    def is_valid(self, tol: float = 1e-3) -> bool:
        """Finite, orthonormal with det +1, and in front of the camera."""
        if not (np.all(np.isfinite(self.R)) and np.all(np.isfinite(self.t))):
            return False
        if np.abs(self.R @ self.R.T - np.eye(3)).max() > tol or abs(np.linalg.det(self.R) - 1) > tol:
            return False
        return bool(self.t[2] > 0)


def skew(w: np.ndarray) -> np.ndarray:
    """The cross-product matrix [w]x."""
    x, y, z = np.asarray(w, dtype=np.float64)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula: rotation matrix exp([w]x) of a rotation vector w (rad)."""
    w = np.asarray(w, dtype=np.float64)
    theta = float(np.linalg.norm(w))
    if theta < 1e-12:
        return np.eye(3) + skew(w)
    K = skew(w / theta)
    return np.eye(3) + np.sin(theta) * K + (1.0 - np.cos(theta)) * (K @ K)


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vector w with exp([w]x) = R."""
    R = np.asarray(R, dtype=np.float64)
    cos = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    theta = float(np.arccos(cos))
    if theta < 1e-9:
        return np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    if np.pi - theta < 1e-6:
        # Near pi: axis from the largest diagonal term of (R + I) / 2.
        M = (R + np.eye(3)) / 2.0
        i = int(np.argmax(np.diag(M)))
        axis = M[:, i] / np.sqrt(max(M[i, i], 1e-12))
        return axis / np.linalg.norm(axis) * theta
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return w * theta / (2.0 * np.sin(theta))


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    """The rotation closest to R (Frobenius norm, SVD). Annotations such as BOP ground truth
    are stored with a few digits, orthonormal only to ~1e-3; code downstream (quaternions,
    validity checks, symmetric errors) needs a true rotation."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def rotation_to(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector `a` onto unit vector `b`."""
    v, c = np.cross(a, b), float(a @ b)
    if c < -1.0 + 1e-9:  # opposite: half a turn about any axis perpendicular to a
        axis = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def rotation_angle(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle (rad) of the relative rotation between two rotation matrices."""
    cos = (np.trace(np.asarray(R_a).T @ np.asarray(R_b)) - 1.0) / 2.0
    return float(np.arccos(np.clip(cos, -1.0, 1.0)))


def perturb(
    pose: Pose,
    lam: float,
    diameter: float,
    rng: np.random.Generator,
    sigma_r: float = SIGMA_R,
    sigma_t: float = SIGMA_T,
) -> Pose:
    """The paper's noise model for simulated initialisation.

    R' = exp([w]x) R with w ~ N(0, (lam * sigma_r)^2 I3);
    t' = t + d with d ~ N(0, (lam * sigma_t * diameter)^2 I3). lam = 0 returns the pose.
    """
    if not np.isfinite(lam) or lam < 0:
        raise ValueError(f"lambda must be a finite number >= 0, got {lam}")
    w = rng.normal(0.0, lam * sigma_r, size=3)
    d = rng.normal(0.0, lam * sigma_t * diameter, size=3)
    return Pose(exp_so3(w) @ pose.R, pose.t + d)


def quaternion_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w), as geometry_msgs/Quaternion orders it."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        q = [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif R[1, 1] > R[2, 2]:
        s = np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        q = [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return q if q[3] >= 0 else -q


def as_transmitted(pose: Pose) -> Pose:
    """The pose as a receiver of its geometry_msgs/Pose reads it back: the rotation through the
    unit quaternion. Operators keep their output hypotheses in this form, in-process and in the
    ROS nodes alike, so a chain of operators sees bit-identical poses whichever way they travel
    (and per-frame renderings keyed by the pose's bytes are found again by the next call)."""
    return Pose(matrix_from_quaternion(quaternion_from_matrix(pose.R)), pose.t)


def matrix_from_quaternion(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a quaternion (x, y, z, w); normalised first."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
