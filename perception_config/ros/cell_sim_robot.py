"""The simulated robot of `perception-config cell-sim --labels robot`: the only one who knows the truth.

In a cell without ground truth the nodes see camera frames only; the robot tries each pick and
says whether it worked. This is that robot, in the cell simulation's process:

- it serves the Pick service the pick node forwards to (`robot_service`), judging each pick
  with the pipeline's own pick block (the simulated pick: symmetry-aware MSSD <= 0.1 x diameter)
  against the ground truth of the frame, which it reads from the dataset and never publishes;
- the robot program then reports the estimate's outcome through the configurator's
  `report_pick_outcome`, as a real robot program does (`report`);
- `reports` makes it a robot program that reports wrong outcomes (the poisoning runs): "truth"
  (honest), "flipped" (each outcome flipped with probability `flip_share`, seeded), "all-failed",
  "all-success". The same (wrong) outcome goes to the Pick answer and to the report: the cell
  acts on it as a real one would (a pick reported failed is followed by more operations);
- frames arrive on `perception/frame_info` (the bag's stamp and BOP ids), which tells this
  process which frame it is; the nodes get no ground-truth topic.

Every pick's true outcome is kept (`true_picked`): an estimate truly succeeded when one of its
picks truly did, whatever was reported.
"""
from __future__ import annotations

import json
from typing import Any

import numpy as np
from perception_config_interfaces.srv import Pick, ReportPickOutcome
from rclpy.node import Node
from std_msgs.msg import String

from ..blocks.base import Block, BlockInput
from ..core.geometry import Pose
from ..datasets.bop_models import ModelFolder
from .operator_node import hypothesis_pose

REPORTS = ("truth", "flipped", "all-failed", "all-success")
ROBOT_SERVICE = "cell_sim/robot_pick"
FRAME_INFO = "perception/frame_info"


class SimulatedRobot:
    """The robot and its program (module docstring), on `node`."""

    def __init__(self, node: Node, truth: dict[int, dict[int, Pose]], models: ModelFolder, pick_block: Block, *,
                 reports: str = "truth", flip_share: float = 0.3, seed: int = 0) -> None:
        if reports not in REPORTS:
            raise ValueError(f"--robot-reports must be one of {REPORTS}, got {reports!r}")
        if not 0.0 <= flip_share <= 1.0:
            raise ValueError(f"--flip-share must be in [0, 1], got {flip_share}")
        self.node, self.truth, self.models, self.block = node, truth, models, pick_block
        self.reports, self.flip_share = reports, float(flip_share)
        self.rng = np.random.default_rng(seed)
        self.picks: list[tuple[bool, bool]] = []  # (true, reported) of the picks since `begin`
        self.reported = 0
        self.refused_reports: list[str] = []
        node.create_service(Pick, ROBOT_SERVICE, self._on_pick)
        self._report = node.create_client(ReportPickOutcome, "report_pick_outcome")

    def _reported(self, true: bool) -> bool:
        if self.reports == "truth":
            return true
        if self.reports == "all-failed":
            return False
        if self.reports == "all-success":
            return True
        return (not true) if self.rng.random() < self.flip_share else true

    def _on_pick(self, request: Pick.Request, response: Pick.Response) -> Pick.Response:
        try:
            stamp, object_id, pose = hypothesis_pose(request.hypothesis)
            truth = self.truth.get(stamp, {}).get(int(object_id))
            if truth is None:
                raise ValueError(f"no object {object_id} in the frame at {stamp} ns")
            result = self.block(BlockInput(frame=None, model=self.models.model(object_id), pose=pose,
                                           ground_truth=truth))
            if not result.ok:
                raise ValueError(result.reason)
        except (ValueError, KeyError) as exc:
            response.success, response.message = False, f"the robot cannot try this pick: {exc}"
            return response
        true = bool(result.picked)
        reported = self._reported(true)
        self.picks.append((true, reported))
        response.success, response.picked = True, reported
        response.message = "picked" if reported else "not picked"
        return response

    def begin(self) -> None:
        """Before an estimate: its picks start here."""
        self.picks.clear()

    def true_success(self) -> bool:
        """Whether a pick of the current estimate truly succeeded."""
        return any(true for true, _ in self.picks)

    def report(self, estimate_id: int, picked: bool, timeout: float = 10.0) -> bool:
        """The robot program's `report_pick_outcome` for the estimate just answered (its last
        pick's outcome as the robot saw it); False when refused or unanswered (kept in
        `refused_reports`)."""
        import rclpy

        if not self._report.wait_for_service(timeout_sec=timeout):
            self.refused_reports.append(f"estimate {estimate_id}: report_pick_outcome not available")
            return False
        future = self._report.call_async(ReportPickOutcome.Request(estimate_id=int(estimate_id), picked=bool(picked)))
        rclpy.spin_until_future_complete(self.node, future, timeout_sec=timeout)
        answer = future.result()
        if answer is None or not answer.success:
            self.refused_reports.append(f"estimate {estimate_id}: {answer.message if answer else 'no answer'}")
            return False
        self.reported += 1
        return True


def frame_info_stamp(msg: String) -> tuple[int, tuple[int, int]] | None:
    """(stamp_ns, (scene_id, im_id)) of a perception/frame_info message (None: not one)."""
    try:
        info: Any = json.loads(msg.data)
        return int(info["stamp_ns"]), (int(info["scene_id"]), int(info["im_id"]))
    except (ValueError, KeyError, TypeError):
        return None
