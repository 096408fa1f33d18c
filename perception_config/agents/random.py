"""The random agent: every action uniformly at random, every step (the paper's baseline).
Uniform over the actions that can run (`info["action_mask"]`) when the mask restricts them."""
from __future__ import annotations

from typing import Any

import numpy as np

from ..rl.trajectory import allowed_actions
from .base import Agent


class RandomAgent(Agent):
    """Uniformly random actions: the baseline every learned agent must beat."""

    kind = "random"

    def act(self, obs: np.ndarray, info: dict[str, Any]) -> int:
        allowed = allowed_actions(info, self.spec.n_actions)
        if allowed is None:
            return int(self.rng.integers(self.spec.n_actions))
        return int(self.rng.choice(np.flatnonzero(allowed)))
