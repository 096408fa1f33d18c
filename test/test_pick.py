"""Pick blocks: the simulated pick's BOP criteria and the external pick's robot-cell contract.

The executors below are the robot-cell stand-ins of a unit test."""
from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from frames import K_LINEMOD, box_mesh, box_model, default_pose
from perception_config.blocks.base import REGISTRY, BlockInput, Kind
from perception_config.blocks.pick import ExternalPick, SimulatedPick
from perception_config.core.geometry import Pose, exp_so3
from perception_config.core.models import make_model
from perception_config.core.scene import Frame

FLIPS = [Pose.identity()] + [Pose(exp_so3(np.pi * np.eye(3)[i]), np.zeros(3)) for i in range(3)]


@pytest.fixture(scope="module")
def frame() -> Frame:
    return Frame(rgb=np.zeros((480, 640, 3), np.uint8), depth=np.full((480, 640), np.nan, np.float32), K=K_LINEMOD)


@pytest.fixture(scope="module")
def box():
    return box_model()


@pytest.fixture(scope="module")
def sym_box():
    v, f = box_mesh((0.08, 0.05, 0.03))
    return make_model(2, v, f, symmetries=FLIPS, n_points=500)


GT = default_pose()


def pick(block, frame, model, pose, gt=GT):
    return block(BlockInput(frame=frame, model=model, pose=pose, ground_truth=gt))


def shifted(d: float, gt: Pose = GT, direction=(1.0, 0.0, 0.0)) -> Pose:
    u = np.asarray(direction) / np.linalg.norm(direction)
    return Pose(gt.R, gt.t + d * u)


def rotated(angle: float, axis=(0.0, 0.0, 1.0), gt: Pose = GT) -> Pose:
    u = np.asarray(axis, float) / np.linalg.norm(axis)
    return gt.compose(Pose(exp_so3(u * angle), np.zeros(3)))


def test_registered_as_pick_blocks() -> None:
    assert REGISTRY["simulated_pick"] is SimulatedPick and REGISTRY["external_pick"] is ExternalPick
    assert SimulatedPick.kind is Kind.PICK and ExternalPick.kind is Kind.PICK
    assert set(SimulatedPick.inputs) == {"pose", "model", "ground_truth"}
    assert set(ExternalPick.inputs) == {"pose", "model"}


# --------------------------------------------------------------------------- simulated pick


def test_hypothesis_at_ground_truth_picks(frame, box) -> None:
    r = pick(SimulatedPick(), frame, box, default_pose())
    assert r.ok and r.picked is True
    assert r.scores["pick_mssd"] == pytest.approx(0.0, abs=1e-7)
    assert r.scores["pick_re"] == pytest.approx(0.0, abs=1e-6) and r.scores["pick_te"] == 0.0
    assert r.elapsed > 0


def test_threshold_on_mssd_relative_to_the_diameter(frame, box) -> None:
    d = box.diameter
    far = pick(SimulatedPick(), frame, box, shifted(0.2 * d, direction=(1, -2, 0.5)))
    assert far.ok and far.picked is False
    assert far.scores["pick_mssd"] == pytest.approx(0.2 * d, abs=1e-9)
    near = pick(SimulatedPick(), frame, box, shifted(0.08 * d))
    assert near.ok and near.picked is True
    assert pick(SimulatedPick(mssd_threshold=0.05), frame, box, shifted(0.08 * d)).picked is False
    assert pick(SimulatedPick(mssd_threshold=0.25), frame, box, shifted(0.2 * d)).picked is True
    # a rotation: MSSD is the largest corner displacement, 2 sin(a/2) x the farthest corner radius
    a = math.radians(8)
    chord = 2 * math.sin(a / 2) * math.hypot(0.04, 0.025)
    r = pick(SimulatedPick(), frame, box, rotated(a))
    assert r.scores["pick_mssd"] == pytest.approx(chord, abs=1e-9)
    assert r.picked is (chord <= 0.1 * d)


def test_symmetric_object_rotated_by_a_symmetry(frame, box, sym_box) -> None:
    for axis in np.eye(3):
        hyp = rotated(math.pi, axis)
        r = pick(SimulatedPick(), frame, sym_box, hyp)
        assert r.ok and r.picked is True and r.scores["pick_mssd"] == pytest.approx(0.0, abs=1e-7)
        # the same pose of the box without declared symmetries is far off
        r = pick(SimulatedPick(), frame, box, hyp)
        assert r.ok and r.picked is False and r.scores["pick_mssd"] > 0.5 * box.diameter
    # re_te: judged at the best symmetry by default, on the plain pose when configured so
    hyp = rotated(math.pi, (1, 0, 0))
    aware = pick(SimulatedPick(criterion="re_te"), frame, sym_box, hyp)
    assert aware.picked is True and aware.scores["pick_re"] == pytest.approx(0.0, abs=1e-6)
    plain = pick(SimulatedPick(criterion="re_te", symmetry_aware=False), frame, sym_box, hyp)
    assert plain.ok and plain.picked is False and plain.scores["pick_re"] == pytest.approx(math.pi, abs=1e-6)
    # a symmetry plus 3 degrees: within 5 degrees, not within 2
    hyp = rotated(math.pi + math.radians(3), (0, 1, 0))
    assert pick(SimulatedPick(criterion="re_te"), frame, sym_box, hyp).picked is True
    r = pick(SimulatedPick(criterion="re_te", max_re_deg=2.0), frame, sym_box, hyp)
    assert r.picked is False and math.degrees(r.scores["pick_re"]) == pytest.approx(3.0, abs=1e-6)



def test_derived_symmetries_let_a_box_that_declares_none_be_picked_flipped(frame, box, sym_box) -> None:
    flipped = rotated(math.pi, (1, 0, 0))
    assert pick(SimulatedPick(), frame, box, flipped).picked is False  # declared: none
    r = pick(SimulatedPick(symmetries="derived"), frame, box, flipped)
    assert r.ok and r.picked is True and r.scores["pick_mssd"] < 1e-3 * box.diameter  # derived: to ~1e-3 rad
    assert pick(SimulatedPick(symmetries="derived", criterion="re_te"), frame, box, flipped).picked is True
    # a turn that is no symmetry of the box still fails, and declared symmetries are kept as declared
    assert pick(SimulatedPick(symmetries="derived"), frame, box, rotated(math.pi / 2, (1, 0, 0))).picked is False
    assert pick(SimulatedPick(symmetries="derived"), frame, sym_box, flipped).picked is True
    with pytest.raises(ValueError, match="symmetries"):
        SimulatedPick(symmetries="guessed")

def test_re_te_criterion_thresholds(frame, box) -> None:
    block = SimulatedPick(criterion="re_te")  # BOP's 5 deg / 5 cm
    assert pick(block, frame, box, rotated(math.radians(4), (1, 1, 0))).picked is True
    assert pick(block, frame, box, rotated(math.radians(6), (1, 1, 0))).picked is False
    assert pick(SimulatedPick(criterion="re_te", max_re_deg=10.0), frame, box,
                rotated(math.radians(6), (1, 1, 0))).picked is True
    r = pick(block, frame, box, shifted(0.04, direction=(0, 1, 1)))
    assert r.picked is True and r.scores["pick_te"] == pytest.approx(0.04)
    assert pick(block, frame, box, shifted(0.06)).picked is False
    assert pick(SimulatedPick(criterion="re_te", max_te=0.01), frame, box, shifted(0.015)).picked is False
    # 0.3 x diameter off (fails MSSD) but within 5 cm: the criteria disagree, each as configured
    hyp = shifted(0.3 * box.diameter)
    assert pick(block, frame, box, hyp).picked is True
    assert pick(SimulatedPick(), frame, box, hyp).picked is False


def test_simulated_pick_cannot_be_attempted(frame, box) -> None:
    block = SimulatedPick()
    r = block(BlockInput(frame=frame, model=box, pose=default_pose(), ground_truth=None))
    assert not r.ok and r.picked is None and "ground-truth" in r.reason
    for bad in (Pose(np.full((3, 3), np.nan), [0, 0, 1]), Pose(np.eye(3) * 2, [0, 0, 1]), Pose(np.eye(3), [0, 0, -1])):
        r = pick(block, frame, box, bad)
        assert not r.ok and r.picked is None and "degenerate" in r.reason
    r = pick(block, frame, box, default_pose(), gt=Pose(np.eye(3), [0, 0, np.nan]))
    assert not r.ok and "ground-truth pose is degenerate" in r.reason
    assert not pick(block, frame, box, None).ok


def test_annotation_rotation_rounding_is_not_degenerate(frame, box) -> None:
    # BOP ground-truth rotations are stored rounded: LM-O's are up to 2e-3 off orthonormal
    gt = default_pose()
    rng = np.random.default_rng(0)
    noisy_gt = Pose(gt.R + rng.normal(0, 1e-3, (3, 3)), gt.t)
    r = pick(SimulatedPick(), frame, box, gt, gt=noisy_gt)
    assert r.ok and r.picked is True


def test_parameters_are_validated() -> None:
    assert SimulatedPick().config == {"criterion": "mssd", "mssd_threshold": 0.1, "max_re_deg": 5.0,
                                      "max_te": 0.05, "symmetry_aware": True, "symmetries": "declared"}
    for bad in ({"mssd_threshold": 2.0}, {"mssd_threshold": 0.0}, {"criterion": "add"}, {"max_te": -1.0},
                {"grip": 1}):
        with pytest.raises(ValueError):
            SimulatedPick(**bad)
    with pytest.raises(ValueError):
        ExternalPick(timeout=0.0)


# --------------------------------------------------------------------------- external pick


def external(frame, box, block, pose=None):
    return block(BlockInput(frame=frame, model=box, pose=pose or default_pose()))


def test_external_pick_without_a_robot_cell(frame, box) -> None:
    r = external(frame, box, ExternalPick())
    assert not r.ok and r.picked is None and "no robot cell connected" in r.reason


def test_external_pick_reports_the_cell_outcome(frame, box) -> None:
    calls = []

    def cell(pose, model, frm):
        calls.append((pose, model, frm))
        return len(calls) == 1  # picks the first time, fails the second

    block = ExternalPick(executor=cell)
    hyp = shifted(0.01)
    first, second = external(frame, box, block, hyp), external(frame, box, block, hyp)
    assert first.ok and first.picked is True
    assert second.ok and second.picked is False  # attempted, failed: the env charges the robot time
    pose, model, frm = calls[0]
    assert np.allclose(pose.t, hyp.t) and model is box and frm is frame
    assert first.scores == {}  # no ground truth involved


@pytest.mark.parametrize("exc", [TimeoutError("cell timed out"), ConnectionError("service unavailable"),
                                 RuntimeError("gripper fault")])
def test_external_pick_executor_errors(frame, box, exc) -> None:
    def cell(pose, model, frm):
        raise exc

    r = external(frame, box, ExternalPick(executor=cell))
    assert not r.ok and r.picked is None
    assert type(exc).__name__ in r.reason and str(exc) in r.reason


def test_external_pick_timeout(frame, box) -> None:
    release = threading.Event()

    def slow_cell(pose, model, frm):
        release.wait(5.0)  # a cell that does not answer in time
        return True

    block = ExternalPick(executor=slow_cell, timeout=0.2)
    t0 = time.perf_counter()
    r = external(frame, box, block)
    waited = time.perf_counter() - t0
    release.set()
    assert not r.ok and "did not answer within 0.2 s" in r.reason
    assert 0.2 <= waited < 1.0 and r.elapsed == pytest.approx(waited, abs=0.05)
    fast = ExternalPick(executor=lambda p, m, f: True, timeout=0.2)
    assert external(frame, box, fast).picked is True


def test_external_pick_rejects_non_boolean_answers(frame, box) -> None:
    for answer in (None, "yes", 1):
        r = external(frame, box, ExternalPick(executor=lambda p, m, f, a=answer: a))
        assert not r.ok and "expected True or False" in r.reason
    assert external(frame, box, ExternalPick(executor=lambda p, m, f: np.bool_(True))).picked is True


def test_external_pick_attachment(frame, box) -> None:
    calls = []
    try:
        ExternalPick.set_default_executor(lambda p, m, f: calls.append("default") or True)
        block = ExternalPick()  # e.g. created from a pipeline configuration
        assert external(frame, box, block).picked is True and calls == ["default"]
        block.set_executor(lambda p, m, f: calls.append("own") or False)  # instance wins
        assert external(frame, box, block).picked is False and calls == ["default", "own"]
        block.set_executor(None)
        assert external(frame, box, block).picked is True and calls[-1] == "default"
    finally:
        ExternalPick.set_default_executor(None)
    assert "no robot cell" in external(frame, box, ExternalPick()).reason


def test_external_pick_degenerate_hypothesis_is_not_sent(frame, box) -> None:
    calls = []
    block = ExternalPick(executor=lambda p, m, f: calls.append(p) or True)
    r = external(frame, box, block, Pose(np.eye(3), [0, 0, -0.5]))
    assert not r.ok and "degenerate" in r.reason and calls == []
