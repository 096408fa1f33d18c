"""D2CO: direct directional chamfer optimisation (Imperoli & Pretto, ICVS 2015).

The model contour visible from the hypothesis (the rendered silhouette plus the visible sharp mesh
edges that are straight, as 3D model points with 3D tangents; vision.edges.model_contour) is
projected into the image with its 2D directions; each point's residual is the directional chamfer
tensor (DCT) at its pixel and orientation (bilinear in the pixel, linear across the two nearest
bins). A hand-written Levenberg-Marquardt loop (vision.pose_solver) minimises the robustified sum
of squared residuals over the 6-DoF pose, parametrised as a rotation about the object origin and a
translation (R = exp([w]x) R0, t = t0 + d), with the analytic Jacobian (the spatial gradient of the
interpolated tensor times the projection Jacobian; the orientation is held fixed within a step, as
in the paper). Analytic steps make an iteration ~0.2 ms.

For real photographs (blurred outlines, clutter, occlusion; the edge cost's minimum is shallow):
- the loss is redescending (Geman-McClure at `huber_px`): a point far from any matching edge
  (occluded, clutter) stops pulling;
- a colour-region term (`region_weight`, vision.region: RBOT / SRT3D's correspondence lines
  with the start's colour histograms) pulls the rendered outline to the most likely
  foreground/background colour transition along its normals, weighted by that transition's
  certainty; the lines are drawn at the start (`region_updates` > 1 re-draws them at the result
  for more descents: on lmo-rgb +1-4 points, but on the synthetic default's convergence from
  lambda >= 0.5 it loses a third of the successes, so off): edges alone are often pulled to
  clutter and texture (measured on lmo-rgb: from lambda 0.3, 57 % of the calls improved MSSD
  with edges alone, 65 % with both);
- weak priors anchored at the call's start hold depth along the viewing ray (edges observe it
  only through the projected size; measured: freeing it loses half the within-tolerance share)
  and the rotation (`rotation_prior_deg`);
- two descents: a local one at the final scale, and a coarse-to-fine one (Huber at
  `coarse_factor` x the scale, then the final loss) kept only if its cost is `coarse_margin` lower
  (it reaches farther on clean edges, synthetic: within tolerance after 3 calls from lambda 0.3
  74 % with it, 71 % without; on lmo-rgb it changes nothing);
- the start comes back unchanged unless the block's own cost (`d2co_cost`, the mean robust loss
  of the contour's edge residuals and of the region residuals of the lines drawn at the start:
  not the cost the last descent minimised) drops by
  `accept_margin`: repeated calls from a correct pose otherwise creep away on drops within the
  cost's noise (lmo-rgb, started at the ground truth, within tolerance after 3 calls: 95 % with
  margin 0 and the region term, 98 % with 0.02).

The tensor is built on a crop around the hypothesis's projected box (+ `crop_margin`) and kept
in the per-frame cache (vision.edges.TensorCache): a later call whose box gets the same crop
(snapped to a 32 px grid) pays only the optimisation. D2CO pairs well with depth refinement or ICP.
"""
from __future__ import annotations

import time

import numpy as np

from ..core.geometry import Pose
from ..core.render import projected_box
from ..vision.edges import TensorCache, edge_refinement_problem, model_contour, sample_tensor
from ..vision.pose_solver import LOSSES, levenberg_marquardt, project_with_jacobian, robust_rho, rotation_prior_weight
from ..vision.region import ColourModel, band_width, colour_model, line_displacements, outline_samples
from ..vision.visibility import hypothesis_rendering
from .base import MODEL, POSE, RGB, Block, BlockInput, BlockResult, Kind, Param, register


@register
class D2CO(Block):
    """Direct directional chamfer optimisation of the pose on image edges plus a colour-region term
    (LM over 6 DoF). Fixes image-plane position and rotation; depth along the viewing ray stays
    weakly observed."""

    kind = Kind.REFINEMENT
    name = "d2co"
    default_cost = 0.04
    inputs = (RGB, MODEL, POSE)
    score_names = ("d2co_cost",)
    lower_is_better = ("d2co_cost",)
    params = (
        Param("n_bins", 60, 8, 180, doc="orientation bins over [0, pi)"),
        Param("penalty", 0.5, 0.0, 10.0,
              doc="tensor cost per bin of orientation difference (px); the notes: 0.5 works, 5 hurts"),
        Param("max_distance", 30.0, 2.0, 200.0, doc="truncation of the chamfer distance (px): robustness to clutter"),
        Param("crop_margin", 40, 0, 400, doc="pixels around the hypothesis's box the tensor covers"),
        Param("canny_low", 15.0, 0.0, 1000.0, doc="Canny low threshold (real photographs' edges are weak)"),
        Param("canny_high", 40.0, 0.0, 1000.0, doc="Canny high threshold"),
        Param("blur_px", 1.0, 0.5, 5.0, doc="sigma (px) of the Gaussian before Canny"),
        Param("depth_prior_mm", 5.0, 0.1, 1000.0,
              doc="depth shift (mm) that costs as much as every point 1 px: keeps the weakly observed depth"),
        Param("rotation_prior_deg", 15.0, 0.1, 1000.0,
              doc="rotation away from the start (deg) that costs as much as every point 1 px (1000: none)"),
        Param("max_points", 300, 20, 5000, doc="contour points used (random subset)"),
        Param("mesh_edges", True, doc="add the visible sharp mesh edges to the silhouette"),
        Param("edge_coherence", 0.95, 0.0, 1.0,
              doc="sharp-edge samples less straight than this are left out (a scanned mesh's are mostly spurious)"),
        Param("loss", "geman_mcclure", choices=LOSSES, doc="robust loss of the per-point cost"),
        Param("huber_px", 2.0, 0.1, 50.0, doc="scale of the robust loss (px): the final stage's"),
        Param("coarse_factor", 2.0, 1.0, 10.0,
              doc="a second, coarse-to-fine descent starts at coarse_factor x huber_px (1: none)"),
        Param("coarse_rotation_prior_deg", 1000.0, 0.1, 1000.0, doc="rotation_prior_deg of the coarse descent"),
        Param("coarse_loss", "huber", choices=LOSSES, doc="robust loss of the coarse descent's wide stages"),
        Param("coarse_margin", 0.2, 0.0, 0.9,
              doc="the coarse-to-fine result replaces the local one only if its cost is this fraction lower"),
        Param("accept_margin", 0.02, 0.0, 0.9,
              doc="the result is kept only if it lowers the cost by this fraction (else the start is returned): "
                  "smaller drops are within the cost's noise and, repeated, walk a correct pose away"),
        Param("holdout", 0.0, 0.0, 0.8,
              doc="share of the contour points held out of the fit: the result must lower their cost too"),
        Param("region_weight", 1.0, 0.0, 10.0,
              doc="weight of the colour-region term (outline to colour transition) against the edge term (0: none)"),
        Param("region_lines", 120, 10, 2000, doc="correspondence lines of the region term"),
        Param("region_line_px", 12, 2, 100, doc="half-length (px) of the region term's correspondence lines"),
        Param("region_updates", 1, 1, 10,
              doc="region correspondences drawn per call: after the first descent, re-drawn at the current pose "
                  "(lines halved, at least 4 px) for one more LM descent each"),
        Param("max_iterations", 30, 1, 500, doc="LM iterations per descent stage"),
        Param("max_seconds", 0.2, 0.001, 10.0, doc="time bound of the whole call (s)"),
    )

    def run(self, inp: BlockInput) -> BlockResult:
        c, frame, model, pose0 = self.config, inp.frame, inp.model, inp.pose
        assert pose0 is not None
        start = time.perf_counter()
        box = projected_box(model, pose0, frame.K, frame.width, frame.height)
        why = edge_refinement_problem(frame, model, pose0, box)
        if why:
            return BlockResult.fail(why)
        margin = int(c["crop_margin"])
        dct, crop, n_edges = TensorCache.get(frame, inp.cache, box, margin, int(c["n_bins"]), c["penalty"],
                                             c["max_distance"], c["canny_low"], c["canny_high"], c["blur_px"])
        if dct is None or n_edges == 0:
            return BlockResult.fail("no image edges around the hypothesis")
        P, D = model_contour(frame, model, pose0, inp.cache, int(c["max_points"]), inp.rng, c["mesh_edges"],
                             c["edge_coherence"])
        if len(P) < 6:
            return BlockResult.fail(f"only {len(P)} contour points visible from the hypothesis")
        K, cap, (x0, y0) = frame.K, float(c["max_distance"]), crop[:2]
        loss, scale = str(c["loss"]), float(c["huber_px"])

        region0, cm = _region_term(frame, model, pose0, inp.cache, c, len(P))

        def residuals(R: np.ndarray, t: np.ndarray, P=P, D=D, region=region0):
            uv, ang, Jp = project_with_jacobian(R, t, P, D, K)
            r, gx, gy = sample_tensor(dct, uv[:, 0] - x0, uv[:, 1] - y0, ang, cap, gradient=True)
            J = gx[:, None] * Jp[:, 0, :] + gy[:, None] * Jp[:, 1, :]
            Pr, nr, target, wr = region
            if len(Pr) == 0:
                return r, J
            # the colour-region term: the outline's distance along its normal to the colour transition
            px, _, Jr = project_with_jacobian(R, t, Pr, np.zeros_like(Pr), K)
            rr = np.nan_to_num((np.sum(nr * px, axis=1) - target) * wr, nan=cap)
            Jn = np.nan_to_num((nr[:, 0:1] * Jr[:, 0, :] + nr[:, 1:2] * Jr[:, 1, :]) * wr[:, None])
            return np.concatenate([r, rr]), np.concatenate([J, Jn])

        def cost(r: np.ndarray) -> float:
            return float(np.mean(robust_rho(r, loss, scale)))

        r0, _ = residuals(pose0.R, pose0.t)
        support = float(np.mean(r0[:len(P)] <= scale))
        n_hold = int(round(c["holdout"] * len(P))) if len(P) - int(round(c["holdout"] * len(P))) >= 6 else 0
        order = inp.rng.permutation(len(P))
        fit, hold = order[n_hold:], order[:n_hold]
        Pf, Df = P[fit], D[fit]
        # Edges barely constrain depth along the viewing ray: a weak prior keeps it where it was
        # (a shift of depth_prior_mm costs as much as every point 1 px further off); likewise rotation.
        ray = pose0.t / np.linalg.norm(pose0.t)
        n_eff = len(Pf) * (1.0 + (c["region_weight"] if len(region0[0]) else 0.0))  # the data term's total weight
        prior = ray * np.sqrt(n_eff) / (c["depth_prior_mm"] * 1e-3)
        rot_prior = rotation_prior_weight(int(round(n_eff)), c["rotation_prior_deg"])
        cost0 = cost(r0)
        deadline = self.deadline(inp, start)
        R, t, iterations = pose0.R, pose0.t, 0
        fit_cost = lambda R_, t_: cost(residuals(R_, t_, Pf, Df)[0])  # noqa: E731

        def descend(R: np.ndarray, t: np.ndarray, first: float, rot_prior: float,
                    wide_loss: str) -> tuple[np.ndarray, np.ndarray, int]:
            """LM with the robust scale halving from `first` down to huber_px (`wide_loss` above it)."""
            stage, total = first, 0
            while True:
                s = max(stage, scale)
                R, t, it = levenberg_marquardt(lambda R_, t_: residuals(R_, t_, Pf, Df), R, t, prior, s,
                                               int(c["max_iterations"]), deadline,
                                               loss=loss if s <= scale else wide_loss,
                                               rotation_prior=rot_prior, anchor=pose0.t, rotation_anchor=pose0.R)
                total += it
                if s <= scale or time.perf_counter() > deadline:
                    return R, t, total
                stage /= 2.0

        # Two hypotheses: a local descent at the final scale, and a coarse-to-fine one whose wide
        # first stage reaches farther; the wide one must beat the local one by coarse_margin (it
        # also finds spurious minima on cluttered photographs).
        R, t, iterations = descend(R, t, scale, rot_prior, loss)
        if c["coarse_factor"] > 1 and time.perf_counter() < deadline:
            wide = c["coarse_rotation_prior_deg"]
            Rc, tc, it = descend(pose0.R, pose0.t, scale * float(c["coarse_factor"]),
                                 rotation_prior_weight(int(round(n_eff)), wide), str(c["coarse_loss"]))
            iterations += it
            if fit_cost(Rc, tc) < fit_cost(R, t) * (1.0 - c["coarse_margin"]):
                R, t = Rc, tc
        # Region updates: the colour correspondences re-drawn at the current pose (its outline has
        # moved, and its contour generator over the surface), shorter lines, the same colour model.
        half = float(c["region_line_px"])
        for _ in range(int(c["region_updates"]) - 1):
            half = max(4.0, half / 2.0)
            if cm is None or time.perf_counter() > deadline:
                break
            region, _ = _region_term(frame, model, Pose(R, t), None, c, len(P), cm, int(round(half)))
            if len(region[0]) == 0:
                break
            R, t, it = levenberg_marquardt(lambda R_, t_, g=region: residuals(R_, t_, Pf, Df, g), R, t, prior, scale,
                                           int(c["max_iterations"]), deadline, loss=loss, rotation_prior=rot_prior,
                                           anchor=pose0.t, rotation_anchor=pose0.R)
            iterations += it
        r, _ = residuals(R, t)  # judged by the start's correspondences: not the cost just minimised
        cost1 = cost(r)
        info = {"cost_before": cost0, "iterations": iterations, "points": len(P), "tensor_crop": crop,
                "support": support, "cost_candidate": cost1}
        accept = (np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and cost1 < cost0 * (1.0 - c["accept_margin"])
                  and (n_hold == 0 or cost(r[hold]) < cost(r0[hold])))
        if not accept:
            return BlockResult(ok=True, pose=pose0, scores={"d2co_cost": cost0}, info={**info, "improved": False})
        return BlockResult(ok=True, pose=Pose(R, t), scores={"d2co_cost": cost1}, info={**info, "improved": True})


def _region_term(frame, model, pose0: Pose, cache: dict | None, c: dict, n_edge: int, cm: ColourModel | None = None,
                 half: int | None = None) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
                                                   ColourModel | None]:
    """The colour-region term's correspondences, fixed at the call's start (vision.region): model
    points on the start's rendered outline (N, 3), their unit inward normals (N, 2), the value of
    n . pixel at the most likely foreground/background transition along each normal (N,), and the
    residual weights (N,): 1 / the transition's standard deviation (floored at 1 px), times
    sqrt(region_weight x n_edge / lines), so the term weighs region_weight x the `n_edge` edge
    points'; and the colour model (`cm`: computed at pose0 unless given; lines of `half` px,
    region_line_px unless given). Empty when region_weight is 0 or the start gives no colour model."""
    empty = np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0), np.zeros(0)
    if c["region_weight"] <= 0:
        return empty, None
    rend = hypothesis_rendering(frame, model, pose0, cache)
    if rend.empty:
        return empty, cm
    half = int(c["region_line_px"]) if half is None else half
    if cm is None:
        cm = colour_model(frame, rend, band_width(rend, 0.15, 10), 4, int(c["region_line_px"]) + 8)
        if cm is None:
            return empty, None
    Pr, uv, nrm = outline_samples(frame, rend, pose0, int(c["region_lines"]))
    if len(Pr) < 6:
        return empty, cm
    d, sd = line_displacements(cm, uv, nrm, half)
    w = np.sqrt(c["region_weight"] * n_edge / len(Pr)) / np.maximum(sd, 1.0)
    return (Pr, nrm, np.sum(nrm * uv, axis=1) + d, w), cm
