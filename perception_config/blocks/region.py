"""Region-based refinement of the pose on the colour image (RBOT / SRT3D style, RGB only).

Colour histograms of the start hypothesis's inner and outer outline bands give a foreground
posterior map; the silhouette, re-rendered at every iteration, is pulled along its normals to
the most likely foreground/background transition on 1D correspondence lines (coarse-to-fine
half-lengths), with robust Levenberg-Marquardt steps on the analytic projection Jacobian and
weak priors (depth along the viewing ray, rotation about it and out of the image plane, each its
own strength: pose_solver.prior_information) anchored at the start. The algorithm is in
vision/region.py. On real photographs of scanned models a tighter out-of-plane prior (8 deg) or
local colour histograms (`sectors` 12) keep correct poses better, from wrong starts they reach
less (docs/results/real_photographs.md); the defaults keep the synthetic figures.
The start comes back unchanged (`info["improved"] = False`) unless the block's own cost
(`region_cost`, 1 - the colour separation of the pose's bands) drops.
"""
from __future__ import annotations

import time

import numpy as np

from ..core.geometry import Pose
from ..core.render import projected_box
from ..vision.edges import edge_refinement_problem
from ..vision.pose_solver import (
    LOSSES,
    NO_TRANSLATION_PRIOR,
    levenberg_marquardt,
    prior_information,
    project_with_jacobian,
)
from ..vision.region import band_width, colour_model, line_displacements, outline_samples, region_cost
from ..vision.visibility import hypothesis_rendering
from .base import MODEL, POSE, RGB, Block, BlockInput, BlockResult, Kind, Param, register


@register
class RegionRefiner(Block):
    """Region-based (colour-histogram) 6-DoF refinement on 1D correspondence lines along the
    rendered outline's normals; RGB only. Fixes image-plane position and rotation; depth along
    the viewing ray is observed only through the silhouette's size."""

    kind = Kind.REFINEMENT
    name = "region"
    default_cost = 0.03
    inputs = (RGB, MODEL, POSE)
    score_names = ("region_cost",)
    lower_is_better = ("region_cost",)
    params = (
        Param("band", 10, 2, 100, doc="largest width (px) of the colour histograms' inner and outer bands"),
        Param("band_fraction", 0.15, 0.0, 10.0, doc="band width as a share of sqrt(object pixels) (psi_rgb's)"),
        Param("gap_px", 0.0, 0.0, 50.0,
              doc="the histograms leave out the pixels within this distance (px) of the outline"),
        Param("sectors", 0, 0, 64,
              doc="local colour histograms: the bands split into this many angular sectors (0 or 1: the whole bands')"),
        Param("sector_prior_px", 50.0, 0.0, 1e6,
              doc="weight (pixels) of the whole bands' histograms in each sector's"),
        Param("bits", 4, 2, 6, doc="bits per colour channel of the histograms"),
        Param("lines", 120, 10, 2000, doc="correspondence lines (outline points) per iteration"),
        Param("line_px", 16, 2, 100, doc="half-length (px) of the lines at the first iteration"),
        Param("min_line_px", 4, 2, 100, doc="half-length (px) of the lines at the last iterations"),
        Param("shrink", 0.7, 0.1, 1.0, doc="line half-length factor per iteration (coarse to fine)"),
        Param("temperature", 0.5, 0.05, 1.0,
              doc="factor on the lines' log-likelihoods (neighbouring pixels are not independent)"),
        Param("min_sigma_px", 1.0, 0.1, 20.0, doc="floor of a line's displacement uncertainty (px)"),
        Param("loss", "huber", choices=LOSSES, doc="robust loss of the normalised line residuals"),
        Param("loss_scale", 2.0, 0.1, 50.0, doc="scale of the robust loss (in line standard deviations)"),
        Param("depth_prior_mm", 5.0, 0.1, 1000.0,
              doc="depth shift (mm) that costs as much as every line one standard deviation"),
        Param("rotation_prior_deg", 15.0, 0.1, 1000.0,
              doc="rotation away from the start (deg) that costs as much as every line one standard deviation"),
        Param("out_of_plane_prior_deg", 15.0, 0.1, 1000.0,
              doc="rotation out of the image plane (deg) that costs as much as every line one standard deviation"),
        Param("histogram_update", 0.0, 0.0, 1.0,
              doc="weight of the histograms re-estimated at the current pose after each update (0: the start's)"),
        Param("lm_iterations", 3, 1, 50, doc="LM iterations per correspondence update"),
        Param("iterations", 10, 1, 100, doc="correspondence updates (re-renders) per call"),
        Param("accept_margin", 0.0, 0.0, 0.9,
              doc="the result is kept only if it lowers region_cost by this fraction (else the start is returned)"),
        Param("max_seconds", 0.2, 0.001, 10.0, doc="time bound of the whole call (s)"),
    )

    def run(self, inp: BlockInput) -> BlockResult:
        c, frame, model, pose0 = self.config, inp.frame, inp.model, inp.pose
        assert frame is not None and pose0 is not None
        start = time.perf_counter()
        box = projected_box(model, pose0, frame.K, frame.width, frame.height)
        why = edge_refinement_problem(frame, model, pose0, box)
        if why:
            return BlockResult.fail(why)
        r0 = hypothesis_rendering(frame, model, pose0, inp.cache)
        if r0.empty:
            return BlockResult.fail("the hypothesis renders no pixel inside the image")
        histograms = {"gap": float(c["gap_px"]), "sectors": int(c["sectors"]),
                      "sector_prior_px": float(c["sector_prior_px"])}
        cm = colour_model(frame, r0, band_width(r0, c["band_fraction"], int(c["band"])), int(c["bits"]),
                          int(c["line_px"]) + 40, **histograms)
        if cm is None:
            return BlockResult.fail("the hypothesis leaves no image pixels outside its outline")
        cost0 = region_cost(frame, r0, cm)
        fit_cm = cm
        deadline = self.deadline(inp, start)
        K, n_lines = frame.K, int(c["lines"])
        R, t, rend = pose0.R, pose0.t, r0
        half, iterations, updates, moved = float(c["line_px"]), 0, 0, []
        for _ in range(int(c["iterations"])):
            if time.perf_counter() > deadline:
                break
            P, uv, nrm = outline_samples(frame, rend, Pose(R, t), n_lines)
            if len(P) < 6:
                break
            L = int(round(half))
            d, sd = line_displacements(fit_cm, uv, nrm, L, c["temperature"])
            sigma = np.maximum(sd, c["min_sigma_px"])
            moved.append(float(np.mean(np.abs(d))))
            target = np.sum(nrm * uv, axis=1) + d  # n . uv the outline should reach

            def residuals(R_: np.ndarray, t_: np.ndarray, P=P, nrm=nrm, target=target, sigma=sigma):
                px, _, J = project_with_jacobian(R_, t_, P, np.zeros_like(P), K)
                r = (np.sum(nrm * px, axis=1) - target) / sigma
                Jn = (nrm[:, 0:1] * J[:, 0, :] + nrm[:, 1:2] * J[:, 1, :]) / sigma[:, None]
                return np.nan_to_num(r, nan=0.0), np.nan_to_num(Jn, nan=0.0)

            information = prior_information(pose0.t, len(P), c["rotation_prior_deg"], c["out_of_plane_prior_deg"],
                                            c["depth_prior_mm"])
            R, t, it = levenberg_marquardt(residuals, R, t, NO_TRANSLATION_PRIOR, float(c["loss_scale"]),
                                           int(c["lm_iterations"]), deadline, loss=str(c["loss"]), anchor=pose0.t,
                                           rotation_anchor=pose0.R, information=information)
            iterations += it
            updates += 1
            rend = hypothesis_rendering(frame, model, Pose(R, t), None)
            if rend.empty:
                break
            if c["histogram_update"] > 0:
                now = colour_model(frame, rend, cm.band, cm.bits, 0, **histograms, box=cm.box)
                if now is not None:
                    fit_cm = fit_cm.blended(now, float(c["histogram_update"]))
            half = max(float(c["min_line_px"]), half * float(c["shrink"]))
        ok_pose = bool(np.all(np.isfinite(R)) and np.all(np.isfinite(t)))
        cost1 = region_cost(frame, rend, cm) if ok_pose else np.inf
        info = {"cost_before": cost0, "cost_candidate": cost1, "iterations": iterations, "updates": updates,
                "band_px": cm.band, "line_shift_px": moved}
        if not (ok_pose and cost1 < cost0 * (1.0 - c["accept_margin"])):
            return BlockResult(ok=True, pose=pose0, scores={"region_cost": cost0}, info={**info, "improved": False})
        return BlockResult(ok=True, pose=Pose(R, t), scores={"region_cost": cost1}, info={**info, "improved": True})


__all__ = ["RegionRefiner"]
