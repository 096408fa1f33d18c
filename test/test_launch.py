"""perception-config launch: real node processes (generation_node) started by the Launcher class
and by the CLI, prefixed log streaming, clean SIGINT shutdown, a dead node reported, a missing
console script refused, and the defaults of the full node set resolved without spawning it."""
from __future__ import annotations

import contextlib
import io
import json
import os
import re
import signal
import subprocess
import time
from pathlib import Path

import pytest

from perception_config import cli
from perception_config.launcher import resolution as launch
from perception_config.launcher.resolution import resolve_nodes
from perception_config.launcher.supervisor import Launcher, NodeSpec, param_value
from ros_helpers import LaunchCli, call, wait_for_service

REPO = Path(__file__).resolve().parents[1]


def _models(folder: Path, n: int) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "models_info.json").write_text(json.dumps({str(i + 1): {"diameter": 100.0} for i in range(n)}))
    return folder


def _script(path: Path, body: str) -> str:
    path.write_text("#!/bin/sh\n" + body)
    path.chmod(0o755)
    return str(path)


# -- the Launcher class with a real generation_node ------------------------------------------
@pytest.fixture(scope="module")
def parts_models(tmp_path_factory) -> Path:
    from perception_config.datasets.parts import write_models

    return write_models(tmp_path_factory.mktemp("parts") / "models")


@pytest.mark.ros
def test_launcher_streams_prefixed_logs_passes_params_and_env_and_stops_cleanly(ros_node, parts_models, tmp_path,
                                                                                 monkeypatch):
    from perception_config_interfaces.srv import GenerateHypothesis
    from rcl_interfaces.srv import GetParameters

    monkeypatch.delenv("PYTHONUNBUFFERED", raising=False)  # the launcher must set it itself
    params_file = tmp_path / "params.yaml"
    params_file.write_text(
        f"generation_node:\n  ros__parameters:\n    models_dir: '{_models(tmp_path / 'other', 1)}'\n"
        "/**:\n  ros__parameters:\n    frame_timeout: 0.25\n"
    )
    out = io.StringIO()
    launcher = Launcher([NodeSpec("generation_node", params={"models_dir": str(parts_models)},
                                  params_file=params_file)],
                        log_dir=tmp_path / "logs", out=out)
    with launcher:
        launcher.wait_for_line("generation_node", "serving generate_hypothesis", timeout=30)
        pid = launcher.pid("generation_node")
        environ = dict(kv.split("=", 1) for kv in Path(f"/proc/{pid}/environ").read_text().split("\0") if "=" in kv)
        assert environ["ROS_DOMAIN_ID"] == os.environ["ROS_DOMAIN_ID"]
        assert environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SYSTEM_DEFAULT"
        assert environ["FASTDDS_DEFAULT_PROFILES_FILE"].endswith("fastdds_profile.xml")
        assert environ["PYTHONUNBUFFERED"] == "1"
        assert os.getsid(pid) != os.getsid(0), "a child must run in its own session"

        service = ros_node.create_client(GenerateHypothesis, "generate_hypothesis")
        params = ros_node.create_client(GetParameters, "generation_node/get_parameters")
        try:
            wait_for_service(ros_node, service, timeout=20)
            answer = call(ros_node, service, GenerateHypothesis.Request(object_id="no_such_object", noise_lambda=0.1))
            assert not answer.success and answer.message  # it answers (and refuses an unknown object)
            wait_for_service(ros_node, params, timeout=20)
            values = call(ros_node, params, GetParameters.Request(names=["models_dir", "frame_timeout"])).values
        finally:
            ros_node.destroy_client(service)
            ros_node.destroy_client(params)
        assert values[0].string_value == str(parts_models), "-p must win over the params file"
        assert values[1].double_value == pytest.approx(0.25), "the params file must reach the node"
        assert launcher.running() == ["generation_node"]
    assert launcher.returncode("generation_node") == 0
    text = out.getvalue()
    assert re.search(r"^\[generation_node\] \[INFO\] .*serving generate_hypothesis", text, re.M), text
    assert "[launch] started generation_node (pid " in text
    assert "[launch] generation_node exited (exit code 0)" in text
    log = (tmp_path / "logs" / "generation_node.log").read_text()
    assert "serving generate_hypothesis" in log and "[generation_node] [INFO]" not in log  # unprefixed in the file


# -- supervision logic with small stand-in executables (fast, no ROS) --------------------------
def test_a_dead_node_stops_the_others_and_a_finished_bag_replay_does_not(tmp_path):
    polite = _script(tmp_path / "polite",
                     "trap 'echo got SIGINT; exit 0' INT\necho up\nwhile true; do sleep 0.05; done\n")
    stubborn = _script(tmp_path / "stubborn", "trap '' INT\necho up\nwhile true; do sleep 0.05; done\n")
    bag = _script(tmp_path / "bag_replay_node", "echo replayed 3 frames\n")
    crash = _script(tmp_path / "crash", "sleep 0.3\necho boom\nexit 3\n")

    out = io.StringIO()
    launcher = Launcher([NodeSpec("polite", polite), NodeSpec("bag_replay_node", bag)], out=out)
    launcher.start()
    try:
        assert launcher.wait(timeout=1.5) is None, out.getvalue()  # the bag finished, the other keeps running
        assert launcher.running() == ["polite"]
        assert "[launch] bag_replay_node finished (exit code 0)" in out.getvalue()
        assert "[bag_replay_node] replayed 3 frames" in out.getvalue()
        launcher.request_stop()
        assert launcher.wait() == 0
    finally:
        launcher.stop()
    assert "[polite] got SIGINT" in out.getvalue() and "[launch] polite exited (exit code 0)" in out.getvalue()

    out = io.StringIO()
    launcher = Launcher([NodeSpec("polite", polite), NodeSpec("stubborn", stubborn), NodeSpec("crash", crash)],
                        out=out, stop_timeout=1.0)
    launcher.start()
    try:
        launcher.wait_for_line("stubborn", "up", timeout=10)
        assert launcher.wait(timeout=20) == 1
        assert launcher.running() == [], "a death must stop the other nodes"
    finally:
        launcher.stop()
    text = out.getvalue()
    assert text.index("[crash] boom") < text.index("[launch] crash died (exit code 3)"), text
    assert "[launch] polite exited (exit code 0)" in text
    assert "[launch] stubborn: killed with SIGKILL after not stopping on SIGINT" in text
    assert launcher.returncode("stubborn") == -signal.SIGKILL

    # Exit code 0 is "finished" only for bag_replay_node: any other node exiting is a death.
    out = io.StringIO()
    launcher = Launcher([NodeSpec("quitter", _script(tmp_path / "quitter", "exit 0\n"))], out=out)
    launcher.start()
    try:
        assert launcher.wait(timeout=20) == 1
    finally:
        launcher.stop()
    assert "[launch] quitter died (exit code 0)" in out.getvalue()


def test_missing_console_script_exits_2_before_starting_anything(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(launch.NODE_EXECUTABLES, "pick", "no_such_pick_node")
    models = _models(tmp_path / "models", 1)
    code = cli.main(["launch", "--nodes", "generation,pick", "--models", str(models)])
    captured = capsys.readouterr()
    assert code == 2
    assert "no_such_pick_node" in captured.err and "./scripts/test.sh" in captured.err
    assert "[launch] started" not in captured.out  # generation_node was not started either


def _gone(pid: int) -> bool:
    """Exited (a zombie counts: in a container nobody may reap an orphan)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except (FileNotFoundError, ProcessLookupError):
        return True


def _cleanup(launcher: "LaunchCli", pid: int | None) -> None:
    """After a failed assertion: Ctrl-C the launcher, then kill it and its node."""
    if launcher.proc.poll() is None:
        os.killpg(launcher.proc.pid, signal.SIGINT)
        try:
            launcher.proc.wait(15)
        except subprocess.TimeoutExpired:
            os.killpg(launcher.proc.pid, signal.SIGKILL)
    if pid is not None and not _gone(pid):
        os.kill(pid, signal.SIGKILL)


@contextlib.contextmanager
def _serving_generation_node(parts_models: Path, cwd: Path, *options: str):
    """`launch --nodes generation` as a process, once its node serves: (launcher, node pid).
    Whatever happens in the block, both are gone after it."""
    launcher = LaunchCli(["--nodes", "generation", "--models", str(parts_models), *options], cwd)
    pid = None
    try:
        pid = int(launcher.wait_for(r"^\[launch\] started generation_node \(pid (\d+)\)").group(1))
        launcher.wait_for(r"^\[generation_node\] .*serving generate_hypothesis")
        yield launcher, pid
    finally:
        _cleanup(launcher, pid)


@pytest.mark.ros
def test_cli_ctrl_c_stops_the_node_cleanly_and_exits_0(parts_models, tmp_path):
    with _serving_generation_node(parts_models, tmp_path, "--log-dir", str(tmp_path / "logs")) as (launcher, pid):
        os.killpg(launcher.proc.pid, signal.SIGINT)  # a terminal's Ctrl-C: the launcher's group only
        code = launcher.finish()
    text = launcher.output()
    assert code == 0, text
    assert "[launch] stopping all nodes" in text and "[launch] generation_node exited (exit code 0)" in text
    assert _gone(pid)
    assert "serving generate_hypothesis" in (tmp_path / "logs" / "generation_node.log").read_text()


@pytest.mark.ros
def test_cli_reports_a_killed_node_as_died_and_exits_1(parts_models, tmp_path):
    with _serving_generation_node(parts_models, tmp_path) as (launcher, pid):
        os.kill(pid, signal.SIGKILL)
        code = launcher.finish()
    assert code == 1, launcher.output()
    assert "[launch] generation_node died (exit code -9: killed by SIGKILL)" in launcher.output()


@pytest.mark.ros
def test_nodes_do_not_outlive_a_killed_launcher(parts_models, tmp_path):
    with _serving_generation_node(parts_models, tmp_path) as (launcher, pid):
        os.killpg(launcher.proc.pid, signal.SIGKILL)  # the launcher's group: not the node's session
        launcher.finish()
        deadline = time.monotonic() + 10
        while not _gone(pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _gone(pid), "the node outlived its launcher"


# -- default resolution of the full node set (command lines only; nothing is spawned) -----------
def _p(spec: NodeSpec) -> dict[str, str]:
    cmd = spec.command()
    return dict(cmd[i + 1].split(":=", 1) for i, a in enumerate(cmd) if a == "-p")


def _policy(path, pipeline: str | None = None, age: float = 0.0):
    """A policy file as training writes it (a fixed agent), recording the pipeline it was trained on."""
    from perception_config.agents.policy_io import FORMAT, write_file

    path.parent.mkdir(parents=True, exist_ok=True)
    env = {"action_names": ["pick"], "action_kinds": ["pick"], "observation_layout": ["progress:step"], "max_ops": 5}
    write_file(path, {"format": FORMAT, "version": 1, "agent": "fixed", "env": env,
                      "extra": {"pipeline": pipeline}})
    os.utime(path, (time.time() - age, time.time() - age))
    return path


def test_defaults_full_set_newest_policy_and_absolute_paths(tmp_path):
    models = _models(tmp_path / "data" / "default" / "models", 2)
    for run, age in (("old", 100), ("new", 10), ("older", 200)):
        _policy(tmp_path / "runs" / run / "policy.safetensors", age=age)
    _policy(tmp_path / "runs" / "cell" / "policy.safetensors", "cell", age=1)  # newest, another pipeline
    broken = tmp_path / "runs" / "broken" / "policy.safetensors"
    broken.parent.mkdir()
    broken.write_bytes(b"x")  # newest of all, unreadable: passed over
    (tmp_path / "replay.mcap").write_bytes(b"")
    said: list[str] = []
    # No --policy: launch refuses, naming the newest policy trained on the pipeline as the candidate
    # (a cell must not start serving a policy nobody chose)
    with pytest.raises(ValueError, match=r"no --policy.*runs/new/policy.safetensors"):
        resolve_nodes(cwd=tmp_path, bag="replay.mcap", rate=2, say=said.append)
    with pytest.raises(ValueError, match=r"newest trained on pipeline cell here is .*runs/cell/policy.safetensors"):
        resolve_nodes(cwd=tmp_path, pipeline="cell", say=said.append)
    with pytest.raises(ValueError, match=r"no runs/\*/policy.safetensors trained on pipeline rgb"):
        resolve_nodes(cwd=tmp_path, pipeline="rgb", say=said.append)
    chosen = tmp_path / "runs" / "old" / "policy.safetensors"
    specs = resolve_nodes(cwd=tmp_path, bag="replay.mcap", rate=2, policy=str(chosen), say=said.append)

    assert [s.name for s in specs] == ["generation_node", "refinement_node", "scoring_node", "pick_node",
                                       "configurator_node", "bag_replay_node"]
    assert [s.executable for s in specs] == [s.name for s in specs]
    for spec in specs[:5]:
        assert spec.command()[:2] == [spec.name, "--ros-args"]
        assert _p(spec)["models_dir"] == str(models.resolve())
    assert "policy" not in _p(specs[0])
    assert _p(specs[4])["policy"] == str(chosen.resolve())
    assert any("runs/old/policy.safetensors" in s for s in said), said
    assert _p(specs[5]) == {"bag": str((tmp_path / "replay.mcap").resolve()), "rate": "2.0"}
    assert specs[5].may_finish and not specs[0].may_finish
    # --pipeline cell: the pipeline to every node
    specs = resolve_nodes(cwd=tmp_path, pipeline="cell", policy="none", say=said.append)
    assert _p(specs[4])["policy"] == "''"
    assert all(_p(s)["pipeline"] == "cell" for s in specs[:5])
    # the operator nodes alone need no policy
    assert len(resolve_nodes(["scoring"], cwd=tmp_path, say=said.append)) == 1


def test_defaults_no_policy_none_and_models_fallback(tmp_path):
    said: list[str] = []
    specs = resolve_nodes(["configurator"], cwd=tmp_path, policy="none", say=said.append)
    assert _p(specs[0])["policy"] == "''"  # empty string: the fixed pipeline
    assert any("policy: none" in s for s in said), said
    # a params file that turns on learning names what serves (the learn directory's versions)
    learn = tmp_path / "learn.yaml"
    learn.write_text("configurator_node:\n  ros__parameters:\n    learn: true\n    learn_dir: /tmp/l\n")
    specs = resolve_nodes(["configurator"], cwd=tmp_path, params_file=str(learn), say=said.append)
    assert "policy" not in _p(specs[0]) and said[-1].startswith("policy: as set in"), said[-1]
    # models fallback: the procedural parts written into data/parts_models, and said so
    fallback = (tmp_path / "data" / "parts_models").resolve()
    assert _p(specs[0])["models_dir"] == str(fallback)
    assert (fallback / "models_info.json").is_file() and len(list(fallback.glob("obj_*.ply"))) == 6
    assert any("data/default/models not found" in s for s in said), said

    _policy(tmp_path / "runs" / "a" / "policy.safetensors")
    specs = resolve_nodes(["configurator"], cwd=tmp_path, policy="none", say=said.append)
    assert _p(specs[0])["policy"] == "''"
    with pytest.raises(FileNotFoundError, match="missing.safetensors"):
        resolve_nodes(["configurator"], cwd=tmp_path, policy="missing.safetensors", say=said.append)


def test_params_file_wins_over_defaults_and_explicit_options_win_over_it(tmp_path):
    _models(tmp_path / "data" / "default" / "models", 1)
    explicit = _models(tmp_path / "mine", 1)
    (tmp_path / "pipe.yaml").write_text("actions: []\n")
    params = tmp_path / "params.yaml"
    params.write_text("/**:\n  ros__parameters:\n    models_dir: /elsewhere\n"
                      "configurator_node:\n  ros__parameters:\n    policy: /p.safetensors\n")
    specs = resolve_nodes(["generation", "configurator"], cwd=tmp_path, params_file="params.yaml", say=lambda _: None)
    for spec in specs:
        assert spec.command()[2:4] == ["--params-file", str(params.resolve())]
        assert "models_dir" not in _p(spec) and "policy" not in _p(spec)  # the file's values stand

    specs = resolve_nodes(["generation", "configurator"], cwd=tmp_path, params_file=params, models="mine",
                          pipeline="pipe.yaml", policy="none", say=lambda _: None)
    cmd = specs[1].command()
    assert cmd.index("--params-file") < cmd.index("-p")  # -p after the file: the options win
    assert _p(specs[1]) == {"models_dir": str(explicit.resolve()), "pipeline": str((tmp_path / "pipe.yaml").resolve()),
                            "policy": "''"}


def test_parameter_values_keep_their_types():
    assert param_value("") == "''" and param_value("123") == "'123'" and param_value("true") == "'true'"
    assert param_value("/a b/c.yaml") == "/a b/c.yaml"
    assert param_value(2.0) == "2.0" and param_value(3) == "3" and param_value(True) == "true"
    assert param_value(Path("/x")) == "/x"


# -- launch --bag: the replay waits for the nodes --------------------------------------------------
def test_bag_replay_waits_for_every_subscribing_node_unless_the_params_file_says(synthetic_dataset, tmp_path):
    from perception_config.datasets.bag.writer import write_frames
    from perception_config.datasets.bop import BopDataset

    root = synthetic_dataset
    ds = BopDataset(root, split="test")
    bag = tmp_path / "one.mcap"
    write_frames([ds.load_frame(*next(iter(ds.image_keys())), with_models=False)], bag, 10.0)
    specs = resolve_nodes(bag=bag, models=root / "models", policy="none", cwd=tmp_path, say=lambda _: None)
    replay = _p(specs[-1])
    assert specs[-1].name == "bag_replay_node"
    assert replay["wait_for"] == ("['camera/color/image_raw:4', 'camera/depth/image_raw:4', 'camera/camera_info:4', "
                                  "'perception/ground_truth:2']")
    assert float(replay["wait_timeout"]) == launch.REPLAY_WAIT_TIMEOUT
    only = _p(resolve_nodes(nodes=["scoring"], bag=bag, models=root / "models", cwd=tmp_path, say=lambda _: None)[-1])
    assert only["wait_for"] == "['camera/color/image_raw:1', 'camera/depth/image_raw:1', 'camera/camera_info:1']"
    params_file = tmp_path / "params.yaml"
    params_file.write_text("bag_replay_node:\n  ros__parameters:\n    wait_for_subscribers: 1\n")
    own = resolve_nodes(bag=bag, models=root / "models", policy="none", params_file=params_file, cwd=tmp_path,
                        say=lambda _: None)[-1]
    assert "wait_for" not in _p(own) and "wait_timeout" not in _p(own)


def test_a_driver_bag_remaps_the_nodes_to_its_camera_topics(parts_models, tmp_path):
    """A RealSense recording (rosbags' writer; jpeg colour under /compressed, compressedDepth):
    the nodes subscribe to the topics the replay publishes them on, decoded under the raw names,
    and the replay waits for those."""
    from real_bags import Spec, write_camera_bag

    bag = tmp_path / "realsense"
    write_camera_bag(bag, Spec(layout="realsense", color="jpeg", depth="compressedDepth-16UC1"))
    said: list[str] = []
    specs = resolve_nodes(bag=bag, models=parts_models, policy="none", cwd=tmp_path, say=said.append)
    expected = {"camera/color/image_raw": "/camera/camera/color/image_raw",
                "camera/depth/image_raw": "/camera/camera/aligned_depth_to_color/image_raw",
                "camera/camera_info": "/camera/camera/color/camera_info"}
    by_name = {s.name: s for s in specs}
    for node in ("generation_node", "refinement_node", "scoring_node", "pick_node", "configurator_node"):
        assert by_name[node].remaps == expected, node
        args = by_name[node].arguments()
        assert "camera/color/image_raw:=/camera/camera/color/image_raw" in args
    assert by_name["bag_replay_node"].remaps == {}
    waits = _p(by_name["bag_replay_node"])["wait_for"]
    assert waits == ("['camera/camera/color/image_raw:4', 'camera/camera/aligned_depth_to_color/image_raw:4', "
                     "'camera/camera/color/camera_info:4']")
    assert any("RealSense" in line and "/camera/camera/color/image_raw as camera/color/image_raw" in line
               for line in said)


def test_an_rgb_only_bag_runs_the_nodes_rgb_only_unless_the_params_file_says(synthetic_dataset, tmp_path):
    from perception_config.datasets.bag.writer import write_frames
    from perception_config.datasets.bop import BopDataset

    root = synthetic_dataset
    ds = BopDataset(root, split="test", use_depth=False)
    bag = tmp_path / "rgb.mcap"
    write_frames([ds.load_frame(*next(iter(ds.image_keys())), with_models=False)], bag, 10.0)
    said: list[str] = []
    specs = resolve_nodes(bag=bag, models=root / "models", policy="none", cwd=tmp_path, say=said.append)
    by_name = {s.name: _p(s) for s in specs}
    for node in ("generation_node", "refinement_node", "scoring_node", "pick_node", "configurator_node"):
        assert by_name[node]["use_depth"] == "false", node
    assert "use_depth" not in by_name["bag_replay_node"]
    assert "camera/depth/image_raw" not in by_name["bag_replay_node"]["wait_for"]
    assert any("no depth topic" in line for line in said)
    params_file = tmp_path / "params.yaml"
    params_file.write_text("/**:\n  ros__parameters:\n    use_depth: true\n")
    own = resolve_nodes(bag=bag, models=root / "models", policy="none", params_file=params_file, cwd=tmp_path,
                        say=lambda _: None)
    assert all("use_depth" not in _p(s) for s in own)
    rgbd = tmp_path / "rgbd.mcap"
    write_frames([BopDataset(root, split="test").load_frame(*next(iter(ds.image_keys())), with_models=False)],
                 rgbd, 10.0)
    assert all("use_depth" not in _p(s) for s in resolve_nodes(bag=rgbd, models=root / "models", policy="none",
                                                                 cwd=tmp_path, say=lambda _: None))


@pytest.mark.ros
def test_launch_bag_replays_a_short_bag_once_the_nodes_listen(ros_node, synthetic_dataset, tmp_path):
    """A 3-frame bag lasts 0.2 s and the nodes serve about 4 s after the start: without the
    default wait_for every estimate fails with 'no frame'."""
    from perception_config_interfaces.srv import EstimatePose

    from perception_config.datasets.bag.writer import RECORDING_EPOCH_NS, write_frames
    from perception_config.datasets.bop import BopDataset
    from rl_helpers import PIPELINE

    ds = BopDataset(synthetic_dataset, split="test")
    frames = [ds.load_frame(s, i, with_models=False) for s, i in list(ds.image_keys())[:3]]
    bag = tmp_path / "three.mcap"
    assert write_frames(frames, bag, 10.0) == 3
    pipeline = tmp_path / "pipeline.yaml"
    pipeline.write_text(PIPELINE)
    launcher = LaunchCli(["--bag", str(bag), "--models", str(synthetic_dataset / "models"), "--pipeline", str(pipeline),
                     "--policy", "none"], tmp_path)
    try:
        launcher.wait_for(r"^\[launch\] bag_replay_node finished \(exit code 0\)", timeout=120)
        est = ros_node.create_client(EstimatePose, "estimate_pose")
        wait_for_service(ros_node, est, timeout=30)
        results = []
        for i, frame in enumerate(frames):
            req = EstimatePose.Request(object_id=str(frame.objects[0].obj_id), noise_lambda=0.5, seed=i)
            req.frame.stamp.sec, req.frame.stamp.nanosec = divmod(RECORDING_EPOCH_NS + i * 100_000_000, 1_000_000_000)
            results.append(call(ros_node, est, req, timeout=60.0))
        assert [r.success for r in results] == [True, True, True], [r.message for r in results]
    finally:
        _cleanup(launcher, None)


def test_the_shipped_real_camera_example_sets_only_declared_parameters_and_remaps_the_camera(tmp_path):
    """config/realsense_cell.yaml (docs/how-to/run_the_cell.md): a valid ROS params file whose every
    parameter is one a node declares, launched with --pipeline cell and the driver's topics."""
    from importlib import resources

    import yaml

    from perception_config.ros.parameter_docs import node_parameter_table

    example = resources.files("perception_config.config").joinpath("realsense_cell.yaml")
    data = yaml.safe_load(example.read_text())
    table = node_parameter_table()  # the very specs the nodes declare
    declared = {node: {row["name"] for row in rows} for node, rows in table.items()}
    anywhere = set().union(*declared.values())
    assert {"sync_tolerance", "robot_service", "estimate_timeout"} <= anywhere
    for node, body in data.items():
        params = body["ros__parameters"]
        names = anywhere if node == "/**" else declared[node]
        assert params and set(params) <= names, (node, set(params) - names)
    assert data["pick_node"]["ros__parameters"]["robot_service"]

    _models(tmp_path / "models", 1)
    remaps = {"camera/color/image_raw": "/camera/camera/color/image_raw",
              "camera/depth/image_raw": "/camera/camera/aligned_depth_to_color/image_raw",
              "camera/camera_info": "/camera/camera/color/camera_info"}
    specs = resolve_nodes(cwd=tmp_path, models="models", pipeline="cell", params_file=str(example), remaps=remaps,
                          policy="none", say=lambda _: None)
    for spec in specs:
        cmd = spec.command()
        assert cmd[2:4] == ["--params-file", str(example)]
        assert [cmd[i + 1] for i, a in enumerate(cmd) if a == "-r"] == [f"{k}:={v}" for k, v in remaps.items()]
        assert _p(spec)["pipeline"] == "cell"
    with pytest.raises(ValueError, match="FROM:=TO"):
        resolve_nodes(cwd=tmp_path, models="models", remaps={"camera/camera_info": ""}, policy="none",
                      say=lambda _: None)
