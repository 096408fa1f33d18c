"""Generators that rank their candidates by a verifier and refuse rather than guess.

A ground-truth-free generator (resting_pose, ppf, global_registration; linemod on RGB-only
frames, where the pick-success model reads the RGB features) ranks its candidates by its own
render-and-compare verification, whose value is not a probability: on real RGB-D frames a
confident first candidate can be far off (a box half a turn away, a mug on the wrong side). With
`verifier` set to a pick-success model (`shipped`, or a folder of `perception-config fit-score`:
blocks/pick_success.py), every candidate the generator returns is scored by it, the probability
that picking it succeeds (symmetry-aware MSSD <= 0.1 x diameter), and

- the candidates are ranked by that probability, which becomes their confidence (the
  generator's own verification stays in its scores and in `info["own_confidence"]`);
- when the best one's probability is below `refuse_below`, the call is refused: ok=False with
  the reason, and the ranked candidates kept for `next_candidate` and the agent to weigh.

Measured on real YCB-Video RGB-D frames with the shipped score (docs: Results, generators):
ranked by it, the cell's generators were confidently wrong on 0-3 % of the objects instead of
7-27 %, answering fewer. The verifier's time is added to the call's. Empty `verifier` (the
default): the generator's own ranking, unchanged. The verifier is made through the registry
(`create`), never imported: this is block infrastructure, not a block.
"""
from __future__ import annotations

import time
from typing import Any

from .base import Block, BlockInput, BlockResult, Param, create

VERIFIER_PARAMS = (
    Param("verifier", "", doc="a pick-success model ('shipped' or a fit-score folder) that ranks the candidates by "
                              "the probability that each is within the pick tolerance; '' keeps the generator's "
                              "own ranking"),
    Param("refuse_below", 0.5, 0.0, 1.0, doc="with a verifier: the call is refused (ok=False, the ranked "
                                             "candidates kept) when the best candidate's probability is below this"),
)


def verifier_block(name: str) -> Block:
    """The pick_success block a verifier name stands for: `shipped` (the packaged model) or a
    model file or fit-score folder."""
    return create("pick_success", **({} if name == "shipped" else {"model": str(name)}))


def probability(verifier: Block, inp: BlockInput, pose: Any) -> float:
    """The verifier's probability that `pose` is within the pick tolerance, for the frame and
    model of `inp` (its cache shared); 0 when the verifier cannot score it."""
    r = verifier(BlockInput(frame=inp.frame, model=inp.model, pose=pose, cache=inp.cache))
    return float(r.scores["pick_success"]) if r.ok else 0.0


class RanksByVerifier:
    """Mixin for a generation Block (listed before Block): the candidates of each call ranked by
    the `verifier` and the call refused below `refuse_below` (module docstring)."""

    config: dict[str, Any]
    name: str

    def __call__(self, inp: BlockInput) -> BlockResult:
        result = super().__call__(inp)  # type: ignore[misc]
        if not self.config.get("verifier") or not result.candidates:
            return result
        spent, start = result.elapsed, time.perf_counter()
        try:
            result = self._rank(result, inp)
        except Exception as exc:  # a block never raises on bad data
            result = BlockResult.fail(f"{self.name}: the verifier failed: {type(exc).__name__}: {exc}")
        result.elapsed = spent + time.perf_counter() - start  # the generator's time and the verifier's
        return result

    def _verifier(self) -> Block:
        name = self.config["verifier"]
        cached = getattr(self, "_verifier_block", None)
        if cached is None or cached[0] != name:
            cached = (name, verifier_block(name))
            self._verifier_block = cached
        return cached[1]

    def _rank(self, result: BlockResult, inp: BlockInput) -> BlockResult:
        judge = self._verifier()
        scored = [(probability(judge, inp, pose), float(own), pose) for own, pose in result.candidates]
        scored.sort(key=lambda c: -c[0])  # stable: equal probabilities keep the generator's order
        candidates = [(p, pose) for p, _, pose in scored]
        info = {**result.info, "own_confidence": [own for _, own, _ in scored],
                "verifier": self.config["verifier"]}
        best = scored[0][0]
        if best < self.config["refuse_below"]:
            reason = (f"{self.name}: best candidate's pick-success probability {best:.2f} < refuse_below "
                      f"{self.config['refuse_below']}")
            return BlockResult(ok=False, scores=result.scores, info=info, candidates=candidates, reason=reason)
        return BlockResult(ok=True, pose=candidates[0][1], scores=result.scores, info=info, candidates=candidates)


__all__ = ["VERIFIER_PARAMS", "RanksByVerifier", "verifier_block", "probability"]
