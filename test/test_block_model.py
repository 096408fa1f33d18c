"""Blocks describe themselves: adding a block is adding one file.

The block below is defined here, in this test file, and nowhere else: it declares its cost for
cost-table mode and the range of its score, and the pipeline loader, the environment (its
observation and its cost table), `perception-config blocks` and the registry take it from
there without any table being edited.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import perception_config.blocks as blocks_package
from perception_config.blocks import REGISTRY, block_modules, load_all
from perception_config.blocks.base import MODEL, POSE, Block, BlockInput, BlockResult, Kind, Param, register
from perception_config.core.geometry import LAMBDA_MAX, Pose, check_noise_lambda
from perception_config.rl.env import PerceptionConfigEnv
from rl_helpers import tiny_dataset


@register
class NudgeX(Block):
    """Moves the hypothesis along the camera's x axis (a block defined only in this test)."""

    kind = Kind.REFINEMENT
    name = "test_nudge_x"
    default_cost = 0.125
    inputs = (MODEL, POSE)
    params = (Param("step", 0.001, 0.0, 0.1, doc="metres"),)

    def run(self, inp: BlockInput) -> BlockResult:
        return BlockResult(ok=True, pose=Pose(inp.pose.R, inp.pose.t + [self.config["step"], 0.0, 0.0]))


@register
class DepthOfCentre(Block):
    """Scores the hypothesis by its distance from the camera (a scoring block of this test)."""

    kind = Kind.SCORING
    name = "test_centre_depth"
    default_cost = 0.25
    inputs = (POSE,)
    score_names = ("centre_depth",)
    score_ranges = {"centre_depth": (0.0, 4.0)}  # metres

    def run(self, inp: BlockInput) -> BlockResult:
        return BlockResult(ok=True, scores={"centre_depth": float(inp.pose.t[2])})


PIPELINE = """\
generator: {block: simulated_init, params: {noise_lambda: 0.5}}
actions:
  - {name: nudge, block: test_nudge_x, params: {step: 0.002}}
  - {name: pick, block: simulated_pick}
scoring: [test_centre_depth]
"""


def test_a_block_defined_in_one_file_runs_in_the_env_with_its_own_cost_and_range(tmp_path_factory, tmp_path):
    pipe = tmp_path / "pipeline.yaml"
    pipe.write_text(PIPELINE)
    env = PerceptionConfigEnv(tiny_dataset(tmp_path_factory), pipe, time_mode="cost_table")
    assert env.action_names == ["nudge", "pick"] and env.score_names == ["centre_depth"]
    obs, info = env.reset(seed=3)
    z = info["scores"]["centre_depth"]
    assert obs[env.observation_layout.index("score:centre_depth")] == pytest.approx(z / 4.0)  # its declared range
    before = info["pose"]
    _, reward, _, _, info = env.step(0)
    assert reward == -(0.125 + 0.25)  # its own cost plus the scoring pass, from the blocks alone
    assert info["ok"] and np.allclose(info["pose"].t - before.t, [0.002, 0.0, 0.0], atol=1e-12)
    # The settings' cost table still wins over a block's declaration, per block and for the scoring pass.
    table = PerceptionConfigEnv(tiny_dataset(tmp_path_factory), pipe, time_mode="cost_table",
                                cost_table={"test_nudge_x": 1.0, "scoring": 0.5})
    table.reset(seed=3)
    assert table.step(0)[1] == -1.5


def test_the_registry_refuses_a_block_that_does_not_describe_itself():
    class NoCost(Block):
        kind = Kind.REFINEMENT
        name = "test_no_cost"

        def run(self, inp):  # pragma: no cover - never called
            raise AssertionError

    with pytest.raises(TypeError, match="must declare default_cost"):
        register(NoCost)

    class ForeignRange(NoCost):
        name = "test_foreign_range"
        default_cost = 0.1
        score_names = ("a",)
        score_ranges = {"b": (0.0, 1.0)}

    with pytest.raises(TypeError, match="range for 'b'"):
        register(ForeignRange)

    class EmptyRange(ForeignRange):
        score_ranges = {"a": (1.0, 1.0)}

    with pytest.raises(TypeError, match="high > low"):
        register(EmptyRange)
    assert "test_no_cost" not in REGISTRY and "test_foreign_range" not in REGISTRY


def test_block_modules_are_discovered_not_listed():
    folder = Path(blocks_package.__file__).parent
    on_disk = sorted(p.stem for p in folder.glob("*.py") if p.stem not in ("__init__", "base", "pipeline", "features"))
    assert block_modules() == on_disk
    registry = load_all()
    shipped = {name: cls for name, cls in registry.items() if cls.__module__.startswith("perception_config.blocks.")}
    assert {cls.__module__.rsplit(".", 1)[1] for cls in shipped.values()} <= set(on_disk)
    for name, cls in shipped.items():  # every shipped block describes itself
        assert math.isfinite(cls.default_cost) and cls.default_cost >= 0, name
        assert set(cls.score_ranges) <= set(cls.score_names) and set(cls.lower_is_better) <= set(cls.score_names), name
    assert {"simulated_init", "global_registration", "d2co", "icp_point_to_plane", "psi_d",
            "simulated_pick"} <= set(shipped)


def test_the_blocks_command_lists_a_new_block(capsys):
    from perception_config.cli import main

    assert main(["blocks"]) == 0
    out = capsys.readouterr().out
    assert "test_nudge_x  (refinement; inputs: model, pose)" in out and "step = 0.001 in [0.0, 0.1]" in out


def test_one_lambda_check_beside_the_noise_model():
    assert check_noise_lambda(0) == 0.0 and check_noise_lambda(LAMBDA_MAX) == LAMBDA_MAX
    for bad in (-0.1, LAMBDA_MAX + 1e-9, float("nan"), "x", None):
        with pytest.raises(ValueError, match="lambda"):
            check_noise_lambda(bad)
    assert REGISTRY["simulated_init"].params[0].high == LAMBDA_MAX  # the generator's parameter range


def test_a_block_never_raises(tmp_path_factory):
    broken = NudgeX(step=0.0)
    result = broken(BlockInput(frame=None, model=None, pose=Pose(np.eye(3), np.array([np.nan, 0.0, 1.0]))))
    assert not result.ok and "degenerate" in result.reason
