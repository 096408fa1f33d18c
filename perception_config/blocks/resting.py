"""`resting_pose`: a ground-truth-free generator for parts lying on a table or a bin floor.

A part at rest on a plane lies on one of its few stable faces (vision/resting_poses.py), so
under an observed region only its turn about the plane's normal and its place on the plane are
unknown. Small, symmetric and flat-topped parts (a hex nut, a bushing) give point pair voting
(`ppf`) a handful of ambiguous references; here the support plane supplies the missing degrees
of freedom instead.

Steps: (1) the frame's segmentation (shared with `ppf` and `global_registration` through the
frame's cache) gives the support plane and the object-like regions whose size fits the model
(`min_extent` .. `max_extent` diameters); (2) under each region, every stable face at `turns`
turns about the normal is scored cheaply (no rendering; in the 2 `max_regions` regions that fit
best with each turn's centroid on the region's, again with each turn placed by two ICP steps),
and in the `max_regions` regions the part fits best the `per_rest` best turns of each face are
aligned in the plane and scored again; (3) the best `per_region` hypotheses of each (regions
that repeat one another across the segmentation's levels counted once), best first, are verified
by rendering, the best `n_polish` polished by ICP and verified again
(verification.verify_polish_rank, as in `ppf`); (4) the `sweep_candidates` best distinct ones
are swept in the plane, turns then shifts, and keep what verifies best
(resting_poses.sweep_in_plane: ICP leaves a flange's or hex nut's turn where it started); up to
`sweep_alternatives` other poses the sweep verified within `sweep_margin` of its best compete
for the remaining ranks (a mug whose handle is hidden verifies alike over a range of turns: the
candidates then span it); (5) a candidate floating above the plane or sunk into it by less than
`settle` diameters is moved onto it unless a verification at a third of the tolerance prefers it
where it was (resting_poses.settled_on_plane); the distinct results are the ranked candidates
(confidence = verification score clipped to [0, 1]). The per-model preparation (the stable faces
from the convex hull, a coarse distance field of the surface samples) takes milliseconds, also
for a model of millions of faces, and is kept in memory: nothing to cache on disk.

Refused at once, with the reason: an RGB-only frame, no support plane in view, a model that
cannot be used (models.model_defect) or is too small for a region of the frame.
"""
from __future__ import annotations

import math
import threading
import time

from ..core.geometry import Pose
from ..core.models import ObjectModel, model_defect
from ..vision.resting_poses import (
    RestingPose,
    plane_basis,
    refine_rests,
    resting_poses,
    settled_on_plane,
    shortlist_rests,
    surface_field,
    sweep_in_plane,
)
from ..vision.segmentation import distinct_regions, frame_segmentation, too_small
from ..vision.verification import ranked_candidates, verify, verify_polish_rank
from .base import DEPTH, MODEL, Block, BlockInput, BlockResult, Kind, Param, register
from .verified import VERIFIER_PARAMS, RanksByVerifier

_RESTS: dict[tuple[ObjectModel, int], list[RestingPose]] = {}  # models are shared and compare by identity
_LOCK = threading.Lock()


def _rests(model: ObjectModel, max_rests: int) -> list[RestingPose]:
    with _LOCK:
        hit = _RESTS.get((model, max_rests))
    if hit is None:
        hit = resting_poses(model, max_rests)
        with _LOCK:
            _RESTS[(model, max_rests)] = hit
    return hit


@register
class RestingPoseGenerator(RanksByVerifier, Block):
    """Stable faces on the support plane under each fitting region (see the module docstring)."""

    kind = Kind.GENERATION
    name = "resting_pose"
    default_cost = 0.4
    inputs = (DEPTH, MODEL)
    uses_rng = False  # deterministic: the same frame, model and parameters give the same result
    score_names = ("gen_verification",)
    params = (
        Param("max_rests", 6, 1, 50, doc="stable faces tried, largest first"),
        Param("turns", 24, 4, 360, doc="turns about the plane's normal tried per face (24: every 15 deg)"),
        Param("per_rest", 3, 1, 50, doc="best turns of each face and region aligned in the plane"),
        Param("max_regions", 8, 1, 1000, doc="regions the part fits best (cheap score) whose hypotheses are aligned"),
        Param("per_region", 8, 1, 100, doc="best aligned hypotheses of each region verified"),
        Param("min_extent", 0.3, 0.0, 1.0, doc="smallest region kept, as a share of the diameter"),
        Param("max_extent", 1.6, 0.5, 20.0, doc="largest region kept, in diameters"),
        Param("plane_distance", 0.008, 0.001, 0.05, doc="metres: points within this of the support plane are removed"),
        Param("n_polish", 8, 1, 50, doc="pre-verified hypotheses polished by ICP and verified again"),
        Param("max_hypotheses", 24, 1, 1000, doc="hypotheses pre-verified by rendering, best first"),
        Param("icp_iterations", 10, 1, 200, doc="ICP iterations per stage (three stages, coarse to fine)"),
        Param("verify_tol", 0.01, 0.001, 0.05, doc="metres: depth agreement counted as an inlier in verification"),
        Param("sweep_candidates", 2, 0, 50, doc="best distinct candidates swept in the plane (turns, then shifts) "
                                                 "by verification; 0: none"),
        Param("sweep_span", 30.0, 0.0, 180.0, doc="degrees: turns swept either side of a candidate"),
        Param("sweep_step", 6.0, 0.5, 90.0, doc="degrees between swept turns (then half a step beside the best)"),
        Param("sweep_shift", 0.03, 0.0, 0.5, doc="diameters: the shifts along the plane tried after the best turn"),
        Param("sweep_alternatives", 1, 0, 10, doc="other turns or shifts of each sweep offered as candidates when "
                                                   "they verify within sweep_margin of its best (a part whose turn "
                                                   "the view cannot settle: a mug with its handle hidden)"),
        Param("sweep_margin", 0.05, 0.0, 1.0, doc="verification below a sweep's best within which its alternatives "
                                                  "count as alike"),
        Param("sweep_stop", 0.9, 0.0, 1.01, doc="when the first candidate sweeps to this verification or above, "
                                                 "the others are not swept (1.01: they always are)"),
        Param("settle", 0.2, 0.0, 1.0, doc="diameters: a candidate floating above the plane or sunk into it by less "
                                            "is moved onto it, unless that verifies worse at settle_tol; 0: never"),
        Param("settle_tol", 0.33, 0.05, 1.0, doc="share of verify_tol: the depth tolerance that judges settling"),
        Param("top_k", 5, 1, 50, doc="ranked candidates returned"),
        Param("min_verification", 0.3, -1.0, 1.0, doc="below this the best candidate is not accepted (ok=False)"),
        Param("max_seconds", 2.0, 0.01, 120.0, doc="time budget (checked between hypotheses)"),
    ) + VERIFIER_PARAMS

    def run(self, inp: BlockInput) -> BlockResult:
        c = self.config
        start = time.perf_counter()
        model, frame = inp.model, inp.frame
        d = model.diameter
        defect = model_defect(model)
        if defect:
            return BlockResult.fail(f"resting_pose: the model cannot be used: {defect}")
        rests = _rests(model, int(c["max_rests"]))
        if not rests:
            return BlockResult.fail("resting_pose: the model has no stable face to rest on")
        surface_field(model)
        t_prep = time.perf_counter() - start  # a model's first call: its hull and distance field, milliseconds
        deadline = self.deadline(inp, start + t_prep)
        seg = frame_segmentation(frame, inp.cache, c["plane_distance"])
        if seg.n_valid < 50:
            return BlockResult.fail(f"resting_pose: only {seg.n_valid} valid depth pixels")
        small = too_small(seg, frame.K, d)
        if small:
            return BlockResult.fail(f"resting_pose: {small}")
        if seg.plane is None:
            return BlockResult.fail("resting_pose: no support plane in view (a table or bin floor covering "
                                    "15 % of the valid depth)")
        regions = [cl for cl in seg.clusters if c["min_extent"] * d <= cl.extent <= c["max_extent"] * d]
        if not regions:
            return BlockResult.fail(f"resting_pose: no object-like region of {c['min_extent']:.2f}-"
                                    f"{c['max_extent']:.1f} diameters ({d * 1000:.0f} mm) on the support plane")
        # The cheap fit gets half the budget at most, the regions nearest the part's size first
        # (a cluttered frame has ~80 of them); alignment and verification get the rest.
        regions.sort(key=lambda cl: abs(math.log(max(cl.extent, 1e-6) / (0.8 * d))))
        regions = distinct_regions(regions)  # the segmentation's levels repeat most regions
        half = start + t_prep + 0.5 * (deadline - start - t_prep) if math.isfinite(deadline) else deadline
        shortlists = []
        for cl in regions:  # centroid placement only: a first ranking of the regions
            if time.perf_counter() >= half:
                break
            sl = shortlist_rests(model, rests, seg.plane, cl.points, int(c["turns"]), int(c["per_rest"]),
                                 shift_steps=0)
            if sl is not None:
                shortlists.append((sl, cl))
        shortlists.sort(key=lambda q: q[0].best)
        # the best 2 max_regions again with each turn placed by ICP steps (a mug behind a brick)
        n_placed = 2 * int(c["max_regions"])
        for k, (sl, cl) in enumerate(shortlists[:n_placed]):
            if time.perf_counter() >= half:
                break
            placed = shortlist_rests(model, rests, seg.plane, cl.points, int(c["turns"]), int(c["per_rest"]))
            shortlists[k] = (placed or sl, cl)
        shortlists = sorted((q[0] for q in shortlists), key=lambda sl: sl.best)  # best-fitting regions first
        hypotheses = []
        for sl in shortlists[: int(c["max_regions"])]:
            if time.perf_counter() >= deadline:
                break
            hypotheses.extend(refine_rests(model, rests, sl, int(c["per_region"])))
        hypotheses.sort(key=lambda h: h[0])
        t_hyp = time.perf_counter()
        poses = [pose for _, pose in hypotheses[: int(c["max_hypotheses"])]]
        pre, polished, ranked = verify_polish_rank(model, frame, seg, poses, max(0.003, 0.05 * d), deadline,
                                                   c["verify_tol"], int(c["n_polish"]), int(c["icp_iterations"]),
                                                   int(c["top_k"]), keep_unpolished=True)
        t_verify = time.perf_counter()
        n_sweep = int(c["sweep_candidates"])

        def score(pose, tol=c["verify_tol"]):
            return verify(model, pose, frame, tol, 1.0, 0.5, seg=seg, explain_weight=0.5)[0]

        n_swept = 0
        if ranked and n_sweep:
            B, _ = plane_basis(seg.plane)
            swept, tried = [], []
            for s, pose in ranked[:n_sweep]:
                if swept and swept[0][0] >= c["sweep_stop"]:
                    swept.append((s, pose))  # the first verifies so well that no rival is swept
                    continue
                n_swept += 1
                seen: list[tuple[float, Pose]] = []
                swept.append(sweep_in_plane(model, pose, s, B, score, deadline, c["sweep_span"], c["sweep_step"],
                                            c["sweep_shift"], seen))
                best = swept[-1]
                near = [q for q in seen if q[0] >= best[0] - c["sweep_margin"]]
                tried.extend(ranked_candidates([best] + near, model, 1 + int(c["sweep_alternatives"]))[1:])
            ranked = ranked_candidates(swept + ranked[n_sweep:] + tried, model, int(c["top_k"]))
        n_settled = 0
        if ranked and c["settle"] > 0:
            # a part at rest touches the plane: close a small gap when a verification at a tighter
            # tolerance (depth noise, not the pose's slack) does not prefer the gap
            tight = c["settle_tol"] * c["verify_tol"]
            settled = []
            for conf, pose in ranked:
                down = settled_on_plane(model, pose, seg.plane, c["settle"] * d)
                if (down is not None and time.perf_counter() < deadline
                        and score(down, tight) >= score(pose, tight)):
                    pose, n_settled = down, n_settled + 1
                settled.append((conf, pose))
            ranked = settled
        now = time.perf_counter()
        info = {"pre_verified": [(q[0], q[2]) for q in pre], "polished": [(q[0], q[1]) for q in polished],
                "regions": len(regions), "rests": len(rests), "hypotheses": len(hypotheses), "swept": n_swept,
                "settled": n_settled,
                "seconds": {"prepare": t_prep, "hypotheses": t_hyp - start - t_prep, "verify": t_verify - t_hyp,
                            "sweep": now - t_verify}}
        if not ranked:
            return BlockResult(ok=False, info=info, reason=f"resting_pose: no candidate could be verified "
                               f"({len(regions)} regions, {len(hypotheses)} hypotheses)")
        best_score = ranked[0][0]
        scores = {"gen_verification": best_score}
        if best_score < c["min_verification"]:
            return BlockResult(ok=False, scores=scores, info=info, candidates=ranked, reason=(
                f"resting_pose: best candidate verifies at {best_score:.2f} < min_verification "
                f"{c['min_verification']}"))
        return BlockResult(ok=True, pose=ranked[0][1], scores=scores, info=info, candidates=ranked)


__all__ = ["RestingPoseGenerator"]
