"""Training that never loses work, and repeats itself: a real `perception-config train` process on
the tiny dataset gets SIGINT twice (and more during the save), SIGTERM, SIGHUP, SIGINT while
started with SIGINT ignored, SIGKILL. The policy, history and checkpoint of the last completed
round are written and load, the exit code is 128 + the signal, no worker process survives, the
checkpoint resumes into the uninterrupted run. Seeded cost-table runs repeat bit for bit."""
from __future__ import annotations

import contextlib
import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from perception_config.agents import load_agent
from perception_config.agents.policy_io import read_file
from perception_config.learning.training import CHECKPOINT, CURVE, train
from perception_config.rl.settings import EnvSettings
from rl_helpers import make_env, pipeline_file, tiny_dataset

FAST = EnvSettings(time_mode="cost_table", lambda_range=(0.2, 0.8), max_ops=5)  # the CLI run's settings
ROUND = 8  # pg's default batch_episodes: one round


def _cli_train(tmp_path_factory, out: Path, episodes: int = 100000, workers: int = 2, pipeline: bool = True,
               ignore_sigint: bool = False, extra: tuple[str, ...] = ()) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "perception_config.cli", "train", "--dataset", str(tiny_dataset(tmp_path_factory)),
           "--agent", "pg", "--episodes", str(episodes), "--time-mode", "cost_table", "--max-ops", "5",
           "--lambda-range", "0.2", "0.8", "--workers", str(workers), "--checkpoint-every", str(ROUND),
           "--out", str(out), "--quiet", "--cost-table", "blocks", "--validation-fraction", "0",
           # the agent's own defaults, as the in-process runs they are compared with (not the CLI's recipe)
           "--agent-param", "entropy_coef=0.01", "--agent-param", "lr_half_life=0", *extra]
    if pipeline:
        cmd += ["--pipeline", str(pipeline_file(tmp_path_factory))]

    def dispositions() -> None:
        # The stop signals as a terminal gives them, whatever the test run inherited (under nohup
        # SIGHUP is ignored, and an ignored signal stays ignored across exec, by design);
        # ignore_sigint: as a background job of a script, SIGINT inherited ignored.
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(sig, signal.SIG_DFL)
        if ignore_sigint:
            signal.signal(signal.SIGINT, signal.SIG_IGN)

    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=dispositions)


def _children(pid: int) -> list[int]:
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(entry))
    return out


def _running(pid: int) -> bool:
    """Alive and not a zombie (an orphan's zombie waits for an init that may never reap it)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _wait_for_training(proc: subprocess.Popen, out: Path, workers: int) -> list[int]:
    """Wait until the first round is checkpointed; the training's child processes (with workers:
    Ray's GCS, raylet and helpers)."""
    deadline = time.monotonic() + 120
    while not (out / CHECKPOINT).exists() or len(_children(proc.pid)) < (workers if workers > 1 else 0):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "training did not checkpoint its first round within 120 s"
        time.sleep(0.05)
    return _children(proc.pid)


def _assert_stopped_cleanly(proc: subprocess.Popen, out: Path, children: list[int], signum: int) -> int:
    """Exit code, files and processes after a stop; returns the episodes done."""
    try:
        stdout, stderr = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:  # not stopped: leave no 100000-episode training behind
        for pid in [proc.pid, *_children(proc.pid)]:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        proc.communicate()
        raise AssertionError(f"training did not stop within 60 s of {signal.Signals(signum).name}") from None
    assert proc.returncode == 128 + signum, (proc.returncode, stdout, stderr)
    assert f"stopped by {signal.Signals(signum).name}" in stderr
    deadline = time.monotonic() + 5  # orphans would be running; the resource tracker leaves on EOF
    while any(_running(p) for p in children) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not [p for p in children if _running(p)], "a worker process outlived the training"
    meta, tensors = read_file(out / CHECKPOINT)
    done = meta["trainer"]["episodes_done"]
    assert done >= ROUND and done % ROUND == 0  # whole rounds only
    assert len(tensors["history/return"]) == done
    policy_meta, _ = read_file(out / "policy.safetensors")
    assert policy_meta["extra"]["interrupted"] is True and policy_meta["extra"]["episodes"] == done
    with open(out / "history.csv") as f:
        rows = list(csv.reader(f))
    assert rows[0][0] == "episode" and len(rows) == done + 1
    np.testing.assert_allclose([float(r[1]) for r in rows[1:]], tensors["history/return"], rtol=1e-5)
    assert (out / CURVE).read_bytes()[:4] == b"\x89PNG"
    assert not [p.name for p in out.iterdir() if ".tmp" in p.name], "a temporary file was left behind"
    return done


def test_double_sigint_and_more_during_the_save_keep_the_work_and_resume(tmp_path_factory, tmp_path):
    out = tmp_path / "run"
    proc = _cli_train(tmp_path_factory, out)
    children = _wait_for_training(proc, out, workers=2)
    proc.send_signal(signal.SIGINT)
    time.sleep(0.2)
    # A second Ctrl-C 0.2 s later, then one every 50 ms: some land in the save.
    deadline = time.monotonic() + 30
    while proc.poll() is None and time.monotonic() < deadline:
        proc.send_signal(signal.SIGINT)
        time.sleep(0.05)
    done = _assert_stopped_cleanly(proc, out, children, signal.SIGINT)
    assert load_agent(out / "policy.safetensors", make_env(tmp_path_factory, max_ops=5)).kind == "pg"
    # The dropped round is drawn again: the resumed run is the uninterrupted one.
    kw = {"settings": FAST, "pipeline": pipeline_file(tmp_path_factory), "workers": 1, "progress": False}
    train(tiny_dataset(tmp_path_factory), "pg", out, done + ROUND, resume=True, **kw)
    straight = train(tiny_dataset(tmp_path_factory), "pg", tmp_path / "straight", done + ROUND, **kw)
    _, resumed_tensors = read_file(out / CHECKPOINT)
    _, straight_tensors = read_file(straight.parent / CHECKPOINT)
    np.testing.assert_array_equal(resumed_tensors["history/return"], straight_tensors["history/return"])
    _, a = read_file(out / "policy.safetensors")
    _, b = read_file(straight)
    for k in b:
        np.testing.assert_allclose(a[k], b[k], rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("signum, workers, ignore_sigint", [
    (signal.SIGTERM, 2, False),
    (signal.SIGHUP, 1, False),
    (signal.SIGINT, 1, True),  # started with SIGINT ignored, as a background job of a script
], ids=["sigterm", "sighup", "sigint-inherited-ignored"])
def test_stop_signal_keeps_the_work(tmp_path_factory, tmp_path, signum, workers, ignore_sigint):
    out = tmp_path / "run"
    proc = _cli_train(tmp_path_factory, out, workers=workers, ignore_sigint=ignore_sigint)
    children = _wait_for_training(proc, out, workers=workers)
    proc.send_signal(signum)
    _assert_stopped_cleanly(proc, out, children, signum)


def _descendants(pid: int) -> list[int]:
    parents = {}
    for entry in os.listdir("/proc"):  # one look at /proc: this runs in a polling loop
        if entry.isdigit():
            try:
                parents[int(entry)] = int(Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()[1])
            except OSError:
                continue
    kids: dict[int, list[int]] = {}
    for child, parent in parents.items():
        kids.setdefault(parent, []).append(child)
    out, todo = [], [pid]
    while todo:
        found = kids.get(todo.pop(), [])
        out.extend(found)
        todo.extend(found)
    return out


RAY_AGENTS = (b"ray::DashboardAgent", b"ray::RuntimeEnvAgent")


def test_a_killed_training_orphans_no_worker(tmp_path_factory, tmp_path):
    """SIGKILL of a training on 2 workers: Ray's GCS, raylet and the workers playing episodes end
    with it. Ray's two node agents notice the raylet's death too, but first try for 60 s (a
    timeout fixed in Ray) to report it to the dead GCS: they are the only ones allowed to stay,
    and are ended here."""
    proc = _cli_train(tmp_path_factory, tmp_path / "run")
    # Killed while both workers play the first round's episodes (no need to wait for its checkpoint).
    deadline = time.monotonic() + 120
    while True:
        family = {p: _title(p) for p in _descendants(proc.pid)}
        if sum(t == b"ray::play_chunk" for t in family.values()) >= 2:
            break
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, f"2 workers did not play episodes within 120 s: {family}"
        time.sleep(0.1)  # a look at all of /proc each time
    assert len([t for t in family.values() if t.startswith(b"ray::") and t not in RAY_AGENTS]) >= 2, family
    proc.kill()
    proc.communicate(timeout=30)
    deadline = time.monotonic() + 15
    while any(_running(p) for p, t in family.items() if t not in RAY_AGENTS) and time.monotonic() < deadline:
        time.sleep(0.05)
    left = {p: t for p, t in family.items() if _running(p)}
    for p in left:
        with contextlib.suppress(ProcessLookupError):
            os.kill(p, signal.SIGKILL)
    assert set(left.values()) <= set(RAY_AGENTS), f"a Ray process outlived its SIGKILLed driver: {left}"


def _title(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")[0].split(b" ")[0]
    except OSError:
        return b""


def test_seeded_cost_table_training_repeats_bit_for_bit(tmp_path_factory, tmp_path):
    """The shipped pipeline (ICP and D2CO: Open3D's threads and the blocks' wall-clock bounds made runs
    diverge): the command with two workers, and meanwhile (each loading the machine for the other) the
    same training in this process with one worker, give the same bits."""
    # Two rounds: the second is played by the policy the first round's update made.
    proc = _cli_train(tmp_path_factory, tmp_path / "cli", episodes=2 * ROUND, pipeline=False)
    inproc = train(tiny_dataset(tmp_path_factory), "pg", tmp_path / "inproc", 2 * ROUND, settings=FAST, workers=1,
                   progress=False)
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 0, (stdout, stderr)
    assert (tmp_path / "cli" / "history.csv").read_bytes() == (tmp_path / "inproc" / "history.csv").read_bytes()
    _, a = read_file(tmp_path / "cli" / "policy.safetensors")
    _, b = read_file(inproc)
    assert sorted(a) == sorted(b)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])


def test_cost_table_mode_lifts_the_blocks_wall_clock_bounds(tmp_path_factory):
    """ICP with a 1 ms bound: measured mode stops after the first stage, cost-table mode runs all 4."""
    from rl_helpers import PIPELINE

    text = PIPELINE.replace("final_distance: 0.01, stages: 2, max_seconds: 10.0", "final_distance: 0.01, stages: 4, "
                            "max_seconds: 0.001")
    stages = {}
    for mode in ("measured", "cost_table"):
        env = make_env(tmp_path_factory, text, "bounds.yaml", time_mode=mode)
        env.reset(options={"episode": 0, "lambda": 0.3, "episode_seed": 1})
        stages[mode] = env.unwrapped.ops.apply("icp_coarse").result.info["stages_run"]
    assert stages == {"measured": 1, "cost_table": 4}
