"""pick_node: serves `pick` (Pick.srv): can the robot pick the object at this hypothesis?

Simulated (default): the pipeline's pick action (`simulated_pick`: symmetry-aware MSSD <= 0.1 x
diameter) against the ground truth replayed on `perception/ground_truth` for the hypothesis'
stamp. In the cell: set `robot_service` to the robot's Pick service; the request is forwarded
and its answer returned (success=false when the robot does not answer within `robot_timeout`).

`success` says the request was handled, `picked` whether the object was picked.

Parameters: PARAMETERS below (those of every operator node and the robot's service).
"""
from __future__ import annotations

import time
from typing import Any

from perception_config_interfaces.srv import Pick
from rclpy.task import Future

from ..blocks.base import Kind
from .node_main import spin
from .operator_node import OPERATOR_PARAMETERS, OperatorNode, hypothesis_pose
from .parameters import NodeParameter

PARAMETERS = OPERATOR_PARAMETERS + (
    NodeParameter("robot_service", "", "name of the robot cell's Pick service (\"\" = simulated pick)",
                  read_only=True),
    NodeParameter("robot_timeout", 30.0, "seconds to wait for the robot's answer"),
)


class PickNode(OperatorNode):
    """Serves `pick`: simulated from the replayed ground truth, or forwarded to the robot."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("pick_node", PARAMETERS, ground_truth=True, **kwargs)

    def setup(self) -> None:
        super().setup()
        robot = self.param("robot_service")
        self._robot = self.create_client(Pick, robot, callback_group=self._wait_group) if robot else None
        picks = [a.name for a in self.pipeline.actions if a.kind == Kind.PICK]
        if not picks and self._robot is None:
            raise ValueError(f"pipeline {self.pipeline.source} has no pick action and no robot_service is set")
        self._pick_action = picks[0] if picks else ""
        self.serve(Pick, "pick", self._on_pick, local=self._robot is None)  # forwarding awaits the robot
        self.serving_line = f"serving pick ({'robot service ' + robot if robot else self._pick_action})"

    def _on_pick(self, request: Pick.Request, response: Pick.Response):
        stamp_ns, object_id, pose = hypothesis_pose(request.hypothesis)
        self.model(object_id)
        if self._robot is not None:
            return self._forward(request, response)
        _, block = self.block(self._pick_action, (Kind.PICK,))
        result, _ = self.run_block(block, stamp_ns, object_id, pose)
        if not result.ok:
            raise ValueError(f"{self._pick_action}: {result.reason}")
        response.picked = bool(result.picked)
        response.message = ("picked" if result.picked
                            else f"not picked ({', '.join(f'{k} {v:.4g}' for k, v in result.scores.items())})")

    async def _forward(self, request: Pick.Request, response: Pick.Response) -> None:
        """Ask the robot cell; awaited, so the executor keeps serving topics meanwhile."""
        name = self._robot.srv_name
        timeout = float(self.param("robot_timeout"))
        deadline = time.monotonic() + min(timeout, 2.0)  # a robot service just started may not be discovered yet
        while not self._robot.service_is_ready() and time.monotonic() < deadline:
            await self.wait_for(Future(), 0.05)
        if not self._robot.service_is_ready():
            raise ValueError(f"the robot's pick service {name} is not available")
        future = self._robot.call_async(request)
        if not await self.wait_for(future, timeout):
            self._robot.remove_pending_request(future)
            raise ValueError(f"the robot's pick service {name} did not answer within {timeout:g} s")
        answer = future.result()
        if answer is None or not answer.success:
            raise ValueError(f"the robot's pick service {name} refused: {answer.message if answer else 'no answer'}")
        response.picked = bool(answer.picked)
        response.message = answer.message or ("picked" if answer.picked else "not picked")


def main(args: list[str] | None = None) -> None:
    spin(PickNode, args)


if __name__ == "__main__":
    main()
