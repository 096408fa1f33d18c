"""Online learning behind the configurator: train candidates on stored estimates, promote only winners.

The configurator (`learn: true`, ros/configurator_node.py) stores every estimate in
`<learn_dir>/episodes.sqlite` (store/episode_store.py) and its camera frame in `<learn_dir>/frames/`
(store/frames.py). This module is the other half, run in a separate process (`run_learner`,
started with multiprocessing "spawn", niced, torch and Open3D on one thread) so that it never
delays `estimate_pose`: it only reads the store and the frames and writes policy files.

One learning cycle, every `every` new stored estimates (`learn_once`):
1. the replayable episodes: stored configurator estimates whose frame file is kept and that can
   be judged: the frame carries the estimated object's ground truth (replayed ground truth, the
   stronger label: the simulated pick judges), or the robot's own pick outcomes of that object in
   that frame agree and include a picked pose (online/pick_labels.py: a replayed pick succeeds
   near a pose the robot picked; a cell without ground truth learns from its robot's picks).
   Such an episode needs a generator that needs no ground truth (the cell pipeline);
2. a candidate: REINFORCE (agents/policy_gradient.py, trained with training.play_round and the
   agent's own update, the same code as `perception-config train`) continued from the learner's
   own weights of the previous cycle while the same version serves (`candidates/learner.safetensors`:
   a candidate that lost keeps learning instead of starting again), else from the serving
   version's weights, or a fresh pg when the serving version has none (the fixed pipeline); it
   plays `train_episodes` episodes on the stored frames: with fresh episode seeds (new initial
   hypotheses) when the generators are cheap draws (simulated_init), with the stored seeds when
   a generator searches the frame (resting_pose, ppf, global_registration: their results are
   reused for a repeated call, operators.GeneratorMemo, so a cycle pays each search once, not
   once per training episode);
   The replayable episodes are split by frame (online/promotion_gate.py: a stable share
   `check_fraction` of the frames is held out); the candidate trains on the others only;
3. the replay check: the serving version and the candidate (both greedy) play the newest
   `check_episodes` stored episodes of the check frames in-process, same operators, same frames,
   same lambda, the stored episode seeds and acting seeds (episode_loop.acting_seed); time is the
   cost table (env time_mode "cost_table"), so both are charged the same seconds for the same
   actions and the comparison is not a race against the machine's load. The blocks keep their
   own time bounds (`max_seconds`, as in the cell: an unbounded global registration took 7 s
   a call against its 1 s), and a generator's result is reused for the same call, so the serving
   version and the candidate meet the same hypotheses. Cost =
   the env's: charged seconds + failed-pick robot time + truncation penalty (Trajectory.cost);
   a cycle with fewer than 15 check episodes on 5 check frames trains nothing and waits;
4. the gate (promotion_gate.paired_gate): promoted only if the per-frame paired cost difference
   is below zero at 95 % confidence, the mean cost below (1 - margin) x the serving one, the
   successes not fewer and at least one of them confirmed (ground truth, or a pose the robot
   reported picked; not the learned score alone): the file is kept as the next version (util/versions.PolicyVersions),
   with the gate's figures; otherwise the candidate is deleted.
Each cycle reports one line (`format_result`), the line the configurator logs:
    learner: candidate from N episodes: cost X vs serving Y -> promoted vN | discarded (the gate's
    reason: difference D s, 95 % upper bound U s over F held-out frames; successes S vs T[, C of
    them confirmed: shown when some are not])
A failure (the store locked or corrupt, a frame file unreadable, training raising) is one line
`learner: no candidate: <reason>; serving vN unchanged`; the worker keeps running.

When the pipeline scores pick_success, each cycle first refits that score (online/score_learner.py:
candidates checked on held-out stored frames, promoted by the same margin, versions in
`<learn_dir>/pick_success/`), then trains the policy candidate on the score that then serves.

The learner reads and writes only inside `learn_dir` (the store, the frames, the versions, the
candidate, learner.log): a symbolic link leading out of it is refused (util/confine.py), the
cycle fails naming the path and where it leads, and nothing is read or written outside.
"""
from __future__ import annotations

import dataclasses
import os
import signal
import sqlite3
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..agents import Agent, EnvSpec, make_agent
from ..agents.policy_io import load_agent, policy_info, save_agent
from ..blocks.base import GROUND_TRUTH
from ..blocks.pick_success import follow_score_versions
from ..blocks.pipeline import load_pipeline
from ..datasets.bop_models import ModelFolder
from ..rl.env import PerceptionConfigEnv
from ..rl.episode_loop import acting_seed, play_episode
from ..rl.operators import Episode, GeneratorMemo, InProcessOperators
from ..rl.settings import EnvSettings
from ..store.episode_store import STORE_NAME, EpisodeStore, EpisodeStoreError
from ..store.frames import frame_path, load_frame
from ..util.confine import confined
from ..util.versions import PolicyVersionError, PolicyVersions
from .learner_link import LearnerEnd
from .learner_state import write_state
from .pick_labels import PickLabels, robot_labels
from .promotion_gate import (
    CHECK_EPISODES,
    CHECK_FRACTION,
    MIN_CHECK_EPISODES,
    MIN_CHECK_FRAMES,
    is_check_frame,
    paired_gate,
)
from .score_learner import SCORES, format_score_result, pick_success_block, refit_score_once

__all__ = ["PolicyVersions", "LearnerSettings", "learn_once", "run_learner", "format_result"]

POLICIES = "policies"
FRAMES = "frames"
LEARNER_LOG = "learner.log"
CANDIDATES = "candidates"
LEARNER_FILE = "learner.safetensors"  # the learner's weights, continued cycle after cycle while one version serves
MIN_EPISODES = 2  # replayable episodes a candidate needs at least


@dataclass
class LearnerSettings:
    """What the learner needs to rebuild the configurator's environment in-process."""

    models_dir: str
    pipeline: str | None  # a pipeline reference (blocks.pipeline.pipeline_reference) or None: the default
    env_settings: dict[str, Any]  # EnvSettings.to_json() of the serving environment
    margin: float = 0.05
    every: int = 20
    train_episodes: int = 200
    check_episodes: int = CHECK_EPISODES
    check_fraction: float = CHECK_FRACTION
    seed: int = 0
    poll_seconds: float = 0.25
    extra: dict[str, Any] = field(default_factory=dict)  # recorded in each candidate's metadata

    def env(self, learn_dir: str | Path | None = None) -> PerceptionConfigEnv:
        """The serving environment in cost-table time, its blocks bounded by their own time limits
        as in the cell (module docstring); its pick_success score follows the score versions of
        `learn_dir` (online/score_learner.py)."""
        settings = EnvSettings.from_json(self.env_settings, "learner settings").replace(time_mode="cost_table")
        pipeline = load_pipeline(self.pipeline)
        if learn_dir is not None:
            follow_score_versions(pipeline, Path(learn_dir) / SCORES)
        return PerceptionConfigEnv(None, pipeline, settings, operators=InProcessOperators(pipeline, time_bounded=True))


class LearnError(RuntimeError):
    """A cycle that produced no candidate; the message says why."""


# -- the stored episodes ---------------------------------------------------------------------
def replayable_episodes(learn_dir: Path, models: ModelFolder, limit: int | None = None,
                        log: Callable[[str], None] = lambda s: None, robot_labels_ok: bool = True,
                        score: bool = False, stats: dict[str, int] | None = None) -> tuple[list[Episode], int]:
    """The stored configurator estimates that can be replayed in-process, newest last, at most
    `limit` (the newest); and how many estimates were looked at. An estimate is replayable when
    its frame is kept and either holds the object's ground truth (the stronger label: the
    simulated pick judges) or, `robot_labels_ok` (a generator that needs no ground truth), the
    robot's pick outcomes of that object in that frame agree (online/pick_labels.py) and include
    a picked pose, or any outcome when the pipeline has the learned pick-success score (`score`).
    `stats` (when given) counts them: ground_truth, robot, conflicting, unlabelled."""
    stats = stats if stats is not None else {}
    for k in ("ground_truth", "robot", "conflicting", "unlabelled"):
        stats.setdefault(k, 0)
    try:
        with EpisodeStore(confined(learn_dir / STORE_NAME, learn_dir, "episode store"), readonly=True,
                          busy_timeout=2.0) as store:
            rows = store.query(
                "SELECT id, frame_stamp_ns, obj_id, noise_lambda, episode_seed FROM episodes "
                "WHERE source = 'configurator' AND frame_stamp_ns IS NOT NULL AND episode_seed IS NOT NULL "
                "AND obj_id IS NOT NULL ORDER BY id DESC")
            labels = robot_labels(store) if robot_labels_ok else {}
    except (sqlite3.Error, OSError, EpisodeStoreError, ValueError) as exc:  # ValueError: a link out of learn_dir
        raise LearnError(f"episode store {learn_dir / STORE_NAME} cannot be read: {exc}") from None
    frames: dict[int, Any] = {}
    judged: dict[tuple[int, int], PickLabels | None] = {}
    out: list[Episode] = []
    for eid, stamp, obj_id, lam, seed in rows:
        if limit is not None and len(out) >= limit:
            break
        if stamp not in frames:
            path = frame_path(learn_dir / FRAMES, stamp)
            frames[stamp] = None
            if path.exists():
                try:
                    frames[stamp] = load_frame(path, root=learn_dir)
                except ValueError as exc:
                    log(f"learner: skipped {exc}")
        loaded = frames[stamp]
        if loaded is None:
            continue  # no frame kept: not replayable
        frame, gt = loaded
        model = models.model(str(obj_id))
        truth, robot = gt.get(int(obj_id)), None
        if truth is None:
            key = (int(stamp), int(obj_id))
            if key not in judged:
                judged[key] = _usable_labels(labels.get(key), model, score, stats)
            robot = judged[key]
            if robot is None:
                continue
        stats["ground_truth" if truth is not None else "robot"] += 1
        out.append(Episode(frame=frame, model=model, ground_truth=truth, labels=robot,
                           noise_lambda=float(lam if lam is not None else 0.5), seed=int(seed),
                           key=(0, int(eid), int(obj_id)), stamp_ns=int(stamp)))
    out.reverse()
    return out, len(rows)


def _usable_labels(labels: PickLabels | None, model: Any, score: bool, stats: dict[str, int]) -> PickLabels | None:
    """The robot labels of one object in one frame when they can judge a replay (module docstring)."""
    if labels is None or not (labels.picked or (score and labels.failed)):
        stats["unlabelled"] += 1
        return None
    if labels.conflict(model) is not None:
        stats["conflicting"] += 1
        return None
    return labels


# -- candidate and replay check ------------------------------------------------------------------
def train_candidate(env: PerceptionConfigEnv, serving_file: Path, episodes: list[Episode], n_episodes: int,
                    seed: int, stop: Callable[[], bool] | None = None) -> Agent:
    """REINFORCE continued from the serving version's weights (a fresh pg when it has none) on
    `n_episodes` episodes drawn from `episodes`, with fresh episode seeds unless a generator
    searches the frame (module docstring); greedy when returned.
    `stop` is asked before each episode of a round (LearnError when it says so): a configurator
    that stops waits for one episode, not a round."""
    from ..learning.training import play_round

    spec = EnvSpec.from_env(env)
    if policy_info(serving_file).get("agent") == "pg":
        learner = load_agent(serving_file, spec, explore=True)
    else:
        learner = make_agent("pg", spec, seed=seed)
    learner.explore = True
    rng = np.random.default_rng(seed)
    blocks = [env.pipeline.generator] + [a.block for a in env.pipeline.actions]
    fresh = not any(GeneratorMemo.applies(b) for b in blocks)
    done = 0
    while done < n_episodes:
        k = learner.episodes_per_actor
        picks = rng.integers(len(episodes), size=k)
        options = [{"episode": dataclasses.replace(episodes[i], seed=int(rng.integers(1, 2**31))) if fresh
                    else episodes[i]} for i in picks]
        act_seeds = rng.integers(2**31, size=(len(learner.actors()), k))
        trajectories: list[list[Any]] = []
        for i, actor in enumerate(learner.actors()):  # play_round's order, one episode at a time
            trajectories.append([])
            for j, opts in enumerate(options):
                if stop is not None and stop():
                    raise LearnError(f"stopped after {done} of {n_episodes} training episodes")
                trajectories[-1].append(play_round(env, [actor], [opts], act_seeds[i:i + 1, j:j + 1])[0][0])
        learner.update(trajectories)
        done += k
    learner.explore = False
    return learner


def replay(env: PerceptionConfigEnv, agent: Agent, episodes: list[Episode],
           confirmed: list[bool] | None = None) -> tuple[list[float], list[bool]]:
    """Cost (charged seconds + failed picks + truncation) and success of `agent` on each stored
    episode, with its stored episode seed and the acting seed derived from it. `confirmed`, when
    given, receives per episode whether its success is confirmed: by the frame's ground truth, or
    at a pose the robot reported picked (PickLabels.confirms), not by the learned score alone."""
    trajectories = [play_episode(env, agent, {"episode": ep}, acting_seed(ep.seed)) for ep in episodes]
    if confirmed is not None:
        confirmed[:] = [bool(t.success) and (ep.ground_truth is not None or (
            ep.labels is not None and bool(t.step_poses) and t.step_poses[-1] is not None
            and ep.labels.confirms(t.step_poses[-1], ep.model))) for ep, t in zip(episodes, trajectories)]
    return [float(t.cost) for t in trajectories], [bool(t.success) for t in trajectories]


def replay_cost(env: PerceptionConfigEnv, agent: Agent, episodes: list[Episode]) -> float:
    """Mean cost of `agent` on the stored episodes (`replay`)."""
    return float(np.mean(replay(env, agent, episodes)[0]))


def split_by_frame(episodes: list[Episode], settings: "LearnerSettings") -> tuple[list[Episode], list[Episode]]:
    """(training, check) episodes: those of check frames (promotion_gate.is_check_frame) are
    never trained on; the check keeps the newest `check_episodes` of them."""
    check = [ep for ep in episodes if is_check_frame(ep.stamp_ns, settings.check_fraction, settings.seed)]
    held = {ep.stamp_ns for ep in check}
    train = [ep for ep in episodes if ep.stamp_ns not in held]
    return train, check[-settings.check_episodes:]


def _save_candidate(agent: Agent, learn_dir: Path, settings: LearnerSettings, extra: dict[str, Any]) -> Path:
    folder = confined(learn_dir / CANDIDATES, learn_dir, "candidates folder")
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "candidate.safetensors"
    save_agent(agent, path, {"env_settings": settings.env_settings, "pipeline": settings.pipeline,
                             **settings.extra, **extra})
    return path


def _kept_learner(learn_dir: Path, serving: str) -> tuple[Path | None, int]:
    """The learner's weights kept by the previous cycle, when they were trained while `serving`
    served (else None: start again from the serving version), and how many episodes they saw."""
    path = confined(learn_dir / CANDIDATES, learn_dir, "candidates folder") / LEARNER_FILE
    if not path.is_file():
        return None, 0
    try:
        extra = policy_info(path).get("extra") or {}
    except (OSError, ValueError):
        return None, 0
    if extra.get("learned_from") != serving:
        return None, 0
    return path, int(extra.get("trained_total") or 0)


def learn_once(learn_dir: str | Path, settings: LearnerSettings, log: Callable[[str], None] = lambda s: None,
               env: PerceptionConfigEnv | None = None, models: ModelFolder | None = None,
               stop: Callable[[], bool] | None = None) -> dict[str, Any]:
    """One cycle (module docstring); the result: outcome "promoted" | "discarded" | "failed",
    episodes, cost, serving_cost, serving (version), version (promoted), reason (failed)."""
    learn_dir = Path(learn_dir)
    serving = None
    try:
        versions = PolicyVersions(learn_dir / POLICIES, root=learn_dir)
        serving = versions.current()
        if serving is None:
            raise LearnError(f"no serving version in {versions.folder}")
        serving_file = versions.path(serving)
        env = env or settings.env(learn_dir)
        models = models or ModelFolder(settings.models_dir)
        stats: dict[str, int] = {}
        episodes, looked = replayable_episodes(
            learn_dir, models, log=log, robot_labels_ok=GROUND_TRUTH not in env.pipeline.generator.inputs,
            score=pick_success_block(env.pipeline) is not None, stats=stats)
        if len(episodes) < MIN_EPISODES:
            raise LearnError(f"{len(episodes)} of {looked} stored estimates can be replayed (a kept frame with the "
                             f"object's ground truth, or agreeing robot pick outcomes: {_label_text(stats)}); "
                             f"at least {MIN_EPISODES} needed")
        train_eps, check = split_by_frame(episodes, settings)
        check_frames = len({ep.stamp_ns for ep in check})
        if len(check) < MIN_CHECK_EPISODES or check_frames < MIN_CHECK_FRAMES:
            raise LearnError(f"too few held-out checks: {len(check)} replayable estimates on {check_frames} check "
                             f"frames (at least {MIN_CHECK_EPISODES} on {MIN_CHECK_FRAMES}); waiting for more")
        if not train_eps:
            raise LearnError("every replayable estimate is on a check frame: nothing to train on")
        started = time.perf_counter()
        kept, trained_before = _kept_learner(learn_dir, serving)
        candidate = train_candidate(env, kept or serving_file, train_eps, settings.train_episodes,
                                    settings.seed + len(episodes), stop)
        trained_total = trained_before + settings.train_episodes
        folder = confined(learn_dir / CANDIDATES, learn_dir, "candidates folder")
        folder.mkdir(parents=True, exist_ok=True)
        save_agent(candidate, folder / LEARNER_FILE,
                   {"env_settings": settings.env_settings, "pipeline": settings.pipeline, **settings.extra,
                    "learned_from": serving, "trained_total": trained_total})
        serving_agent = load_agent(serving_file, env)
        serving_costs, serving_wins = replay(env, serving_agent, check)
        confirmed: list[bool] = []
        costs, wins = replay(env, candidate, check, confirmed)
        gate = paired_gate(costs, serving_costs, wins, serving_wins, [ep.stamp_ns for ep in check],
                           margin=settings.margin, confirmed=confirmed)
        result = {"outcome": "discarded", "episodes": len(check), "trained_on": len(train_eps), "labels": stats,
                  "train_episodes": settings.train_episodes, "trained_total": trained_total, "cost": gate.cost,
                  "serving_cost": gate.serving_cost,
                  "serving": serving, "margin": settings.margin, "gate": gate.to_json(),
                  "seconds": time.perf_counter() - started}
        path = _save_candidate(candidate, learn_dir, settings, {"learned_from": serving, "replay_check": result})
        if gate.promote:
            result["version"] = versions.promote(path, result)
            result["outcome"] = "promoted"
        path.unlink(missing_ok=True)
        return result
    except (LearnError, PolicyVersionError, EpisodeStoreError, sqlite3.Error, OSError, ValueError, RuntimeError,
            KeyError, IndexError) as exc:
        return {"outcome": "failed", "serving": serving, "reason": f"{type(exc).__name__}: {exc}"[:500]}


def _label_text(stats: dict[str, int]) -> str:
    return (f"{stats.get('ground_truth', 0)} by ground truth, {stats.get('robot', 0)} by the robot's picks, "
            f"{stats.get('conflicting', 0)} objects in frames with conflicting robot outcomes left out")


def _confirmed_text(gate: dict[str, Any]) -> str:
    n = int(gate.get("confirmed", -1))
    return f", {n} of them confirmed" if 0 <= n < int(gate["successes"]) else ""


def format_result(r: dict[str, Any]) -> str:
    """The learner's one line per cycle (the configurator logs it; the cell simulation parses it)."""
    if r["outcome"] == "failed":
        return f"learner: no candidate: {r['reason']}; serving {r.get('serving') or 'nothing'} unchanged"
    verdict = f"promoted {r['version']}" if r["outcome"] == "promoted" else "discarded"
    g = r.get("gate") or {}
    why = (f" ({g['reason']}: difference {g['difference']:+.3f} s, {g['confidence']:.0%} upper bound "
           f"{g['upper']:+.3f} s over {g['frames']} held-out frames; successes {g['successes']} vs "
           f"{g['serving_successes']}{_confirmed_text(g)})") if g else ""
    labels = f"; replayed {_label_text(r['labels'])}" if r.get("labels") else ""
    return (f"learner: candidate from {r['episodes']} episodes: cost {r['cost']:.3f} vs serving "
            f"{r['serving_cost']:.3f} -> {verdict}{why}{labels}")


# -- the worker process ----------------------------------------------------------------------
def _stored_count(learn_dir: Path) -> int | None:
    try:
        store = confined(learn_dir / STORE_NAME, learn_dir, "episode store")
        with EpisodeStore(store, readonly=True, busy_timeout=1.0) as db:
            return int(db.query("SELECT COUNT(*) FROM episodes WHERE source = 'configurator'")[0][0])
    except (sqlite3.Error, OSError, EpisodeStoreError, ValueError):  # ValueError: a link out of learn_dir
        return None


def run_learner(learn_dir: str | Path, settings: LearnerSettings, link: LearnerEnd | None = None,
                nice: int = 10) -> None:
    """The worker process: every `settings.every` new stored estimates one `learn_once`; each
    result goes to the configurator through `link` (learner_link.py) and, as its line, to
    `<learn_dir>/learner.log`; its state (idle, training) to `<learn_dir>/learner_state.json`
    (learner_state.py). Ends when the link says stop, or the parent dies. The link's
    ready flag is set once the worker has started (its imports done): before that it has done
    nothing, and its configurator may end it at once instead of waiting for it."""
    learn_dir = Path(learn_dir)
    parent = os.getppid()
    # A launcher stops a node with SIGINT to its whole process group: the configurator ends this
    # process through `stop` (or its death), so Ctrl-C is not ours to handle; SIGTERM still ends it.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        os.nice(nice)
    except OSError:
        pass
    import torch

    torch.set_num_threads(1)
    from ..util.open3d_threads import open3d_single_thread

    def log(line: str) -> None:
        try:
            with open(confined(learn_dir / LEARNER_LOG, learn_dir, "learner log"), "a") as f:
                f.write(f"{time.strftime('%Y-%m-%d %H:%M:%S')} {line}\n")
        except (OSError, ValueError):  # ValueError: a link out of learn_dir, not written
            pass

    def report(kind: str, payload: dict[str, Any]) -> None:
        if link is not None:
            link.send(kind, payload)

    def stopped() -> bool:
        return (link is not None and link.stopped()) or os.getppid() != parent

    env = None
    models = None
    last = None
    log(f"learner: started (pid {os.getpid()}, nice {nice}), a candidate every {settings.every} new estimates")
    try:
        confined(learn_dir / STORE_NAME, learn_dir, "episode store")
    except ValueError as exc:
        log(f"learner: {exc}; no candidate is trained until it is replaced")
    if link is not None:
        link.set_ready()
    cycles = 0
    while not stopped():
        count = _stored_count(learn_dir)
        if count is not None and last is None:
            last = count  # the first cycle comes `every` estimates after the worker started
            write_state(learn_dir, "idle", count, settings.every, cycles)
        if count is not None and count - last >= settings.every:
            last = count
            write_state(learn_dir, "training", count, settings.every, cycles)
            report("status", {"state": "training", "stored": count})
            log(f"learner: training a candidate ({count} estimates stored)")
            try:
                if env is None:
                    env, models = settings.env(learn_dir), ModelFolder(settings.models_dir)
                if pick_success_block(env.pipeline) is not None:
                    with open3d_single_thread(True):
                        scored = refit_score_once(learn_dir, settings.models_dir, settings.margin, settings.seed)
                    log(format_score_result(scored))
                    report("result", scored)
                with open3d_single_thread(True):
                    result = learn_once(learn_dir, settings, log, env=env, models=models, stop=stopped)
            except Exception as exc:  # noqa: BLE001  (the worker must survive any bad cycle)
                result = {"outcome": "failed", "serving": None, "reason": f"{type(exc).__name__}: {exc}"[:500]}
            log(format_result(result))
            report("result", result)
            cycles += 1
            write_state(learn_dir, "idle", count, settings.every, cycles)
            report("status", {"state": "idle", "stored": count})
        if link is not None:
            link.wait(settings.poll_seconds)
        else:
            time.sleep(settings.poll_seconds)
