"""The fixed agent: an engineer's hand-made sequence of actions, e.g. ICP coarse, ICP fine, pick.

The sequence is played from the start of each episode. When it is used up and the episode
goes on (its pick failed, or it contains no pick), `after` decides:
- "repeat" (default): continue with sequence[restart:], again and again (restart=0 replays
  the whole sequence; restart=1 with [icp_coarse, icp_fine, pick] loops "icp_fine, pick");
- "pick": keep picking (the sequence's last pick action, else the env's first pick action).
The names are checked against the environment's action set when the agent is built.

Actions that cannot run on the episode's frame (`info["action_mask"]`: e.g. the ICPs and
depth_refine on an RGB-only frame) are skipped: the sequence is played without them
([icp_coarse, icp_fine, pick] is [pick] on RGB-only data; `restart` indexes the full sequence
and the loop is sequence[restart:] without them). A sequence left empty picks.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from .base import Agent, EnvSpec, allowed_actions
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

    def act(self, obs: np.ndarray, info: dict[str, Any]) -> int:
        # Steps count from the env when it tells us (robust if begin_episode was not called).
        t = int(info.get("steps", self._t)) if isinstance(info, dict) else self._t
        self._t = t + 1
        ids, loop = self._ids, self._ids[self.restart:]
        allowed = allowed_actions(info, self.spec.n_actions)
        if allowed is not None:  # skip the actions that cannot run on this frame
            ids, loop = [i for i in ids if allowed[i]], [i for i in loop if allowed[i]]
            if not ids:
                return self._pick
        n = len(ids)
        if t < n:
            return ids[t]
        if self.after == "pick" or not loop:
            return self._pick
        return loop[(t - n) % len(loop)]

    def hparams(self) -> dict[str, Any]:
        return {"sequence": list(self.sequence), "restart": self.restart, "after": self.after, "seed": self.seed}
