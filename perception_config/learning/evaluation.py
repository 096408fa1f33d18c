"""Evaluation: every agent on the same test episodes at every noise level (the paper's Fig. 5).

`evaluate(...)` runs each agent (the given policies or agent names, plus the baselines: the
oracle, a few fixed engineer pipelines, the untrained random agent) on the episodes of the
TEST image ids only (the seeded split of `episodes.split_image_keys`, with the same seed and
fraction as the training run), for each noise level lambda. The comparison is paired: at a
given lambda every agent sees the same episodes with the same episode seeds, hence the same
initial hypothesis. Episode seeds depend on the episode, not on lambda, so the hypotheses of
one episode at growing lambda lie along the same random direction (common random numbers:
smoother curves over lambda, and the Fig. 4 grid shows one hypothesis moving away).

Success accounting. An episode succeeds when a pick succeeds within `max_ops` operations.
`ops_to_success` and `time_to_success` are statistics over the SUCCESSFUL episodes only
(operations counted up to and including the successful pick; time = the seconds the
environment charged, failed picks included at their robot attempt cost); `success` is the
share of episodes that succeeded, and must be read next to them: an agent that solves only
the easy episodes looks fast. Over ALL episodes: `episode_time`, the seconds charged (a
failed episode at the time it used up), and `episode_cost`, minus the return (episode_time
plus the env's truncation penalty for giving up); the best fixed pipeline is the one with the
lowest mean episode_cost. `first_pick_success` is the share of all episodes whose first
attempted pick succeeded (an episode without any pick attempt counts as a miss).

Outputs in `out/`:
- results.json   list of records, one per (agent, lambda) (schema in `summarise`)
- meta.json      settings: dataset, split, test image ids, pipeline, seeds, definitions
- episodes.jsonl one line per (agent, lambda, episode): action trace, poses, errors
- bop/<agent>-lam<x>_<dataset>-<split>.csv  BOP results of the final poses, one file per (agent,
  lambda), named as bop_toolkit's parser reads `{method}_{dataset}-{split}.csv`: no '.' and no
  '_' in the method (lambda 0.5 is written lam0p5), the dataset folder's name without '_', '-'
  or '.'; each (image, object) evaluated once (a plan cycling over the test episodes keeps its
  first pass in the CSV)
- bop/targets_<dataset>-<split>.json  bop_toolkit's test_targets_bop19.json format (im_id,
  inst_count, obj_id, scene_id) for exactly the episodes of the CSVs: pass its absolute path
  as eval_calc_errors/eval_calc_scores' --targets_filename (bop_toolkit_eval.py does)
- fig5.png, lambda_grid.png, episode_*.png   plots (see core/plots.py)
- episodes.sqlite the episode store (store/episode_store.py): every episode played, appended as it ends
  (source "evaluate"; a second evaluation into the same folder adds to it); a store that fails
  is one log line on stderr, the evaluation goes on

Parallel: `workers` N > 1 (or `ray_address`) plays the sweep as Ray tasks (learning/ray_workers.py), each
a chunk of one (agent, lambda)'s planned episodes; a worker rebuilds the agent from its snapshot
(the oracle searches in the worker's env) and its env from the dataset path, the pipeline and the
test image ids. Every episode carries its seeds, so the records are the same as in-process, in
cost-table mode bit for bit (Open3D then runs on one thread here and in the workers).
"""
from __future__ import annotations

import json
import math
import os
import re as _re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from ..agents.base import EnvRecipe
from ..agents.policy_settings import is_policy_file, policy_settings
from ..blocks.pipeline import Pipeline, load_pipeline, pipeline_reference
from ..core.geometry import LAMBDA_MAX, Pose, check_noise_lambda
from ..core.metrics import (
    VSD_DELTA,
    VSD_TAUS,
    average_recall_mspd,
    average_recall_mssd,
    average_recall_vsd,
    pose_errors,
    recall,
)
from ..datasets.bop import BopDataset
from ..datasets.bop_results import BopResult, write_results_csv
from ..rl.env import PerceptionConfigEnv, normalise_score
from ..rl.episode_loop import Trajectory, acting_seed, play_episode
from ..rl.episodes import EpisodeSource, split_image_keys
from ..store.episode_store import STORE_NAME, StoreWriter, policy_version, store_episode
from ..util.atomic_file import atomic_write
from ..util.open3d_threads import open3d_single_thread
from .ray_workers import RayRunner, chunks, ray_wanted, rebuild, snapshot, worker_env

DEFAULT_LAMBDAS: tuple[float, ...] = tuple(round(0.1 * i, 1) for i in range(1, 11))
# Engineer pipelines evaluated as baselines; those naming actions the pipeline lacks are skipped.
DEFAULT_FIXED_SEQUENCES: tuple[tuple[str, ...], ...] = (
    ("icp_coarse", "icp_fine", "pick"),
    ("icp_coarse", "pick"),
    ("d2co", "icp_fine", "pick"),
    # The cell pipeline's ground-truth-free engineer sequences: refine, pick, and on a failed
    # pick the next ranked candidate (or another generator: ppf, global registration) and again.
    ("icp_coarse", "icp_fine", "pick", "next_candidate"),
    ("icp_fine", "pick", "next_candidate"),
    ("icp_coarse", "icp_fine", "pick", "ppf"),
    ("icp_coarse", "icp_fine", "pick", "global_registration"),
)
RECALL_MSSD_THRESHOLD = 0.1  # share of the diameter, the simulated pick's tolerance
MM = 1000.0

DEFINITIONS = {
    "ops_to_success": "operations up to and including the successful pick; successful episodes only",
    "time_to_success": "seconds charged by the environment (failed picks at their robot cost); "
                       "successful episodes only",
    "episode_time": "seconds charged, all episodes (a failed episode at the time it used up)",
    "episode_cost": "minus the return: episode_time plus the truncation penalty of failed episodes",
    "success": "share of episodes with a successful pick within max_ops",
    "first_pick_success": "share of all episodes whose first attempted pick succeeded",
    "recall_mssd": f"share of final poses with MSSD < {RECALL_MSSD_THRESHOLD} x diameter, strictly as every "
                   "recall here and in bop_toolkit (no pose: miss)",
    "ar_mssd": "BOP AR_MSSD: recall (error < threshold) averaged over 0.05..0.5 x diameter; "
               "bop_toolkit's figure on bop/*.csv",
    "ar_mspd": "BOP AR_MSPD: recall (error < threshold) averaged over 5..50 px x width / 640; "
               "bop_toolkit's figure on bop/*.csv",
    "ar_vsd": f"BOP AR_VSD: recall (error < threshold) averaged over thresholds 0.05..0.5 and taus 0.05..0.5 x "
              f"diameter, delta {VSD_DELTA * MM:g} mm (frames with depth); bop_toolkit's figure on bop/*.csv",
    "ar": "BOP's overall AR (bop19_average_recall): the mean of ar_vsd, ar_mssd and ar_mspd (frames with depth)",
    "errors": "BOP errors of the final poses, episodes with a pose: mm, degrees, px",
}


@dataclass
class EvalAgent:
    """An agent under evaluation: its report name, its kind (random, fixed, oracle, pg, ...)."""

    name: str
    kind: str
    agent: Any  # an agents.Agent, or any object with act(obs, info) (begin_episode/observe optional)
    version: str | None = None  # a policy file's version (episode_store.policy_version); None for the others


# --------------------------------------------------------------------------- small helpers


def episode_seed(seed: int, j: int) -> int:
    """The seed of the j-th evaluation episode (the same at every lambda and for every agent)."""
    return int(np.random.SeedSequence([int(seed), int(j)]).generate_state(1)[0] % 2**31)


def _finite_or_none(x: Any) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def _stats(values: Sequence[float]) -> dict[str, float | None]:
    """mean, q1, median, q3 of the finite values (None when there are none)."""
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return {"mean": None, "q1": None, "median": None, "q3": None}
    q1, med, q3 = np.percentile(v, [25, 50, 75])
    return {"mean": float(v.mean()), "q1": float(q1), "median": float(med), "q3": float(q3)}


def _mean_median(values: Sequence[float | None]) -> dict[str, float | None]:
    s = _stats([x for x in values if x is not None])
    return {"mean": s["mean"], "median": s["median"]}


def _pose_json(pose: Pose | None) -> dict[str, list[float]] | None:
    if pose is None:
        return None
    return {"R": [float(x) for x in pose.R.reshape(-1)], "t": [float(x) for x in pose.t]}


def pose_from_json(d: dict[str, list[float]] | None) -> Pose | None:
    """The inverse of the pose entries of episodes.jsonl (R row-major, t metres)."""
    if d is None:
        return None
    return Pose(np.asarray(d["R"]).reshape(3, 3), np.asarray(d["t"]))


def _errors(pose: Pose | None, gt: Pose, model: Any, K: np.ndarray,
            depth: np.ndarray | None = None) -> dict[str, Any]:
    """BOP errors of a hypothesis in report units (mm, degrees, px); None for no hypothesis.
    With the frame's depth also "vsd": one error per tau of BOP's 0.05..0.5 x diameter, delta
    15 mm (None for no hypothesis)."""
    keys = ("add_mm", "adi_mm", "mssd_mm", "mspd_px", "re_deg", "te_mm") + (("vsd",) if depth is not None else ())
    if pose is None or not pose.is_valid():
        return dict.fromkeys(keys)
    e = pose_errors(pose, gt, model, K, depth)
    out: dict[str, Any] = {
        "add_mm": _finite_or_none(e["add"] * MM), "adi_mm": _finite_or_none(e["adi"] * MM),
        "mssd_mm": _finite_or_none(e["mssd"] * MM), "mspd_px": _finite_or_none(e["mspd"]),
        "re_deg": _finite_or_none(math.degrees(e["re"])), "te_mm": _finite_or_none(e["te"] * MM),
    }
    if "vsd" in e:
        out["vsd"] = [float(v) for v in e["vsd"]]
    return out


def _confidence(scores: dict[str, float], pipeline: Pipeline) -> float:
    """A BOP score in [0, 1] for a final hypothesis, from its own scores only (no ground
    truth): the mean of the normalised scores, flipped where lower is better."""
    ranges, lower = pipeline.score_ranges, pipeline.lower_is_better
    vals = [1.0 - normalise_score(v, ranges.get(k)) if k in lower else normalise_score(v, ranges.get(k))
            for k, v in scores.items() if math.isfinite(v)]
    return float(np.mean(vals)) if vals else 0.0


def _slug(name: str) -> str:
    """A bop_toolkit method name: letters, digits, '+' and '-' only (its parser cuts the file
    name at the first '.' and splits it at '_')."""
    return _re.sub(r"[^A-Za-z0-9+-]+", "-", name).strip("-") or "agent"


def bop_dataset_name(name: str) -> str:
    """The dataset part of a bop_toolkit file name: the dataset folder's name without '_', '-'
    and '.' (bop_toolkit reads `{method}_{dataset}-{split}` and finds the dataset at
    BOP_PATH/<dataset>: a folder whose name has those characters must be linked under this one)."""
    return _re.sub(r"[^A-Za-z0-9]+", "", name) or "dataset"


# --------------------------------------------------------------------------- agents


def fixed_sequences(pipeline: Pipeline,
                    sequences: Iterable[Sequence[str]] = DEFAULT_FIXED_SEQUENCES) -> list[tuple[str, ...]]:
    """The engineer sequences whose actions all exist in the pipeline."""
    names = set(pipeline.action_names)
    return [tuple(s) for s in sequences if set(s) <= names]


def _policy_name(path: Path, kind: str) -> str:
    """A report name for a policy file: kind:<file stem>, or kind:<folder> for training's
    policy.* files (one run per folder)."""
    label = path.parent.name if path.stem == "policy" and path.parent.name else path.stem
    return kind if label == kind else f"{kind}:{label}"


def build_agents(
    env: PerceptionConfigEnv, policies: Sequence[Any], seed: int, include_baselines: bool = True,
    sequences: Iterable[Sequence[str]] = DEFAULT_FIXED_SEQUENCES, oracle_budget: int | None = None,
) -> list[EvalAgent]:
    """The agents to evaluate: policy files (checked against the env's action set), agent
    names, or (name, agent) pairs / objects with `act`; then the baselines (oracle, the fixed
    pipelines, random) unless already given; `oracle_budget`: the oracle's operator calls per
    episode (its `node_budget`; default 2000)."""
    from .. import agents

    out: list[EvalAgent] = []
    for spec in policies:
        if isinstance(spec, tuple) and len(spec) == 2 and hasattr(spec[1], "act"):
            out.append(EvalAgent(str(spec[0]), "custom", spec[1]))
        elif hasattr(spec, "act"):
            out.append(EvalAgent(str(getattr(spec, "name", type(spec).__name__)), "custom", spec))
        elif is_policy_file(spec):
            agent = agents.load_agent(Path(spec), env)
            out.append(EvalAgent(_policy_name(Path(spec), agent.kind), agent.kind, agent, policy_version(spec)))
        elif isinstance(spec, str):
            if spec not in agents.AGENTS:
                hint = f" and there is no file {spec}" if (os.sep in spec or "." in spec) else ""
                raise ValueError(f"unknown agent {spec!r}{hint}; known agents: {', '.join(sorted(agents.AGENTS))}")
            out.append(EvalAgent(spec, spec, agents.make_agent(spec, env=env, seed=seed)))
        else:
            raise ValueError(f"cannot evaluate {spec!r}: give a policy file, an agent name or an agent")
    names = [a.name for a in out]
    if len(set(names)) != len(names):
        raise ValueError(f"two agents under evaluation have the same name: {names}")
    if include_baselines:
        if "oracle" not in names:
            budget = {} if oracle_budget is None else {"node_budget": int(oracle_budget)}
            out.append(EvalAgent("oracle", "oracle", agents.make_agent("oracle", env=env, seed=seed, **budget)))
        for seq in fixed_sequences(env.pipeline, sequences):
            name = "fixed:" + "+".join(seq)
            if name not in names:
                out.append(EvalAgent(name, "fixed", agents.make_agent("fixed", env=env, seed=seed, sequence=list(seq))))
        if "random" not in names:
            out.append(EvalAgent("random", "random", agents.make_agent("random", env=env, seed=seed)))
    if not out:
        raise ValueError("nothing to evaluate: no policies given and include_baselines is off")
    return out


# --------------------------------------------------------------------------- episodes


class _Duck:
    """An object with only `act` (a custom agent) under the episode loop's agent interface."""

    def __init__(self, agent: Any) -> None:
        self.agent = agent

    def begin_episode(self, seed: int | None = None) -> None:
        if hasattr(self.agent, "begin_episode"):
            self.agent.begin_episode(seed)

    def act(self, obs: np.ndarray, info: dict[str, Any]) -> int:
        return self.agent.act(obs, info)

    def observe(self, *args: Any) -> None:
        if hasattr(self.agent, "observe"):
            self.agent.observe(*args)


def episode_record(env: PerceptionConfigEnv, agent: Any, index: int, lam: float, ep_seed: int,
                   on_trajectory: Callable[[Trajectory], None] | None = None) -> dict[str, Any]:
    """Play one evaluation episode (the agent's acting randomness seeded from the episode
    seed, so every agent's run of an episode is reproducible whatever ran before it); the
    per-episode record: trace, poses, scores, errors. `on_trajectory` gets the trajectory
    (evaluate stores it in the episode store)."""
    from ..agents.base import Agent

    player = agent if isinstance(agent, Agent) else _Duck(agent)
    traj = play_episode(env, player, {"episode": int(index), "lambda": float(lam), "episode_seed": int(ep_seed)},
                        acting_seed(ep_seed))
    if on_trajectory is not None:
        on_trajectory(traj)
    ep = env.episode
    assert ep is not None
    info = traj.final_info
    initial, final = traj.initial_info["pose"], info["pose"]
    model, gt, K = ep.model, ep.ground_truth, ep.frame.K
    scene_id, im_id, obj_id = ep.key
    rec: dict[str, Any] = {
        "episode": int(index), "episode_seed": int(ep_seed), "lambda": float(lam),
        "scene_id": int(scene_id), "im_id": int(im_id), "obj_id": int(obj_id),
        "instance": int(env.source.episodes[int(index)].index),
        "diameter_mm": float(model.diameter * MM), "image_width": int(ep.frame.width),
        "actions": traj.names, "seconds": [float(x) for x in traj.seconds], "ok": traj.oks,
        "success": traj.success, "ops": traj.steps, "time": traj.time, "cost": traj.cost,
        "generation_time": float(traj.initial_info.get("generation_seconds", 0.0)),
        "first_pick_success": traj.first_pick_success,
        "final_scores": {k: _finite_or_none(v) for k, v in info["scores"].items()},
        "confidence": _confidence(info["scores"], env.pipeline),
        "initial_pose": _pose_json(initial), "final_pose": _pose_json(final),
    }
    masked = [n for n, m in zip(env.action_names, env.frame_mask()) if not m]
    if masked:  # actions that could not run on this frame (depth actions on RGB-only data)
        rec["masked_actions"] = masked
    search = getattr(agent, "last_result", None)  # the oracle's search of this episode
    if search is not None and hasattr(search, "exact"):
        rec["search"] = {"found": bool(search.found), "exact": bool(search.exact),
                         "evaluations": int(search.evaluations)}
    if gt is not None:
        rec["initial_errors"] = _errors(initial, gt, model, K)
        rec["final_errors"] = _errors(final, gt, model, K, ep.frame.depth if ep.frame is not None else None)
    return rec


def summarise(agent: str, lam: float, episodes: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The record of one (agent, lambda):

    agent, lambda, episodes (count), success (share within max_ops), n_success,
    ops_to_success / time_to_success {mean, q1, median, q3} over the successful episodes
    (seconds), episode_time and episode_cost (time + truncation penalty: minus the return)
    {mean, q1, median, q3} over all episodes, first_pick_success
    (share), and BOP errors of the final poses {mean, median}: mssd_mm, mspd_px, add_mm, adi_mm,
    re_deg, te_mm (episodes without a pose are left out), recall_mssd (share with MSSD < 0.1
    diameter; no pose = miss), ar_mssd / ar_mspd (BOP average recalls), initial_recall_mssd; with depth
    also ar_vsd and ar (BOP's overall AR, the mean of the three).
    """
    n = len(episodes)
    ok = [e for e in episodes if e["success"]]
    rec: dict[str, Any] = {
        "agent": agent, "lambda": float(lam), "episodes": n,
        "success": len(ok) / n if n else 0.0, "n_success": len(ok),
        "ops_to_success": _stats([e["ops"] for e in ok]),
        "time_to_success": _stats([e["time"] for e in ok]),
        # with the first generator call, which the episode's time leaves out (common to all agents;
        # next to nothing for simulated_init, a search for a ground-truth-free generator)
        "time_to_success_with_generation": _stats([e["time"] + e.get("generation_time", 0.0) for e in ok]),
        "episode_time": _stats([e["time"] for e in episodes]),
        "episode_cost": _stats([e["cost"] for e in episodes]),
        "first_pick_success": float(np.mean([e["first_pick_success"] for e in episodes])) if n else 0.0,
    }
    with_err = [e for e in episodes if "final_errors" in e]
    if with_err:
        for key in ("mssd_mm", "mspd_px", "add_mm", "adi_mm", "re_deg", "te_mm"):
            rec[key] = _mean_median([e["final_errors"][key] for e in with_err])

        def err(e: dict[str, Any], which: str, key: str) -> float:
            v = e[which][key]
            return math.inf if v is None else float(v)

        diam = np.array([e["diameter_mm"] for e in with_err])
        final_mssd = np.array([err(e, "final_errors", "mssd_mm") for e in with_err])
        init_mssd = np.array([err(e, "initial_errors", "mssd_mm") for e in with_err])
        rec["recall_mssd"] = float(recall(final_mssd / diam, [RECALL_MSSD_THRESHOLD])[0])
        rec["initial_recall_mssd"] = float(recall(init_mssd / diam, [RECALL_MSSD_THRESHOLD])[0])
        rec["ar_mssd"] = average_recall_mssd(final_mssd, diam)
        # BOP scales the MSPD thresholds with the image width (all frames of a dataset share it)
        width = int(with_err[0].get("image_width", 640))
        rec["ar_mspd"] = average_recall_mspd([err(e, "final_errors", "mspd_px") for e in with_err], width)
        if all("vsd" in e["final_errors"] for e in with_err):  # frames with depth: VSD and BOP's overall AR
            rows = [e["final_errors"]["vsd"] or [1.0] * len(VSD_TAUS) for e in with_err]  # no pose = miss
            rec["ar_vsd"] = average_recall_vsd(rows)
            rec["ar"] = float(np.mean([rec["ar_vsd"], rec["ar_mssd"], rec["ar_mspd"]]))
    return rec


def bop_results(episodes: Sequence[dict[str, Any]]) -> list[BopResult]:
    """BOP results rows of the final poses. bop_toolkit wants one time per image: the time of an
    image is the sum of the times of its episodes (the objects are handled one after another)."""
    image_time: dict[tuple[int, int], float] = {}
    for e in episodes:
        key = (e["scene_id"], e["im_id"])
        image_time[key] = image_time.get(key, 0.0) + e["time"]
    rows = []
    for e in episodes:
        pose = pose_from_json(e["final_pose"])
        if pose is None:
            continue
        rows.append(BopResult(e["scene_id"], e["im_id"], e["obj_id"], e["confidence"], pose,
                              image_time[(e["scene_id"], e["im_id"])]))
    return rows


def bop_csv_name(agent: str, lam: float, dataset_name: str, split: str = "test") -> str:
    """`<method>_<dataset>-<split>.csv` with method = <agent>-lam<lambda, '.' written 'p'>
    (e.g. `oracle-lam0p5_default-test.csv`), as bop_toolkit's inout.parse_result_filename reads it."""
    return f"{_slug(agent)}-lam{format(lam, 'g').replace('.', 'p')}_{bop_dataset_name(dataset_name)}-{_slug(split)}.csv"


def bop_targets_name(dataset_name: str, split: str = "test") -> str:
    """The targets file of the BOP CSVs: `targets_<dataset>-<split>.json`."""
    return f"targets_{bop_dataset_name(dataset_name)}-{_slug(split)}.json"


def first_pass(per_episode: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The episodes of each (agent, lambda) with the first occurrence of every (scene, image,
    object instance) only: what a BOP results file can hold (one estimate per target)."""
    seen: set[tuple[Any, ...]] = set()
    out = []
    for e in per_episode:
        key = (e["agent"], e["lambda"], e["scene_id"], e["im_id"], e["obj_id"], e["instance"])
        if key not in seen:
            seen.add(key)
            out.append(e)
    return out


def bop_targets(episodes: Sequence[dict[str, Any]]) -> list[dict[str, int]]:
    """bop_toolkit's test_targets_bop19.json entries for the evaluated episodes of one (agent,
    lambda): one per (scene, image, object), inst_count = its distinct evaluated instances."""
    instances: dict[tuple[int, int, int], set[int]] = {}
    for e in episodes:
        instances.setdefault((e["scene_id"], e["im_id"], e["obj_id"]), set()).add(e["instance"])
    return [{"im_id": im, "inst_count": len(inst), "obj_id": obj, "scene_id": sc}
            for (sc, im, obj), inst in sorted(instances.items())]


# --------------------------------------------------------------------------- evaluate


def _check_lambdas(lambdas: Iterable[float]) -> list[float]:
    out = [check_noise_lambda(lam) for lam in lambdas]
    if not out:
        raise ValueError("no lambda to evaluate")
    return out


def episode_plan(n_available: int, episodes_per_lambda: int | None, seed: int) -> list[tuple[int, int]]:
    """(episode index, episode seed) of the evaluation episodes, the same at every lambda.
    None = every test episode once; fewer = a seeded random subset; more = cycled (each pass
    with fresh seeds, so the hypotheses differ)."""
    if episodes_per_lambda is None:
        n = n_available
    else:
        n = int(episodes_per_lambda)
        if n < 1:
            raise ValueError(f"episodes_per_lambda must be >= 1, got {episodes_per_lambda}")
    order = np.random.default_rng(seed).permutation(n_available) if n < n_available else np.arange(n_available)
    return [(int(order[j % n_available]), episode_seed(seed, j)) for j in range(n)]


def evaluate(
    dataset: str | Path | BopDataset,
    policies: Sequence[Any] = (),
    lambdas: Sequence[float] = DEFAULT_LAMBDAS,
    out: str | Path = "evaluation",
    episodes_per_lambda: int | None = None,
    seed: int = 0,
    pipeline: str | Path | Pipeline | None = None,
    split_seed: int | None = None,
    test_fraction: float | None = None,
    include_baselines: bool = True,
    progress: bool = True,
    *,
    split: str = "test",
    fixed: Iterable[Sequence[str]] = DEFAULT_FIXED_SEQUENCES,
    plots: bool = True,
    n_example_episodes: int = 2,
    use_depth: bool = True,
    store_episodes: bool = True,
    workers: int | None = None,
    ray_address: str | None = None,
    oracle_budget: int | None = None,
    **env_overrides: Any,
) -> Path:
    """Evaluate agents on the test images at each lambda; write the reports to `out`; return
    the path of results.json. See the module docstring for the outputs and definitions.

    policies: policy files, agent names of `perception_config.agents.AGENTS`, or agent objects
    / (name, agent) pairs. split_seed, test_fraction, pipeline and the environment settings
    default to what the policy files record from training (agents/policy_settings.py: the split, the
    pipeline and max_ops must agree with explicit values; other settings given here, e.g.
    time_mode="cost_table", win and are reported), else 0, 0.3, the shipped pipeline and
    `EnvSettings()`. `env_overrides`: EnvSettings fields. `fixed`: the engineer sequences
    evaluated as baselines (those naming actions the pipeline lacks are skipped; on RGB-only
    frames they skip the actions that cannot run). `use_depth=False` reads a dataset folder as
    RGB-only; every agent then chooses among the actions that can run (`info["action_mask"]`).
    `store_episodes`: append every episode to out/episodes.sqlite. `workers` N > 1 plays the
    episodes as tasks on a local Ray with N workers, `ray_address` on a running cluster (module
    docstring); neither (or N = 1): in this process, without Ray. `oracle_budget`: the oracle's
    operator calls per episode (default 2000; with generators among the actions each call can
    be a search of a second, so the cell pipeline's evaluation gives it fewer).
    """
    lams = _check_lambdas(lambdas)
    if workers is not None and int(workers) < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    out = Path(out)
    settings = policy_settings(policies, split_seed=split_seed, test_fraction=test_fraction, pipeline=pipeline,
                               **env_overrides)
    for note in settings.notes:
        print(f"note: {note}", file=sys.stderr)
    ds = dataset if isinstance(dataset, BopDataset) else BopDataset(Path(dataset), split=split, use_depth=use_depth)
    train_keys, test_keys = split_image_keys(ds.image_keys(), settings.test_fraction, settings.split_seed)
    pipe = settings.pipeline if isinstance(settings.pipeline, Pipeline) else load_pipeline(settings.pipeline)
    env_settings = settings.env.replace(lambda_range=(0.0, LAMBDA_MAX))  # every lambda is set per episode
    source = EpisodeSource(ds, test_keys, min_visib_fract=env_settings.min_visib_fract)
    env = PerceptionConfigEnv(source, pipe, env_settings)
    agents = build_agents(env, policies, seed, include_baselines, fixed, oracle_budget)
    plan = episode_plan(len(source), episodes_per_lambda, seed)

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(agents) * len(lams) * len(plan), desc="evaluate", unit="ep", dynamic_ncols=True)
    records: list[dict[str, Any]] = []
    per_episode: list[dict[str, Any]] = []
    writer = StoreWriter(out / STORE_NAME, lambda line: print(line, file=sys.stderr, flush=True)) \
        if store_episodes else None

    def storer(ea: EvalAgent, ep_seed: int) -> Callable[[Trajectory], None] | None:
        if writer is None:
            return None
        return lambda t: store_episode(writer, t, source="evaluate", agent=ea.name, policy_version=ea.version,
                                       dataset=str(ds.root), episode_seed=ep_seed)

    try:
        if ray_wanted(workers, ray_address):
            pipe_ref = settings.pipeline
            if not isinstance(pipe_ref, Pipeline):
                pipe_ref = pipeline_reference(pipe_ref)
            recipe = EnvRecipe(str(Path(ds.root).resolve()), pipe_ref, tuple(test_keys), split, env_settings,
                               use_depth=bool(getattr(ds, "use_depth", True)))
            sweep = _sweep_on_ray(recipe, agents, lams, plan, workers, ray_address, bar, storer)
        else:
            with open3d_single_thread(env_settings.time_mode == "cost_table"):
                sweep = _sweep_here(env, agents, lams, plan, bar, storer)
        for lam in lams:
            for ea in agents:
                eps = [{"agent": ea.name, **rec} for rec in sweep[(ea.name, lam)]]
                per_episode.extend(eps)
                records.append({**summarise(ea.name, lam, eps), "kind": ea.kind})
    finally:
        if bar is not None:
            bar.close()
        if writer is not None:
            writer.close()
    _mark_best_fixed(records)
    _oracle_ratios(records, per_episode)

    out.mkdir(parents=True, exist_ok=True)
    atomic_write(out / "results.json", json.dumps(records, indent=1, allow_nan=False) + "\n")
    atomic_write(out / "episodes.jsonl", "".join(json.dumps(e, allow_nan=False) + "\n" for e in per_episode))
    es = env.settings
    meta = {
        "dataset": str(ds.root), "split": split, "use_depth": bool(getattr(ds, "use_depth", True)),
        "split_seed": settings.split_seed,
        "test_fraction": settings.test_fraction, "test_images": [list(k) for k in test_keys],
        "n_train_images": len(train_keys), "episodes_per_lambda": len(plan), "seed": seed, "lambdas": lams,
        "time_mode": es.time_mode, "max_ops": es.max_ops, "failed_pick_cost": es.failed_pick_cost,
        "truncation_cost": es.truncation_cost, "min_visib_fract": es.min_visib_fract, "env_settings": es.to_json(),
        "settings_notes": settings.notes, "pipeline": pipe.describe(),
        "agents": [{"name": a.name, "kind": a.kind} for a in agents],
        "definitions": DEFINITIONS,
    }
    atomic_write(out / "meta.json", json.dumps(meta, indent=1, allow_nan=False) + "\n")
    write_bop_csvs(out / "bop", per_episode, Path(ds.root).name, split)
    if plots:
        make_plots(out, records, per_episode, env, lams, plan, n_example_episodes)
    return out / "results.json"


Sweep = dict[tuple[str, float], list[dict[str, Any]]]  # (agent, lambda) -> episode records, plan order
Storer = Callable[[EvalAgent, int], Callable[[Trajectory], None] | None]


def _sweep_here(env: PerceptionConfigEnv, agents: Sequence[EvalAgent], lams: Sequence[float],
                plan: Sequence[tuple[int, int]], bar: Any, storer: Storer) -> Sweep:
    """Every (agent, lambda)'s planned episodes in this process."""
    out: Sweep = {}
    for lam in lams:
        for ea in agents:
            if bar is not None:
                bar.set_postfix_str(f"{ea.name} lambda={lam:g}")
            eps = out.setdefault((ea.name, lam), [])
            for index, ep_seed in plan:
                eps.append(episode_record(env, ea.agent, index, lam, ep_seed, storer(ea, ep_seed)))
                if bar is not None:
                    bar.update(1)
    return out


def evaluation_chunk(recipe: EnvRecipe, agent: Any, lam: float,
                     plan: Sequence[tuple[int, int]]) -> list[tuple[dict[str, Any], Trajectory]]:
    """A Ray task: one agent (a `ray_workers.snapshot` or a picklable object with `act`) plays
    planned episodes at one lambda in the worker's env; (record, trajectory) per episode."""
    env, spec = worker_env(recipe)
    player = rebuild(agent, spec, env) if isinstance(agent, tuple) else agent
    trajs: list[Trajectory] = []
    recs = [episode_record(env, player, index, lam, ep_seed, trajs.append) for index, ep_seed in plan]
    return list(zip(recs, trajs))


def _sweep_on_ray(recipe: EnvRecipe, agents: Sequence[EvalAgent], lams: Sequence[float],
                  plan: Sequence[tuple[int, int]], workers: int | None, address: str | None, bar: Any,
                  storer: Storer) -> Sweep:
    """The sweep as Ray tasks: each (agent, lambda)'s plan in pieces (ray_workers.chunks)."""
    from ..agents.base import Agent

    with RayRunner(workers, address) as runner:
        recipe_ref = runner.put(recipe)
        pieces = chunks(len(plan), len(agents) * len(lams), runner.cpus)
        refs = [runner.put(snapshot(ea.agent) if isinstance(ea.agent, Agent) else ea.agent) for ea in agents]
        calls, keys = [], []
        for lam in lams:  # the in-process order
            for ea, ref in zip(agents, refs):
                for lo, hi in pieces:
                    calls.append((recipe_ref, ref, lam, list(plan[lo:hi])))
                    keys.append((ea, lam))

        done: dict[int, list[tuple[dict[str, Any], Trajectory]]] = {}
        stored = [0]  # the calls before this one are in the store: it gets the in-process order

        def arrived(k: int, result: list[tuple[dict[str, Any], Trajectory]]) -> None:
            done[k] = result
            while stored[0] in done:
                j = stored[0]
                ea = keys[j][0]
                for (_rec, traj), (_index, ep_seed) in zip(done.pop(j), calls[j][3]):
                    store = storer(ea, ep_seed)
                    if store is not None:
                        store(traj)
                stored[0] += 1
            if bar is not None:
                bar.set_postfix_str(f"{keys[k][0].name} lambda={keys[k][1]:g}")
                bar.update(len(result))

        results = runner.map(evaluation_chunk, calls, arrived)
    out: Sweep = {}
    for (ea, lam), result in zip(keys, results):
        out.setdefault((ea.name, lam), []).extend(rec for rec, _traj in result)
    return out


def _oracle_ratios(records: list[dict[str, Any]], per_episode: Sequence[dict[str, Any]]) -> None:
    """`oracle_ratio` of each agent's record: its mean time to success over the mean of the
    hindsight oracle's on the same episodes (those both succeeded on, paired by lambda, episode
    and seed, the first generator call included); `oracle_ratio_n`: how many. None without an oracle."""
    oracle = {(e["lambda"], e["episode"], e["episode_seed"]): e for e in per_episode
              if e["agent"] == "oracle" and e["success"]}
    for r in records:
        pairs = [(e, oracle[k]) for e in per_episode
                 if e["agent"] == r["agent"] and e["lambda"] == r["lambda"] and e["success"]
                 and (k := (e["lambda"], e["episode"], e["episode_seed"])) in oracle]
        mine = sum(e["time"] + e.get("generation_time", 0.0) for e, _ in pairs)
        best = sum(o["time"] + o.get("generation_time", 0.0) for _, o in pairs)
        r["oracle_ratio"] = mine / best if pairs and best > 0 else None
        r["oracle_ratio_n"] = len(pairs)


def _mark_best_fixed(records: list[dict[str, Any]]) -> None:
    """Flag the fixed pipeline with the lowest mean episode cost over all lambdas (time plus the
    penalty of giving up: a pipeline that fails is not 'fast') as `best_fixed` in its records."""
    fixed = {r["agent"] for r in records if r.get("kind") == "fixed"}
    if not fixed:
        return
    def score(name: str) -> float:
        return float(np.mean([r["episode_cost"]["mean"] for r in records if r["agent"] == name]))
    best = min(sorted(fixed), key=score)
    for r in records:
        if r.get("kind") == "fixed":
            r["best_fixed"] = r["agent"] == best


def write_bop_csvs(folder: Path, per_episode: Sequence[dict[str, Any]], dataset_name: str,
                   split: str = "test") -> list[Path]:
    """One BOP results CSV per (agent, lambda) of the final poses (first pass of each episode),
    and the targets file of those episodes (the same for every agent and lambda: one plan);
    returns the CSV paths."""
    groups: dict[tuple[str, float], list[dict[str, Any]]] = {}
    for e in first_pass(per_episode):
        groups.setdefault((e["agent"], e["lambda"]), []).append(e)
    paths = []
    targets: list[dict[str, int]] | None = None
    for (agent, lam), eps in groups.items():
        path = folder / bop_csv_name(agent, lam, dataset_name, split)
        folder.mkdir(parents=True, exist_ok=True)
        write_results_csv(path, bop_results(eps))
        paths.append(path)
        mine = bop_targets(eps)
        if targets is not None and mine != targets:
            raise ValueError(f"{agent} at lambda {lam:g} was evaluated on other episodes than the first agent")
        targets = mine
    if targets is not None:
        atomic_write(folder / bop_targets_name(dataset_name, split), json.dumps(targets, indent=1) + "\n")
    return paths


def make_plots(
    out: Path, records: list[dict[str, Any]], per_episode: list[dict[str, Any]], env: PerceptionConfigEnv,
    lams: Sequence[float], plan: Sequence[tuple[int, int]], n_examples: int = 2,
) -> list[Path]:
    """fig5.png, lambda_grid.png (the first planned episode) and a few Fig. 2-style episodes."""
    from ..core import plots

    paths = [plots.plot_fig5(records, out / "fig5.png")]
    index, ep_seed = plan[0]
    hyps = []
    for lam in lams:
        _obs, info = env.reset(options={"episode": index, "lambda": lam, "episode_seed": ep_seed})
        hyps.append((lam, info["pose"]))
    ep = env.episode
    assert ep is not None
    if ep.ground_truth is not None:
        paths.append(plots.plot_lambda_grid(ep.frame, ep.model, ep.ground_truth, hyps, out / "lambda_grid.png"))
    for i, e in enumerate(example_episodes(per_episode, n_examples)):
        frame = env.source.frame(e["scene_id"], e["im_id"])
        obj = frame.objects[e["instance"]]
        title = (f"{e['agent']}  lambda={e['lambda']:g}  scene {e['scene_id']} image {e['im_id']} obj {e['obj_id']}\n"
                 f"{' > '.join(e['actions'])}  ({e['time']:.2f} s, {'picked' if e['success'] else 'not picked'})")
        paths.append(plots.plot_episode(frame, obj.model, obj.gt, pose_from_json(e["initial_pose"]),
                                        pose_from_json(e["final_pose"]), title, out / f"episode_{i}.png"))
    return paths


def example_episodes(per_episode: Sequence[dict[str, Any]], n: int = 2) -> list[dict[str, Any]]:
    """Episodes worth a Fig. 2 picture, of the first agent under evaluation that is not a
    baseline (else the oracle), at the middle lambda: the successful one that started furthest
    from the ground truth (MSSD / diameter), then failures. Without a success there, the
    success comes from the nearest lambda with one, else from the oracle."""
    if n <= 0 or not per_episode:
        return []
    names = list(dict.fromkeys(e["agent"] for e in per_episode))
    agent = next((a for a in names if a not in ("random", "oracle") and not a.startswith("fixed:")),
                 "oracle" if "oracle" in names else names[0])
    lams = sorted({e["lambda"] for e in per_episode})
    mid = lams[len(lams) // 2]
    drawable = [e for e in per_episode if e["initial_pose"] and e["final_pose"]]

    def rel_init(e: dict[str, Any]) -> float:
        v = (e.get("initial_errors") or {}).get("mssd_mm")
        return -1.0 if v is None else v / e["diameter_mm"]

    def successes(name: str) -> list[dict[str, Any]]:
        by_lam = sorted(lams, key=lambda lam: abs(lam - mid))
        for lam in by_lam:
            ok = [e for e in drawable if e["agent"] == name and e["lambda"] == lam and e["success"]]
            if ok:
                return sorted(ok, key=rel_init, reverse=True)
        return []

    ok = successes(agent) or successes("oracle")
    failed = [e for e in drawable if e["agent"] == agent and e["lambda"] == mid and not e["success"]]
    chosen = ok[:1] + failed[: n - 1] if failed else ok[:n]
    return (chosen + [e for e in ok if e not in chosen])[:n]


# --------------------------------------------------------------------------- table


def format_table(records: Sequence[dict[str, Any]]) -> str:
    """A plain-text table, grouped by lambda: mean time and ops to success (successful episodes),
    first-pick share, success share and mean episode time (all episodes). '*' marks the best
    fixed pipeline. With a ground-truth-free generator (its first call takes measurable time),
    'gen+time' adds it; 'vs oracle' is the time ratio to the oracle on the episodes both solved."""
    def gen_time(r: dict[str, Any]) -> float | None:
        return (r.get("time_to_success_with_generation") or {}).get("mean")

    show_gen = any(gen_time(r) is not None and r["time_to_success"]["mean"] is not None
                   and gen_time(r) - r["time_to_success"]["mean"] > 0.005 for r in records)
    show_ratio = any(r.get("oracle_ratio") is not None for r in records)
    width = min(60, max([34] + [len(r["agent"]) + 2 for r in records]))
    header = (f"{'lambda':>6}  {'agent':<{width}} {'time s':>8} {'ops':>6} {'1st pick':>8} {'success':>8} "
              f"{'ep. time':>9} {'n':>5}" + (f" {'gen+time':>9}" if show_gen else "")
              + (f" {'vs oracle':>9}" if show_ratio else ""))
    lines = [header, "-" * len(header)]

    def num(x: float | None, fmt: str) -> str:
        return format(x, fmt) if x is not None else "-".rjust(int(fmt.split(".")[0]))

    last = None
    for r in sorted(records, key=lambda r: (r["lambda"],)):
        if last is not None and r["lambda"] != last:
            lines.append("")
        last = r["lambda"]
        name = r["agent"] + (" *" if r.get("best_fixed") else "")
        lines.append(
            f"{r['lambda']:>6.2f}  {name[:width]:<{width}} {num(r['time_to_success']['mean'], '8.3f')} "
            f"{num(r['ops_to_success']['mean'], '6.2f')} {100 * r['first_pick_success']:>7.1f}% "
            f"{100 * r['success']:>7.1f}% {num(r['episode_time']['mean'], '9.3f')} {r['episodes']:>5d}"
            + (f" {num(gen_time(r), '9.3f')}" if show_gen else "")
            + (f" {num(r.get('oracle_ratio'), '8.2f')}x" if show_ratio and r.get("oracle_ratio") is not None
               else f" {'-':>9}" if show_ratio else "")
        )
    lines.append("")
    lines.append("time s / ops: means over successful episodes; ep. time: mean over all episodes; "
                 "* best fixed pipeline")
    if show_gen or show_ratio:
        lines.append("gen+time: time s with the first generator call; vs oracle: time (with the first call) "
                     "over the oracle's on the episodes both picked")
    return "\n".join(lines)


__all__ = [
    "evaluate", "format_table", "summarise", "episode_record", "build_agents", "episode_plan",
    "episode_seed", "bop_results", "bop_csv_name", "bop_dataset_name", "bop_targets", "bop_targets_name",
    "first_pass", "write_bop_csvs", "example_episodes", "fixed_sequences",
    "pose_from_json", "EvalAgent", "DEFAULT_LAMBDAS", "DEFAULT_FIXED_SEQUENCES",
]
