"""Labels from the robot's own picks: what a cell without ground truth knows about a pose.

A robot cell has no ground truth, but every pick the robot tries is an answer: a success says
the true pose is within the pick tolerance of the pose it picked at (symmetry-aware MSSD <= 0.1 x
the diameter, the simulated pick's criterion: "picked here"), a failure says that pose is wrong.
This is self-supervised labelling by interaction (Deng et al., ICRA 2020: the robot's successful
grasps label the data it learns from). The learner (online/policy_learner.py) replays a stored
estimate of a frame without ground truth when its object has robot labels in that frame, and
judges each replayed pick with `PickLabels.judge`:

| the replayed pose is ...                                                    | judged      |
|-----------------------------------------------------------------------------|-------------|
| within `LABEL_TOLERANCE` (0.05 d) of a pose the robot picked                | picked      |
| within `LABEL_TOLERANCE` of a pose the robot failed to pick                 | not picked  |
| farther than 2 x the pick tolerance (0.2 d) from every picked pose (if any) | not picked  |
| otherwise, with the pipeline's learned pick-success score                   | score >= 0.5|
| otherwise                                                                   | not picked  |

A picked pose is within 0.1 d of the truth, so a pose within 0.05 d of it is within 0.15 d: the
label tolerance is half the pick's, and what it cannot decide counts as a failure. Both err on the
side of "not picked": a candidate earns a success only where the robot has confirmed one, so it
cannot look better by picking where nobody looked (the spirit of SPIBB: where the data says
nothing, no credit beyond the policy that collected it).

**Label rules against wrong reports.** The labels of one object in one frame must agree, or none
of them is used (`conflict`): two picked poses more than 0.2 d apart cannot both be within 0.1 d
of one truth, and a failed pose within `CONFLICT_TOLERANCE` (0.02 d) of a picked one contradicts
it. A robot program that reports at random is caught whenever a frame is estimated twice; one that
reports every pick failed leaves no picked pose (nothing to replay without the learned score, and
with it no success is confirmed, so the gate promotes nothing: promotion_gate); one that reports
every pick successful labels the serving policy's own poses, so a candidate gains
nothing there over the policy that made them.

What this cannot learn: a frame where the robot never succeeded teaches nothing without the
learned score (no pose is known to be right there), and a pose no estimate reached is unknown, so
a better action the serving policy never tried earns no credit until a served policy tries it.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from ..core.geometry import Pose
from ..core.metrics import pose_mssd
from ..core.models import ObjectModel
from ..core.pose_json import pose_from_json
from ..store.episode_store import EpisodeStore

PICK_TOLERANCE = 0.1  # share of the diameter: the simulated pick's MSSD criterion
LABEL_TOLERANCE = 0.05  # a replayed pose within this share of a labelled pose takes its label
CONFLICT_TOLERANCE = 0.02  # a failed pose this close to a picked one contradicts it
SCORE = "pick_success"  # the learned score that decides a pose the labels do not cover


@dataclass
class PickLabels:
    """The robot's pick outcomes for one object in one frame (module docstring)."""

    picked: list[Pose] = field(default_factory=list)
    failed: list[Pose] = field(default_factory=list)

    def add(self, pose: Pose, picked: bool) -> None:
        (self.picked if picked else self.failed).append(pose)

    @staticmethod
    def _nearest(pose: Pose, poses: list[Pose], model: ObjectModel) -> float:
        """The smallest symmetry-aware MSSD from `pose` to `poses`, as a share of the diameter."""
        if not poses:
            return math.inf
        return min(pose_mssd(pose, p, model) for p in poses) / float(model.diameter)

    def conflict(self, model: ObjectModel) -> str | None:
        """Why these labels contradict each other (None: they agree)."""
        for i, a in enumerate(self.picked):
            for b in self.picked[i + 1:]:
                d = pose_mssd(a, b, model) / float(model.diameter)
                if d > 2 * PICK_TOLERANCE:
                    return f"two picked poses {d:.2f} d apart"
        for f in self.failed:
            d = self._nearest(f, self.picked, model)
            if d <= CONFLICT_TOLERANCE:
                return f"a failed pose {d:.3f} d from a picked one"
        return None

    def confirms(self, pose: Pose, model: ObjectModel) -> bool:
        """Whether a pick at `pose` is judged picked by a pose the robot picked (the table's first
        row), not by the learned score: a confirmed success."""
        return self._nearest(pose, self.picked, model) <= LABEL_TOLERANCE

    def judge(self, pose: Pose, model: ObjectModel, scores: dict[str, float] | None = None
              ) -> tuple[bool, dict[str, float]]:
        """(picked, figures) for a pick at `pose` (module docstring's table); `scores`: the
        hypothesis' current scores (the learned pick-success score decides the uncovered poses)."""
        d_picked = self._nearest(pose, self.picked, model)
        d_failed = self._nearest(pose, self.failed, model)
        figures = {"label_picked_d": d_picked, "label_failed_d": d_failed}
        if d_picked <= LABEL_TOLERANCE:
            return True, figures
        if d_failed <= LABEL_TOLERANCE or (self.picked and d_picked > 2 * PICK_TOLERANCE):
            return False, figures
        score = (scores or {}).get(SCORE)
        if score is not None and math.isfinite(float(score)):
            return float(score) >= 0.5, {**figures, "label_score": float(score)}
        return False, figures


def robot_labels(store: EpisodeStore) -> dict[tuple[int, int], PickLabels]:
    """Every pick the robot answered (`pick_source` "robot": the pick node's robot service, or a
    `report_pick_outcome`), grouped by (frame stamp, object id), oldest first."""
    rows = store.query(
        "SELECT e.frame_stamp_ns, e.obj_id, s.pose, s.picked FROM steps s JOIN episodes e ON e.id = s.episode_id "
        "WHERE e.source = 'configurator' AND e.frame_stamp_ns IS NOT NULL AND e.obj_id IS NOT NULL "
        "AND s.picked IS NOT NULL AND s.pick_source = 'robot' AND s.pose IS NOT NULL ORDER BY e.id, s.step")
    out: dict[tuple[int, int], PickLabels] = {}
    for stamp, obj_id, pose_text, picked in rows:
        try:
            pose = pose_from_json(json.loads(pose_text))
        except (ValueError, TypeError, KeyError):
            continue
        if pose is None:
            continue
        out.setdefault((int(stamp), int(obj_id)), PickLabels()).add(pose, bool(picked))
    return out


def label_counts(store_path: str | Path) -> dict[str, int]:
    """Stored configurator estimates by label kind (episode_store.LABEL_KINDS; "unknown" for
    rows stored before the column existed)."""
    with EpisodeStore(store_path, readonly=True, busy_timeout=2.0) as store:
        if not store.has_column("episodes", "label"):
            return {}
        rows = store.query("SELECT COALESCE(label, 'unknown'), COUNT(*) FROM episodes "
                           "WHERE source = 'configurator' GROUP BY 1")
    return {str(k): int(n) for k, n in rows}


__all__ = ["PickLabels", "robot_labels", "label_counts", "LABEL_TOLERANCE", "PICK_TOLERANCE",
           "CONFLICT_TOLERANCE"]
