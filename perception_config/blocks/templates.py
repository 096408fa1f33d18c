"""`linemod`: a ground-truth-free generator from the RGB image (and the depth image when the frame
has one) and the model: LINE-MOD template matching (vision/linemod.py), then verification and
polishing of the best matches. It returns its ranked candidates (best first, a confidence each)
in `BlockResult.candidates`, on RGB-D and RGB-only frames alike.

Steps: (1) the model's templates (renderings over a view sphere x in-plane rotations x apparent
sizes, built once per model and parameter set, cached on disk) are matched over the image by
cv2.linemod: colour gradients, plus surface normals when there is depth; (2) the `n_matches` best
distinct matches become poses (the template's rotation along the matched ray; the depth from the
template's size, or from the observed depth under the match); (3) each is verified: with depth by
render-and-compare (vision/verification.py `verify`, as ppf), without by `psi_rgb` (colour-region
separation and oriented edges of the outline); (4) the best `n_polish` are polished (ICP against
the observed points; without depth, the depth along the ray by a scan over the template size step,
then hill climbing of psi_rgb over depth, image position and rotation) and verified again; the distinct
results, best first, are the candidates. Confidence = the verification score clipped to [0, 1].
"""
from __future__ import annotations

import math
import time

import numpy as np

from ..core.geometry import Pose, exp_so3
from ..core.render import render_box
from ..vision.linemod import (
    TemplateParams,
    depth_agreement,
    distinct_matches,
    linemod_templates,
    match,
    poses_from_matches,
)
from ..vision.segmentation import dominant_label, frame_segmentation
from ..vision.verification import icp_polish, icp_target, ranked_candidates, verify
from .base import MODEL, RGB, Block, BlockInput, BlockResult, Kind, Param, create, register
from .verified import VERIFIER_PARAMS, RanksByVerifier


@register
class LineMod(RanksByVerifier, Block):
    """LINE-MOD template matching with verification and polishing (see the module docstring)."""

    kind = Kind.GENERATION
    name = "linemod"
    default_cost = 0.7  # median on the synthetic test images (benchmarks/results/candidates_linemod.json)
    inputs = (RGB, MODEL)
    score_names = ("gen_verification",)
    params = (
        Param("subdivisions", 2, 0, 3, doc="icosphere subdivisions of the template views (1: 42, 2: 162)"),
        Param("n_inplane", 12, 1, 72, doc="template rotations about the optical axis per view"),
        Param("n_scales", 5, 1, 12, doc="template sizes (LINE-MOD has no scale search)"),
        Param("min_px", 32.0, 16.0, 400.0, doc="apparent model diameter (px) of the smallest templates"),
        Param("max_px", 160.0, 16.0, 600.0, doc="apparent model diameter (px) of the largest templates"),
        Param("num_features", 63, 8, 200, doc="LINE-MOD features per template and modality"),
        Param("threshold", 70.0, 10.0, 100.0,
              doc="LINE-MOD similarity (percent) a match must reach (on cluttered, textured images the "
                  "match time grows steeply below 80: 5-9 s on LM-O at 70, 0.2-1 s at 80-85)"),
        Param("threshold_low", 70.0, 10.0, 100.0, doc="the threshold of a second match when the first finds few"),
        Param("min_raw", 500, 0, 100000, doc="fewer matches at `threshold`: matched again at `threshold_low`"),
        Param("mask_support", False, doc="with depth: image features on the support planes are left out of matching"),
        Param("use_depth", True, doc="with depth in the frame: the surface-normal modality and depth verification"),
        Param("max_raw", 4000, 10, 100000, doc="LINE-MOD matches read, best first"),
        Param("per_place", 30, 1, 1000, doc="matches kept per place (half the smallest template size)"),
        Param("n_matches", 60, 1, 1000,
              doc="matches verified (with depth: the best by a render-free depth check; without: by similarity)"),
        Param("n_polish", 5, 0, 50,
              doc="with depth: best verified matches polished by ICP and verified again"),
        Param("n_climb", 2, 0, 50, doc="without depth: best verified matches polished by psi_rgb hill climbing"),
        Param("top_k", 5, 1, 50, doc="ranked candidates returned"),
        Param("plane_distance", 0.008, 0.001, 0.05, doc="metres: points within this of the support plane are removed"),
        Param("icp_iterations", 10, 1, 200, doc="ICP iterations per stage (three stages, coarse to fine)"),
        Param("verify_tol", 0.01, 0.001, 0.05, doc="metres: depth agreement counted as an inlier in verification"),
        Param("explain_weight", 0.5, 0.0, 1.0,
              doc="weight of the covered share of the regions under a candidate in its depth verification "
                  "(a small part fitted onto a face of a larger object covers little of that object's region)"),
        Param("min_verification", 0.3, -1.0, 1.0,
              doc="below this (depth verification) the best candidate is not accepted (ok=False)"),
        Param("min_verification_rgb", 0.4, 0.0, 1.0,
              doc="the same for RGB-only frames (psi_rgb)"),
        Param("min_contrast", 2.0, 0.0, 255.0, doc="grey-level standard deviation below which the image is blank"),
        Param("max_seconds", 1.0, 0.01, 120.0,
              doc="time budget after the templates are at hand (checked between candidates)"),
    ) + VERIFIER_PARAMS

    def template_params(self) -> TemplateParams:
        c = self.config
        return TemplateParams(int(c["subdivisions"]), int(c["n_inplane"]), int(c["n_scales"]), float(c["min_px"]),
                              float(max(c["max_px"], c["min_px"])), int(c["num_features"]))

    def run(self, inp: BlockInput) -> BlockResult:
        c = self.config
        start = time.perf_counter()
        model, frame = inp.model, inp.frame
        d = model.diameter
        try:
            t, source = linemod_templates(model, self.template_params())
        except ValueError as exc:
            return BlockResult.fail(f"linemod: the model cannot be prepared: {exc}")
        t_prep = time.perf_counter() - start
        deadline = self.deadline(inp, start + t_prep)
        grey = frame.rgb.astype(np.float32).mean(axis=2)
        if float(grey.std()) < c["min_contrast"]:
            return BlockResult.fail(f"linemod: the image is flat (grey-level spread {grey.std():.2f}): blank image?")
        use_depth = bool(c["use_depth"]) and frame.depth is not None and bool(np.any(np.isfinite(frame.depth)))
        depth_mm = None
        if use_depth:
            depth_mm = np.nan_to_num(np.clip(frame.depth * 1000.0, 0, 65535), nan=0.0).astype(np.uint16)
        seg = frame_segmentation(frame, inp.cache, c["plane_distance"]) if use_depth else None
        mask = None
        if use_depth and c["mask_support"]:  # features on the support surfaces (table, bin floor) do not count
            mask = np.where(seg.support, 0, 255).astype(np.uint8)
        found = match(t, frame.rgb, depth_mm, c["threshold"], int(c["max_raw"]), mask)
        if len(found) < c["min_raw"] and c["threshold_low"] < c["threshold"]:
            # few matches (an untextured scene): the lower threshold is cheap there and finds more
            found = match(t, frame.rgb, depth_mm, c["threshold_low"], int(c["max_raw"]), mask)
        n_raw = len(found)
        found = distinct_matches(found, max(4.0, 0.5 * c["min_px"]), int(c["per_place"]))
        t_match = time.perf_counter()
        if not found:
            return BlockResult(ok=False, info={"templates": source, "matches": 0}, reason=(
                f"linemod: no template matches at {min(c['threshold'], c['threshold_low']):.0f} % "
                "(object not in view?)"))
        z = np.array([_observed_depth(t, m, frame, d) for m in found], float) if use_depth else None
        Rs, ts = poses_from_matches(t, found, frame.K, d, z)
        if use_depth:  # the best by a render-free depth check (support surfaces neutral)
            observed = np.where(seg.support, np.nan, frame.depth)
            sub = np.linspace(0, len(model.points) - 1, min(len(model.points), 200)).astype(np.intp)
            tol = max(c["verify_tol"], 0.03 * d)
            quick = np.concatenate([depth_agreement(model.points[sub], model.point_normals[sub], Rs[i:i + 256],
                                                    ts[i:i + 256], observed, frame.K, tol)
                                    for i in range(0, len(Rs), 256)])
            order = np.argsort(-quick, kind="stable")
        else:
            order = np.arange(len(Rs))
        order = order[: int(c["n_matches"])]
        poses = {int(k): Pose(Rs[k], ts[k]) for k in order}
        t_quick = time.perf_counter()
        psi = create("psi_rgb")
        pre = []
        for k in order:
            if time.perf_counter() >= deadline:
                break
            pose = poses[int(k)]
            if not pose.is_valid():
                continue
            score = self._score(inp, pose, seg, psi)
            if math.isfinite(score):
                pre.append((score, k, pose))
        pre.sort(key=lambda q: (-q[0], q[1]))
        t_verify = time.perf_counter()
        polished: list[tuple[float, Pose]] = [(q[0], q[2]) for q in pre]
        for score, _, pose in pre[: c["n_polish"] if use_depth else c["n_climb"]]:
            if time.perf_counter() >= deadline:
                break
            new = self._polish(inp, pose, seg, deadline)
            if new is not None:
                s = self._score(inp, new, seg, psi)
                if math.isfinite(s) and s > score:
                    polished.append((s, new))
        polished.sort(key=lambda q: -q[0])
        ranked = ranked_candidates(polished, model, c["top_k"])
        now = time.perf_counter()
        info = {"templates": source, "raw_matches": n_raw, "matches": len(found), "n_verified": len(pre),
                "depth": use_depth, "best_similarity": found[0].similarity,
                "seconds": {"prepare": t_prep, "match": t_match - start - t_prep, "quick": t_quick - t_match,
                            "verify": t_verify - t_quick,
                            "polish": now - t_verify}}
        if not ranked:
            why = (f"the time budget ({c['max_seconds']} s) ran out in matching" if not pre and now >= deadline
                   else "none could be verified")
            return BlockResult(ok=False, info=info, reason=f"linemod: {len(found)} matches, {why}")
        best_score = polished[0][0]
        scores = {"gen_verification": best_score}
        floor = c["min_verification"] if use_depth else c["min_verification_rgb"]
        if best_score < floor:
            return BlockResult(ok=False, scores=scores, info=info, candidates=ranked, reason=(
                f"linemod: best candidate verifies at {best_score:.2f} < {floor}"))
        return BlockResult(ok=True, pose=ranked[0][1], scores=scores, info=info, candidates=ranked)

    def _score(self, inp: BlockInput, pose: Pose, seg, psi) -> float:
        """Depth verification (as ppf's) with depth, psi_rgb without; -inf when it cannot be scored."""
        if seg is not None:
            return float(verify(inp.model, pose, inp.frame, self.config["verify_tol"], 1.0, 0.5, seg=seg,
                                explain_weight=self.config["explain_weight"])[0])
        r = psi(BlockInput(frame=inp.frame, model=inp.model, pose=pose, cache=inp.cache))
        return float(r.scores["psi_rgb"]) if r.ok else -math.inf

    def _best_depth(self, inp: BlockInput, pose: Pose) -> Pose:
        """`pose` moved along its viewing ray to the depth (within the template size step) where
        psi_rgb at the outline's exact place fits best: the template's size gives the depth only
        to that step."""
        exact = create("psi_rgb", search_radius=0)
        best, best_score = pose, -math.inf
        for f in _depth_factors(self.config):
            cand = Pose(pose.R, pose.t * f)
            score = self._score(inp, cand, None, exact)
            if score > best_score:
                best, best_score = cand, score
        return best

    def _climb(self, inp: BlockInput, pose: Pose, deadline: float) -> tuple[float, Pose]:
        """RGB only: hill climbing of psi_rgb at the outline's exact place (no shift search) over
        the depth along the ray, the image position and the rotation about the camera axes, the
        steps halved when no move helps (a template's rotation and size are a grid step off)."""
        exact = create("psi_rgb", search_radius=0)
        score = self._score(inp, pose, None, exact)
        step_rot, step_z, step_px = math.radians(8.0), 0.06, 4.0
        f = float(inp.frame.K[0, 0])
        while step_rot >= math.radians(1.0) and time.perf_counter() < deadline:
            z = max(float(pose.t[2]), 1e-3)
            moves = []
            for sign in (1.0, -1.0):
                moves.append(Pose(pose.R, pose.t * (1.0 + sign * step_z)))
                for axis in range(3):
                    w = np.zeros(3)
                    w[axis] = sign * step_rot
                    c = pose.transform(inp.model.points.mean(axis=0)[None])[0]
                    R = exp_so3(w) @ pose.R
                    moves.append(Pose(R, c - R @ inp.model.points.mean(axis=0)))
                    if axis < 2:
                        dt = np.zeros(3)
                        dt[axis] = sign * step_px * z / f
                        moves.append(Pose(pose.R, pose.t + dt))
            scored = [(self._score(inp, m, None, exact), k) for k, m in enumerate(moves)]
            best, k = max(scored)
            if best > score:
                score, pose = best, moves[k]
            else:
                step_rot, step_z, step_px = step_rot / 2, step_z / 2, max(step_px / 2, 0.5)
        return score, pose

    def _polish(self, inp: BlockInput, pose: Pose, seg, deadline: float) -> Pose | None:
        if seg is None:  # RGB only: the depth along the ray by psi_rgb over the scale step, then a climb
            pose = self._best_depth(inp, pose)
            return self._climb(inp, pose, deadline)[1]
        model, frame = inp.model, inp.frame
        r = render_box(model, pose, frame.K, frame.width, frame.height)
        label = dominant_label(seg, r)
        if label < 0:
            return None
        target = icp_target(seg, pose, model, r, label)
        if len(target.points) < 10:
            return None
        voxel = max(0.003, 0.03 * model.diameter)
        dists = (max(3.0 * voxel, 0.006), max(1.2 * voxel, 0.003), max(0.5 * voxel, 0.002))
        return icp_polish(model, pose, target, dists, self.config["icp_iterations"])[0]


def _depth_factors(c: dict) -> np.ndarray:
    """Depth factors (1 first) covering the step between two template sizes, about 3 % apart."""
    step = (max(c["max_px"], c["min_px"]) / c["min_px"]) ** (1.0 / max(1, c["n_scales"] - 1))
    half = math.sqrt(step) * 1.05
    n = max(1, int(math.ceil(math.log(half) / math.log(1.03))))
    f = half ** (np.arange(-n, n + 1) / n)
    return np.r_[1.0, f[np.abs(f - 1.0) > 1e-9]]


def _observed_depth(t, m, frame, diameter: float) -> float:
    """The depth of the model centre for match `m`: the median observed depth within a quarter
    of the template's size around the matched centre, behind it by the template's surface
    offset (the template's size gives the depth only to a scale step). NaN without depth there."""
    r = max(2, int(0.25 * t.pixels[m.template]))
    u, v = int(round(m.u)), int(round(m.v))
    obs = frame.depth[max(0, v - r):v + r + 1, max(0, u - r):u + r + 1]
    obs = obs[np.isfinite(obs) & (obs > 0)]
    if len(obs) < 5:
        return math.nan
    return float(np.median(obs)) - float(t.surface[m.template]) * diameter


__all__ = ["LineMod"]
