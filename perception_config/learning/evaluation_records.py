"""The records of an evaluation (learning/evaluation.py): one per played episode
(`episode_record`: the action trace, the poses, scores and BOP errors) and one per (agent,
lambda) (`summarise`: success, time and operations to success, episode time and cost, BOP
errors and average recalls; `DEFINITIONS` says what each figure is), with the ratio to the
oracle's time and the best fixed pipeline marked."""
from __future__ import annotations

import math
from typing import Any, Callable, Sequence

import numpy as np

from ..blocks.pipeline import Pipeline
from ..core.geometry import Pose
from ..core.metrics import (
    VSD_DELTA,
    VSD_TAUS,
    average_recall_mspd,
    average_recall_mssd,
    average_recall_vsd,
    pose_errors,
    recall,
)
from ..core.pose_json import pose_json
from ..rl.env import PerceptionConfigEnv, normalise_score
from ..rl.episode_loop import Trajectory, acting_seed, play_episode
from ..rl.pose_memory import loop_steps

RECALL_MSSD_THRESHOLD = 0.1  # share of the diameter, the simulated pick's tolerance
MM = 1000.0  # millimetres per metre: errors are reported in mm

DEFINITIONS = {
    "ops_to_success": "operations up to and including the successful pick; successful episodes only",
    "time_to_success": "seconds charged by the environment (failed picks at their robot cost); "
                       "successful episodes only",
    "episode_time": "seconds charged, all episodes (a failed episode at the time it used up)",
    "episode_cost": "minus the return: episode_time plus the truncation penalty of failed episodes",
    "measured_time_to_success / measured_episode_time": "the same episodes in measured wall time: the seconds the "
                                                        "operators took on this machine (failed picks at their robot "
                                                        "cost), next to the cost model's seconds they were charged",
    "truncated": "episodes that used up max_ops without a successful pick",
    "loop_truncations": "truncated episodes with a step that repeated an action already taken at the same "
                        "hypothesis (an action that left it unchanged taken again, or a cycle of two come round; "
                        "picks left out)",
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
    kinds = [env.pipeline.action(n).kind.value for n in traj.names]
    failed_picks = sum(1 for p in traj.step_picked if p is False)
    truncated = not traj.success and not traj.stopped and traj.steps >= env.max_ops
    loops = loop_steps(initial, traj.step_poses, traj.names, kinds, float(model.diameter))
    rec: dict[str, Any] = {
        "episode": int(index), "episode_seed": int(ep_seed), "lambda": float(lam),
        "scene_id": int(scene_id), "im_id": int(im_id), "obj_id": int(obj_id),
        "instance": int(env.source.episodes[int(index)].index),
        "diameter_mm": float(model.diameter * MM), "image_width": int(ep.frame.width),
        "actions": traj.names, "seconds": [float(x) for x in traj.seconds], "ok": traj.oks,
        "success": traj.success, "ops": traj.steps, "time": traj.time, "cost": traj.cost,
        "generation_time": float(traj.initial_info.get("generation_seconds", 0.0)),
        "measured_time": float(sum(traj.operation_seconds)) + failed_picks * env.settings.failed_pick_cost,
        "truncated": truncated, "loop_steps": loops, "loop_truncated": truncated and loops > 0,
        "first_pick_success": traj.first_pick_success,
        "final_scores": {k: _finite_or_none(v) for k, v in info["scores"].items()},
        "confidence": _confidence(info["scores"], env.pipeline),
        "initial_pose": pose_json(initial), "final_pose": pose_json(final),
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
    (share), measured_time_to_success / measured_episode_time (the same in measured wall time),
    truncated and loop_truncations (counts), and BOP errors of the final poses {mean, median}:
    mssd_mm, mspd_px, add_mm, adi_mm, re_deg, te_mm (episodes without a pose are left out),
    recall_mssd (share with MSSD < 0.1 diameter; no pose = miss), ar_mssd / ar_mspd (BOP average
    recalls), initial_recall_mssd; with depth also ar_vsd and ar (BOP's overall AR, the mean of the three).
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
        "measured_time_to_success": _stats([e.get("measured_time") for e in ok]),
        "measured_episode_time": _stats([e.get("measured_time") for e in episodes]),
        "truncated": sum(1 for e in episodes if e.get("truncated")),
        "loop_truncations": sum(1 for e in episodes if e.get("loop_truncated")),
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


def oracle_ratios(records: list[dict[str, Any]], per_episode: Sequence[dict[str, Any]]) -> None:
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


def mark_best_fixed(records: list[dict[str, Any]]) -> None:
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
