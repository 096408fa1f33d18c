"""A configurator with `learn:=true` stops cleanly on SIGTERM or SIGINT, whatever its learner
process is doing: starting up, idle, or mid-cycle (training a candidate).

SIGTERM to the process group (what `timeout`, systemd and container runtimes send) reaches the
node and its learner at once; the learner dies where it stands. The node must still end within
5 s (it once hung on the multiprocessing Event it shared with the learner), and the episode store
and the policy versions must stay intact: the store passes SQLite's integrity check and every
version loads. The learn directories are made from the tiny dataset's recorded estimates; a
cycle is started without operator nodes by storing one more estimate row (the learner counts
the store's rows), so no estimate is needed.
"""
from __future__ import annotations

import os
import shutil
import signal
import sqlite3
import time
from pathlib import Path

import pytest

from learn_helpers import learner_log, make_data, make_recorded, record_like_the_configurator
from ros_helpers import NodeProcess, wait_until

STOP_WITHIN = 5.0  # s


@pytest.fixture(scope="module")
def data(synthetic_dataset, tmp_path_factory):
    return make_data(synthetic_dataset, tmp_path_factory)


@pytest.fixture(scope="module")
def recorded(data, tmp_path_factory):
    return make_recorded(data, tmp_path_factory)


def _one_more_estimate(store: Path) -> None:
    """Store a copy of the first estimate's row: the learner sees a new estimate and starts a cycle."""
    with sqlite3.connect(store, timeout=5.0) as db:
        cols = [r[1] for r in db.execute("PRAGMA table_info(episodes)") if r[1] != "id"]
        db.execute(f"INSERT INTO episodes ({', '.join(cols)}) SELECT {', '.join(cols)} FROM episodes "
                   "ORDER BY id LIMIT 1")


def _intact(learn: Path, data, stored: int) -> None:
    from perception_config.agents import load_agent
    from perception_config.online.policy_learner import POLICIES, PolicyVersions

    with sqlite3.connect(f"file:{learn / 'episodes.sqlite'}?mode=ro", uri=True) as db:
        assert db.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        assert db.execute("SELECT COUNT(*) FROM episodes").fetchone()[0] >= stored
    versions = PolicyVersions(learn / POLICIES)
    kept = [v["version"] for v in versions.list()]
    assert kept and kept[0] == "v0000", kept
    for version in kept:
        load_agent(versions.path(version), data["env"])


# rounds of the four cases (the suite runs one; PERCEPTION_CONFIG_SIGTERM_ROUNDS=10 for a measurement)
ROUNDS = int(os.environ.get("PERCEPTION_CONFIG_SIGTERM_ROUNDS", "1"))


@pytest.mark.ros
@pytest.mark.parametrize("round_", range(ROUNDS))
def test_sigterm_or_sigint_stops_a_learning_configurator_within_5_s(data, recorded, tmp_path, round_):
    """Four configurators started together (one start-up's time): SIGTERM to the group while the
    learner starts, while it is idle and while it trains; SIGINT to the node alone while it trains
    (what `perception-config launch` sends). Each exits 0 within 5 s, no learner left behind."""
    common = {"models_dir": data["root"] / "models", "pipeline": data["pipeline"], "publish_debug": "false",
              "learn": "true", "learn_every": 1, "learn_train_episodes": 100000}
    cases = {"starting": signal.SIGTERM, "idle": signal.SIGTERM, "mid-cycle": signal.SIGTERM,
             "mid-cycle, SIGINT to the node": signal.SIGINT}
    learn, nodes, stored = {}, {}, {}
    for case in cases:
        learn[case] = tmp_path / case.replace(" ", "_").replace(",", "")
        stored[case] = record_like_the_configurator(learn[case], data, recorded, ["icp_coarse", "icp_fine", "pick"])
        nodes[case] = NodeProcess("configurator_node", {**common, "learn_dir": str(learn[case])}, tmp_path,
                                  own_group=True)
    try:
        wait_until(lambda: "learner process" in nodes["starting"].output(), 90.0, "starting: no learner process")
        code, took = nodes["starting"].signal_group(signal.SIGTERM, STOP_WITHIN)  # the learner is importing
        assert code == 0 and took < STOP_WITHIN, (code, took, nodes["starting"].output())
        print(f"learning configurator, starting: SIGTERM -> exit {code} in {took:.2f} s")
        _intact(learn["starting"], data, stored["starting"])
        for case in ("idle", "mid-cycle", "mid-cycle, SIGINT to the node"):
            wait_until(lambda c=case: "learner: started" in learner_log(learn[c]), 90.0, f"{case}: no learner")
        for case in ("mid-cycle", "mid-cycle, SIGINT to the node"):
            _one_more_estimate(learn[case] / "episodes.sqlite")
        for case in ("mid-cycle", "mid-cycle, SIGINT to the node"):
            wait_until(lambda c=case: "learner: training a candidate" in learner_log(learn[c]), 30.0,
                  f"{case}: the learner did not start a cycle")
        time.sleep(1.0)  # into the training
        for case in ("idle", "mid-cycle", "mid-cycle, SIGINT to the node"):
            node = nodes[case]
            pid = node.proc.pid
            learner = [int(line.split("learner process ")[1].split()[0]) for line in node.output().splitlines()
                       if "learner process " in line]
            if cases[case] == signal.SIGINT:
                start = time.monotonic()
                node.proc.send_signal(signal.SIGINT)
                node.proc.wait(STOP_WITHIN + 5)
                code, took = node.proc.returncode, time.monotonic() - start
            else:
                code, took = node.signal_group(signal.SIGTERM, STOP_WITHIN)
            assert code == 0 and took < STOP_WITHIN, (case, code, took, node.output())
            print(f"learning configurator, {case}: {cases[case].name} -> exit {code} in {took:.2f} s")
            assert learner and not Path(f"/proc/{learner[0]}").exists(), f"{case}: the learner outlived node {pid}"
            _intact(learn[case], data, stored[case])
    finally:
        for node in nodes.values():
            node.stop()
    shutil.rmtree(tmp_path, ignore_errors=True)
