"""generation_node: serves `generate_hypothesis` (GenerateHypothesis.srv), a first pose hypothesis.

Methods: the pipeline's generator, its generation actions (e.g. `regenerate`) and the
registered generators (`simulated_init`, `global_registration`, `ppf`). `simulated_init` perturbs the
ground truth replayed on `perception/ground_truth` (ObjectPoses) by the lambda noise model, as
in the paper's systematic evaluation; it needs no camera frame. `global_registration` and `ppf` find
the object in the camera frame named by `frame.stamp` (zero = the latest).

Parameters: PARAMETERS below (those of every operator node and two defaults of a request).
A request's seed makes simulated_init reproducible (0 = draw one); with `score` the hypothesis
comes back scored by the pipeline's scoring set (the camera frame is then needed too). The
ground-truth-free generators also answer their ranked candidates (`candidates`, `confidences`),
also with success=false when the best of them verified below the generator's threshold.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from perception_config_interfaces.srv import GenerateHypothesis

from ..blocks.base import Kind
from ..core.geometry import LAMBDA_MAX, check_noise_lambda
from .conversions import stamp_to_nanoseconds
from .node_main import spin
from .operator_node import OPERATOR_PARAMETERS, OperatorNode, answered_pose, make_hypothesis
from .parameters import NodeParameter
from .request_fields import parse_method, parse_noise_lambda, parse_object_id, parse_stamp

PARAMETERS = OPERATOR_PARAMETERS + (
    NodeParameter("default_method", "", "generator used when a request's method is empty "
                  "(\"\" = the pipeline's generator)"),
    NodeParameter("default_lambda", 0.5, "noise level of simulated_init when a request's noise_lambda is negative",
                  limits=(0.0, LAMBDA_MAX)),
)


class GenerationNode(OperatorNode):
    """Serves `generate_hypothesis`: the pipeline's generators on a cached camera frame."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("generation_node", PARAMETERS, ground_truth=True, **kwargs)
        self._rng = np.random.default_rng()

    def setup(self) -> None:
        super().setup()
        self.serve(GenerateHypothesis, "generate_hypothesis", self._on_generate)
        self.serving_line = ("serving generate_hypothesis "
                             f"(default {self.param('default_method') or self.pipeline.generator.name})")

    def _on_generate(self, request: GenerateHypothesis.Request, response: GenerateHypothesis.Response) -> None:
        method = parse_method(request.method) or self.param("default_method") or self.pipeline.generator.name
        lam = parse_noise_lambda(request.noise_lambda)
        if lam is None:
            lam = float(self.param("default_lambda"))
        lam = check_noise_lambda(lam, "noise_lambda (negative = the node's default)")
        object_id = parse_object_id(request.object_id)
        stamp_ns = parse_stamp(request.frame.stamp, "frame.stamp")
        self.model(object_id)  # an unknown object is refused before any waiting
        _, block = self.block(method, (Kind.GENERATION,), lam)
        rng = np.random.default_rng(request.seed if request.seed else int(self._rng.integers(1, 2**32)))
        result, header = self.run_block(block, stamp_ns, object_id, None, rng)
        # the ranked candidates go out also with a refusal (best verified below the threshold):
        # the caller may still take them in turn (next_candidate)
        response.candidates = [make_hypothesis(header, object_id, answered_pose(p)[0]) for _, p in result.candidates]
        response.confidences = [float(conf) for conf, _ in result.candidates]
        if not result.ok:
            raise ValueError(f"{method}: {result.reason}")
        pose_msg, pose = answered_pose(result.pose)
        scores = None
        if request.score:
            scores = self.score(stamp_to_nanoseconds(header.stamp), object_id, pose)[0]
        response.hypothesis = make_hypothesis(header, object_id, pose_msg, scores)


def main(args: list[str] | None = None) -> None:
    spin(GenerationNode, args)


if __name__ == "__main__":
    main()
