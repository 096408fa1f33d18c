"""ICP polishing and render-and-compare verification of pose hypotheses (the model-only
generator's last steps, blocks/generation.py).

- `icp_target`: the observed points a candidate is polished against (its cluster and the
  fragments under its silhouette); `icp_polish`: coarse-to-fine ICP of the camera-facing model
  samples (`visible_model_points`) against them.
- `verify`: depth agreement, free-space violations, cluster coverage and hue agreement of a
  hypothesis's rendering with the frame.
- `ranked_candidates`: verified hypotheses as a generator's ranked, distinct candidates;
  `verify_polish_rank`: the three as a generator's last steps (ppf, resting_pose).
"""
from __future__ import annotations

import math
import time

import numpy as np
import open3d as o3d

from ..core.geometry import Pose
from ..core.models import ObjectModel
from ..core.render import Rendering, project, render_box
from ..core.scene import Frame
from .colour import chromaticity, colours_agree, model_point_colours
from .features import point_cloud
from .segmentation import Segmentation, dominant_label

MAX_TARGET_POINTS = 8000
TARGET_NORMAL_RADIUS = 0.005  # metres: normals fitted to the target's points when the image gives too few
COLOUR_SAMPLES = 1000  # model samples whose colour is compared (of 3000): a third of the cost


def icp_target(
    seg: Segmentation, pose: Pose, model: ObjectModel, rendering: Rendering, source: int,
    min_share: float = 0.3, margin: float = 1.6,
) -> o3d.geometry.PointCloud:
    """Observed points (with normals) for polishing a candidate: those of the cluster it came
    from and of every cluster lying mostly (`min_share` of its pixels) under the candidate's
    rendered silhouette (fragments of the same object), inside a generous sphere around the
    model at `pose`. Neighbouring objects stay out: on flat parts they drag ICP sideways.
    Every pixel is used (sparser targets let point-to-plane slide on flat parts), thinned to
    about 1.5 mm spacing beyond MAX_TARGET_POINTS. Normals are the segmentation's (from the
    box-filtered depth) when at least 80 % of the points have one; otherwise (sensor dropout
    leaves few complete filter windows: on the synthetic parts often under 10 %) they are fitted
    to the points within TARGET_NORMAL_RADIUS, rather than dropping the points without one."""
    include = {source}
    if not rendering.empty:
        rs, cs = rendering.crop_slices()
        m = rendering.mask >= 0
        for level in seg.whole_levels:  # a split level's piece would take in a neighbour's parts
            under = level[rs, cs][m]
            under = under[under >= 0]
            if len(under):
                counts = np.bincount(under, minlength=len(seg.clusters))
                for i in np.flatnonzero(counts):
                    if counts[i] >= min_share * len(seg.clusters[i].pixels):
                        include.add(int(i))
    pix = np.unique(np.concatenate([seg.clusters[i].pixels for i in sorted(include)]))
    pts = seg.points.reshape(-1, 3)[pix]
    nrm = seg.normals.reshape(-1, 3)[pix]
    centre = pose.transform(model.points.mean(axis=0)[None])[0]
    radius = margin * float(np.max(np.linalg.norm(model.points - model.points.mean(axis=0), axis=1)))
    near = np.isfinite(pts[:, 2]) & (np.sum((pts - centre) ** 2, axis=1) < radius**2)
    has_normal = np.isfinite(nrm[near, 0])
    if len(has_normal) == 0 or has_normal.mean() >= 0.8:
        pc = point_cloud(pts[near][has_normal], nrm[near][has_normal])
    else:  # noisy depth with dropout leaves few complete windows for the image normals: fit them here
        pc = point_cloud(pts[near])
        if len(pc.points) >= 3:
            pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=TARGET_NORMAL_RADIUS, max_nn=30))
            pc.orient_normals_towards_camera_location(np.zeros(3))
    if len(pc.points) > MAX_TARGET_POINTS:  # close-up views: thin out to about 1.5 mm spacing
        pc = pc.voxel_down_sample(0.0015)
        pc.normalize_normals()
    return pc


def visible_model_points(model: ObjectModel, pose: Pose, max_points: int = 600) -> tuple[np.ndarray, np.ndarray]:
    """Model samples (model frame) whose normals face the camera at `pose` (back-face culling;
    whole-surface samples bias ICP towards the hidden side)."""
    pc = pose.transform(model.points)
    nc = model.point_normals @ pose.R.T
    front = np.flatnonzero(np.einsum("ij,ij->i", nc, pc) < 0)
    if len(front) < 10:
        front = np.arange(len(pc))
    front = front[:: max(1, len(front) // max_points)]
    return model.points[front], model.point_normals[front]


def icp_polish(
    model: ObjectModel, pose: Pose, target: o3d.geometry.PointCloud, distances: tuple[float, ...], iterations: int = 15
) -> tuple[Pose, float, float]:
    """Coarse-to-fine ICP (legacy open3d) of the camera-facing model samples against the
    observed points (which carry normals): point-to-point at the first (coarsest) distance,
    point-to-plane after. Point-to-plane alone slides along flat faces when started centimetres
    off (measured on the synthetic cover: 0.13 d -> 1.2 d); point-to-point is constrained in
    all six degrees of freedom. Returns (pose, fitness, inlier rmse)."""
    reg = o3d.pipelines.registration
    T = pose.matrix()
    fitness, rmse = 0.0, math.inf
    for k, dist in enumerate(distances):
        est = reg.TransformationEstimationPointToPoint() if k == 0 else reg.TransformationEstimationPointToPlane()
        pts, nrm = visible_model_points(model, Pose.from_matrix(T))
        res = reg.registration_icp(point_cloud(pts, nrm), target, dist, T, est,
                                   reg.ICPConvergenceCriteria(max_iteration=iterations))
        if res.fitness > 0:
            T = np.asarray(res.transformation).copy()
        fitness, rmse = float(res.fitness), float(res.inlier_rmse)
    U, _, Vt = np.linalg.svd(T[:3, :3])  # re-orthonormalise accumulated float error
    return Pose(U @ Vt, T[:3, 3]), fitness, rmse


def verify(
    model: ObjectModel, pose: Pose, frame: Frame, tol: float = 0.01, penalty: float = 1.0,
    colour_weight: float = 0.5, rendering: Rendering | None = None, seg: Segmentation | None = None,
    explain_weight: float = 0.5,
) -> tuple[float, dict[str, float]]:
    """Render-and-compare score of a hypothesis against the observed frame.

    Depth: over the rendered object pixels, inliers = observed depth within `tol` of the
    rendered one; violations = observed surface more than `tol` *behind* the rendered one (the
    sensor sees through where the object would be: free-space violation). Pixels where the
    observed surface is in front (occlusion) or missing are neutral. Depth score = (inliers -
    penalty * violations) / the rendered pixels with an observed depth (at least half of all
    rendered pixels, so a pose over a hole cannot score high), in [-2 penalty, 1]: sensor
    dropout on shiny parts does not mark the right pose down.

    Colour (models with vertex colours): of the camera-facing model samples that land on a
    depth inlier, the share whose image chromaticity agrees with the model's (dark pixels
    neutral). The score is depth * (1 - colour_weight * (1 - colour agreement)), so depth alone
    decides for uncoloured models and a right shape in the wrong colour is marked down.
    With the frame's segmentation `seg`, agreement on support surfaces (table, bin) does not
    count, so a flat hypothesis sunk into the table does not explain anything; and the
    clusters lying mostly (30 %) under the rendered silhouette should be covered by it: an
    object ends where its region ends. The covered share of their pixels ("explained", best of
    the segmentation levels) scales the score by (1 - explain_weight * (1 - explained)):
    it marks down a part hypothesised onto a face or corner of a larger object (an L-bracket
    on a box corner), which depth agreement alone accepts.
    -inf when nothing is rendered or the frame is RGB-only (depth None). `rendering`: render_box
    of the model at `pose`, if at hand."""
    if not pose.is_valid() or frame.depth is None:  # an RGB-only frame: nothing to verify against
        return -math.inf, {}
    r = rendering
    if r is None:
        r = render_box(model, pose, frame.K, frame.width, frame.height, with_normals=False)
    m = r.mask >= 0
    n = int(m.sum())
    if n == 0:
        return -math.inf, {}
    rs, cs = r.crop_slices()
    obs_box = frame.depth[rs, cs]
    obs = obs_box[m]
    ren = r.depth[m]
    with np.errstate(invalid="ignore"):
        diff = obs - ren
        close = np.abs(diff) < tol
        if seg is not None:
            close &= ~seg.support[rs, cs][m]
        inl = int(np.sum(close))
        viol = int(np.sum(diff > tol))
    n_obs = max(int(np.sum(np.isfinite(obs))), (n + 1) // 2)
    depth_score = (inl - penalty * viol) / n_obs
    details = {"gen_depth_score": depth_score, "gen_inlier_share": inl / n_obs, "gen_violation_share": viol / n_obs,
               "gen_rendered_px": float(n), "gen_colour_agreement": 1.0, "gen_explained": 1.0}
    score = depth_score
    if seg is not None and explain_weight > 0:
        explained = _explained_share(seg, r)
        details["gen_explained"] = explained
        score = score * (1.0 - explain_weight * (1.0 - explained)) if score > 0 else score
    mc = model_point_colours(model) if colour_weight > 0 else None
    if mc is not None:
        agree = _colour_agreement(model, pose, frame, r, obs_box, mc[0], tol)
        if agree is not None:
            details["gen_colour_agreement"] = agree
            score = score * (1.0 - colour_weight * (1.0 - agree)) if score > 0 else score
    return score, details


def _explained_share(seg: Segmentation, r: Rendering, min_share: float = 0.3) -> float:
    """Covered share of the pixels of the clusters that lie at least `min_share` under the
    rendered silhouette (best of Segmentation.whole_levels); 0 when no cluster does."""
    rs, cs = r.crop_slices()
    m = r.mask >= 0
    sizes = np.array([len(c.pixels) for c in seg.clusters])
    best = 0.0
    for level in seg.whole_levels:
        under = level[rs, cs][m]
        under = under[under >= 0]
        if not len(under):
            continue
        counts = np.bincount(under, minlength=len(sizes))
        sel = (counts > 0) & (counts >= min_share * sizes)
        if sel.any():
            best = max(best, float(counts[sel].sum() / sizes[sel].sum()))
    return best


def _colour_agreement(model: ObjectModel, pose: Pose, frame: Frame, r: Rendering, obs_box: np.ndarray,
                      colours: np.ndarray, tol: float) -> float | None:
    """Share of the visible, depth-confirmed model samples whose image colour agrees with the
    model's (colours_agree); None with fewer than 10 such samples that are bright enough.
    About COLOUR_SAMPLES of the model's samples are compared."""
    step = max(1, len(model.points) // COLOUR_SAMPLES)
    pc = pose.transform(model.points[::step])
    colours = colours[::step]
    facing = np.einsum("ij,ij->i", model.point_normals[::step] @ pose.R.T, pc) < 0
    uv = project(pc, frame.K)
    with np.errstate(invalid="ignore"):
        u = np.rint(uv[:, 0]) - r.offset[0]
        v = np.rint(uv[:, 1]) - r.offset[1]
    h, w = r.depth.shape
    ok = facing & np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    u, v, z, cols = u[ok].astype(np.int64), v[ok].astype(np.int64), pc[ok, 2], colours[ok]
    with np.errstate(invalid="ignore"):
        seen = (np.abs(r.depth[v, u] - z) < tol) & (np.abs(obs_box[v, u] - z) < tol)
    if seen.sum() < 10:
        return None
    ci, bi = chromaticity(frame.rgb[v[seen] + r.offset[1], u[seen] + r.offset[0]])
    cm, bm = chromaticity(cols[seen])
    use = bi & bm
    if use.sum() < 10:
        return None
    return float(np.mean(colours_agree(ci[use], cm[use])))


def ranked_candidates(verified: list[tuple[float, Pose]], model: ObjectModel, keep: int,
                      dist_share: float = 0.1, angle_deg: float = 15.0) -> list[tuple[float, Pose]]:
    """The best `keep` of (verification score, pose), best first, each differing from every
    better one by at least `dist_share` diameters (model centre) or `angle_deg`; confidence =
    the score clipped to [0, 1]. Near-copies (the same pose found from two clusters) would
    waste a `next_candidate`."""
    centre = model.points.mean(axis=0)
    cos_max = math.cos(math.radians(angle_deg))
    kept: list[tuple[float, Pose, np.ndarray]] = []
    for score, pose in sorted(verified, key=lambda q: -q[0]):
        c = pose.transform(centre[None])[0]
        if all(np.linalg.norm(c - ck) >= dist_share * model.diameter
               or (np.trace(pk.R.T @ pose.R) - 1.0) / 2.0 <= cos_max for _, pk, ck in kept):
            kept.append((float(min(max(score, 0.0), 1.0)), pose, c))
        if len(kept) >= keep:
            break
    return [(conf, pose) for conf, pose, _ in kept]


def verify_polish_rank(
    model: ObjectModel, frame: Frame, seg: Segmentation, poses: list[Pose], voxel: float, deadline: float,
    verify_tol: float = 0.01, n_polish: int = 16, icp_iterations: int = 10, top_k: int = 5,
    keep_unpolished: bool = False,
) -> tuple[list, list, list[tuple[float, Pose]]]:
    """A generator's last steps over its hypotheses `poses` (best first): each is pre-verified
    by rendering (`verify`), the best `n_polish` are polished by coarse-to-fine ICP (`icp_polish`,
    from 3 to 0.5 `voxel`s) against the observed points under them (`icp_target`) and verified
    again; with `keep_unpolished` the pose before ICP competes with the polished one (ICP on a
    few hundred pixels can pull a well-placed small part off). Stops starting new work at
    `deadline` (perf_counter). Returns (pre-verified (score,
    index, pose, rendering), polished (score, pose, details) best first, ranked_candidates)."""
    pre = []
    for k, pose in enumerate(poses):
        if time.perf_counter() >= deadline:
            break
        if not pose.is_valid():
            continue
        r = render_box(model, pose, frame.K, frame.width, frame.height, with_normals=False)
        score = verify(model, pose, frame, verify_tol, 1.0, 0.5, r, seg, 0.5)[0]
        if math.isfinite(score):
            pre.append((score, k, pose, r))
    pre.sort(key=lambda q: (-q[0], q[1]))
    icp_dists = (max(3.0 * voxel, 0.006), max(1.2 * voxel, 0.003), max(0.5 * voxel, 0.002))
    polished: list[tuple[float, Pose, dict[str, float]]] = []
    for pre_score, _, pose, r in pre[:n_polish]:
        if time.perf_counter() >= deadline:
            break
        if keep_unpolished:
            polished.append((float(pre_score), pose, {}))
        source_label = dominant_label(seg, r)
        if source_label < 0:
            continue
        target = icp_target(seg, pose, model, r, source_label)
        if len(target.points) >= 10:
            pose, _, _ = icp_polish(model, pose, target, icp_dists, icp_iterations)
        score, details = verify(model, pose, frame, verify_tol, 1.0, 0.5, seg=seg, explain_weight=0.5)
        if math.isfinite(score):
            polished.append((float(score), pose, details))
    polished.sort(key=lambda q: -q[0])
    return pre, polished, ranked_candidates([(q[0], q[1]) for q in polished], model, top_k)
