"""The learner's state file and the simulated cell's pacing by it (online/learner_state.py)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time

import pytest

from perception_config.online.learner_state import STATE_FILE, LearnerPace, read_state, write_state


def test_the_state_round_trips_and_anything_else_reads_as_none(tmp_path):
    assert read_state(tmp_path) is None
    write_state(tmp_path, "training", 40, 20, 1)
    s = read_state(tmp_path)
    assert (s["state"], s["stored"], s["every"], s["cycles"], s["pid"]) == ("training", 40, 20, 1, os.getpid())
    with pytest.raises(ValueError, match="idle"):
        write_state(tmp_path, "asleep", 0, 20, 0)
    for bad in ("{", "[]", json.dumps({"state": "busy", "stored": 1, "every": 1, "cycles": 0}),
                json.dumps({"state": "idle", "stored": "1", "every": 1, "cycles": 0}),
                json.dumps({"state": "idle", "stored": True, "every": 1, "cycles": 0})):
        (tmp_path / STATE_FILE).write_text(bad)
        assert read_state(tmp_path) is None, bad


def test_a_link_out_of_the_learn_dir_is_not_written(tmp_path):
    learn, outside = tmp_path / "learn", tmp_path / "outside.json"
    learn.mkdir()
    (learn / STATE_FILE).symlink_to(outside)
    write_state(learn, "idle", 0, 20, 0)
    assert not outside.exists()


def test_pace_holds_an_estimate_while_the_learner_trains_and_not_otherwise(tmp_path):
    pace = LearnerPace(tmp_path, start_wait=0.5, poll=0.02)
    pace(5)  # no learner yet: nothing to wait for
    write_state(tmp_path, "idle", 0, 20, 0)
    pace(5)  # idle, no cycle due
    assert pace.holds == 0
    write_state(tmp_path, "training", 20, 20, 0)
    threading.Timer(0.4, write_state, (tmp_path, "idle", 20, 20, 1)).start()
    calls = []
    t0 = time.monotonic()
    pace(21, lambda: calls.append(1))
    assert 0.35 < time.monotonic() - t0 < 5 and pace.holds == 1 and calls  # `alive` is checked while it waits
    t0 = time.monotonic()
    pace(40)  # due (20 + 20) but never begun: waits `start_wait`, then goes on
    assert 0.45 < time.monotonic() - t0 < 5 and pace.holds == 2 and pace.timeouts == 0
    rec = pace.record()
    assert rec["holds"] == 2 and rec["seconds"] > 0.8


def test_pace_does_not_wait_for_a_learner_that_is_gone(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    write_state(tmp_path, "training", 20, 20, 0)
    record = json.loads((tmp_path / STATE_FILE).read_text())
    (tmp_path / STATE_FILE).write_text(json.dumps({**record, "pid": dead.pid}))
    pace = LearnerPace(tmp_path, poll=0.02)
    t0 = time.monotonic()
    pace(25)
    assert time.monotonic() - t0 < 0.5 and pace.holds == 0


def test_pace_gives_up_after_its_timeout(tmp_path):
    write_state(tmp_path, "training", 20, 20, 0)
    pace = LearnerPace(tmp_path, timeout=0.3, poll=0.02)
    pace(21)
    assert pace.timeouts == 1 and pace.holds == 1
