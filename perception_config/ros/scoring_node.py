"""scoring_node: serves `score_hypothesis` (ScoreHypothesis.srv), the scores an agent decides on.

`methods` are scoring blocks (empty = the pipeline's scoring set); the answer is the hypothesis
with `scores` / `score_names` filled, in the order of the blocks' score names. A block that
cannot score this hypothesis (e.g. it projects outside the image) gives NaN for its scores,
as in-process, and is named in the message; the request still succeeds. At most 16 methods,
each named once (request_fields.MAX_METHODS).

Parameters: PARAMETERS below, those of every operator node.
"""
from __future__ import annotations

from typing import Any

from perception_config_interfaces.srv import ScoreHypothesis

from ..blocks.base import Kind
from .node_main import spin
from .operator_node import OPERATOR_PARAMETERS, OperatorNode, hypothesis_pose, make_hypothesis
from .request_fields import parse_methods

PARAMETERS = OPERATOR_PARAMETERS  # no parameters of its own


class ScoringNode(OperatorNode):
    """Serves `score_hypothesis`: the pipeline's scoring set on a cached camera frame."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("scoring_node", PARAMETERS, **kwargs)

    def setup(self) -> None:
        super().setup()
        self.serve(ScoreHypothesis, "score_hypothesis", self._on_score)
        self.serving_line = f"serving score_hypothesis ({', '.join(self.pipeline.score_names)})"

    def _on_score(self, request: ScoreHypothesis.Request, response: ScoreHypothesis.Response) -> None:
        stamp_ns, object_id, pose = hypothesis_pose(request.hypothesis)
        methods = parse_methods(request.methods)  # at most MAX_METHODS, each once
        blocks = None if not methods else [self.block(m, (Kind.SCORING,))[1] for m in methods]
        scores, failed, header = self.score(stamp_ns, object_id, pose, blocks)
        response.hypothesis = make_hypothesis(header, object_id, request.hypothesis.pose, scores)
        response.message = "ok" if not failed else "scored; NaN from " + "; ".join(failed)

def main(args: list[str] | None = None) -> None:
    spin(ScoringNode, args)


if __name__ == "__main__":
    main()
