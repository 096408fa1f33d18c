"""The evolutionary agent: a population of three-layer networks, the best two breed.

Network (numpy only): logits = W3 tanh(W2 tanh(W1 s + b1) + b2) + b3; the action is the
argmax (a deterministic policy: the evolution, not the policy, explores) over the actions that
can run (`info["action_mask"]`).

One generation (the trainer runs it, see perception_config.learning.training):
1. every one of the `population` individuals plays the same `episodes_per_generation`
   episodes (same frames, objects, lambdas and episode seeds: a fair comparison); the
   trainer spreads these episodes over worker processes;
2. fitness = mean return (minus the mean seconds to the end of the episode);
3. elitism: the `elites` fittest individuals pass unchanged into the next generation (and are
   evaluated again on new episodes there, so a lucky draw does not survive for free);
4. the rest are offspring of the best two: per weight, a random 50/50 mask picks the parent,
   then Gaussian mutation w += N(0, sigma^2) on a `mutation_rate` share of the weights;
   sigma decays per generation to `sigma_min`.
The policy saved is the champion: the fittest individual of the last generation.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..rl.trajectory import Trajectory, allowed_actions
from .base import Agent, EnvSpec
from .hparams import SEED, Float, Int, IntList

Weights = list[np.ndarray]  # [W1, b1, W2, b2, W3, b3]


def init_network(rng: np.random.Generator, sizes: list[int]) -> Weights:
    """Weights ~ N(0, 1/fan_in), biases 0."""
    out: Weights = []
    for fan_in, fan_out in zip(sizes[:-1], sizes[1:]):
        out.append(rng.normal(0.0, 1.0 / np.sqrt(fan_in), (fan_in, fan_out)))
        out.append(np.zeros(fan_out))
    return out


def forward(weights: Weights, obs: np.ndarray) -> np.ndarray:
    """Logits of the three-layer tanh network."""
    h = np.asarray(obs, np.float64)
    n_layers = len(weights) // 2
    for i in range(n_layers):
        h = h @ weights[2 * i] + weights[2 * i + 1]
        if i < n_layers - 1:
            h = np.tanh(h)
    return h


def crossover(rng: np.random.Generator, a: Weights, b: Weights) -> Weights:
    """A child taking each weight from parent a or b with probability 1/2."""
    return [np.where(rng.random(wa.shape) < 0.5, wa, wb) for wa, wb in zip(a, b)]


def mutate(rng: np.random.Generator, w: Weights, sigma: float, rate: float) -> Weights:
    """Gaussian noise on a random `rate` share of the weights."""
    return [x + np.where(rng.random(x.shape) < rate, rng.normal(0.0, sigma, x.shape), 0.0) for x in w]


class EvolutionaryAgent(Agent):
    """A population of three-layer networks; the best two breed (module docstring: one generation)."""

    kind = "es"
    HPARAM_BOUNDS = {"population": Int(3, 10_000), "episodes_per_generation": Int(1, 10_000),
                     "hidden": IntList(2, Int(1, 4096)), "sigma": Float(0.0, 100.0), "sigma_decay": Float(0.0, 1.0),
                     "sigma_min": Float(0.0, 100.0), "mutation_rate": Float(0.0, 1.0), "elites": Int(1, 9_999),
                     "seed": SEED}

    @classmethod
    def expected_tensors(cls, spec: EnvSpec, hparams: dict[str, Any]) -> dict[str, tuple[int, ...]]:
        sizes = [spec.obs_dim, *[int(h) for h in hparams.get("hidden", (32, 32))], spec.n_actions]
        out: dict[str, tuple[int, ...]] = {}
        for i, (fan_in, fan_out) in enumerate(zip(sizes[:-1], sizes[1:])):
            out[f"net.{2 * i}"], out[f"net.{2 * i + 1}"] = (fan_in, fan_out), (fan_out,)
        return out

    def __init__(self, spec: EnvSpec, population: int = 8, episodes_per_generation: int = 4,
                 hidden: list[int] | tuple[int, int] = (32, 32), sigma: float = 0.1, sigma_decay: float = 0.98,
                 sigma_min: float = 0.01, mutation_rate: float = 0.5, elites: int = 2, seed: int = 0) -> None:
        super().__init__(spec, seed)
        if population < 3 or not 1 <= elites < population:
            raise ValueError(f"need population >= 3 and 1 <= elites < population, got {population}, {elites}")
        if episodes_per_generation < 1 or len(hidden) != 2 or sigma <= 0 or not 0 < mutation_rate <= 1:
            raise ValueError("need episodes_per_generation >= 1, two hidden sizes, sigma > 0, 0 < mutation_rate <= 1")
        self.n_pop, self.k = int(population), int(episodes_per_generation)
        self.hidden = [int(h) for h in hidden]
        self.sigma0, self.sigma_decay, self.sigma_min = float(sigma), float(sigma_decay), float(sigma_min)
        self.sigma = self.sigma0  # the current mutation scale
        self.mutation_rate, self.elites = float(mutation_rate), int(elites)
        self.sizes = [spec.obs_dim, *self.hidden, spec.n_actions]
        self.evo_rng = np.random.default_rng([int(seed), 1])  # breeding; self.rng is for acting
        self.weights: Weights = init_network(np.random.default_rng([int(seed), 0]), self.sizes)  # the champion
        self.population: list[Weights] = []  # created by the first actors() call
        self.generation = 0
        self.last_fitness: list[float] = []

    def act(self, obs: np.ndarray, info: dict[str, Any]) -> int:
        logits = forward(self.weights, obs)
        allowed = allowed_actions(info, self.spec.n_actions)
        if allowed is not None:
            logits = np.where(allowed, logits, -np.inf)
        return int(np.argmax(logits))

    # -- evolution ------------------------------------------------------------------------
    @property
    def episodes_per_actor(self) -> int:
        return self.k

    def _individual(self, weights: Weights) -> "EvolutionaryAgent":
        ind = EvolutionaryAgent(self.spec, **self.hparams())
        ind.weights = [w.copy() for w in weights]
        return ind

    def actors(self) -> list[Agent]:
        if not self.population:
            self.population = [self.weights] + [init_network(self.evo_rng, self.sizes) for _ in range(self.n_pop - 1)]
        return [self._individual(w) for w in self.population]

    def update(self, trajectories: list[list[Trajectory]]) -> dict[str, float]:
        """One generation (module docstring) from trajectories[individual][episode]; returns its figures:
        best_fitness and mean_fitness (the population's best and mean fitness: mean return, minus
        seconds) and sigma (the mutation scale of the next generation, after the decay)."""
        if len(trajectories) != len(self.population):
            raise ValueError(f"got results for {len(trajectories)} individuals, "
                             f"the population has {len(self.population)}")
        fitness = np.array([np.mean([t.ret for t in per]) for per in trajectories])
        order = np.argsort(-fitness, kind="stable")  # fittest first
        ranked = [self.population[i] for i in order]
        self.weights = [w.copy() for w in ranked[0]]
        parent_a, parent_b = ranked[0], ranked[1]
        nxt = [[w.copy() for w in ind] for ind in ranked[: self.elites]]
        while len(nxt) < self.n_pop:
            child = crossover(self.evo_rng, parent_a, parent_b)
            nxt.append(mutate(self.evo_rng, child, self.sigma, self.mutation_rate))
        self.population = nxt
        self.sigma = max(self.sigma_min, self.sigma * self.sigma_decay)
        self.generation += 1
        self.last_fitness = fitness.tolist()
        return {"best_fitness": float(fitness.max()), "mean_fitness": float(fitness.mean()), "sigma": self.sigma}

    # -- persistence ----------------------------------------------------------------------
    def hparams(self) -> dict[str, Any]:
        return {"population": self.n_pop, "episodes_per_generation": self.k, "hidden": list(self.hidden),
                "sigma": self.sigma0, "sigma_decay": self.sigma_decay, "sigma_min": self.sigma_min,
                "mutation_rate": self.mutation_rate, "elites": self.elites, "seed": self.seed}

    def tensors(self) -> dict[str, np.ndarray]:
        return {f"net.{i}": w.astype(np.float64) for i, w in enumerate(self.weights)}

    def set_tensors(self, tensors: dict[str, np.ndarray]) -> None:
        want = [tuple(w.shape) for w in init_network(np.random.default_rng(0), self.sizes)]
        got = [tuple(tensors[f"net.{i}"].shape) if f"net.{i}" in tensors else None for i in range(len(want))]
        if got != want or len(tensors) != len(want):
            raise ValueError(f"network tensors {sorted(tensors)} with shapes {got} do not match {want}")
        self.weights = [np.array(tensors[f"net.{i}"], np.float64) for i in range(len(want))]

    def checkpoint(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        tensors = {f"train/pop.{j}.{i}": w for j, ind in enumerate(self.population) for i, w in enumerate(ind)}
        return tensors, {"generation": self.generation, "evo_rng": self.evo_rng.bit_generator.state,
                         "sigma_now": self.sigma, "population_size": len(self.population)}

    def load_checkpoint(self, tensors: dict[str, np.ndarray], state: dict[str, Any]) -> None:
        n_layers = len(self.sizes) - 1
        self.population = [[np.array(tensors[f"train/pop.{j}.{i}"]) for i in range(2 * n_layers)]
                           for j in range(int(state.get("population_size", 0)))]
        self.generation = int(state.get("generation", 0))
        self.sigma = float(state.get("sigma_now", self.sigma))
        if "evo_rng" in state:
            self.evo_rng.bit_generator.state = state["evo_rng"]
