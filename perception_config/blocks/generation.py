"""Generation blocks: the initial hypothesis of an episode.

`simulated_init` is the paper's systematic evaluation: the ground truth perturbed by the
documented lambda noise model (geometry.perturb), seeded through the block input's rng.
"""
from __future__ import annotations

from ..geometry import SIGMA_R, SIGMA_T, perturb
from .base import GROUND_TRUTH, MODEL, Block, BlockInput, BlockResult, Kind, Param, register

MAX_RESAMPLES = 20


@register
class SimulatedInit(Block):
    """Ground truth + noise: R' = exp([w]x) R, w ~ N(0, (lambda sigma_r)^2 I3);
    t' = t + d, d ~ N(0, (lambda sigma_t diameter)^2 I3). lambda = 0 gives the ground truth.
    A draw that puts the object behind the camera is re-drawn (at most 20 times)."""

    kind = Kind.GENERATION
    name = "simulated_init"
    inputs = (MODEL, GROUND_TRUTH)
    params = (
        Param("noise_lambda", 0.5, 0.0, 2.0, doc="noise level lambda (the paper sweeps 0.1..1.0)"),
        Param("sigma_r", SIGMA_R, 0.0, 3.14, doc="rotation noise (rad) at lambda = 1"),
        Param("sigma_t", SIGMA_T, 0.0, 2.0, doc="translation noise (share of the diameter) at lambda = 1"),
    )

    def run(self, inp: BlockInput) -> BlockResult:
        gt = inp.ground_truth
        assert gt is not None
        c = self.config
        for _ in range(MAX_RESAMPLES):
            pose = perturb(gt, c["noise_lambda"], inp.model.diameter, inp.rng, c["sigma_r"], c["sigma_t"])
            if pose.t[2] > 0.01:
                return BlockResult(ok=True, pose=pose)
        return BlockResult.fail(f"{MAX_RESAMPLES} noise draws all put the object behind the camera")
