"""The fixed agent: an engineer's hand-made sequence of actions, e.g. ICP coarse, ICP fine, pick.

The sequence is played from the start of each episode. When it is used up and the episode
goes on (its pick failed, or it contains no pick), `after` decides:
- "repeat" (default): continue with sequence[restart:], again and again (restart=0 replays
  the whole sequence; restart=1 with [icp_coarse, icp_fine, pick] loops "icp_fine, pick");
- "pick": keep picking (the sequence's last pick action, else the env's first pick action).
The names are checked against the environment's action set when the agent is built.

Actions that cannot run (`info["action_mask"]`: e.g. the ICPs and depth_refine on an RGB-only
frame, `pick` right after a failed pick on the same hypothesis) are skipped where they come:
the sequence is played without them ([icp_coarse, icp_fine, pick] is [pick] on RGB-only data;
after a failed pick the loop goes on with its next action). With `after="pick"` and the pick
masked, the loop's first action that can run comes before the next pick. When nothing of the
sequence can run, it picks. The loop rule's mask (`info["loop_mask"]`: actions masked only
because they were taken at this hypothesis before, rl/pose_memory.py) does not bind a fixed plan:
an engineer's pipeline plays its sequence as it was written.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..rl.trajectory import allowed_actions
from .base import Agent, EnvSpec
from .hparams import SEED, Choice, Int, StrList

DEFAULT_SEQUENCE = ("icp_coarse", "icp_fine", "pick")


class FixedAgent(Agent):
    """An engineer's fixed action sequence (module docstring: what happens when it runs out)."""

    kind = "fixed"
    HPARAM_BOUNDS = {"sequence": StrList(1000, nullable=True), "restart": Int(0, 999),
                     "after": Choice(("repeat", "pick")), "seed": SEED}

    def __init__(self, spec: EnvSpec, sequence: list[str] | tuple[str, ...] | None = None,
                 restart: int = 0, after: str = "repeat", seed: int = 0) -> None:
        super().__init__(spec, seed)
        if sequence is None:
            sequence = (DEFAULT_SEQUENCE if set(DEFAULT_SEQUENCE) <= set(spec.action_names)
                        else (spec.action_names[spec.pick_actions[0]],) if spec.pick_actions else ())
        sequence = [str(s) for s in sequence]
        if not sequence:
            raise ValueError("a fixed agent needs a non-empty sequence of action names")
        unknown = [s for s in sequence if s not in spec.action_names]
        if unknown:
            raise ValueError(f"fixed sequence names unknown action(s) {unknown}; "
                             f"the environment's actions are {list(spec.action_names)}")
        if after not in ("repeat", "pick"):
            raise ValueError(f"after must be 'repeat' or 'pick', got {after!r}")
        if not 0 <= int(restart) < len(sequence):
            raise ValueError(f"restart must index the sequence (0..{len(sequence) - 1}), got {restart}")
        if after == "pick" and not spec.pick_actions:
            raise ValueError("after='pick' but the environment has no pick action")
        self.sequence = sequence
        self.restart = int(restart)
        self.after = after
        self._ids = [spec.action_names.index(s) for s in sequence]
        picks_in_seq = [i for i in self._ids if i in spec.pick_actions]
        self._pick = picks_in_seq[-1] if picks_in_seq else (spec.pick_actions[0] if spec.pick_actions else -1)
        self._t = 0

    def begin_episode(self, seed: int | None = None) -> None:
        super().begin_episode(seed)
        self._t = 0

    def _planned(self, k: int) -> int:
        """The k-th action of the plan: the sequence, then its loop (or the pick) forever."""
        n = len(self._ids)
        if k < n:
            return self._ids[k]
        return self._pick if self.after == "pick" else self._ids[self.restart + (k - n) % (n - self.restart)]

    def act(self, obs: np.ndarray, info: dict[str, Any]) -> int:
        # The plan's position: 0 at an episode's first step (the env's step count tells us, also
        # when begin_episode was not called), then one past the last action played.
        if isinstance(info, dict) and info.get("steps", None) == 0:
            self._t = 0
        allowed = allowed_actions(_without_loop_rule(info), self.spec.n_actions)
        if allowed is None:
            a, self._t = self._planned(self._t), self._t + 1
            return a
        for k in range(self._t, self._t + len(self._ids) + 1):  # every planned action comes up once in there
            if allowed[self._planned(k)]:
                self._t = k + 1
                return self._planned(k)
        if self.after == "pick":  # the pick is masked: the loop's first action that can run first
            loop = [i for i in self._ids[self.restart:] if allowed[i]]
            if loop:
                return loop[0]
        return self._pick

    def hparams(self) -> dict[str, Any]:
        return {"sequence": list(self.sequence), "restart": self.restart, "after": self.after, "seed": self.seed}


def _without_loop_rule(info: Any) -> Any:
    """The env's info with the loop rule's masking undone (module docstring)."""
    if not isinstance(info, dict) or info.get("loop_mask") is None or info.get("action_mask") is None:
        return info
    mask = np.asarray(info["action_mask"]) | np.asarray(info["loop_mask"])
    return {**info, "action_mask": mask}
