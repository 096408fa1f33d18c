"""What an episode's actions did to the hypothesis: the rule that keeps a policy out of loops.

An operator that leaves the hypothesis where it was (an ICP at its own fixed point, depth_refine
with nothing to shift, next_candidate with no candidate left) does the same when called again;
two refiners that undo each other (A moves p0 to p1, B moves p1 back to p0) do so forever. A
greedy policy that picks the same action in the same state repeats such a step until `max_ops`
and the episode ends truncated. `PoseMemory` remembers, per episode, every hypothesis reached
and which actions were taken at each: back at a hypothesis (within `POSE_TOL`), an action
already taken there is *stale*: a deterministic operator would go where it went before, to a
hypothesis already reached. The environment masks stale actions while the hypothesis stays
(rl/env.py). A stochastic action (regenerate, a randomised generator) moves elsewhere each call,
so it is only stale when the episode really came back to where it was called.

An ICP re-deriving its correspondences from each new hypothesis does not stop at a fixed point:
called again it keeps nudging the pose by a few thousandths of the diameter, more than
`POSE_TOL`, far less than a pick can tell apart (trained policies spent 3-6 such calls waiting for
the nudges to fade). `converged(pose, tol)` names the actions whose latest call moved no point of
the object by more than `tol` x diameter (`surface_move`) and left the hypothesis within that of
where it is: with `EnvSettings.converge_tol` > 0 (off by default) the environment masks them too.

`loop_steps` counts the steps of a played episode that took a stale action (the evaluation's loop
count).
"""
from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from ..core.geometry import rotation_angle

# Two hypotheses are the same when they are within this share of the object's diameter and this
# many radians (0.2 mm and 0.11 degrees on a 100 mm part): far below what a pick can tell apart,
# far above the drift of an ICP re-converging at its fixed point.
POSE_TOL = 2e-3


def within(a: Any, b: Any, metres: float, radians: float) -> bool:
    """Whether two poses (geometry.Pose) are within `metres` and `radians` of each other."""
    return bool(np.linalg.norm(np.asarray(a.t) - np.asarray(b.t)) <= metres and rotation_angle(a.R, b.R) <= radians)


def same_pose(a: Any, b: Any, diameter: float, tol: float = POSE_TOL) -> bool:
    """Whether two poses (geometry.Pose or None) are the same hypothesis: within `tol` x diameter
    (m) and `tol` rad; None is only itself."""
    if a is None or b is None:
        return a is None and b is None
    return within(a, b, tol * diameter, tol)


def surface_move(a: Any, b: Any, diameter: float) -> float:
    """How far a point of the object moves between poses `a` and `b`, at most, as a share of its
    diameter: |t_a - t_b| / d + angle(R_a, R_b) / 2 (a bound for points within d / 2 of the
    model's origin, as on BOP's centred models); inf when either is None."""
    if a is None or b is None:
        return math.inf
    return float(np.linalg.norm(np.asarray(a.t) - np.asarray(b.t)) / diameter + rotation_angle(a.R, b.R) / 2.0)


class PoseMemory:
    """The hypotheses of one episode and the actions taken at each (module docstring).

    `visit(pose)` at the start; `record(before, action, after)` after every action; `stale(pose)`:
    the actions already taken at `pose`."""

    def __init__(self, diameter: float) -> None:
        self.diameter = float(diameter)
        self.poses: list[Any] = []  # distinct hypotheses reached, in order (None = no hypothesis)
        self.taken: set[tuple[int, int]] = set()  # (hypothesis, action) pairs played
        self.latest: dict[int, tuple[Any, Any]] = {}  # action -> (before, after) of its latest call

    def index(self, pose: Any) -> int:
        """The index of `pose` among the hypotheses reached; -1 when new."""
        for i, p in enumerate(self.poses):
            if same_pose(p, pose, self.diameter):
                return i
        return -1

    def visit(self, pose: Any) -> tuple[int, bool]:
        """(index, True when reached before) of `pose`, remembering it."""
        i = self.index(pose)
        if i >= 0:
            return i, True
        self.poses.append(pose)
        return len(self.poses) - 1, False

    def record(self, before: Any, action: int, after: Any) -> bool:
        """Remember that `action` was taken at `before` and led to `after`; True when `after` had
        been reached before (this step went round in a loop)."""
        src, _ = self.visit(before)
        _, seen = self.visit(after)
        self.taken.add((src, int(action)))
        self.latest[int(action)] = (before, after)
        return seen

    def stale(self, pose: Any) -> set[int]:
        """The actions already taken at `pose` (none when it was never reached)."""
        src = self.index(pose)
        return {a for s, a in self.taken if s == src} if src >= 0 else set()

    def converged(self, pose: Any, tol: float) -> set[int]:
        """The actions whose latest call moved no point of the object by more than `tol` x
        diameter and left the hypothesis within that of `pose` (still where they left it): called
        again here they would move it as little (module docstring). None for tol <= 0."""
        if tol <= 0 or pose is None:
            return set()
        return {a for a, (before, after) in self.latest.items()
                if surface_move(before, after, self.diameter) <= tol
                and surface_move(after, pose, self.diameter) <= tol}

    def copy(self) -> "PoseMemory":
        out = PoseMemory(self.diameter)
        out.poses, out.taken, out.latest = list(self.poses), set(self.taken), dict(self.latest)
        return out


def loop_steps(initial_pose: Any, step_poses: Sequence[Any], actions: Sequence[str], kinds: Sequence[str],
               diameter: float) -> int:
    """How many actions of a played episode (the hypothesis after each, the action names, their
    kinds "pick" or other) repeated an action already taken at the same hypothesis: an action that
    left the hypothesis unchanged taken again, or a cycle (A, B, A with B undoing A) come round.
    These are the steps the loop rule masks; picks are left out (a repeated failed pick has its own
    rule)."""
    memory = PoseMemory(diameter)
    memory.visit(initial_pose)
    names: dict[str, int] = {}
    before, count = initial_pose, 0
    for pose, name, kind in zip(step_poses, actions, kinds):
        action = names.setdefault(name, len(names))
        if kind != "pick" and action in memory.stale(before):
            count += 1
        memory.record(before, action, pose)
        before = pose
    return count
