"""Managed nodes and the composed cell, on real node processes: every lifecycle transition of an
operator node (what it serves in each state, cleanup freeing its services, configure again,
shutdown ending the process), a bad policy failing the configurator's configure with its
reason (on /diagnostics and through `perception-config launch`), deactivate answering the
queued estimates while refusing new ones, and a composed cell answering estimates through the
in-process path."""
from __future__ import annotations

import re
import time
from pathlib import Path

import pytest

from ros_helpers import LaunchCli, NodeProcess, call, wait_for_service, wait_until

pytestmark = pytest.mark.ros



@pytest.fixture(scope="module")
def parts_models(tmp_path_factory) -> Path:
    from perception_config.datasets.parts import write_models

    return write_models(tmp_path_factory.mktemp("parts") / "models")


def _refine_request(object_id: str = "1"):
    from perception_config_interfaces.srv import RefineHypothesis

    request = RefineHypothesis.Request(method="icp_point")
    request.hypothesis.object_id = object_id
    request.hypothesis.pose.position.z = 0.5
    request.hypothesis.pose.orientation.w = 1.0
    return request


def test_every_transition_of_an_operator_node(ros_node, parts_models, tmp_path):
    from perception_config_interfaces.srv import RefineHypothesis

    from perception_config.ros.lifecycle_manager import LifecycleManager

    node = NodeProcess("refinement_node", {"models_dir": parts_models, "autostart": "false", "frame_timeout": 0.2},
                       log_dir=tmp_path)
    manager = LifecycleManager(["refinement_node"])
    client = ros_node.create_client(RefineHypothesis, "refine_hypothesis")
    try:
        wait_until(lambda: manager.state("refinement_node") == "unconfigured", 30, "unconfigured")
        assert not client.wait_for_service(timeout_sec=1.0), "an unconfigured node offers its service"

        assert manager.transition("refinement_node", "configure") == (True, "")
        assert manager.state("refinement_node") == "inactive"
        wait_for_service(ros_node, client, process=node)
        answer = call(ros_node, client, _refine_request())
        assert not answer.success and "refinement_node is inactive" in answer.message, answer.message

        assert manager.transition("refinement_node", "activate") == (True, "")
        answer = call(ros_node, client, _refine_request())  # served: no frame has arrived
        assert not answer.success and "no camera frame" in answer.message, answer.message
        answer = call(ros_node, client, _refine_request("999"))
        assert "unknown object id '999'" in answer.message, answer.message

        assert manager.transition("refinement_node", "deactivate") == (True, "")
        answer = call(ros_node, client, _refine_request())
        assert not answer.success and "is inactive" in answer.message, answer.message
        level, message = manager.fresh_status("refinement_node")
        assert (level, message) == (1, "inactive: not serving")  # WARN

        assert manager.transition("refinement_node", "cleanup") == (True, "")
        assert manager.state("refinement_node") == "unconfigured"
        wait_until(lambda: not client.service_is_ready(), 10, "the service gone after cleanup")

        assert manager.transition("refinement_node", "configure") == (True, "")  # again, from scratch
        assert manager.transition("refinement_node", "activate") == (True, "")
        wait_for_service(ros_node, client, process=node)
        answer = call(ros_node, client, _refine_request())
        assert "no camera frame" in answer.message, answer.message

        assert manager.transition("refinement_node", "shutdown") == (True, "")
        assert node.proc.wait(15) == 0, node.output()  # finalized: the process ends
    finally:
        manager.close()
        ros_node.destroy_client(client)
        node.stop()
    text = node.output()
    for line in ("unconfigured: waiting for a lifecycle manager", "configured", "serving refine_hypothesis",
                 "inactive: new requests are refused", "cleaned up: unconfigured"):
        assert line in text, text


def test_a_bad_policy_fails_the_configurators_configure_with_its_reason(ros_node, parts_models, tmp_path):
    from perception_config.ros.lifecycle_manager import LifecycleManager

    bad = tmp_path / "policy.safetensors"
    bad.write_bytes(b"not a policy")
    node = NodeProcess("configurator_node", {"models_dir": parts_models, "policy": bad, "autostart": "false"},
                       log_dir=tmp_path)
    manager = LifecycleManager(["configurator_node"])
    try:
        wait_until(lambda: manager.state("configurator_node") == "unconfigured", 60, "unconfigured")
        done, reason = manager.transition("configurator_node", "configure")
        assert not done
        assert f"policy file {bad} is corrupt or not a policy" in reason, reason
        assert manager.state("configurator_node") == "unconfigured"
        level, message = manager.fresh_status("configurator_node")
        assert level == 2 and message.startswith("configure failed: policy file"), message  # ERROR, the reason
        assert node.alive()  # a failed transition is not a crash: a fixed file may be configured next
        assert not manager.transition("configurator_node", "activate")[0]  # nothing to activate
    finally:
        manager.close()
        node.stop()
    assert "configure failed: policy file" in node.output()


def test_launch_names_the_node_that_fails_to_configure_and_stops_the_cell(parts_models, tmp_path):
    bad = tmp_path / "policy.safetensors"
    bad.write_bytes(b"not a policy")
    launch = LaunchCli(["--models", str(parts_models), "--policy", str(bad), "--composed"], tmp_path)
    try:
        assert launch.proc.wait(120) == 1, launch.output()
    finally:
        launch.stop()
    text = launch.output()
    assert "[launch] pick_node: configured" in text, text  # the operator nodes first, in order
    assert f"[launch] configurator_node failed to configure: policy file {bad} is corrupt" in text, text
    assert "configurator_node: active" not in text and "generation_node: active" not in text, text


def test_a_composed_cell_answers_and_deactivate_answers_the_queued_estimates(ros_node, parts_models, tmp_path):
    """Three estimates queued (each waits frame_timeout for a frame that never comes), then the
    configurator is deactivated: the three are answered as estimates, a fourth is refused; then
    cleaned up, configured and activated again, it serves."""
    from perception_config_interfaces.srv import EstimatePose

    from perception_config.ros.lifecycle_manager import LifecycleManager

    params = tmp_path / "params.yaml"
    params.write_text("/**:\n  ros__parameters:\n    frame_timeout: 0.5\n")
    launch = LaunchCli(["--models", str(parts_models), "--policy", "none", "--composed",
                      "--params-file", str(params)], tmp_path)
    manager = LifecycleManager(["configurator_node"])
    client = ros_node.create_client(EstimatePose, "estimate_pose")
    try:
        launch.wait_for(re.escape("[launch] configurator_node: active"), 120)
        assert "[launch] started perception_cell" in launch.output()
        wait_for_service(ros_node, client)
        answer = call(ros_node, client, EstimatePose.Request(object_id="1"), timeout=30)
        # the generator was asked (in-process) and waited frame_timeout for the frame's ground truth
        assert not answer.success and "no first hypothesis: no ground truth" in answer.message, answer.message
        futures = [client.call_async(EstimatePose.Request(object_id="1")) for _ in range(3)]
        import rclpy

        deadline = time.monotonic() + 0.3  # let the three be taken before deactivating
        while time.monotonic() < deadline:
            rclpy.spin_once(ros_node, timeout_sec=0.05)
        assert manager.transition("configurator_node", "deactivate") == (True, "")
        refused = call(ros_node, client, EstimatePose.Request(object_id="1"))
        assert not refused.success and "configurator_node is inactive" in refused.message, refused.message
        for future in futures:
            rclpy.spin_until_future_complete(ros_node, future, timeout_sec=30)
            assert future.done()
            assert "no first hypothesis: no ground truth" in future.result().message, future.result().message
        # cleanup frees the configurator's clients, store and queue; configure makes them anew
        assert manager.transition("configurator_node", "cleanup") == (True, "")
        assert manager.transition("configurator_node", "configure") == (True, "")
        assert manager.transition("configurator_node", "activate") == (True, "")
        answer = call(ros_node, client, EstimatePose.Request(object_id="1"), timeout=30)
        assert "no first hypothesis: no ground truth" in answer.message, answer.message
    finally:
        manager.close()
        ros_node.destroy_client(client)
        code = launch.stop()
    assert code == 0, launch.output()
