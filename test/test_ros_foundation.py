"""The foundation: compiled interfaces import, loopback defaults, and a real service call
between two OS processes over Fast DDS (generation_node serving, this test process calling)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from perception_config.core.geometry import Pose, exp_so3, rotation_angle
from ros_helpers import NodeProcess, call, wait_for_service


def test_interfaces_import_with_fields():
    from perception_config_interfaces.msg import Hypothesis, ObjectPoses, OperatorTrace
    from perception_config_interfaces.srv import (
        EstimatePose,
        GenerateHypothesis,
        Pick,
        RefineHypothesis,
        ScoreHypothesis,
    )

    h = Hypothesis(object_id="5", scores=[0.5, 0.25], score_names=["psi_c", "psi_d"])
    assert list(h.scores) == [0.5, 0.25] and h.pose.orientation.w == 1.0
    assert ObjectPoses().object_ids == [] and OperatorTrace().operations == []
    assert hasattr(GenerateHypothesis.Request(), "noise_lambda")
    assert hasattr(RefineHypothesis.Response(), "hypothesis")
    assert hasattr(ScoreHypothesis.Request(), "methods")
    assert hasattr(Pick.Response(), "picked")
    assert hasattr(EstimatePose.Response(), "operations")


def test_environment_defaults_are_loopback_and_respect_the_user():
    from perception_config.launcher.ros_environment import FASTDDS_PROFILE, configure_ros_environment

    env = configure_ros_environment({})
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SYSTEM_DEFAULT"  # the shipped profile decides
    assert env["ROS_DOMAIN_ID"] == "42"
    assert env["FASTDDS_DEFAULT_PROFILES_FILE"] == str(FASTDDS_PROFILE) and FASTDDS_PROFILE.is_file()
    assert "127.0.0.1" in FASTDDS_PROFILE.read_text()
    user = configure_ros_environment({"ROS_DOMAIN_ID": "7", "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"})
    assert user["ROS_DOMAIN_ID"] == "7" and user["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SUBNET"
    own_profile = configure_ros_environment({"FASTDDS_DEFAULT_PROFILES_FILE": "/etc/my_profile.xml"})
    assert own_profile["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"  # not ours: rmw keeps it local
    with pytest.raises(ValueError, match="ROS_DOMAIN_ID"):
        configure_ros_environment({"ROS_DOMAIN_ID": "abc"})


def test_a_pose_reads_back_from_its_message_as_operators_keep_it():
    """geometry.as_transmitted is bit for bit what a receiver of the message reconstructs, so the
    in-process operators and a chain of nodes work on the same poses."""
    from perception_config.core.geometry import as_transmitted
    from perception_config.ros.conversions import msg_to_pose, pose_to_msg

    rng = np.random.default_rng(3)
    rotations = [exp_so3(rng.normal(size=3) * s) for s in (0.01, 1.0, 3.0) for _ in range(50)]
    rotations += [exp_so3(np.array([np.pi - 1e-9, 0, 0])), exp_so3(np.array([0, 0, np.pi])), np.eye(3)]
    for R in rotations:
        pose = Pose(R, rng.normal(size=3) + [0, 0, 1])
        kept = as_transmitted(pose)
        read = msg_to_pose(pose_to_msg(pose))
        assert np.array_equal(kept.R, read.R) and np.array_equal(kept.t, read.t) and np.array_equal(kept.t, pose.t)
        assert rotation_angle(kept.R, pose.R) < 1e-7


@pytest.fixture(scope="module")
def generation_node(tmp_path_factory):
    from frames import box_mesh
    from perception_config.core.ply import write_ply

    models = tmp_path_factory.mktemp("models")
    info = {}
    for obj_id, diameter in ((3, 120.0), (7, 80.0)):  # cubes (mm) with these diameters
        v, f = box_mesh((diameter / math.sqrt(3),) * 3)
        write_ply(models / f"obj_{obj_id:06d}.ply", v, f)
        info[str(obj_id)] = {"diameter": diameter}
    (models / "models_info.json").write_text(json.dumps(info))
    node = NodeProcess("generation_node", {"models_dir": str(models), "frame_timeout": 0.5},
                       tmp_path_factory.mktemp("logs"))
    yield node
    code = node.stop()
    assert code == 0, f"generation_node did not stop cleanly on SIGINT (exit {code}):\n{node.output()}"


def _publish_ground_truth(ros_node, stamp_sec: int, poses: dict[str, Pose]):
    import rclpy
    from perception_config_interfaces.msg import ObjectPoses

    from perception_config.ros.conversions import pose_to_msg

    pub = ros_node.create_publisher(ObjectPoses, "perception/ground_truth", 10)
    msg = ObjectPoses()
    msg.header.stamp.sec = stamp_sec
    msg.header.frame_id = "camera_color_optical_frame"
    msg.object_ids = list(poses)
    msg.poses = [pose_to_msg(p) for p in poses.values()]
    # Wait until the node's subscription has matched, then publish.
    for _ in range(100):
        if pub.get_subscription_count() > 0:
            break
        rclpy.spin_once(ros_node, timeout_sec=0.05)
    assert pub.get_subscription_count() > 0, "generation_node's ground-truth subscription never matched"
    pub.publish(msg)
    return pub


@pytest.mark.ros
def test_generate_hypothesis_across_processes(ros_node, generation_node):
    from perception_config_interfaces.srv import GenerateHypothesis

    from perception_config.ros.conversions import msg_to_pose

    client = ros_node.create_client(GenerateHypothesis, "generate_hypothesis")
    wait_for_service(ros_node, client, process=generation_node)
    gt = {"3": Pose(exp_so3([0.1, -0.4, 0.2]), [0.05, -0.02, 0.8]), "7": Pose(np.eye(3), [0.0, 0.1, 0.6])}
    _publish_ground_truth(ros_node, 100, gt)

    def request(obj: str, lam: float, seed: int = 0, sec: int = 100, method: str = ""):
        req = GenerateHypothesis.Request(object_id=obj, noise_lambda=lam, seed=seed, method=method)
        req.frame.stamp.sec = sec
        return call(ros_node, client, req)

    exact = request("3", 0.0)
    assert exact.success, exact.message
    pose = msg_to_pose(exact.hypothesis.pose)
    assert np.allclose(pose.t, gt["3"].t, atol=1e-9) and rotation_angle(pose.R, gt["3"].R) < 1e-6
    assert exact.hypothesis.header.stamp.sec == 100 and exact.hypothesis.object_id == "3"
    assert exact.elapsed > 0

    # Seeded noise: same seed, same hypothesis; errors of the documented scale.
    a, b = request("3", 0.5, seed=11), request("3", 0.5, seed=11)
    assert a.success and b.success
    pa, pb = msg_to_pose(a.hypothesis.pose), msg_to_pose(b.hypothesis.pose)
    assert np.allclose(pa.t, pb.t) and np.allclose(pa.R, pb.R)
    errs_t, errs_r = [], []
    for seed in range(1, 41):
        r = request("3", 0.5, seed=seed)
        p = msg_to_pose(r.hypothesis.pose)
        errs_t.append(np.linalg.norm(p.t - gt["3"].t))
        errs_r.append(rotation_angle(p.R, gt["3"].R))
    # E|d| for a 3-D Gaussian with sigma = 0.5*0.15*0.12 m is sigma*sqrt(8/pi) = 14.4 mm.
    assert 0.009 < np.mean(errs_t) < 0.020
    # Rotation: sigma 0.175 rad per axis -> mean angle about 0.28 rad.
    assert 0.18 < np.mean(errs_r) < 0.38

    # The latest frame (zero stamp).
    latest = request("7", 0.0, sec=0)
    assert latest.success and abs(latest.hypothesis.pose.position.y - 0.1) < 1e-9


@pytest.mark.ros
@pytest.mark.parametrize(
    "kwargs, expected",
    [
        ({"obj": "99", "lam": 0.3}, "unknown object id"),
        ({"obj": "3", "lam": 0.3, "method": "magic"}, "unknown method"),
        ({"obj": "3", "lam": math.nan}, "noise_lambda"),
        ({"obj": "3", "lam": 50.0}, "noise_lambda"),
        ({"obj": "3", "lam": 0.3, "sec": 12345}, "no ground truth for the frame at 12345"),
    ],
)
def test_bad_requests_answer_false_and_the_node_keeps_serving(ros_node, generation_node, kwargs, expected):
    from perception_config_interfaces.srv import GenerateHypothesis

    client = ros_node.create_client(GenerateHypothesis, "generate_hypothesis")
    wait_for_service(ros_node, client, process=generation_node)
    _publish_ground_truth(ros_node, 200, {"3": Pose(np.eye(3), [0.0, 0.0, 0.7])})
    req = GenerateHypothesis.Request(object_id=kwargs["obj"], noise_lambda=kwargs["lam"],
                                     method=kwargs.get("method", ""))
    req.frame.stamp.sec = kwargs.get("sec", 200)
    bad = call(ros_node, client, req)
    assert not bad.success and expected in bad.message
    good = GenerateHypothesis.Request(object_id="3", noise_lambda=0.0)
    good.frame.stamp.sec = 200
    assert call(ros_node, client, good).success, "node stopped serving after a bad request"
    assert generation_node.alive()


@pytest.mark.ros
def test_the_parameters_describe_themselves_as_the_reference_table_says(ros_node, generation_node):
    """`ros2 param describe` (DescribeParameters) gives each parameter's description, type, range
    and read-only flag, the same as parameter_docs' table; a read-only parameter and a value
    outside its range are refused at run time, a run-time parameter is set."""
    from rcl_interfaces.srv import DescribeParameters, SetParameters
    from rclpy.parameter import Parameter

    from perception_config.ros.parameter_docs import node_parameter_table
    from perception_config.ros.parameters import TYPE_NAMES

    rows = node_parameter_table()["generation_node"]
    describe = ros_node.create_client(DescribeParameters, "generation_node/describe_parameters")
    wait_for_service(ros_node, describe, process=generation_node)
    described = call(ros_node, describe, DescribeParameters.Request(names=[r["name"] for r in rows])).descriptors
    assert len(described) == len(rows) and all(row["description"] for row in rows)
    for row, d in zip(rows, described):
        assert (d.name, d.description, TYPE_NAMES[d.type], d.read_only) == \
            (row["name"], row["description"], row["type"], row["read_only"])
        limits = [(r.from_value, r.to_value) for r in (*d.integer_range, *d.floating_point_range)]
        assert bool(limits) == bool(row["range"]), row
    by_name = {d.name: d for d in described}
    assert by_name["cache_size"].read_only and by_name["cache_size"].integer_range[0].from_value == 1
    assert by_name["camera_qos"].additional_constraints == "one of: reliable, sensor_data"
    assert by_name["default_lambda"].floating_point_range[0].to_value == 2.0

    set_parameters = ros_node.create_client(SetParameters, "generation_node/set_parameters")
    wait_for_service(ros_node, set_parameters, process=generation_node)
    values = [Parameter("cache_size", value=5), Parameter("default_lambda", value=3.0),
              Parameter("frame_timeout", value=0.5)]  # the value the node was started with
    results = call(ros_node, set_parameters,
                   SetParameters.Request(parameters=[p.to_parameter_msg() for p in values])).results
    assert [r.successful for r in results] == [False, False, True], results
    assert "read-only" in results[0].reason and "out of range" in results[1].reason


@pytest.mark.ros
def test_a_value_outside_its_range_stops_the_node_at_start_naming_it(tmp_path):
    node = NodeProcess("scoring_node", {"cache_size": 0}, tmp_path)
    assert node.proc.wait(60) == 2, node.output()
    assert "cannot start" in node.output() and "cache_size" in node.output()
    node.stop()
