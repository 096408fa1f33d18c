"""The operator nodes and bag_replay_node start without torch: each in a fresh interpreter, its
module is imported and the node built as its main() builds it (real rclpy: init, the node, its
start (configure and activate) and shutdown transitions, destroy, shutdown), once with the
default parameters and once with a models folder and the test pipeline as the ROS tests start
them; then torch is not among the loaded modules. (The configurator runs the agents, which need
torch.)"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from rl_helpers import PIPELINE, pipeline_file
from ros_helpers import ros_test_env

pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parents[1]

NODES = {  # executable -> the class its main() builds
    "generation_node": "GenerationNode",
    "refinement_node": "RefinementNode",
    "scoring_node": "ScoringNode",
    "pick_node": "PickNode",
    "bag_replay_node": "BagReplayNode",
}

# Run in the repository (the source tree is imported, not the installed copy). argv: module,
# class, a JSON list of --ros-args lists (one node per list). Prints the torch modules loaded.
BUILD_NODES = """
import importlib, json, sys
import rclpy
from perception_config.launcher.ros_environment import configure_ros_environment

module = importlib.import_module("perception_config.ros." + sys.argv[1])
assert module.__file__.startswith(sys.argv[4]), module.__file__
configure_ros_environment()
for args in json.loads(sys.argv[3]):
    rclpy.init(args=["--ros-args", *args])
    node = getattr(module, sys.argv[2])()
    if hasattr(node, "shutdown_now"):  # a managed node: configure and activate (autostart), then shut down
        node.start()
        node.shutdown_now()
    if hasattr(node, "stop"):
        node.stop()
    node.destroy_node()
    rclpy.shutdown()
print(json.dumps(sorted(m for m in sys.modules if m.split(".")[0] == "torch")))
"""


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, Path]:
    from frames import box_model, default_pose, synthetic_frame
    from perception_config.datasets.bag import write_frames
    from perception_config.datasets.parts import write_models

    folder = tmp_path_factory.mktemp("startup")
    bag = folder / "frames.mcap"
    frame = synthetic_frame([box_model()], [default_pose()], width=64, height=48)
    assert write_frames([frame, frame], bag, 10.0) == 2
    return {"models": write_models(folder / "models"), "pipeline": pipeline_file(tmp_path_factory, PIPELINE),
            "bag": bag}


def _parameter_sets(executable: str, inputs: dict[str, Path]) -> list[list[str]]:
    if executable == "bag_replay_node":  # a bag is required; rate 0 so the replay is over at once
        return [["-p", f"bag:={inputs['bag']}"], ["-p", f"bag:={inputs['bag']}", "-p", "rate:=0"]]
    return [[], ["-p", f"models_dir:={inputs['models']}", "-p", f"pipeline:={inputs['pipeline']}",
                 "-p", "frame_timeout:=1.0", "-p", "request_queue:=4"]]


@pytest.mark.parametrize("executable", list(NODES))
def test_an_operator_node_starts_without_torch(executable, inputs):
    args = json.dumps(_parameter_sets(executable, inputs))
    proc = subprocess.run([sys.executable, "-c", BUILD_NODES, executable, NODES[executable], args,
                           str(ROOT / "perception_config")],
                          cwd=ROOT, env=ros_test_env(), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, f"{executable} did not start and stop:\n{proc.stdout}\n{proc.stderr}"
    torch_modules = json.loads(proc.stdout.strip().splitlines()[-1])
    assert torch_modules == [], f"{executable} imported torch: {torch_modules[:5]}"
