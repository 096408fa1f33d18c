"""The random agent: every action uniformly at random, every step (the paper's baseline)."""
from __future__ import annotations

from typing import Any

import numpy as np

from .base import Agent


class RandomAgent(Agent):
    """Uniformly random actions: the baseline every learned agent must beat."""

    kind = "random"

    def act(self, obs: np.ndarray, info: dict[str, Any]) -> int:
        return int(self.rng.integers(self.spec.n_actions))
