"""REINFORCE with a learned baseline (Williams 1992; Sutton & Barto 2018, sec. 13.4).

Policy (as in the paper): two linear layers, tanh between them, softmax over the actions:
    pi(a | s) = softmax(W2 tanh(W1 s + b1) + b2)
Baseline: `baseline="value"` (default) is a separate value network of the same shape with one
output, V(s), fitted by mean-squared error to the returns; it knows from the scores how much
time an episode still needs, which a constant cannot. `baseline="mean"` uses instead a running
(exponential, factor `mean_decay`) mean of the return-to-go per step index.

One update per batch of `batch_episodes` complete episodes (sampled with the current policy):
    G_t   = sum_{k >= t} gamma^(k-t) r_k                  (returns to go; r = minus seconds)
    A_t   = G_t - b(s_t), then normalised over the batch   (advantage)
            (value baseline with `gae_lambda` = l < 1: A_t = sum_k (gamma l)^k delta_{t+k},
             delta_t = r_t + gamma V(s_{t+1}) - V(s_t), V = 0 after the last step: generalised
             advantage estimation, Schulman et al. 2016; l = 1 is G_t - V(s_t), op for op as before)
    loss  = -mean_t[ log pi(a_t | s_t) A_t ] - entropy_coef * mean_t[ H(pi(. | s_t)) ]
    Adam step on the policy; Adam step on the value network's MSE (value baseline).
Learning rate: constant by default; `lr_half_life` = H > 0 halves the policy's every H training
episodes (lr * 0.5^(episodes learned / H), episodes learned = updates x batch_episodes): late
updates then move the policy less, so it settles instead of jumping between neighbours (the
value network keeps its rate: it has to track the changing policy).
Several passes over a batch (`update_epochs` = K > 1; PPO's clipped surrogate, Schulman et al.
2017): the first pass is the REINFORCE step above; each further pass steps again on the same
episodes with the importance ratio rho = pi(a|s) / pi_old(a|s) (pi_old: the policy that sampled
them) and the objective mean_t[min(rho A_t, clip(rho, 1 - clip, 1 + clip) A_t)] (gradient
log pi A at rho = 1, as REINFORCE's), so no step moves an action's probability far from the
sampling policy's. The value network keeps one step per batch. K = 1 is plain REINFORCE, op for op.
Diagnostics: `update` also reports, read off without changing the step, the gradient norms before
clipping, the learning rate used and the approximate KL between the policy before and after the
step over the batch (CleanRL's approx_kl); training.py writes them to history.csv.
Warm start (`warm_start` = "best_static", "hindsight" or "threshold", default "none"): before the first update,
training (learning/warm_start.py) has a teacher play `warm_start_episodes` train episodes, and
`imitate` fits the policy to its actions by cross-entropy (behaviour cloning, `imitation_epochs`
full-batch Adam steps at `lr`, targets smoothed by `imitation_smoothing` over the allowed actions
so the policy keeps exploring) and the value network to their returns; reinforcement learning
goes on from there.
Acting: sample from pi while training (explore=True); argmax when evaluating a loaded policy.
Action mask (`info["action_mask"]`): the logits of the actions that cannot run are -inf, when
acting and in the update's log pi and entropy (the masks of every step are in the trajectory),
so pi is the distribution the actions were sampled from. Without a restricting mask nothing
changes (same draws, same update).
"""
from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import nn

from ..rl.trajectory import Trajectory, allowed_actions, returns_to_go
from .base import Agent, EnvSpec
from .hparams import SEED, Choice, Float, Int

MAX_HIDDEN = 4096  # units of the hidden layer a policy file may declare
WARM_STARTS = ("none", "hindsight", "best_static", "threshold")  # the teachers of a warm start (module docstring)


class PolicyNet(nn.Module):
    """obs -> hidden (tanh) -> one logit per action (softmax in the loss / when acting)."""

    def __init__(self, obs_dim: int, n_out: int, hidden: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(obs_dim, hidden)
        self.fc2 = nn.Linear(hidden, n_out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(torch.tanh(self.fc1(x)))


def _optim_tensors(prefix: str, opt: torch.optim.Optimizer) -> dict[str, np.ndarray]:
    out = {}
    for pid, st in opt.state_dict()["state"].items():
        for name, value in st.items():
            out[f"train/{prefix}.{pid}.{name}"] = torch.as_tensor(value).detach().cpu().numpy().copy()
    return out


def _load_optim(prefix: str, opt: torch.optim.Optimizer, tensors: dict[str, np.ndarray]) -> None:
    """Adam's moments and step counts; the parameter groups (lr, betas) come from hparams."""
    state: dict[int, dict[str, torch.Tensor]] = {}
    head = f"train/{prefix}."
    for key, value in tensors.items():
        if key.startswith(head):
            pid, name = key[len(head):].split(".", 1)
            state.setdefault(int(pid), {})[name] = torch.from_numpy(np.array(value))
    sd = opt.state_dict()
    sd["state"] = state
    opt.load_state_dict(sd)


class PolicyGradientAgent(Agent):
    """REINFORCE with a value (or running-mean) baseline; the policy network is `PolicyNet`."""

    kind = "pg"
    HPARAM_BOUNDS = {"hidden": Int(1, MAX_HIDDEN), "lr": Float(0.0, 10.0), "value_lr": Float(0.0, 10.0),
                     "gamma": Float(0.0, 1.0), "batch_episodes": Int(1, 10_000), "entropy_coef": Float(0.0, 100.0),
                     "baseline": Choice(("value", "mean")), "mean_decay": Float(0.0, 1.0),
                     "grad_clip": Float(0.0, 1e6), "lr_half_life": Float(0.0, 1e9),
                     "update_epochs": Int(1, 100), "clip": Float(0.0, 10.0),
                     "gae_lambda": Float(0.0, 1.0),
                     "warm_start": Choice(WARM_STARTS), "warm_start_episodes": Int(1, 100_000),
                     "imitation_epochs": Int(1, 100_000), "imitation_smoothing": Float(0.0, 0.99), "seed": SEED}

    @classmethod
    def expected_tensors(cls, spec: EnvSpec, hparams: dict[str, Any]) -> dict[str, tuple[int, ...]]:
        h, n, d = int(hparams.get("hidden", 32)), spec.n_actions, spec.obs_dim
        return {"policy.fc1.weight": (h, d), "policy.fc1.bias": (h,), "policy.fc2.weight": (n, h),
                "policy.fc2.bias": (n,)}

    def __init__(self, spec: EnvSpec, hidden: int = 32, lr: float = 0.02, value_lr: float = 0.01,
                 gamma: float = 1.0, batch_episodes: int = 8, entropy_coef: float = 0.01,
                 baseline: str = "value", mean_decay: float = 0.9, grad_clip: float = 1.0, lr_half_life: float = 0.0,
                 update_epochs: int = 1, clip: float = 0.2, gae_lambda: float = 1.0,
                 warm_start: str = "none", warm_start_episodes: int = 48,
                 imitation_epochs: int = 300, imitation_smoothing: float = 0.1, seed: int = 0) -> None:
        super().__init__(spec, seed)
        if baseline not in ("value", "mean"):
            raise ValueError(f"baseline must be 'value' or 'mean', got {baseline!r}")
        if not (0.0 < gamma <= 1.0) or batch_episodes < 1 or hidden < 1:
            raise ValueError("need 0 < gamma <= 1, batch_episodes >= 1, hidden >= 1; "
                             f"got {gamma}, {batch_episodes}, {hidden}")
        torch.set_num_threads(1)  # tiny networks: threads only add overhead (and fight the workers)
        self.hidden, self.lr, self.value_lr, self.gamma = int(hidden), float(lr), float(value_lr), float(gamma)
        self.batch_episodes, self.entropy_coef = int(batch_episodes), float(entropy_coef)
        self.baseline, self.mean_decay, self.grad_clip = baseline, float(mean_decay), float(grad_clip)
        if lr_half_life < 0:
            raise ValueError(f"lr_half_life must be >= 0 (0: a constant learning rate), got {lr_half_life}")
        self.lr_half_life = float(lr_half_life)
        if int(update_epochs) < 1 or not clip > 0:
            raise ValueError(f"need update_epochs >= 1 and clip > 0, got {update_epochs}, {clip}")
        self.update_epochs, self.clip = int(update_epochs), float(clip)
        if not 0.0 <= gae_lambda <= 1.0 or (gae_lambda < 1.0 and baseline != "value"):
            raise ValueError(f"gae_lambda must be in [0, 1], and 1 unless the baseline is 'value'; got {gae_lambda} "
                             f"with baseline {baseline!r}")
        self.gae_lambda = float(gae_lambda)
        if warm_start not in WARM_STARTS:
            raise ValueError(f"warm_start must be one of {', '.join(WARM_STARTS)}, got {warm_start!r}")
        if int(warm_start_episodes) < 1 or int(imitation_epochs) < 1 or not 0.0 <= imitation_smoothing < 1.0:
            raise ValueError("need warm_start_episodes >= 1, imitation_epochs >= 1 and 0 <= imitation_smoothing < 1; "
                             f"got {warm_start_episodes}, {imitation_epochs}, {imitation_smoothing}")
        self.warm_start, self.warm_start_episodes = warm_start, int(warm_start_episodes)
        self.imitation_epochs, self.imitation_smoothing = int(imitation_epochs), float(imitation_smoothing)
        gen = torch.Generator().manual_seed(int(seed))
        self.policy = PolicyNet(spec.obs_dim, spec.n_actions, self.hidden)
        self.value = PolicyNet(spec.obs_dim, 1, self.hidden)
        with torch.no_grad():  # seeded initialisation, independent of the global torch rng
            for p in list(self.policy.parameters()) + list(self.value.parameters()):
                bound = 1.0 / np.sqrt(p.shape[-1]) if p.dim() > 1 else 0.0
                p.copy_(torch.empty(p.shape).uniform_(-bound, bound, generator=gen) if bound else torch.zeros(p.shape))
        # The optimizers are made on first use: building one imports torch._dynamo (seconds), which a
        # policy that only acts (a configurator serving it, an evaluation) never needs.
        self._optimizer: torch.optim.Adam | None = None
        self._value_optimizer: torch.optim.Adam | None = None
        self.mean_baseline = np.zeros(spec.max_ops)  # per step index ("mean" baseline)
        self.updates = 0

    @property
    def optimizer(self) -> torch.optim.Adam:
        """Adam on the policy network (made on first use)."""
        if self._optimizer is None:
            self._optimizer = torch.optim.Adam(self.policy.parameters(), lr=self.lr)
        return self._optimizer

    @property
    def value_optimizer(self) -> torch.optim.Adam:
        """Adam on the value network (made on first use)."""
        if self._value_optimizer is None:
            self._value_optimizer = torch.optim.Adam(self.value.parameters(), lr=self.value_lr)
        return self._value_optimizer

    # -- acting ---------------------------------------------------------------------------
    def probabilities(self, obs: np.ndarray, allowed: np.ndarray | None = None) -> np.ndarray:
        """pi(. | obs); with `allowed` (bool per action) the others have probability 0."""
        with torch.no_grad():
            logits = self.policy(torch.as_tensor(np.asarray(obs, np.float32)))
            if allowed is not None:
                logits = logits.masked_fill(~torch.as_tensor(allowed), -torch.inf)
            return torch.softmax(logits, -1).double().numpy()

    def act(self, obs: np.ndarray, info: dict[str, Any]) -> int:
        p = self.probabilities(obs, allowed_actions(info, self.spec.n_actions))
        if self.explore:
            return int(self.rng.choice(len(p), p=p / p.sum()))
        return int(np.argmax(p))

    # -- learning -------------------------------------------------------------------------
    def current_lr(self) -> float:
        """The policy's learning rate for the next update (module docstring: `lr_half_life`)."""
        if self.lr_half_life <= 0:
            return self.lr
        return self.lr * 0.5 ** (self.updates * self.batch_episodes / self.lr_half_life)

    @property
    def episodes_per_actor(self) -> int:
        return self.batch_episodes

    def _log_pi(self, obs: torch.Tensor, actions: torch.Tensor, allowed: np.ndarray,
                masked: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """log pi(a_t | s_t) of the taken actions (masked actions: -inf logits, as when they were
        sampled) and the mean entropy over the states. Without a restricting mask the graph is the
        unmasked one, op for op (bitwise the same update)."""
        logits = self.policy(obs)
        if masked:
            logits = logits.masked_fill(~torch.as_tensor(allowed), -torch.inf)
        logp_all = torch.log_softmax(logits, -1)
        logp = logp_all.gather(1, actions.view(-1, 1)).squeeze(1)
        if masked:  # p log p is 0 where p = 0: the -inf log p is kept out of the product and its gradient
            safe = torch.where(torch.as_tensor(allowed), logp_all, torch.zeros(()))
            return logp, -(logp_all.exp() * safe).sum(-1).mean()
        return logp, -(logp_all.exp() * logp_all).sum(-1).mean()

    def _gae(self, trajs: list[Trajectory], values: np.ndarray) -> np.ndarray:
        """Generalised advantage estimates (module docstring), the batch's steps in order."""
        out, start = [], 0
        for t in trajs:
            v = np.append(values[start:start + t.steps].astype(np.float64), 0.0)
            delta = t.rewards + self.gamma * v[1:] - v[:-1]
            adv, running = np.zeros(t.steps), 0.0
            for k in range(t.steps - 1, -1, -1):
                running = delta[k] + self.gamma * self.gae_lambda * running
                adv[k] = running
            out.append(adv)
            start += t.steps
        return np.concatenate(out)

    def update(self, trajectories: list[list[Trajectory]]) -> dict[str, float]:
        """One REINFORCE step on the round's episodes (module docstring); returns its figures:
        loss, value_loss (MSE, seconds^2), entropy (nats, mean over states), grad_norm and
        value_grad_norm (total L2 norms before clipping; the latter only with the value baseline),
        lr (the policy's rate used) and approx_kl (policy after vs before the step, nats).
        Nothing (an empty dict) when no episode took a step."""
        trajs = [t for per_actor in trajectories for t in per_actor if t.steps > 0]
        if not trajs:
            return {}
        obs = torch.as_tensor(np.concatenate([t.obs for t in trajs]), dtype=torch.float32)
        actions = torch.as_tensor(np.concatenate([t.actions for t in trajs]))
        g_np = np.concatenate([returns_to_go(t.rewards, self.gamma) for t in trajs])
        returns = torch.as_tensor(g_np, dtype=torch.float32)
        step_idx = np.concatenate([np.arange(t.steps) for t in trajs])

        # Baseline b(s_t) and the advantage A_t = G_t - b(s_t).
        figures: dict[str, float] = {}  # read-outs only (diagnostics): they change nothing above
        value_loss = torch.zeros(())
        if self.baseline == "value":
            v = self.value(obs).squeeze(-1)
            advantages = returns - v.detach() if self.gae_lambda == 1.0 else \
                torch.as_tensor(self._gae(trajs, v.detach().numpy()), dtype=torch.float32)
            value_loss = ((v - returns) ** 2).mean()
            self.value_optimizer.zero_grad()
            value_loss.backward()
            value_grad_norm = nn.utils.clip_grad_norm_(self.value.parameters(), self.grad_clip * 10)
            self.value_optimizer.step()
            figures["value_grad_norm"] = value_grad_norm.item()
        else:
            b = self.mean_baseline[np.minimum(step_idx, len(self.mean_baseline) - 1)]
            advantages = returns - torch.as_tensor(b, dtype=torch.float32)
            for t in range(len(self.mean_baseline)):
                at_t = g_np[step_idx == t]
                if len(at_t):
                    self.mean_baseline[t] = (self.mean_decay * self.mean_baseline[t]
                                             + (1 - self.mean_decay) * at_t.mean())
        if len(advantages) > 1:
            advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)

        # Policy gradient step: maximise E[log pi(a|s) A] plus a little entropy (masks: _log_pi).
        allowed = np.concatenate([t.allowed_actions(self.spec.n_actions) for t in trajs])
        masked = not allowed.all()
        logp, entropy = self._log_pi(obs, actions, allowed, masked)
        loss = -(logp * advantages).mean() - self.entropy_coef * entropy
        if self.lr_half_life > 0:
            for group in self.optimizer.param_groups:
                group["lr"] = self.current_lr()
        self.optimizer.zero_grad()
        loss.backward()
        grad_norm = nn.utils.clip_grad_norm_(self.policy.parameters(), self.grad_clip)  # the norm before clipping
        self.optimizer.step()
        logp = logp.detach()  # pi_old of the further passes (the approx_kl below compares with it too)
        for _ in range(self.update_epochs - 1):
            logp_k, entropy_k = self._log_pi(obs, actions, allowed, masked)
            ratio = (logp_k - logp).exp()
            surrogate = torch.minimum(ratio * advantages, ratio.clamp(1 - self.clip, 1 + self.clip) * advantages)
            self.optimizer.zero_grad()
            (-surrogate.mean() - self.entropy_coef * entropy_k).backward()
            nn.utils.clip_grad_norm_(self.policy.parameters(), self.grad_clip)
            self.optimizer.step()
        self.updates += 1

        # Diagnostics (CleanRL's): how far the step moved the policy on this batch's states and actions,
        # approx_kl = mean[(ratio - 1) - log ratio], ratio = pi_new(a|s) / pi_old(a|s) (Schulman's k3 estimator).
        with torch.no_grad():
            log_ratio = self._log_pi(obs, actions, allowed, masked)[0] - logp
            approx_kl = ((log_ratio.exp() - 1) - log_ratio).mean()
        return {"loss": loss.item(), "value_loss": value_loss.item(), "entropy": entropy.item(),
                "grad_norm": grad_norm.item(), **figures, "lr": float(self.optimizer.param_groups[0]["lr"]),
                "approx_kl": approx_kl.item()}

    def imitate(self, demos: list[Trajectory]) -> dict[str, float]:
        """Behaviour cloning on a teacher's episodes (module docstring: warm start): the policy's
        cross-entropy to the teacher's actions (smoothed over each state's allowed actions; a step
        whose action the mask forbade is left out), the value network's MSE to their returns.
        Returns the final loss, the share of steps where the greedy policy takes the teacher's
        action (`imitation_accuracy`) and the number of steps."""
        trajs = [t for t in demos if t.steps > 0]
        if not trajs:
            raise ValueError("imitation needs at least one demonstrated step")
        n = self.spec.n_actions
        allowed = np.concatenate([t.allowed_actions(n) for t in trajs])
        actions = np.concatenate([t.actions for t in trajs]).astype(np.int64)
        keep = allowed[np.arange(len(actions)), actions]
        obs = torch.as_tensor(np.concatenate([t.obs for t in trajs])[keep], dtype=torch.float32)
        allowed, actions = torch.as_tensor(allowed[keep]), torch.as_tensor(actions[keep])
        returns = torch.as_tensor(np.concatenate([returns_to_go(t.rewards, self.gamma) for t in trajs])[keep],
                                  dtype=torch.float32)
        if len(actions) == 0:
            raise ValueError("imitation: every demonstrated action was masked")
        target = allowed.float() / allowed.sum(-1, keepdim=True) * self.imitation_smoothing
        target[torch.arange(len(actions)), actions] += 1.0 - self.imitation_smoothing
        # Optimizers of its own: reinforcement learning starts with fresh moments (and its lr schedule).
        opt = torch.optim.Adam(self.policy.parameters(), lr=self.lr)
        value_opt = torch.optim.Adam(self.value.parameters(), lr=self.value_lr)
        for _ in range(self.imitation_epochs):
            logp = torch.log_softmax(self.policy(obs).masked_fill(~allowed, -torch.inf), -1)
            loss = -(target * torch.where(allowed, logp, torch.zeros(()))).sum(-1).mean()
            opt.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(self.policy.parameters(), self.grad_clip)
            opt.step()
            if self.baseline == "value":
                value_loss = ((self.value(obs).squeeze(-1) - returns) ** 2).mean()
                value_opt.zero_grad()
                value_loss.backward()
                nn.utils.clip_grad_norm_(self.value.parameters(), self.grad_clip * 10)
                value_opt.step()
        with torch.no_grad():
            greedy = self.policy(obs).masked_fill(~allowed, -torch.inf).argmax(-1)
        return {"imitation_loss": loss.item(), "imitation_accuracy": float((greedy == actions).float().mean()),
                "imitation_steps": int(len(actions))}

    # -- persistence ----------------------------------------------------------------------
    def hparams(self) -> dict[str, Any]:
        return {"hidden": self.hidden, "lr": self.lr, "value_lr": self.value_lr, "gamma": self.gamma,
                "batch_episodes": self.batch_episodes, "entropy_coef": self.entropy_coef,
                "baseline": self.baseline, "mean_decay": self.mean_decay, "grad_clip": self.grad_clip,
                "lr_half_life": self.lr_half_life, "update_epochs": self.update_epochs, "clip": self.clip,
                "gae_lambda": self.gae_lambda, "warm_start": self.warm_start,
                "warm_start_episodes": self.warm_start_episodes,
                "imitation_epochs": self.imitation_epochs, "imitation_smoothing": self.imitation_smoothing,
                "seed": self.seed}

    def tensors(self) -> dict[str, np.ndarray]:
        return {f"policy.{k}": v.detach().numpy().copy() for k, v in self.policy.state_dict().items()}

    def set_tensors(self, tensors: dict[str, np.ndarray]) -> None:
        sd = self.policy.state_dict()
        want = {f"policy.{k}": tuple(v.shape) for k, v in sd.items()}
        got = {k: tuple(v.shape) for k, v in tensors.items()}
        if want != got:
            raise ValueError(f"policy tensors {got} do not match the network {want}")
        self.policy.load_state_dict({k: torch.from_numpy(np.array(tensors[f"policy.{k}"])) for k in sd})

    def checkpoint(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        tensors = {f"train/value.{k}": v.detach().numpy().copy() for k, v in self.value.state_dict().items()}
        tensors.update(_optim_tensors("optim", self.optimizer))
        tensors.update(_optim_tensors("value_optim", self.value_optimizer))
        tensors["train/mean_baseline"] = self.mean_baseline.copy()
        return tensors, {"updates": self.updates}

    def load_checkpoint(self, tensors: dict[str, np.ndarray], state: dict[str, Any]) -> None:
        """Value network, both optimizers' moments and the baseline from a checkpoint."""
        self.value.load_state_dict({k: torch.from_numpy(np.array(tensors[f"train/value.{k}"]))
                                    for k in self.value.state_dict()})
        _load_optim("optim", self.optimizer, tensors)
        _load_optim("value_optim", self.value_optimizer, tensors)
        self.mean_baseline = np.array(tensors["train/mean_baseline"], np.float64)
        self.updates = int(state.get("updates", 0))
