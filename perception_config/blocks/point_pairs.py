"""`ppf`: a ground-truth-free generator from the depth image and the model: point pair feature
voting (vision/ppf.py), then render-and-compare verification and ICP of the best pose clusters.
It returns its ranked candidates (best first, a confidence each) in `BlockResult.candidates`.

Steps: (1) the frame's segmentation (shared with `global_registration` through the frame's
cache) keeps the points of object-like regions whose size fits the model (`min_extent` ..
`max_extent` diameters: the table, bin walls and the far background go); (2) those points,
down-sampled to `sampling_rel` diameters, vote with every `ref_step`-th of them as reference
against the model's point pair table (built once per model and parameter set, cached on disk),
for at most half of the budget left (the references that voted by then are a uniform sample);
(3) the reference points' poses are clustered (0.1 d, 30 deg) and the `n_clusters` strongest
are pre-verified by rendering (`verify`: depth agreement, free-space violations, coverage of
their regions); (4) the best `n_polish` are polished by coarse-to-fine ICP against the observed
points under them and verified again; the distinct results, best first, are the candidates.
Confidence = the verification score clipped to [0, 1]. A model that cannot be used
(models.model_defect: degenerate, no normals) or too small to make a region of the frame
(segmentation.too_small) is refused at once with that reason.
"""
from __future__ import annotations

import math
import time

import numpy as np

from ..core.geometry import Pose
from ..core.models import model_defect
from ..vision.features import flipped, principal_flips
from ..vision.ppf import cluster_poses, ppf_model, scene_cloud, vote
from ..vision.segmentation import frame_segmentation, too_small
from ..vision.verification import verify_polish_rank
from .base import DEPTH, MODEL, Block, BlockInput, BlockResult, Kind, Param, register
from .verified import VERIFIER_PARAMS, RanksByVerifier

_SCORE_NAMES = ("gen_verification",)


@register
class PointPairFeatures(RanksByVerifier, Block):
    """Point pair feature voting with render-and-compare verification (see the module docstring)."""

    kind = Kind.GENERATION
    name = "ppf"
    default_cost = 0.5
    inputs = (DEPTH, MODEL)
    uses_rng = False  # deterministic: the same frame, model and parameters give the same result
    score_names = _SCORE_NAMES
    params = (
        Param("sampling_rel", 0.05, 0.02, 0.2, doc="model and scene sampling as a share of the diameter"),
        Param("n_angle", 30, 8, 90, doc="angle bins of the point pair feature (over 180 deg)"),
        Param("ref_step", 5, 1, 100, doc="every n-th scene point is a voting reference"),
        Param("min_extent", 0.15, 0.0, 1.0, doc="smallest region kept, as a share of the diameter"),
        Param("max_extent", 3.0, 0.5, 20.0, doc="largest region kept (touching objects merge), in diameters"),
        Param("min_sampling", 0.003, 0.0, 0.05, doc="metres: the sampling is never finer (sensor noise)"),
        Param("plane_distance", 0.008, 0.001, 0.05, doc="metres: points within this of the support plane are removed"),
        Param("n_clusters", 16, 1, 200, doc="strongest pose clusters pre-verified by rendering"),
        Param("n_polish", 16, 1, 50, doc="pre-verified candidates polished by ICP and verified again"),
        Param("symmetric_clusters", True, doc="poses the model's symmetries make alike vote in one cluster"),
        Param("flip_variants", True,
              doc="also verify each pose cluster flipped by 180 deg about the model's principal axes"),
        Param("top_k", 5, 1, 50, doc="ranked candidates returned"),
        Param("icp_iterations", 10, 1, 200, doc="ICP iterations per stage (three stages, coarse to fine)"),
        Param("verify_tol", 0.01, 0.001, 0.05, doc="metres: depth agreement counted as an inlier in verification"),
        Param("min_verification", 0.3, -1.0, 1.0, doc="below this the best candidate is not accepted (ok=False)"),
        Param("max_seconds", 2.0, 0.01, 120.0,
              doc="time budget after the model's table is at hand (checked between candidates)"),
    ) + VERIFIER_PARAMS

    def run(self, inp: BlockInput) -> BlockResult:
        c = self.config
        start = time.perf_counter()
        model, frame = inp.model, inp.frame
        d = model.diameter
        defect = model_defect(model)
        if defect:
            return BlockResult.fail(f"ppf: the model cannot be prepared: {defect}")
        try:
            table, source = ppf_model(model, max(c["sampling_rel"], c["min_sampling"] / d), c["n_angle"])
        except ValueError as exc:
            return BlockResult.fail(f"ppf: the model cannot be prepared: {exc}")
        t_prep = time.perf_counter() - start
        # The budget starts after the preparation: a model's first call (table built, ~0.5-1 s,
        # once per machine) searches as long as every later one.
        deadline = self.deadline(inp, start + t_prep)
        seg = frame_segmentation(frame, inp.cache, c["plane_distance"])
        if seg.n_valid < 50:
            return BlockResult.fail(f"ppf: only {seg.n_valid} valid depth pixels")
        small = too_small(seg, frame.K, d)
        if small:
            return BlockResult.fail(f"ppf: {small}")
        voxel = table.dist_step
        # The regions kept depend on the diameter, the sampling on the voxel: both name the cloud
        # (two small models share the 3 mm floor of the sampling, not their regions).
        key = (f"ppf:scene:{voxel:.5f}:{c['min_extent'] * d:.4f}:{c['max_extent'] * d:.4f}:"
               f"{c['plane_distance']:.4f}")
        scene = inp.cache.get(key)
        if scene is None:
            P = seg.points.reshape(-1, 3)
            label = seg.labels[-1].ravel() if seg.labels else np.full(len(P), -1)
            extent = np.array([cl.extent for cl in seg.clusters] + [0.0])[label]
            keep = (label >= 0) & (extent >= c["min_extent"] * d) & (extent <= c["max_extent"] * d)
            scene = scene_cloud(P[keep], voxel)
            inp.cache[key] = scene
        if len(scene.points) < 10:
            return BlockResult.fail(f"ppf: no object-like region of {c['min_extent']:.2f}-{c['max_extent']:.1f} "
                                    f"diameters ({d * 1000:.0f} mm) above the support surfaces")
        t_scene = time.perf_counter()
        # the vote takes at most half of what is left: the rest verifies (a cluttered frame's
        # full vote takes 1-2 s; its references are then a uniform sample of the scene's)
        R, t, votes = vote(table, scene, c["ref_step"], deadline=t_scene + 0.5 * (deadline - t_scene))
        centre = model.points.mean(axis=0)
        leaders = cluster_poses(R, t, votes, centre, 0.1 * d, math.radians(30.0), c["n_clusters"],
                               model.symmetries if c["symmetric_clusters"] else None)
        t_vote = time.perf_counter()
        flips = principal_flips(model) if c["flip_variants"] else []
        poses = []
        for _, Rk, tk in leaders:  # each leader and its 180 deg flips about the principal axes
            poses.append(Pose(Rk, tk))
            poses.extend(flipped(poses[-1], F, centre) for F in flips)
        pre, polished, ranked = verify_polish_rank(model, frame, seg, poses, voxel, deadline, c["verify_tol"],
                                                   c["n_polish"], c["icp_iterations"], c["top_k"])
        now = time.perf_counter()
        info = {"pre_verified": [(q[0], q[2]) for q in pre],
                "polished": [(q[0], q[1]) for q in polished], "table": source,
                "scene_points": len(scene.points), "references": len(votes), "pose_clusters": len(leaders),
                "n_verified": len(pre), "n_polished": len(polished),
                "seconds": {"prepare": t_prep, "scene": t_scene - start - t_prep, "vote": t_vote - t_scene,
                            "verify": now - t_vote}}
        if not ranked:
            return BlockResult(ok=False, info=info, reason="ppf: no candidate could be verified "
                               f"(scene points {len(scene.points)}, pose clusters {len(leaders)})")
        best_score, best = polished[0][0], ranked[0][1]
        scores = {"gen_verification": best_score}
        if best_score < c["min_verification"]:
            return BlockResult(ok=False, scores=scores, info=info, candidates=ranked, reason=(
                f"ppf: best candidate verifies at {best_score:.2f} < min_verification {c['min_verification']}"))
        return BlockResult(ok=True, pose=best, scores=scores, info=info, candidates=ranked)


__all__ = ["PointPairFeatures"]
