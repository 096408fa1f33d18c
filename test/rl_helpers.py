"""Shared setup of the environment/agent/training tests: a tiny synthetic dataset (2 scenes x
2 images, generated once per session) and small pipeline YAMLs of fast blocks."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

_CACHE: dict[str, Path] = {}

# Fast actions only (no D2CO): the tests exercise the environment and the agents, not blocks.
# The blocks' wall-clock bounds (max_seconds) are lifted: a bound that cuts a block short on a
# loaded machine (or on a frame's first, cache-building call) would make results depend on
# timing, and the tests rely on the cost-table mode being deterministic.
PIPELINE = """\
generator: {block: simulated_init, params: {noise_lambda: 0.5}}
actions:
  - {name: icp_coarse, block: icp_point_to_plane,
     params: {max_correspondence_distance: 0.03, final_distance: 0.01, stages: 2, max_seconds: 10.0}}
  - {name: icp_fine, block: icp_point_to_plane,
     params: {max_correspondence_distance: 0.01, final_distance: 0.003, stages: 2, max_seconds: 10.0}}
  - {name: depth_refine, block: depth_refine, params: {max_seconds: 10.0}}
  - {name: regenerate, block: simulated_init}
  - {name: pick, block: simulated_pick}
scoring: [psi_d, psi_c, icp_fitness]
"""

# The same blocks, another action set (order and one action differ): policies must not load.
OTHER_PIPELINE = (PIPELINE.replace("  - {name: depth_refine, block: depth_refine, params: {max_seconds: 10.0}}\n", "")
                  .replace("{name: icp_fine,", "{name: icp_finest,"))

# Without ICP: bitwise reproducible in every time mode (Open3D's ICP is only with one thread,
# which the cost-table env sets itself: open3d_threads).
BITWISE_PIPELINE = """\
generator: {block: simulated_init, params: {noise_lambda: 0.5}}
actions:
  - {name: depth_refine, block: depth_refine, params: {max_seconds: 10.0}}
  - {name: regenerate, block: simulated_init}
  - {name: pick, block: simulated_pick}
scoring: [psi_d, psi_c, icp_fitness]
"""

# A cell-like pipeline: a generator that needs no ground truth (its refused call's candidates
# wait for next_candidate), one refiner, the pick.
CELL_PIPELINE = """\
generator: {block: resting_pose}
actions:
  - {name: icp_fine, block: icp_point_to_plane,
     params: {max_correspondence_distance: 0.01, final_distance: 0.003, stages: 2, max_seconds: 10.0}}
  - {name: next_candidate, block: next_candidate}
  - {name: pick, block: simulated_pick}
scoring: [psi_d, icp_fitness]
"""

# Same actions, other scores: a different observation layout.
OTHER_SCORES_PIPELINE = PIPELINE.replace("scoring: [psi_d, psi_c, icp_fitness]", "scoring: [psi_d, icp_fitness]")


def tiny_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """2 scenes x 2 images of the synthetic generator, once per test session."""
    if "tiny" not in _CACHE:
        from perception_config.datasets.synthetic import generate

        out = tmp_path_factory.mktemp("rl_data") / "tiny"
        generate(out, scenes=2, images_per_scene=2, seed=0, progress=False)
        _CACHE["tiny"] = out
    return _CACHE["tiny"]


def pipeline_file(tmp_path_factory: pytest.TempPathFactory, text: str = PIPELINE, name: str = "pipeline.yaml") -> Path:
    key = f"pipe:{name}"
    if key not in _CACHE:
        path = tmp_path_factory.mktemp("rl_pipe") / name
        path.write_text(text)
        _CACHE[key] = path
    return _CACHE[key]


def make_env(tmp_path_factory: pytest.TempPathFactory, text: str = PIPELINE, name: str = "pipeline.yaml", **kw: Any):
    """A cost-table PerceptionConfigEnv over the tiny dataset (deterministic)."""
    from perception_config.rl.env import PerceptionConfigEnv

    kw.setdefault("time_mode", "cost_table")
    return PerceptionConfigEnv(tiny_dataset(tmp_path_factory), pipeline_file(tmp_path_factory, text, name), **kw)


def same_run(a: Path, b: Path) -> None:
    """Two training run folders with the same history and checkpoint, bit for bit."""
    import numpy as np

    from perception_config.agents.policy_io import read_file
    from perception_config.learning.training import CHECKPOINT

    assert (a / "history.csv").read_bytes() == (b / "history.csv").read_bytes()
    _, ta = read_file(a / CHECKPOINT)
    _, tb = read_file(b / CHECKPOINT)
    assert sorted(ta) == sorted(tb)
    for k in ta:
        np.testing.assert_array_equal(ta[k], tb[k], err_msg=k)


def own_ray_task_processes(title: str) -> dict[int, int]:
    """{pid: parent pid} of the processes titled Ray's `ray::<task>` (the workers running that
    task now) that descend from this test process: its local Ray or cluster_utils cluster, never
    another Ray on the machine (a user's training, a concurrent test run)."""
    import os

    parents, titles = {}, {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
                cmd = Path(f"/proc/{entry}/cmdline").read_bytes()
            except OSError:
                continue
            parents[int(entry)] = int(stat.rsplit(")", 1)[1].split()[1])
            titles[int(entry)] = cmd
    me, out = os.getpid(), {}
    for pid, cmd in titles.items():
        if cmd.startswith(title.encode()):
            up = parents.get(pid, 0)
            for _ in range(64):  # bounded: a snapshot of /proc taken while processes come and go
                if up <= 1 or up == me:
                    break
                up = parents.get(up, 0)
            if up == me:
                out[pid] = parents[pid]
    return out


# What an evaluation measures on the wall clock (different in every run by nature): the measured
# wall time of the episodes beside the charged time, and the seconds best_static's and
# best_threshold's searches took.
WALL_FIELDS = ("measured_time", "measured_time_to_success", "measured_episode_time", "seconds")


def _without_wall_clock(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _without_wall_clock(v) for k, v in value.items()
                if not (k in WALL_FIELDS and (k != "seconds" or "sequences" in value or "rules" in value))}
    if isinstance(value, list):
        return [_without_wall_clock(v) for v in value]
    return value


def same_evaluation(results_a: Path, results_b: Path) -> None:
    """Two evaluate() outputs give the same figures: results.json and episodes.jsonl equal, value
    for value (JSON numbers as written, so bit for bit), except the wall-clock fields (WALL_FIELDS),
    which must be there in both."""
    import json

    a, b = json.loads(results_a.read_text()), json.loads(results_b.read_text())
    assert all("measured_time_to_success" in r for r in a + b)
    assert _without_wall_clock(a) == _without_wall_clock(b)
    lines_a = [json.loads(x) for x in (results_a.parent / "episodes.jsonl").read_text().splitlines()]
    lines_b = [json.loads(x) for x in (results_b.parent / "episodes.jsonl").read_text().splitlines()]
    assert all("measured_time" in e for e in lines_a + lines_b)
    assert _without_wall_clock(lines_a) == _without_wall_clock(lines_b)
