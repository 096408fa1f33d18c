"""The episode store: played episodes round-trip, WAL + schema version, a SIGKILLed writer loses
no committed episode, unusable files are refused by name, failures never stop the caller, pick
outcomes are checked, exports read back, and training and evaluation write their stores."""
from __future__ import annotations

import csv
import hashlib
import json
import math
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from perception_config import cli
from perception_config.agents import make_agent
from perception_config.core.geometry import Pose
from perception_config.learning.evaluation import evaluate
from perception_config.learning.training import train
from perception_config.rl.episode_loop import play_episode
from perception_config.rl.settings import EnvSettings
from perception_config.store.episode_record import EpisodeRecord, StepRecord, record_from_trajectory
from perception_config.store.episode_store import (
    APPLICATION_ID,
    SCHEMA_VERSION,
    STORE_NAME,
    EpisodeStore,
    EpisodeStoreError,
    StoreWriter,
    store_episode,
)
from perception_config.store.report import export_table, store_info
from rl_helpers import make_env, pipeline_file, tiny_dataset

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def played(tmp_path_factory):
    """Four episodes of the random agent on the tiny dataset (cost-table time, max_ops 6)."""
    env = make_env(tmp_path_factory, max_ops=6)
    agent = make_agent("random", env=env, seed=3)
    out = []
    for j in range(4):
        seed = 100 + j
        traj = play_episode(env, agent, {"episode": j % len(env.source), "lambda": 0.3 + 0.1 * j,
                                         "episode_seed": seed}, 7 + j)
        out.append((traj, seed, env.episode.key))
    return out


def synthetic_record(n_steps: int = 10, obj_id: int = 1) -> EpisodeRecord:
    rng = np.random.default_rng(obj_id)
    steps = [StepRecord(i, "pick" if i == n_steps else "icp", True, 0.1 * i, 0.05, {"psi_d": float(rng.random())},
                        Pose(np.eye(3), rng.normal(size=3)), (i == n_steps) or None,
                        "simulated" if i == n_steps else None) for i in range(n_steps + 1)]
    return EpisodeRecord("test", "v1", "random", "data", 0, 1, obj_id, None, 0.5, "generate", 5, True, True,
                         1.0, 1.0, False, steps)


def test_a_played_episode_round_trips(played, tmp_path):
    store = EpisodeStore(tmp_path / STORE_NAME)
    ids = [store.append(record_from_trajectory(t, source="evaluate", agent="random", policy_version="p1",
                                               dataset="tiny", episode_seed=seed)) for t, seed, _ in played]
    assert ids == sorted(ids) and len(set(ids)) == 4
    for eid, (traj, seed, key) in zip(ids, played):
        rows = list(store.iter_steps("s.episode_id = ?", (eid,)))
        assert [r["step"] for r in rows] == list(range(traj.steps + 1))
        first = rows[0]
        assert (first["episode_scene_id"], first["episode_im_id"], first["episode_obj_id"]) == tuple(key)
        assert first["episode_episode_seed"] == seed and first["episode_source"] == "evaluate"
        assert first["episode_noise_lambda"] == pytest.approx(traj.noise_lambda)
        assert first["episode_success"] == int(traj.success) and first["episode_steps"] == traj.steps
        assert first["episode_time_s"] == pytest.approx(traj.time) and first["episode_cost"] == pytest.approx(traj.cost)
        assert first["episode_generator"] == traj.initial_info["action"] == first["action"]
        assert np.allclose(first["pose"]["R"], traj.initial_info["pose"].R)
        for r, name, ok, sec, sc, pose, picked in zip(rows[1:], traj.names, traj.oks, traj.seconds,
                                                      traj.step_scores, traj.step_poses, traj.step_picked):
            assert (r["action"], r["ok"], r["seconds"]) == (name, int(ok), pytest.approx(sec))
            assert r["scores"] == {k: (v if math.isfinite(v) else None) for k, v in sc.items()}
            if pose is None:
                assert r["pose"] is None
            else:
                assert np.allclose(r["pose"]["R"], pose.R) and np.allclose(r["pose"]["t"], pose.t)
            assert r["picked"] == (None if picked is None else int(picked))
            assert r["pick_source"] == (None if picked is None else "simulated")
    # the random agent picked at least once in these episodes: the pick column is exercised
    assert any(p is not None for t, _, _ in played for p in t.step_picked)
    store.close()


def test_wal_schema_version_and_marker(tmp_path):
    path = tmp_path / STORE_NAME
    with EpisodeStore(path) as store:
        store.append(synthetic_record())
        assert store.journal_mode == "wal"
    db = sqlite3.connect(path)
    assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert db.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
    assert db.execute("PRAGMA application_id").fetchone()[0] == APPLICATION_ID
    cols = [r[1] for r in db.execute("PRAGMA table_info(steps)")]
    assert cols[:10] == ["episode_id", "step", "action", "ok", "seconds", "operation_seconds", "scores", "pose",
                         "picked", "pick_source"]
    db.close()


WRITER = """
import sys
import numpy as np
sys.path.insert(0, {test!r})
from test_episode_store import synthetic_record
from perception_config.store.episode_store import EpisodeStore
store = EpisodeStore({path!r})
i = 0
while True:
    i += 1
    eid = store.append(synthetic_record(n_steps=10, obj_id=i))
    print(eid, flush=True)
"""


def test_a_sigkilled_writer_loses_no_committed_episode(tmp_path):
    path = tmp_path / STORE_NAME
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([sys.executable, "-c", WRITER.format(test=str(ROOT / "test"), path=str(path))],
                            stdout=subprocess.PIPE, env=env, text=True)
    committed = []
    try:
        deadline = time.monotonic() + 60
        while len(committed) < 200 and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            committed.append(int(line))
        os.kill(proc.pid, signal.SIGKILL)  # in the middle of the next appends
    finally:
        proc.kill()
        proc.wait()
    assert len(committed) >= 200, "the writer did not get going"
    with EpisodeStore(path, readonly=True) as store:
        assert store.integrity() == "ok"
        ids = [r[0] for r in store.query("SELECT id FROM episodes ORDER BY id")]
        assert set(committed) <= set(ids)
        per_episode = dict(store.query("SELECT episode_id, COUNT(*) FROM steps GROUP BY episode_id"))
        assert all(per_episode[i] == 11 for i in ids), "an episode was stored without all its steps"
    assert store_info(path)["episodes"] == len(ids)
    with EpisodeStore(path) as store:  # and it takes more
        store.append(synthetic_record())


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_unusable_files_are_refused_by_name_and_left_alone(tmp_path):
    text = tmp_path / "notes.sqlite"
    text.write_text("not a database\n")
    foreign = tmp_path / "foreign.sqlite"
    db = sqlite3.connect(foreign)
    db.execute("CREATE TABLE robots (name TEXT)")
    db.commit()
    db.close()
    newer = tmp_path / "newer.sqlite"
    EpisodeStore(newer).close()
    db = sqlite3.connect(newer)
    db.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    db.commit()
    db.close()
    corrupt = tmp_path / "corrupt.sqlite"
    with EpisodeStore(corrupt) as store:
        store.append(synthetic_record())
    data = bytearray(corrupt.read_bytes())
    data[100:4096] = os.urandom(3996)  # page 1 past the header: the schema
    corrupt.write_bytes(bytes(data))
    for path, words in ((text, "not an SQLite database"), (foreign, "not a perception_config episode store"),
                        (newer, f"schema version {SCHEMA_VERSION + 1}, newer"), (corrupt, "corrupt")):
        before = _digest(path)
        with pytest.raises(EpisodeStoreError, match=words) as exc:
            EpisodeStore(path)
        assert str(path) in str(exc.value)
        logged: list[str] = []
        writer = StoreWriter(path, logged.append)
        assert writer.append(synthetic_record()) is None and writer.append(synthetic_record()) is None
        assert len(logged) == 1 and str(path) in logged[0], logged  # one line, repeats counted
        assert _digest(path) == before, f"{path.name} was changed"
    assert cli.main(["episodes", "info", str(foreign)]) == 2


def test_a_full_disk_and_a_lock_are_one_log_line_and_nothing_stored_is_lost(tmp_path):
    path = tmp_path / STORE_NAME
    logged: list[str] = []
    writer = StoreWriter(path, logged.append, busy_timeout=0.2)
    first = [writer.append(synthetic_record(obj_id=i)) for i in range(3)]
    assert None not in first
    # A full disk: SQLite's page limit stands in for the filesystem's (SQLITE_FULL either way).
    pages = writer.store.query("PRAGMA page_count")[0][0]
    writer.store.query(f"PRAGMA max_page_count = {pages}")
    big = synthetic_record(n_steps=400)
    assert writer.append(big) is None
    assert "full" in logged[-1] and str(path) in logged[-1]
    writer.store.query("PRAGMA max_page_count = 1073741823")
    # Another process holds the write lock longer than busy_timeout.
    other = sqlite3.connect(path, isolation_level=None)
    other.execute("BEGIN EXCLUSIVE")
    t0 = time.perf_counter()
    assert writer.append(synthetic_record()) is None
    assert time.perf_counter() - t0 < 5 and "locked" in logged[-1]
    other.execute("ROLLBACK")
    other.close()
    assert writer.append(synthetic_record(obj_id=9)) is not None
    writer.close()
    with EpisodeStore(path, readonly=True) as store:
        assert store.count() == 4 and store.integrity() == "ok"
        assert [r[0] for r in store.query("SELECT id FROM episodes ORDER BY id")][:3] == first
    assert writer.appended == 4 and writer.failed == 2


def test_pick_outcomes_refuse_unknown_and_duplicated_reports(tmp_path):
    with EpisodeStore(tmp_path / STORE_NAME) as store:
        eid = store.append(synthetic_record(n_steps=3))
        with pytest.raises(EpisodeStoreError, match="no episode 99: an outcome for an unknown estimate"):
            store.record_pick_outcome(99, 3, True, "robot")
        with pytest.raises(EpisodeStoreError, match=f"episode {eid} has no step 7"):
            store.record_pick_outcome(eid, 7, True, "robot")
        with pytest.raises(EpisodeStoreError, match="source must be one of"):
            store.record_pick_outcome(eid, 3, True, "camera")
        store.record_pick_outcome(eid, 3, False, "robot")
        with pytest.raises(EpisodeStoreError, match="duplicated outcome"):
            store.record_pick_outcome(eid, 3, True, "robot")
        step = [r for r in store.iter_steps() if r["step"] == 3][0]
        assert (step["picked"], step["pick_source"]) == (0, "robot")
        assert store.query("SELECT picked, source, previous_picked, previous_source FROM pick_outcomes") == \
            [(0, "robot", 1, "simulated")]


def test_export_csv_and_parquet_read_back_and_cli_info(played, tmp_path, capsys):
    import pyarrow.parquet as pq

    path = tmp_path / STORE_NAME
    writer = StoreWriter(path, print)
    for t, seed, _ in played:
        store_episode(writer, t, source="train", agent="pg", policy_version="a", episode_seed=seed)
    writer.close()
    n_steps = sum(t.steps + 1 for t, _, _ in played)
    for table, n in (("episodes", len(played)), ("steps", n_steps)):
        assert cli.main(["episodes", "export", str(path), "--out", str(tmp_path / f"{table}.csv"),
                         "--table", table]) == 0
        with open(tmp_path / f"{table}.csv", newline="") as f:
            rows = list(csv.DictReader(f))
        assert len(rows) == n
        assert export_table(path, tmp_path / f"{table}.parquet", table) == n
        pt = pq.read_table(tmp_path / f"{table}.parquet")
        assert pt.num_rows == n and pt.column_names == list(rows[0])
    eps = pq.read_table(tmp_path / "episodes.parquet").to_pylist()
    assert [e["episode_seed"] for e in eps] == [seed for _, seed, _ in played]
    assert str(pq.read_table(tmp_path / "episodes.parquet").schema.field("obj_id").type) == "int64"
    steps = pq.read_table(tmp_path / "steps.parquet").to_pylist()
    assert json.loads(steps[1]["scores"]) == json.loads(rows[1]["scores"])
    with pytest.raises(ValueError, match="must end in .csv or .parquet"):
        export_table(path, tmp_path / "x.txt")
    capsys.readouterr()
    assert cli.main(["episodes", "info", str(path)]) == 0
    out = capsys.readouterr().out
    success = np.mean([t.success for t, _, _ in played])
    assert f"schema version {SCHEMA_VERSION}, journal wal" in out
    assert f"{len(played)} episodes, {n_steps} steps" in out
    assert any(line.split()[:3] == ["train", "pg", str(len(played))] and f"{success:.3f}" in line
               for line in out.splitlines()), out


def test_append_cost_of_a_ten_step_episode(tmp_path):
    record = synthetic_record(n_steps=10)
    costs = {}
    for sync in ("NORMAL", "FULL"):
        with EpisodeStore(tmp_path / f"{sync}.sqlite", synchronous=sync) as store:
            store.append(record)
            t0 = time.perf_counter()
            for _ in range(50):
                store.append(record)
            costs[sync] = (time.perf_counter() - t0) / 50 * 1000
    print(f"append of a 10-step episode: {costs['NORMAL']:.2f} ms (NORMAL), {costs['FULL']:.2f} ms (FULL)")
    assert costs["NORMAL"] < 20, costs  # a cost-table training episode takes ~50-500 ms


def test_the_configurators_store_call_never_raises(played, tmp_path):
    traj, seed, _ = played[0]
    logged: list[str] = []
    writer = StoreWriter(tmp_path / STORE_NAME, logged.append, synchronous="FULL")
    eid = store_episode(writer, traj, source="configurator", agent="fixed:icp_coarse+pick", policy_version=None,
                        episode_seed=seed, frame_stamp_ns=1_700_000_000_123, pick_source="robot", image_ids=False)
    row = writer.store.query("SELECT scene_id, im_id, obj_id, frame_stamp_ns, source FROM episodes WHERE id = ?",
                             (eid,))[0]
    assert row[:2] == (None, None) and row[2] == played[0][2][2] and row[3:] == (1_700_000_000_123, "configurator")
    picks = writer.store.query("SELECT DISTINCT pick_source FROM steps WHERE picked IS NOT NULL")
    assert picks in ([], [("robot",)])
    writer.close()
    bad = StoreWriter(tmp_path, logged.append)  # a folder: cannot be a store
    assert not bad.open() and store_episode(bad, traj, source="configurator", agent="x", policy_version=None) is None
    assert store_episode(writer, object(), source="configurator", agent="x", policy_version=None) is None
    assert len(logged) == 2 and str(tmp_path) in logged[0] and "AttributeError" in logged[1], logged


def test_training_and_evaluation_write_their_stores(tmp_path_factory, tmp_path):
    settings = EnvSettings(time_mode="cost_table", lambda_range=(0.2, 0.8), max_ops=5)
    run = tmp_path / "run"
    policy = train(tiny_dataset(tmp_path_factory), "pg", run, 8, settings=settings, seed=0, workers=1,
                   progress=False, agent_kwargs={"batch_episodes": 8}, pipeline=pipeline_file(tmp_path_factory))
    with EpisodeStore(run / STORE_NAME, readonly=True) as store:
        rows = store.query("SELECT source, agent, policy_version, episode_seed, steps, noise_lambda FROM episodes")
        assert len(rows) == 8 and {r[:3] for r in rows} == {("train", "pg", "train:run@0")}
        history = list(csv.DictReader(open(run / "history.csv")))
        assert [r[4] for r in rows] == [int(float(h["steps"])) for h in history]
        assert [r[5] for r in rows] == pytest.approx([float(h["lambda"]) for h in history], rel=1e-5)  # 6 digits
        assert store.count("steps") == sum(r[4] for r in rows) + 8
    out = tmp_path / "eval"
    evaluate(tiny_dataset(tmp_path_factory), [str(policy), "random"], [0.5], out, episodes_per_lambda=2,
             include_baselines=False, progress=False, plots=False)
    records = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    from perception_config.agents.policy_io import read_file

    version = "sha256:" + read_file(policy)[0]["sha256"][:16]
    with EpisodeStore(out / STORE_NAME, readonly=True) as store:
        rows = store.query("SELECT agent, policy_version, episode_seed, obj_id, success, steps FROM episodes "
                           "ORDER BY id")
    assert [(r[0], r[2], r[3], bool(r[4]), r[5]) for r in rows] == \
        [(e["agent"], e["episode_seed"], e["obj_id"], e["success"], e["ops"]) for e in records]
    assert {r[0]: r[1] for r in rows} == {"pg:run": version, "random": None}
