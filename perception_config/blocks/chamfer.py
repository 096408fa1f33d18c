"""The paper's comparison methods for edge-based refinement: chamfer matching and chamfer-ICP.

Both use the model contour visible from the hypothesis (vision.edges.model_contour) and the
image's Canny edges, computed once per frame and shared by every object and call on that frame.
- `chamfer`: local search over pose perturbations (random rotations about the object origin
  and image-plane translations, the radius halving each round), evaluated in batches, keeping
  the pose with the lowest mean truncated chamfer distance of the projected contour points. By
  default the distance is directional (D2CO's tensor, vision.edges.TensorCache: distance plus
  orientation mismatch; a frame shares it with d2co): the plain distance to the dense edges of
  a real photograph is ~1.5 px almost anywhere, so it barely prefers the ground truth over a
  start at lambda 0.3 (76 % of the cases on lmo-rgb; directional: 87 %). A careful search
  (small radii, short truncation, a rotation prior) and a wide one (the paper's radii, long
  truncation); the wide result must be `wide_margin` cheaper on the careful cost.
- `chamfer_icp`: ICP in the image: each projected contour point is matched to its nearest
  image edge pixel (the distance transform's labels), then a few damped Gauss-Newton
  (Levenberg-Marquardt) steps minimise the reprojection error of the 3D contour points to
  their matches (Geman-McClure-robust), plus a Gaussian prior anchored at the start
  (`prior_information`, pose_solver.levenberg_marquardt); the matching distance shrinks from
  `max_match_px` to `min_match_px`.
Out-of-image-plane rotation is what drifts (measured on lmo-rgb: the depth prior holds depth;
calls that left the ground truth had turned the object 1-2 deg out of the image plane, and at
lambda 0.3 the worsening calls mostly grew that rotation): an outline's contour generator
slides over the surface as the object turns, so a silhouette barely shows it; inner (sharp
mesh) edges do (`inner_edge_share`). So chamfer samples out-of-plane rotation `out_of_plane` x
narrower than rotation about the viewing ray, the wide search as far wider as the contour is
inner edges, and lowers the wide search's margin as far as the image shows those inner edges at
its result; the wide result must also separate the image colours across its outline clearly
better than the careful one (`wide_colour_check`, by `wide_colour_margin`; psi_rgb's region cue:
clutter edges that pull the wide search on a photograph rarely do; on lmo-rgb the taken wide
results that were worse than the careful one separated them a median 0.09 better, those that
were better 0.18. Paired runs, 3 seeds x 3 calls, within tolerance after 1 / 3 calls, no check
-> at least as well -> 0.08 better: lmo-rgb from the ground truth 92 / 90 -> 94 / 91 -> 97 / 96 %,
lambda 0.1 90 / 86 -> 92 / 89 -> 96 / 93 %, lambda 0.3 improved 64 -> 64 -> 66 %, within after
3 calls 31 -> 32 -> 32 %; the synthetic default 98 / 96 -> 100 / 99 -> 100 / 99 %, 97 / 96 ->
100 / 99 -> 100 / 100 %, lambda 0.3 unchanged. The margin's price: the synthetic convergence
table, 40 images, up to 5 calls from lambda 0.3, 0.67-0.68 -> 0.64-0.65 (docs/results/real_photographs.md));
chamfer-ICP's prior holds out-of-plane rotation (`out_of_plane_prior_deg`, loosened by
1 / (1 - inner-edge share)) far more than rotation about the ray (`rotation_prior_deg`).
Both return the start unchanged unless their own cost (`chamfer_cost`, the mean truncated
chamfer distance, directional where the matching is) is lower at the result.
Like D2CO, both fix the image-plane position and rotation well and depth weakly: chamfer does
not search depth at all, chamfer-ICP keeps it with the same weak prior as D2CO (unconstrained
PnP on nearest-edge matches drifts along the viewing ray by centimetres).
"""
from __future__ import annotations

import time

import numpy as np

from ..core.geometry import Pose, exp_so3
from ..core.render import projected_box
from ..vision.appearance import outline_separation
from ..vision.chamfer import edge_distance, inner_edge_share
from ..vision.edges import (
    TensorCache,
    bilinear,
    canny_edges,
    edge_refinement_problem,
    model_contour,
    project_with_directions,
    sample_tensor,
)
from ..vision.pose_solver import (
    LOSSES,
    NO_TRANSLATION_PRIOR,
    levenberg_marquardt,
    prior_information,
    project_with_jacobian,
)
from ..vision.region import band_width
from ..vision.visibility import hypothesis_rendering
from .base import MODEL, POSE, RGB, Block, BlockInput, BlockResult, Kind, Param, register


def _start(inp: BlockInput, c: dict, labels: bool) -> tuple[str, tuple | None, np.ndarray, np.ndarray]:
    """Common checks: (reason or '', edge distance, contour points, contour directions)."""
    frame, pose = inp.frame, inp.pose
    assert pose is not None
    none = np.zeros((0, 3))
    box = projected_box(inp.model, pose, frame.K, frame.width, frame.height)
    why = edge_refinement_problem(frame, inp.model, pose, box)
    if why:
        return why, None, none, none
    edge = edge_distance(frame, inp.cache, c["canny_low"], c["canny_high"], labels)
    if edge[3] == 0:
        return "the image has no edges", None, none, none
    x, y, w, h = box
    if not np.any(edge[0][y:y + h, x:x + w] < 1.0):
        return "no image edges around the hypothesis", None, none, none
    P, D = model_contour(frame, inp.model, pose, inp.cache, int(c["max_points"]), inp.rng, c["mesh_edges"],
                         c["edge_coherence"])
    if len(P) < 6:
        return f"only {len(P)} contour points visible from the hypothesis", None, P, D
    return "", edge, P, D


_COMMON = (
    Param("canny_low", 15.0, 0.0, 1000.0, doc="Canny low threshold (real photographs' edges are weak)"),
    Param("canny_high", 40.0, 0.0, 1000.0, doc="Canny high threshold"),
    Param("max_points", 300, 20, 5000, doc="contour points used (random subset)"),
    Param("mesh_edges", True, doc="add the visible sharp mesh edges to the silhouette"),
    Param("edge_coherence", 0.95, 0.0, 1.0,
          doc="sharp-edge samples less straight than this are left out (a scanned mesh's are mostly spurious)"),
    Param("accept_margin", 0.0, 0.0, 0.9,
          doc="the result is kept only if it lowers the cost by this fraction (else the start is returned)"),
)


@register
class ChamferMatching(Block):
    """Simple chamfer matching: a random local search minimising the mean chamfer distance.
    Searches rotation and image-plane translation; depth is left as it was."""

    kind = Kind.REFINEMENT
    name = "chamfer"
    default_cost = 0.03
    inputs = (RGB, MODEL, POSE)
    score_names = ("chamfer_cost",)
    lower_is_better = ("chamfer_cost",)
    params = (
        Param("rounds", 4, 1, 20, doc="search rounds; the radius halves each round"),
        Param("candidates", 40, 4, 1000, doc="random poses tried per round"),
        Param("batch", 10, 1, 1000, doc="candidates evaluated together; the best of a batch becomes the centre"),
        Param("rotation_deg", 2.0, 0.1, 45.0, doc="first-round rotation radius (deg)"),
        Param("translation_mm", 1.5, 0.1, 100.0, doc="first-round image-plane translation radius (mm)"),
        Param("max_distance", 6.0, 1.0, 200.0,
              doc="truncation of the chamfer distance (px): occluded or unsupported points stop counting"),
        Param("rotation_prior_deg", 2.0, 0.1, 1000.0,
              doc="rotation away from the start (deg) that costs as much as every point 1 px further (1000: none)"),
        Param("wide_rotation_deg", 4.0, 0.0, 45.0, doc="the wide search's first-round rotation radius (deg; 0: none)"),
        Param("wide_translation_mm", 6.0, 0.1, 100.0, doc="the wide search's first-round translation radius (mm)"),
        Param("wide_max_distance", 20.0, 1.0, 200.0, doc="the wide search's truncation of the chamfer distance (px)"),
        Param("wide_margin", 0.2, 0.0, 0.9,
              doc="the wide search's result replaces the careful one's only if its cost is this fraction lower"),
        Param("wide_colour_check", True,
              doc="the wide result must also separate the image colours across its outline better than the "
                  "careful one (an independent cue: clutter edges that pull the wide search rarely do)"),
        Param("wide_colour_margin", 0.08, 0.0, 1.0,
              doc="by this much (psi_rgb's region cue, 0 to 1) with wide_colour_check: a wide result that moved "
                  "off a correct start separates them little better, one that found the object far better"),
        Param("inner_support_px", 1.5, 0.0, 100.0,
              doc="the wide result's inner-edge points count as shown by the image within this chamfer distance (px)"),
        Param("out_of_plane", 0.3, 0.0, 1.0,
              doc="spread of the sampled out-of-image-plane rotation relative to that about the viewing ray"),
        Param("out_of_plane_prior_deg", 1000.0, 0.1, 1000.0,
              doc="out-of-image-plane rotation (deg) that costs as much as every point 1 px further (1000: none)"),
        Param("directional", True,
              doc="directional chamfer distance (D2CO's tensor: distance + orientation mismatch), not the plain one"),
        Param("n_bins", 60, 8, 180, doc="orientation bins of the directional tensor (as d2co's, so a frame shares it)"),
        Param("penalty", 0.5, 0.0, 10.0, doc="directional tensor cost per bin of orientation difference (px)"),
        Param("crop_margin", 40, 0, 400, doc="pixels around the hypothesis's box the directional tensor covers"),
        *_COMMON,
        Param("max_seconds", 0.1, 0.001, 10.0, doc="time bound (s)"),
    )

    def run(self, inp: BlockInput) -> BlockResult:
        c, frame, pose0 = self.config, inp.frame, inp.pose
        start = time.perf_counter()
        why, edge, P, D = _start(inp, c, labels=False)
        if why:
            return BlockResult.fail(why)
        K = frame.K
        dct, x0, y0 = None, 0, 0
        if c["directional"]:
            box = projected_box(inp.model, pose0, K, frame.width, frame.height)
            margin = int(c["crop_margin"])
            dct, crop, _ = TensorCache.get(frame, inp.cache, box, margin, int(c["n_bins"]), c["penalty"],
                                           max(30.0, float(c["max_distance"]), float(c["wide_max_distance"])),
                                           c["canny_low"], c["canny_high"])
            if dct is None:
                return BlockResult.fail("no image edges around the hypothesis")
            x0, y0 = crop[:2]

        def costs(Rs: np.ndarray, ts: np.ndarray, cap: float, per_point: bool = False, P_: np.ndarray = P,
                  D_: np.ndarray = D) -> np.ndarray:
            """Mean chamfer distance truncated at `cap` of the contour (P_, D_) under each of C poses
            (C, 3, 3), (C, 3) (with `per_point`, the (C, N) distances)."""
            P, D = P_, D_
            pc = np.einsum("cij,nj->cni", Rs, P) + ts[:, None, :]
            z = pc[..., 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                u = (K[0, 0] * pc[..., 0] + K[0, 1] * pc[..., 1]) / z + K[0, 2]
                v = K[1, 1] * pc[..., 1] / z + K[1, 2]
                if dct is not None:  # the tangent's image angle: the projection Jacobian applied to R D
                    dc = np.einsum("cij,nj->cni", Rs, D)
                    du = K[0, 0] * (dc[..., 0] * z - pc[..., 0] * dc[..., 2]) / z**2
                    dv = K[1, 1] * (dc[..., 1] * z - pc[..., 1] * dc[..., 2]) / z**2
                    ang = np.mod(np.arctan2(dv, du), np.pi)
            u[z <= 1e-3] = np.nan
            if dct is None:
                r = bilinear(np.minimum(edge[0], cap), u.ravel(), v.ravel(), cap).reshape(u.shape)
            else:
                r = sample_tensor(dct, u.ravel() - x0, v.ravel() - y0, ang.ravel(), cap)
                r = np.minimum(r, cap).reshape(u.shape)
            return r if per_point else r.mean(axis=1)

        # the image plane at the object: translations perpendicular to the viewing ray
        ray = pose0.t / np.linalg.norm(pose0.t)
        e1 = np.cross(ray, [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        plane = np.stack([e1, np.cross(ray, e1)])
        frame3 = np.stack([ray, *plane])
        cap = float(c["max_distance"])

        def shown_share(R_: np.ndarray, t_: np.ndarray, support_px: float) -> float:
            """inner_edge_share at (R_, t_); with support_px > 0, of the inner edges the image shows
            there (chamfer distance within support_px)."""
            if not c["mesh_edges"]:
                return 0.0
            shown = (lambda P_, D_: costs(R_[None], t_[None], cap, per_point=True, P_=P_, D_=D_)[0] <= support_px)
            return inner_edge_share(frame, inp.model, Pose(R_, t_), inp.cache, c["edge_coherence"],
                                    shown if support_px > 0 else None)

        # the wide search samples out-of-plane rotation as far as the model's contour has inner edges
        share = shown_share(pose0.R, pose0.t, 0.0)
        deadline = self.deadline(inp, start)

        def rotations(ws: np.ndarray) -> np.ndarray:
            """exp(w) R0 for rotation vectors (C, 3) about the object origin."""
            return np.stack([exp_so3(w) @ pose0.R for w in ws])

        def search(rot_deg: float, trans_mm: float, cap: float, prior_deg: float,
                   out_prior_deg: float, spread: float) -> tuple[np.ndarray, np.ndarray, int]:
            """The random local search from the start: (R, t, candidates tried); the objective is
            the chamfer distance truncated at `cap` plus (rotation about the viewing ray / prior_deg)^2
            plus (rotation out of the image plane / out_prior_deg)^2 (1000: none). Out-of-plane
            rotation barely changes an outline, so it is sampled `spread` x narrower."""
            w_in = 1.0 / np.radians(prior_deg) ** 2 if prior_deg < 1000 else 0.0
            w_out = 1.0 / np.radians(out_prior_deg) ** 2 if out_prior_deg < 1000 else 0.0
            best_w, best_t = np.zeros(3), pose0.t
            best = float(costs(pose0.R[None], best_t[None], cap)[0])
            rot, trans = np.radians(rot_deg), trans_mm * 1e-3
            tried, n_batch = 0, int(c["batch"])
            shape = np.array([1.0, spread, spread])
            for _ in range(int(c["rounds"])):
                done = 0
                while done < c["candidates"] and time.perf_counter() < deadline:
                    k = int(min(n_batch, c["candidates"] - done))
                    # rotation vectors in the (ray, e1, e2) frame: about the ray, then out of plane
                    ws = best_w + (inp.rng.normal(0.0, rot, (k, 3)) * shape) @ frame3
                    ts = best_t + inp.rng.normal(0.0, trans / np.sqrt(2), (k, 2)) @ plane
                    values = costs(rotations(ws), ts, cap)
                    if w_in or w_out:
                        a = ws @ ray
                        values = values + w_in * a**2 + w_out * np.sum((ws - a[:, None] * ray) ** 2, axis=1)
                    i = int(np.argmin(values))
                    if values[i] < best:
                        best, best_w, best_t = float(values[i]), ws[i], ts[i]
                    done += k
                tried += done
                rot, trans = rot / 2, trans / 2
            return exp_so3(best_w) @ pose0.R, best_t, tried

        own = lambda R_, t_: float(costs(R_[None], t_[None], cap)[0])  # noqa: E731

        def separation(R_: np.ndarray, t_: np.ndarray) -> float:
            """The image colours' separation across the outline at (R_, t_) (psi_rgb's region cue)."""
            rendering = hypothesis_rendering(frame, inp.model, Pose(R_, t_), inp.cache)
            return outline_separation(frame, rendering, band_width(rendering, 0.15, 10))

        cost0 = own(pose0.R, pose0.t)
        # Two searches: a careful one (small radii, short truncation, rotation prior) and a wide
        # one (larger radii, long truncation, no prior) that must beat it by wide_margin on the
        # careful one's cost: it reaches farther but also finds clutter on real photographs.
        best_R, best_t, tried = search(c["rotation_deg"], c["translation_mm"], cap, c["rotation_prior_deg"],
                                       c["rotation_prior_deg"] if c["out_of_plane_prior_deg"] >= 1000
                                       else min(c["rotation_prior_deg"], c["out_of_plane_prior_deg"]),
                                       float(c["out_of_plane"]))
        wide = "not run"  # the wide search's outcome: "taken", or rejected on the "edges" / "colour"
        if c["wide_rotation_deg"] > 0 and time.perf_counter() < deadline:
            spread = float(c["out_of_plane"]) + (1.0 - float(c["out_of_plane"])) * share
            Rw, tw, n = search(c["wide_rotation_deg"], c["wide_translation_mm"], c["wide_max_distance"], 1000.0,
                               c["out_of_plane_prior_deg"], spread)
            tried += n
            # the margin shrinks as far as the image shows the inner edges at the wide result
            # (evidence for its out-of-plane rotation, which an outline alone hardly gives)
            seen = shown_share(Rw, tw, float(c["inner_support_px"])) if share > 0 else 0.0
            if not own(Rw, tw) < own(best_R, best_t) * (1.0 - c["wide_margin"] * (1.0 - seen)):
                wide = "edges"
            elif c["wide_colour_check"] and separation(Rw, tw) < separation(best_R, best_t) + c["wide_colour_margin"]:
                wide = "colour"
            else:
                best_R, best_t, wide = Rw, tw, "taken"
        best_data = own(best_R, best_t)
        info = {"cost_before": cost0, "candidates": tried, "points": len(P), "cost_candidate": best_data, "wide": wide}
        if not best_data < cost0 * (1.0 - c["accept_margin"]):
            return BlockResult(ok=True, pose=pose0, scores={"chamfer_cost": cost0}, info={**info, "improved": False})
        return BlockResult(ok=True, pose=Pose(best_R, best_t), scores={"chamfer_cost": best_data},
                           info={**info, "improved": True})


@register
class ChamferIcp(Block):
    """Chamfer-ICP: nearest image edge pixel per contour point, then damped Gauss-Newton on the
    reprojection error; repeated with a shrinking matching distance. Depth is weakly observed
    and held by a prior (see the module docstring)."""

    kind = Kind.REFINEMENT
    name = "chamfer_icp"
    default_cost = 0.03
    inputs = (RGB, MODEL, POSE)
    score_names = ("chamfer_cost",)
    lower_is_better = ("chamfer_cost",)
    params = (
        Param("iterations", 8, 1, 100, doc="match-and-solve iterations"),
        Param("steps", 3, 1, 20, doc="LM steps per set of matches"),
        Param("max_match_px", 15.0, 1.0, 200.0, doc="first-iteration matching distance (px)"),
        Param("min_match_px", 3.0, 0.5, 200.0, doc="last-iteration matching distance (px)"),
        Param("depth_prior_mm", 5.0, 0.1, 1000.0, doc="depth shift (mm) that costs as much as every point 1 px"),
        Param("rotation_prior_deg", 15.0, 0.1, 1000.0,
              doc="rotation about the viewing ray (deg) that costs as much as every point 1 px (1000: none)"),
        Param("inner_support_px", 0.0, 0.0, 100.0,
              doc="an inner-edge point counts only if the image shows it within this chamfer distance at the start"
                  " (px; 0: every inner-edge point counts)"),
        Param("out_of_plane_prior_deg", 3.0, 0.1, 1000.0,
              doc="rotation out of the image plane (deg) that costs as much as every point 1 px (1000: none)"),
        Param("max_angle_deg", 90.0, 1.0, 90.0,
              doc="a match's image edge must run within this angle of the contour point's tangent (90: any)"),
        Param("directional", False,
              doc="match along each contour point's normal to the cheapest directional chamfer cell (d2co's tensor)"),
        Param("match_cost_px", 3.0, 0.1, 30.0, doc="directional matching: a match must cost at most this (px)"),
        Param("match_distance_cost", 0.2, 0.0, 10.0,
              doc="directional matching: tensor cost added per px away from the point (the nearer edge first)"),
        Param("n_bins", 60, 8, 180, doc="orientation bins of the directional tensor (as d2co's, so a frame shares it)"),
        Param("penalty", 0.5, 0.0, 10.0, doc="directional tensor cost per bin of orientation difference (px)"),
        Param("crop_margin", 40, 0, 400, doc="pixels around the hypothesis's box the directional tensor covers"),
        Param("point_to_line", False,
              doc="residual along the matched edge's normal only (the contour may slide along the edge)"),
        Param("loss", "geman_mcclure", choices=LOSSES, doc="robust loss of the reprojection error"),
        Param("max_distance", 20.0, 1.0, 200.0, doc="truncation of the chamfer distance of the reported cost (px)"),
        *_COMMON,
        Param("max_seconds", 0.1, 0.001, 10.0, doc="time bound (s)"),
    )

    def run(self, inp: BlockInput) -> BlockResult:
        c, frame, pose0 = self.config, inp.frame, inp.pose
        start = time.perf_counter()
        why, edge, P, D = _start(inp, c, labels=True)
        if why:
            return BlockResult.fail(why)
        dt, labels, lut, _ = edge
        H, W = dt.shape
        K = frame.K
        cap = float(c["max_distance"])
        dtc = np.minimum(dt, cap)
        edge_dir = canny_edges(frame, inp.cache, c["canny_low"], c["canny_high"])[1]
        dct, x0, y0, tcap = None, 0, 0, max(30.0, cap)
        if c["directional"]:
            box = projected_box(inp.model, pose0, K, frame.width, frame.height)
            margin = int(c["crop_margin"])
            dct, crop, _ = TensorCache.get(frame, inp.cache, box, margin, int(c["n_bins"]), c["penalty"],
                                           tcap, c["canny_low"], c["canny_high"])
            if dct is None:
                return BlockResult.fail("no image edges around the hypothesis")
            x0, y0 = crop[:2]

        def point_costs(R_: np.ndarray, t_: np.ndarray, P_: np.ndarray = P, D_: np.ndarray = D) -> np.ndarray:
            """Per-point chamfer distance truncated at `cap` (directional with `directional`)."""
            uv_, ang_ = project_with_directions(R_, t_, P_, D_, K)
            if dct is None:
                return bilinear(dtc, uv_[:, 0], uv_[:, 1], cap)
            return np.minimum(sample_tensor(dct, uv_[:, 0] - x0, uv_[:, 1] - y0, ang_, tcap), cap)

        def chamfer_cost(R_: np.ndarray, t_: np.ndarray) -> float:
            return float(np.mean(point_costs(R_, t_)))

        cost0 = chamfer_cost(pose0.R, pose0.t)
        # out-of-plane rotation: held in proportion to how little of the contour is inner edges the image shows
        support = float(c["inner_support_px"])
        shown = (lambda P_, D_: point_costs(pose0.R, pose0.t, P_, D_) <= support) if support > 0 else None
        share = (inner_edge_share(frame, inp.model, pose0, inp.cache, c["edge_coherence"], shown)
                 if c["mesh_edges"] else 0.0)
        out_deg = c["out_of_plane_prior_deg"] / max(1.0 - share, 1e-3) if c["out_of_plane_prior_deg"] < 1000 else 1000.0
        out_deg = min(out_deg, max(c["rotation_prior_deg"], c["out_of_plane_prior_deg"]))  # <= about the ray
        information = prior_information(pose0.t, len(P), c["rotation_prior_deg"], out_deg, c["depth_prior_mm"])
        max_angle = np.radians(float(c["max_angle_deg"]))
        R, t = pose0.R, pose0.t
        n_it = int(c["iterations"])
        dists = np.geomspace(c["max_match_px"], min(c["min_match_px"], c["max_match_px"]), n_it)
        mean_dist, matched = np.nan, 0
        deadline = self.deadline(inp, start)
        for it in range(n_it):
            if time.perf_counter() > deadline:
                break
            uv, ang = project_with_directions(R, t, P, D, K)
            if dct is not None:  # directional matching along each point's normal on d2co's tensor
                normal = np.stack([-np.sin(ang), np.cos(ang)], axis=1)
                L = int(np.ceil(dists[it]))
                steps = np.arange(-L, L + 1, dtype=np.float64)
                q = uv[:, None, :] + steps[None, :, None] * normal[:, None, :]
                vals = sample_tensor(dct, q[..., 0].ravel() - x0, q[..., 1].ravel() - y0,
                                     np.repeat(ang, len(steps)), tcap).reshape(len(P), len(steps))
                vals = vals + float(c["match_distance_cost"]) * np.abs(steps)[None, :]  # the nearer edge first
                k = np.argmin(vals, axis=1)
                best = vals[np.arange(len(P)), k]
                with np.errstate(invalid="ignore"):
                    near = np.isfinite(best) & (best <= float(c["match_cost_px"]))
                if near.sum() < 6:
                    break
                idx = np.flatnonzero(near)
                Pm, Dm, nm = P[idx], D[idx], normal[idx]
                offs = steps[k[idx]]
                mean_dist, matched = float(np.mean(np.abs(offs))), int(len(idx))
                target = uv[idx] + offs[:, None] * nm

                def evaluate(R_: np.ndarray, t_: np.ndarray, *, Pm=Pm, Dm=Dm, target=target, nm=nm):
                    uv_, _, J = project_with_jacobian(R_, t_, Pm, Dm, K)
                    return np.einsum("ni,ni->n", uv_ - target, nm), np.einsum("ni,nij->nj", nm, J)

                R, t, _ = levenberg_marquardt(evaluate, R, t, NO_TRANSLATION_PRIOR, max(2.0, float(dists[it])),
                                              int(c["steps"]), deadline, anchor=pose0.t, loss=str(c["loss"]),
                                              rotation_anchor=pose0.R, information=information)
                continue
            with np.errstate(invalid="ignore"):
                iu, iv = np.rint(uv[:, 0]), np.rint(uv[:, 1])
                inside = np.isfinite(iu) & (iu >= 0) & (iv >= 0) & (iu < W) & (iv < H)
            idx = np.flatnonzero(inside)
            iu, iv = iu[idx].astype(np.intp), iv[idx].astype(np.intp)
            d = dt[iv, iu]
            target = lut[labels[iv, iu]]
            # the matched edge must run like the contour there (clutter and texture edges mostly do not)
            diff = np.abs(edge_dir[target[:, 1].astype(np.intp), target[:, 0].astype(np.intp)] - ang[idx])
            diff = np.minimum(diff, np.pi - diff)
            near = (d <= dists[it]) & (diff <= max_angle)
            if near.sum() < 6:
                break
            idx, target, d = idx[near], target[near], d[near]
            Pm, Dm = P[idx], D[idx]
            mean_dist, matched = float(np.mean(d)), int(len(idx))
            if c["point_to_line"]:  # the matched edge's normal (edge direction + 90 deg)
                a = edge_dir[target[:, 1].astype(np.intp), target[:, 0].astype(np.intp)] + np.pi / 2
                normal = np.stack([np.cos(a), np.sin(a)], axis=1)

                def evaluate(R_: np.ndarray, t_: np.ndarray, *, Pm=Pm, Dm=Dm, target=target, normal=normal):
                    uv_, _, J = project_with_jacobian(R_, t_, Pm, Dm, K)
                    return np.einsum("ni,ni->n", uv_ - target, normal), np.einsum("ni,nij->nj", normal, J)
            else:
                def evaluate(R_: np.ndarray, t_: np.ndarray, *, Pm=Pm, Dm=Dm, target=target):
                    uv_, _, J = project_with_jacobian(R_, t_, Pm, Dm, K)
                    return (uv_ - target).ravel(), J.reshape(-1, 6)

            # the prior is anchored at the call's start, not at each iteration's pose
            R, t, _ = levenberg_marquardt(evaluate, R, t, NO_TRANSLATION_PRIOR, max(2.0, float(dists[it])),
                                          int(c["steps"]), deadline, anchor=pose0.t, loss=str(c["loss"]),
                                          rotation_anchor=pose0.R, information=information)
        if not np.isfinite(mean_dist):
            if it == 0 and time.perf_counter() > deadline:
                return BlockResult.fail(f"the time budget ({c['max_seconds']} s) ran out before any contour match")
            return BlockResult.fail("too few contour points near image edges to match")
        cost = chamfer_cost(R, t)
        info = {"match_distance": mean_dist, "matches": matched, "iterations": it + 1, "cost_before": cost0,
                "cost_candidate": cost}
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and cost < cost0 * (1.0 - c["accept_margin"])):
            return BlockResult(ok=True, pose=pose0, scores={"chamfer_cost": cost0}, info={**info, "improved": False})
        return BlockResult(ok=True, pose=Pose(R, t), scores={"chamfer_cost": cost}, info={**info, "improved": True})
