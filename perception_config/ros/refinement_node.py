"""refinement_node: serves `refine_hypothesis` (RefineHypothesis.srv), one refinement step.

`method` is a refinement action of the pipeline (e.g. `icp_coarse`, with its parameter preset)
or a registered refinement block with its defaults (`icp_point_to_plane`, `d2co`, ...). The
hypothesis' header.stamp names the camera frame (zero = the latest). A refiner that fails (no
depth where the model is, diverged) answers success=false with its reason; the hypothesis is
then the one sent. `seed` seeds a stochastic refiner (D2CO samples model contour points;
0 = draw one). With `score` the result comes back scored by the pipeline's scoring set.

Parameters: PARAMETERS below, those of every operator node.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from perception_config_interfaces.srv import RefineHypothesis

from ..blocks.base import Kind
from .node_main import spin
from .operator_node import OPERATOR_PARAMETERS, OperatorNode, answered_pose, hypothesis_pose, make_hypothesis
from .request_fields import parse_method

PARAMETERS = OPERATOR_PARAMETERS  # no parameters of its own


class RefinementNode(OperatorNode):
    """Serves `refine_hypothesis`: the pipeline's refiners on a cached camera frame."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("refinement_node", PARAMETERS, **kwargs)

    def setup(self) -> None:
        super().setup()
        self.serve(RefineHypothesis, "refine_hypothesis", self._on_refine)
        actions = [a.name for a in self.pipeline.actions if a.kind == Kind.REFINEMENT]
        self.serving_line = f"serving refine_hypothesis ({', '.join(actions)})"

    def _on_refine(self, request: RefineHypothesis.Request, response: RefineHypothesis.Response) -> None:
        stamp_ns, object_id, pose = hypothesis_pose(request.hypothesis)
        if not parse_method(request.method):
            raise ValueError("method is empty: name a refinement action of the pipeline or a refinement block")
        method, block = self.block(request.method, (Kind.REFINEMENT,))
        rng = np.random.default_rng(request.seed if request.seed else None)
        result, header = self.run_block(block, stamp_ns, object_id, pose, rng)
        response.hypothesis = make_hypothesis(header, object_id, request.hypothesis.pose)
        if not result.ok:
            raise ValueError(f"{method}: {result.reason}")
        pose_msg, refined = answered_pose(result.pose)
        scores = self.score(stamp_ns, object_id, refined)[0] if request.score else None
        response.hypothesis = make_hypothesis(header, object_id, pose_msg, scores)


def main(args: list[str] | None = None) -> None:
    spin(RefinementNode, args)


if __name__ == "__main__":
    main()
