"""`next_candidate`: the next ranked hypothesis of the last generator call, nearly free.

The ground-truth-free generators (`ppf`, `global_registration`, ...) return their distinct
candidates best first (`BlockResult.candidates`); the first becomes the hypothesis. When
refinement and scoring say it is wrong, taking the second costs no search at all: this block
answers the first candidate not yet taken (`BlockInput.candidates`, which both operator backends
keep for the episode: in-process, and in the configurator from GenerateHypothesis' `candidates`).
It fails when none is left (the last generator call gave one pose only, e.g. `simulated_init`,
or all were taken); the hypothesis then stays. A new generator call replaces the list.
"""
from __future__ import annotations

from .base import Block, BlockInput, BlockResult, Kind, register


@register
class NextCandidate(Block):
    """The next of the last generator call's ranked candidates (see the module docstring)."""

    kind = Kind.GENERATION
    name = "next_candidate"
    default_cost = 0.0005
    inputs = ()
    uses_rng = False
    takes_candidate = True

    def run(self, inp: BlockInput) -> BlockResult:
        if not inp.candidates:
            return BlockResult.fail("no candidate left: the last generator call gave no further ranked "
                                    "hypotheses (next_candidate is served by the operator backend from them)")
        confidence, pose = inp.candidates[0]
        return BlockResult(ok=True, pose=pose, info={"confidence": float(confidence),
                                                      "left": len(inp.candidates) - 1})
