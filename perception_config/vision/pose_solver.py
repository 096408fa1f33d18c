"""The Levenberg-Marquardt pose solver of the edge-based refiners (D2CO, chamfer-ICP).

The pose is parametrised as a rotation about the object origin and a translation
(R = exp([w]x) R0, t = t0 + d). `project_with_jacobian` projects model points with their 3D
tangents and gives the analytic Jacobian of the pixels with respect to (w, d);
`levenberg_marquardt` minimises a robustified sum of squared residuals (Huber, or the
redescending Geman-McClure / Tukey losses under which a point far from any supporting image
edge stops pulling: occluded contour, clutter) plus a weak prior on one translation direction
(the viewing ray, which edges observe weakly) and optionally on the rotation away from the start.
"""
from __future__ import annotations

import time

import numpy as np

from ..core.geometry import exp_so3, log_so3

LOSSES = ("huber", "geman_mcclure", "tukey")


def project_with_jacobian(R: np.ndarray, t: np.ndarray, P: np.ndarray, D: np.ndarray, K: np.ndarray):
    """Pixels (N, 2), tangent angles (N,) in [0, pi) and the Jacobian (N, 2, 6) of the pixels
    with respect to a pose update (w, d): R' = exp([w]x) R, t' = t + d (rotation about the
    object origin). Points within 1 mm of the camera plane get NaN pixels."""
    pc = P @ R.T + t
    dc = D @ R.T
    x, y, z = pc[:, 0], pc[:, 1], pc[:, 2]
    fx, fy, s = K[0, 0], K[1, 1], K[0, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        iz = np.where(z > 1e-3, 1.0 / z, np.nan)
    u = fx * x * iz + s * y * iz + K[0, 2]
    v = fy * y * iz + K[1, 2]
    # d(u, v)/d(x, y, z)
    Jp = np.zeros((len(P), 2, 3))
    Jp[:, 0, 0] = fx * iz
    Jp[:, 0, 1] = s * iz
    Jp[:, 0, 2] = -(fx * x + s * y) * iz * iz
    Jp[:, 1, 1] = fy * iz
    Jp[:, 1, 2] = -fy * y * iz * iz
    # image direction of the tangent: the projection Jacobian applied to it
    du = np.einsum("nij,nj->ni", Jp, dc)
    angle = np.mod(np.arctan2(du[:, 1], du[:, 0]), np.pi)
    # d(pc)/dw = -[pc - t]x, d(pc)/dd = I
    q = pc - t
    J = np.empty((len(P), 2, 6))
    # (Jp @ -[q]x): columns are Jp @ (e_k x q) = -Jp @ (q x e_k)
    J[:, :, 0] = Jp[:, :, 1] * (-q[:, 2:3]) + Jp[:, :, 2] * q[:, 1:2]
    J[:, :, 1] = Jp[:, :, 0] * q[:, 2:3] + Jp[:, :, 2] * (-q[:, 0:1])
    J[:, :, 2] = Jp[:, :, 0] * (-q[:, 1:2]) + Jp[:, :, 1] * q[:, 0:1]
    J[:, :, 3:] = Jp
    return np.stack([u, v], axis=1), angle, J


def update_pose(R: np.ndarray, t: np.ndarray, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apply a step (w, d) of the parametrisation of `project_with_jacobian`."""
    return exp_so3(delta[:3]) @ R, t + delta[3:]


def huber_weights(r: np.ndarray, delta: float) -> np.ndarray:
    """IRLS weights of the Huber loss: 1 inside `delta`, delta/|r| outside."""
    a = np.abs(r)
    return np.where(a <= delta, 1.0, delta / np.maximum(a, 1e-12))


def robust_rho(r: np.ndarray, loss: str, scale: float) -> np.ndarray:
    """Per-residual loss: 'huber' (quadratic within `scale`, then linear), 'geman_mcclure'
    (0.5 r^2 s^2 / (s^2 + r^2): bounded by s^2 / 2, influence falls off beyond s) or 'tukey'
    (biweight: constant s^2 / 6 beyond s, no pull at all). All are 0.5 r^2 near 0."""
    a = np.abs(r)
    s2 = scale * scale
    if loss == "huber":
        return np.where(a <= scale, 0.5 * a * a, scale * (a - 0.5 * scale))
    if loss == "geman_mcclure":
        return 0.5 * a * a * s2 / (s2 + a * a)
    if loss == "tukey":
        q = np.minimum(a / scale, 1.0) ** 2
        return s2 / 6.0 * (1.0 - (1.0 - q) ** 3)
    raise ValueError(f"unknown loss {loss!r}: expected one of {LOSSES}")


def robust_weights(r: np.ndarray, loss: str, scale: float) -> np.ndarray:
    """IRLS weights rho'(r) / r of `robust_rho`."""
    a = np.abs(r)
    s2 = scale * scale
    if loss == "huber":
        return huber_weights(r, scale)
    if loss == "geman_mcclure":
        return (s2 / (s2 + a * a)) ** 2
    if loss == "tukey":
        return np.where(a < scale, (1.0 - (a / scale) ** 2) ** 2, 0.0)
    raise ValueError(f"unknown loss {loss!r}: expected one of {LOSSES}")


NO_PRIOR_DEG = 1000.0  # a rotation_prior_deg parameter at this value or above means no rotation prior


def rotation_prior_weight(n_residuals: int, degrees: float) -> float:
    """The `rotation_prior` of `levenberg_marquardt` (per rad) that makes a rotation of `degrees`
    cost as much as all `n_residuals` one unit off; 0 (none) for degrees >= NO_PRIOR_DEG."""
    return float(np.sqrt(n_residuals) / np.radians(degrees)) if degrees < NO_PRIOR_DEG else 0.0


def viewing_frame(t: np.ndarray) -> np.ndarray:
    """Rows (ray, e1, e2): the viewing ray through the object origin and two image-plane directions."""
    ray = t / np.linalg.norm(t)
    e1 = np.cross(ray, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return np.stack([ray, e1, np.cross(ray, e1)])


NO_TRANSLATION_PRIOR = np.zeros(3)  # levenberg_marquardt's rank-1 depth prior: the information matrix holds depth


def prior_information(t0: np.ndarray, n: int, in_plane_deg: float, out_of_plane_deg: float,
                      depth_mm: float) -> np.ndarray:
    """The 6x6 information matrix (on (w, d) of project_with_jacobian) of a Gaussian prior anchored at the
    start: rotation about the viewing ray of `in_plane_deg`, out of the image plane of
    `out_of_plane_deg`, and depth along the ray of `depth_mm` each cost as much as all `n`
    residuals 1 px off; image-plane translation is free (edges observe it well). >= 1000: none."""
    B = viewing_frame(t0)
    weight = lambda x, unit: n / (unit * x) ** 2 if x < 1000 else 0.0  # noqa: E731
    A = np.zeros((6, 6))
    A[:3, :3] = B.T @ np.diag([weight(in_plane_deg, np.pi / 180), *[weight(out_of_plane_deg, np.pi / 180)] * 2]) @ B
    A[3:, 3:] = weight(depth_mm, 1e-3) * np.outer(B[0], B[0])
    return A


def levenberg_marquardt(
    evaluate, R0: np.ndarray, t0: np.ndarray, prior: np.ndarray, huber: float,
    max_iterations: int, deadline: float, tol: float = 1e-4, anchor: np.ndarray | None = None,
    loss: str = "huber", rotation_prior: float = 0.0, rotation_anchor: np.ndarray | None = None,
    information: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Minimise sum rho(r_i) + 0.5 (prior . (t - anchor))^2 + 0.5 rotation_prior^2 |log(R Ra^T)|^2
    from (R0, t0); rho is `loss` (see robust_rho) with scale `huber` (px); `prior` (3,) weighs a
    translation direction (the viewing ray) that the residuals observe weakly; `anchor`
    and `rotation_anchor` Ra default to t0 and R0; `rotation_prior` (per rad) holds the rotation there.
    `information` (6, 6), if given, adds a Gaussian prior 0.5 e^T A e on e = (log(R Ra^T), t - anchor),
    whose directions may differ in strength (e.g. rotation out of the image plane held harder than
    about the viewing ray).

    `evaluate(R, t) -> (r (N,), J (N, 6))`. Steps are accepted when they lower the cost (the
    damping shrinks) and rejected otherwise (the damping grows); the loop ends on a relative
    cost change below `tol`, `max_iterations`, or the `deadline` (perf_counter seconds).
    Returns (R, t, iterations)."""
    R, t = R0, t0
    ref = t0 if anchor is None else anchor
    P2 = np.outer(prior, prior)

    rp2 = float(rotation_prior) ** 2
    Ra = R0 if rotation_anchor is None else rotation_anchor

    def change(R: np.ndarray, t: np.ndarray) -> np.ndarray:
        return np.concatenate([log_so3(R @ Ra.T), t - ref])

    def total(r: np.ndarray, R: np.ndarray, t: np.ndarray) -> float:
        cost = float(np.sum(robust_rho(r, loss, huber))) + 0.5 * float(prior @ (t - ref)) ** 2
        if information is not None:
            e = change(R, t)
            cost += 0.5 * float(e @ information @ e)
        return cost + (0.5 * rp2 * float(np.sum(log_so3(R @ Ra.T) ** 2)) if rp2 > 0 else 0.0)

    r, J = evaluate(R, t)
    cost = total(r, R, t)
    mu, it = 1e-3, 0
    while it < max_iterations and time.perf_counter() < deadline:
        it += 1
        w = robust_weights(r, loss, huber)
        A = (J * w[:, None]).T @ J
        g = J.T @ (w * r)
        A[3:, 3:] += P2
        g[3:] += P2 @ (t - ref)
        if rp2 > 0:  # the left-perturbation Jacobian of log(R R0^T) is ~I for the small angles here
            A[:3, :3] += rp2 * np.eye(3)
            g[:3] += rp2 * log_so3(R @ Ra.T)
        if information is not None:
            A += information
            g += information @ change(R, t)
        improved = False
        while time.perf_counter() < deadline:
            step = np.linalg.solve(A + mu * np.diag(np.diag(A) + 1e-9), -g)
            Rn, tn = update_pose(R, t, step)
            rn, Jn = evaluate(Rn, tn)
            cn = total(rn, Rn, tn)
            if np.isfinite(cn) and cn < cost:
                rel = (cost - cn) / max(cost, 1e-12)
                R, t, r, J, cost = Rn, tn, rn, Jn, cn
                mu = max(mu * 0.3, 1e-7)
                improved = True
                break
            mu *= 10.0
            if mu > 1e4:
                break
        if not improved or rel < tol:
            break
    return R, t, it
