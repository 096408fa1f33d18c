"""BOP pose errors and recalls, as plain numpy functions in the style of bop_toolkit's
`pose_error.py` (Hodan et al., "BOP: Benchmark for 6D Object Pose Estimation", ECCV 2018;
BOP Challenge 2019+ for MSSD / MSPD).

Units differ from bop_toolkit on purpose (REP 103, like the rest of the code):
- poses, points, depth, diameters and the 3D errors (add, adi, mssd, te, vsd's delta and
  un-normalised taus) are in **metres**; bop_toolkit uses millimetres.
- `re` is in **radians**; bop_toolkit returns degrees.
- `mspd` is in pixels, as in bop_toolkit.

Symmetries are a sequence of `Pose` in the model frame (identity first), as
`ObjectModel.symmetries` holds them (discrete ones combined with sampled continuous ones);
bop_toolkit-style dicts {"R": 3x3, "t": 3 (metres)} are accepted too. An empty sequence means
"no symmetry" (identity only).

Depth images follow the code's convention (float32 metres, NaN = missing); `vsd` maps missing
depth to 0 and then treats it exactly as bop_toolkit's "bop19" visibility mode does.
"""
from __future__ import annotations

import math
import threading
import weakref
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
from scipy.spatial import cKDTree

from .geometry import Pose
from .models import ObjectModel
from .render import projected_box, render
from .symmetry import DEFAULT_SYM_TOLERANCE, declared_or_derived_symmetries, symmetries_from_info

# BOP 2019+ evaluation settings, converted to metres where they carry a unit.
VSD_DELTA = 0.015  # m: tolerance of the visibility test (BOP: 15 mm)
VSD_TAUS = tuple(round(0.05 * i, 2) for i in range(1, 11))  # misalignment tolerances, x diameter
VSD_THRESHOLDS = tuple(round(0.05 * i, 2) for i in range(1, 11))  # correctness thresholds on e_vsd
MSSD_THRESHOLDS = tuple(round(0.05 * i, 2) for i in range(1, 11))  # x object diameter
MSPD_THRESHOLDS = tuple(float(v) for v in range(5, 51, 5))  # px at an image width of 640
MAX_SYM_DISC_STEP = 0.01  # continuous symmetries sampled so points move <= 1 % of the diameter

SymmetryLike = Pose | Mapping[str, Any]

_MAX_BATCH = 1_000_000  # points x symmetries transformed at once (bounds memory of mssd/mspd)


# --------------------------------------------------------------------------- helpers


def _transform(pts: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return np.asarray(pts, dtype=np.float64).reshape(-1, 3) @ np.asarray(R, dtype=np.float64).reshape(3, 3).T \
        + np.asarray(t, dtype=np.float64).reshape(3)


def _project(pts_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pinhole projection (..., 3) -> (..., 2), as bop_toolkit's misc.project_pts (no z check:
    a point on or behind the camera plane gives inf/NaN, which makes the error inf/NaN)."""
    uvw = pts_cam @ np.asarray(K, dtype=np.float64).reshape(3, 3).T
    with np.errstate(divide="ignore", invalid="ignore"):
        return uvw[..., :2] / uvw[..., 2:3]


def _sym_arrays(syms: Sequence[SymmetryLike] | None) -> tuple[np.ndarray, np.ndarray]:
    """Stacked rotations (S, 3, 3) and translations (S, 3) of the symmetry transformations."""
    if syms is None or len(syms) == 0:
        return np.eye(3)[None], np.zeros((1, 3))
    Rs, ts = [], []
    for s in syms:
        if isinstance(s, Pose):
            Rs.append(s.R)
            ts.append(s.t)
        else:
            Rs.append(np.asarray(s["R"], dtype=np.float64).reshape(3, 3))
            ts.append(np.asarray(s["t"], dtype=np.float64).reshape(3))
    return np.stack(Rs), np.stack(ts)


def _gt_sym_points(pts: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, Rs: np.ndarray, ts: np.ndarray) -> np.ndarray:
    """Points (S, N, 3) of the model at the ground truth composed with each symmetry:
    R_gt S_R x + R_gt S_t + t_gt."""
    R_gt = np.asarray(R_gt, dtype=np.float64).reshape(3, 3)
    t_gt = np.asarray(t_gt, dtype=np.float64).reshape(3)
    R_sym = np.matmul(R_gt, Rs)  # (S, 3, 3)
    t_sym = ts @ R_gt.T + t_gt
    return np.matmul(pts, R_sym.transpose(0, 2, 1)) + t_sym[:, None, :]


def _min_over_symmetries(n_pts: int, n_sym: int, errors) -> float:
    """min over the symmetries of errors(point_sel, sym_idx) -> (len(sym_idx),), each error a
    max over the selected points.

    Exact branch and bound for long symmetry lists (finely sampled continuous symmetries): the
    max over a subset of the points is a lower bound of the max over all of them, so symmetries
    are visited in the order of their bound and the search stops once the bound reaches the best
    full error. Memory stays bounded by batching."""
    step = max(1, _MAX_BATCH // max(1, n_pts))
    if n_sym <= step and (n_sym <= 16 or n_pts <= 512):
        errs = errors(slice(None), slice(None))
        return math.nan if np.any(np.isnan(errs)) else float(errs.min())
    sub = slice(None, None, max(1, n_pts // 256))
    sub_step = max(1, _MAX_BATCH // len(range(n_pts)[sub]))
    bound = np.concatenate([errors(sub, slice(i, i + sub_step)) for i in range(0, n_sym, sub_step)])
    if np.any(np.isnan(bound)):
        return math.nan
    order = np.argsort(bound, kind="stable")
    best = math.inf
    step = min(step, 16)  # few symmetries survive the bound: check them in small batches
    for i in range(0, n_sym, step):
        idx = order[i:i + step]
        if bound[idx[0]] >= best:
            break
        best = min(best, float(errors(slice(None), idx).min()))
    return best


# --------------------------------------------------------------------------- pose errors


def add(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, pts: np.ndarray) -> float:
    """ADD (Hinterstoisser et al. ACCV 2012): mean distance (m) between corresponding model
    points at the estimated and the ground-truth pose. For objects without ambiguous views."""
    pts_est = _transform(pts, R_est, t_est)
    pts_gt = _transform(pts, R_gt, t_gt)
    return float(np.linalg.norm(pts_est - pts_gt, axis=1).mean())


def adi(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, pts: np.ndarray) -> float:
    """ADI / ADD-S (Hinterstoisser et al. ACCV 2012): mean distance (m) from each model point at
    the ground truth to the closest model point at the estimate. Always <= ADD."""
    pts_est = _transform(pts, R_est, t_est)
    pts_gt = _transform(pts, R_gt, t_gt)
    if not (np.all(np.isfinite(pts_est)) and np.all(np.isfinite(pts_gt))):
        return math.nan
    nn_dists, _ = cKDTree(pts_est).query(pts_gt, k=1)
    return float(nn_dists.mean())


def mssd(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, pts: np.ndarray,
         syms: Sequence[SymmetryLike] | None) -> float:
    """MSSD (BOP 2019): min over the symmetry transformations S of the max distance (m) between
    the model points at the estimate and at gt∘S.

    The per-symmetry max distance ||A x + b|| is convex in x, so over a mesh it is attained at a
    convex-hull vertex: passing `ObjectModel.hull_points` gives the exact value for the whole
    surface (bop_toolkit approximates it with the model vertices)."""
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    Rs, ts = _sym_arrays(syms)
    R_gt = np.asarray(R_gt, dtype=np.float64).reshape(3, 3)
    # Squared distances |A_s p + b_s - q|^2 with A_s = R_gt S_R, b_s = R_gt S_t, q = est - t_gt
    # (centred on t_gt, so every term is of the object's size and cancellation stays ~1e-9 m)
    # expand into (N, 9) x (9, S) products: no (S, N, 3) temporaries. Nothing assumes the
    # rotations orthonormal (annotated BOP rotations are off by up to ~2e-3).
    q = _transform(pts, R_est, t_est) - np.asarray(t_gt, dtype=np.float64).reshape(3)
    A = np.matmul(R_gt, Rs)  # (S, 3, 3)
    b = ts @ R_gt.T  # (S, 3)
    AtA = np.matmul(A.transpose(0, 2, 1), A).reshape(-1, 9).T  # (9, S)
    Atb = np.einsum("sik,si->sk", A, b)  # (S, 3)
    bb = np.einsum("si,si->s", b, b)
    pp = (pts[:, :, None] * pts[:, None, :]).reshape(-1, 9)  # p_i p_k
    qp = (q[:, :, None] * pts[:, None, :]).reshape(-1, 9)  # q_i p_k
    qq = np.einsum("ni,ni->n", q, q)
    Aflat = A.reshape(-1, 9).T  # (9, S)

    def errors(sel: slice | np.ndarray, idx: slice | np.ndarray) -> np.ndarray:
        d2 = (pp[sel] @ AtA[:, idx] + bb[None, idx] + qq[sel, None] + 2.0 * pts[sel] @ Atb[idx].T
              - 2.0 * qp[sel] @ Aflat[:, idx] - 2.0 * q[sel] @ b[idx].T)
        return np.sqrt(np.maximum(d2.max(axis=0), 0.0))

    return _min_over_symmetries(len(pts), len(Rs), errors)


def mspd(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, K: np.ndarray,
         pts: np.ndarray, syms: Sequence[SymmetryLike] | None) -> float:
    """MSPD (BOP 2019): min over the symmetry transformations S of the max distance (pixels)
    between the projections of the model points at the estimate and at gt∘S."""
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    proj_est = _project(_transform(pts, R_est, t_est), K)
    Rs, ts = _sym_arrays(syms)

    def errors(sel: slice | np.ndarray, idx: slice | np.ndarray) -> np.ndarray:
        diff = _project(_gt_sym_points(pts[sel], R_gt, t_gt, Rs[idx], ts[idx]), K) - proj_est[sel][None]
        return np.sqrt(np.einsum("snc,snc->sn", diff, diff).max(axis=1))

    return _min_over_symmetries(len(pts), len(Rs), errors)


def re(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """Rotation error in **radians** (bop_toolkit: degrees): the angle of R_est R_gt^-1."""
    R_est = np.asarray(R_est, dtype=np.float64).reshape(3, 3)
    R_gt = np.asarray(R_gt, dtype=np.float64).reshape(3, 3)
    error_cos = 0.5 * (float(np.trace(R_est @ R_gt.T)) - 1.0)
    if math.isnan(error_cos):
        return math.nan
    return math.acos(min(1.0, max(-1.0, error_cos)))  # clip numerical noise


def te(t_est: np.ndarray, t_gt: np.ndarray) -> float:
    """Translation error in metres: ||t_gt - t_est||."""
    t_est = np.asarray(t_est, dtype=np.float64).reshape(3)
    t_gt = np.asarray(t_gt, dtype=np.float64).reshape(3)
    return float(np.linalg.norm(t_gt - t_est))


def depth_to_distance(depth: np.ndarray, K: np.ndarray, offset: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Distance from the camera centre of each pixel's 3D point (bop_toolkit's
    misc.depth_im_to_dist_im_fast), for a depth image (possibly a crop at `offset` = (x, y))."""
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    h, w = depth.shape
    xs = (np.arange(offset[0], offset[0] + w, dtype=np.float64) - K[0, 2]) / K[0, 0]
    ys = (np.arange(offset[1], offset[1] + h, dtype=np.float64) - K[1, 2]) / K[1, 1]
    return depth * np.sqrt(xs[None, :] ** 2 + ys[:, None] ** 2 + 1.0)


def _union_box(boxes: Iterable[tuple[int, int, int, int] | None]) -> tuple[int, int, int, int] | None:
    bs = [b for b in boxes if b is not None]
    if not bs:
        return None
    x0, y0 = min(b[0] for b in bs), min(b[1] for b in bs)
    x1, y1 = max(b[0] + b[2] for b in bs), max(b[1] + b[3] for b in bs)
    return (x0, y0, x1 - x0, y1 - y0)


def vsd(
    R_est: np.ndarray,
    t_est: np.ndarray,
    R_gt: np.ndarray,
    t_gt: np.ndarray,
    depth_test: np.ndarray | None,
    K: np.ndarray,
    delta: float,
    taus: Sequence[float],
    normalized_by_diameter: bool,
    diameter: float,
    model: ObjectModel,
    cost_type: str = "step",
) -> np.ndarray:
    """Visible Surface Discrepancy (Hodan, Michel et al. ECCV 2018), one error per tau in [0, 1].

    As bop_toolkit's `pose_error.vsd` with visibility mode "bop19": render the model's depth at
    both poses, estimate the visible surfaces against the test depth with tolerance `delta` (m;
    pixels with missing test depth count as visible), and average a per-pixel cost over the
    union of the visible masks (pixels in only one mask cost 1). `taus` are in metres, or in
    units of `diameter` when `normalized_by_diameter`. `depth_test` is float metres with NaN
    (or 0) for missing. Rendering is cropped to the union of the two projected boxes: pixels
    outside it belong to neither mask, so the result equals a full-frame evaluation.
    """
    if cost_type not in ("step", "tlinear"):
        raise ValueError(f"unknown VSD pixel matching cost {cost_type!r} (step | tlinear)")
    if depth_test is None:
        raise ValueError("VSD needs depth: the test frame is RGB-only (no depth image)")
    depth_test = np.asarray(depth_test)
    H, W = depth_test.shape
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    est, gt = Pose(R_est, t_est), Pose(R_gt, t_gt)
    est_ok = bool(np.all(np.isfinite(est.R)) and np.all(np.isfinite(est.t)))
    poses = [est, gt] if est_ok else [gt]
    box = _union_box(projected_box(model, p, K, W, H) for p in poses)
    if box is None:
        return np.ones(len(taus))
    x, y, w, h = box

    def rendered_dist(pose: Pose) -> np.ndarray:
        d = render([model], [pose], K, W, H, crop=box).depth
        return depth_to_distance(np.nan_to_num(d, nan=0.0), K, (x, y))  # 0 = no surface, as BOP

    dist_est = rendered_dist(est) if est_ok else np.zeros((h, w))
    dist_gt = rendered_dist(gt)
    d = np.asarray(depth_test[y:y + h, x:x + w], dtype=np.float64)
    d = np.where(np.isfinite(d) & (d > 0), d, 0.0)  # missing depth -> 0, bop_toolkit's convention
    dist_test = depth_to_distance(d, K, (x, y))

    # bop_toolkit visibility.estimate_visib_mask_{gt,est}, mode "bop19" (missing depth = visible).
    test_missing = dist_test == 0
    visib_gt = ((dist_gt - dist_test <= delta) | test_missing) & (dist_gt > 0)
    visib_est = ((dist_est - dist_test <= delta) | test_missing) & (dist_est > 0)
    visib_est |= visib_gt & (dist_est > 0)

    visib_inter = visib_gt & visib_est
    visib_union_count = int(np.count_nonzero(visib_gt | visib_est))
    visib_comp_count = visib_union_count - int(np.count_nonzero(visib_inter))
    if visib_union_count == 0:
        return np.ones(len(taus))
    dists = np.abs(dist_gt[visib_inter] - dist_est[visib_inter])
    if normalized_by_diameter:
        dists = dists / diameter
    errors = []
    for tau in taus:
        costs = (dists >= tau).astype(np.float64) if cost_type == "step" else np.minimum(dists / tau, 1.0)
        errors.append((float(costs.sum()) + visib_comp_count) / visib_union_count)
    return np.asarray(errors)


# --------------------------------------------------------------------------- Pose / model wrappers


_EVAL_SYMS: "weakref.WeakKeyDictionary[ObjectModel, dict[float, list[Pose]]]" = weakref.WeakKeyDictionary()
_EVAL_SYMS_LOCK = threading.Lock()


def eval_symmetries(model: ObjectModel, max_sym_disc_step: float = MAX_SYM_DISC_STEP) -> list[Pose]:
    """The symmetry transformations to evaluate errors with, as bop_toolkit samples them.

    A model's own list samples continuous symmetries every 10 degrees (core/symmetry.py), which is
    cheap for blocks but lets a perfect pose of a rotationally symmetric part show an MSSD of
    up to ~4 % of the diameter. For evaluation, continuous symmetries declared in the model's
    models_info are resampled as bop_toolkit's get_symmetry_transformations does:
    ceil(pi / max_sym_disc_step) steps, so no surface point moves more than about
    max_sym_disc_step x diameter between two samples. Cached per model."""
    info = model.info or {}
    if not info.get("symmetries_continuous"):
        return list(model.symmetries)
    with _EVAL_SYMS_LOCK:
        per_model = _EVAL_SYMS.setdefault(model, {})
        if max_sym_disc_step not in per_model:
            steps = int(math.ceil(math.pi / max_sym_disc_step))
            per_model[max_sym_disc_step] = symmetries_from_info(info, cont_step_deg=360.0 / steps)
        return per_model[max_sym_disc_step]


def pose_mssd(est: Pose, gt: Pose, model: ObjectModel) -> float:
    """Symmetry-aware MSSD (m) of a hypothesis for a model: exact over the surface (its convex
    hull), with continuous symmetries sampled finely (see `eval_symmetries`)."""
    return mssd(est.R, est.t, gt.R, gt.t, model.hull_points, eval_symmetries(model))


_DERIVED_SYMS: "weakref.WeakKeyDictionary[ObjectModel, dict[tuple[float, float], list[Pose]]]" = (
    weakref.WeakKeyDictionary())
_DERIVED_SYMS_LOCK = threading.Lock()


def derived_eval_symmetries(model: ObjectModel, tolerance: float = DEFAULT_SYM_TOLERANCE,
                            max_sym_disc_step: float = MAX_SYM_DISC_STEP) -> list[Pose]:
    """The symmetries to evaluate errors with when near-symmetries count: those the model
    declares (as `eval_symmetries` samples them) if it declares any, else those derived from its
    surface (core/symmetry.py: declared_or_derived_symmetries, within tolerance x diameter;
    a continuous one sampled as finely as `eval_symmetries` samples declared ones). Cached per
    model and settings."""
    if len(model.symmetries) > 1:
        return eval_symmetries(model, max_sym_disc_step)
    key = (float(tolerance), float(max_sym_disc_step))
    with _DERIVED_SYMS_LOCK:
        per_model = _DERIVED_SYMS.setdefault(model, {})
        if key not in per_model:
            steps = int(math.ceil(math.pi / max_sym_disc_step))
            per_model[key] = declared_or_derived_symmetries(model, tolerance, cont_step_deg=360.0 / steps)
        return per_model[key]


def pose_mssd_derived(est: Pose, gt: Pose, model: ObjectModel, tolerance: float = DEFAULT_SYM_TOLERANCE) -> float:
    """MSSD (m) as `pose_mssd`, but over the symmetries the model declares or, declaring none,
    over those derived from its geometry (`derived_eval_symmetries`): a 180-degree flip of a
    nearly symmetric box scores about its asymmetry here (at most ~tolerance x diameter), not
    the box's size as in `pose_mssd` (which the simulated pick keeps)."""
    return mssd(est.R, est.t, gt.R, gt.t, model.hull_points, derived_eval_symmetries(model, tolerance))


def pose_errors(
    est: Pose,
    gt: Pose,
    model: ObjectModel,
    K: np.ndarray | None = None,
    depth: np.ndarray | None = None,
    *,
    vsd_delta: float = VSD_DELTA,
    vsd_taus: Sequence[float] = VSD_TAUS,
    vsd_normalized_by_diameter: bool = True,
) -> dict[str, Any]:
    """All BOP errors of a hypothesis: add, adi, mssd, re, te (metres / radians) and, with K,
    mspd (px); with K and a depth image (metres, NaN missing) also `vsd`, an array with one
    error per tau of `vsd_taus` (BOP defaults: delta 15 mm, taus 0.05..0.5 x diameter). VSD
    needs depth: for an RGB-only frame (depth None) "vsd" is absent.

    ADD/ADI use the model's area-uniform surface samples (BOP uses the uniformly resampled
    models_eval vertices), MSSD the convex hull (exact), MSPD the mesh vertices."""
    out: dict[str, Any] = {
        "add": add(est.R, est.t, gt.R, gt.t, model.points),
        "adi": adi(est.R, est.t, gt.R, gt.t, model.points),
        "mssd": pose_mssd(est, gt, model),
        "re": re(est.R, gt.R),
        "te": te(est.t, gt.t),
    }
    if K is not None:
        out["mspd"] = mspd(est.R, est.t, gt.R, gt.t, K, model.vertices, eval_symmetries(model))
        if depth is not None:
            out["vsd"] = vsd(est.R, est.t, gt.R, gt.t, depth, K, vsd_delta, vsd_taus,
                             vsd_normalized_by_diameter, model.diameter, model)
    elif depth is not None:
        raise ValueError("pose_errors: VSD needs the camera matrix K along with the depth image")
    return out


# --------------------------------------------------------------------------- recall


def recall(errors: Sequence[float] | np.ndarray, thresholds: Sequence[float] | np.ndarray) -> np.ndarray:
    """Share of errors below each threshold (one value per threshold): strictly, `error <
    threshold`, as bop_toolkit's pose_matching counts a match. NaN/inf errors (missing or failed
    estimates) count as wrong; an empty error list gives recall 0."""
    e = np.asarray(errors, dtype=np.float64).ravel()
    th = np.asarray(thresholds, dtype=np.float64).ravel()
    if e.size == 0:
        return np.zeros(th.size)
    with np.errstate(invalid="ignore"):
        return (e[None, :] < th[:, None]).mean(axis=1)


def average_recall_mssd(errors_m: Sequence[float] | np.ndarray, diameters: float | Sequence[float] | np.ndarray,
                        thresholds: Sequence[float] = MSSD_THRESHOLDS) -> float:
    """BOP AR_MSSD: recall averaged over thresholds 0.05..0.5 x object diameter. `diameters` is
    one value or one per error (estimates of different objects)."""
    e = np.asarray(errors_m, dtype=np.float64).ravel()
    d = np.broadcast_to(np.asarray(diameters, dtype=np.float64), e.shape)
    return float(recall(e / d, thresholds).mean())


def average_recall_mspd(errors_px: Sequence[float] | np.ndarray, image_width: int,
                        thresholds: Sequence[float] = MSPD_THRESHOLDS) -> float:
    """BOP AR_MSPD: recall averaged over thresholds 5..50 px x image_width / 640."""
    r = float(image_width) / 640.0
    return float(recall(errors_px, np.asarray(thresholds) * r).mean())


def average_recall_vsd(errors: Sequence[Sequence[float]] | np.ndarray,
                       thresholds: Sequence[float] = VSD_THRESHOLDS) -> float:
    """BOP AR_VSD: recall averaged over the VSD thresholds 0.05..0.5 and over the taus.
    `errors` is (N, n_taus): one row of `vsd` errors per estimate."""
    e = np.asarray(errors, dtype=np.float64)
    if e.ndim == 1:
        e = e[None, :]
    if e.size == 0:
        return 0.0
    return float(np.mean([recall(e[:, j], thresholds) for j in range(e.shape[1])]))


__all__ = [
    "add", "adi", "mssd", "mspd", "re", "te", "vsd", "depth_to_distance", "eval_symmetries", "pose_mssd",
    "derived_eval_symmetries", "pose_mssd_derived", "pose_errors",
    "recall", "average_recall_mssd", "average_recall_mspd", "average_recall_vsd",
    "VSD_DELTA", "VSD_TAUS", "VSD_THRESHOLDS", "MSSD_THRESHOLDS", "MSPD_THRESHOLDS", "MAX_SYM_DISC_STEP",
]
