"""EnvSettings (one settings object for the environment) and the atomic file writer."""
from __future__ import annotations

import os

import pytest

from perception_config.rl.settings import EnvSettings, settings_from_policy_meta
from perception_config.util.atomic_file import atomic_output, atomic_write


def test_settings_round_trip_and_defaults():
    s = EnvSettings(max_ops=7, time_mode="cost_table", cost_table={"d2co": 0.1}, lambda_range=(0.2, 0.4))
    assert EnvSettings.from_json(s.to_json()) == s
    assert EnvSettings().to_json() == {"max_ops": 10, "failed_pick_cost": 2.0, "truncation_cost": 10.0,
                                       "time_mode": "cost_table", "cost_table": {}, "min_visib_fract": 0.3,
                                       "lambda_range": [0.1, 1.0], "loop_mask": True, "final_pick": True,
                                       "final_pick_best": False, "converge_tol": 0.0}
    # a policy written before loop_mask, final_pick and converge_tol existed loads with the rules on
    old = {k: v for k, v in s.to_json().items() if k not in ("loop_mask", "final_pick", "converge_tol")}
    assert EnvSettings.from_json(old).loop_mask is True and EnvSettings.from_json(old).final_pick is True
    assert EnvSettings.from_json(old).converge_tol == 0.0
    assert s.replace(max_ops=None) == s  # None = not given
    assert s.differences(s.replace(failed_pick_cost=3.0, lambda_range=(0.0, 1.0))) == ["failed_pick_cost: 2.0 -> 3.0"]


@pytest.mark.parametrize("bad, message", [
    ({"max_ops": 0}, "max_ops"), ({"max_ops": 2.5}, "max_ops"), ({"max_ops": True}, "max_ops"),
    ({"failed_pick_cost": -1.0}, "failed_pick_cost"), ({"truncation_cost": float("inf")}, "truncation_cost"),
    ({"time_mode": "fast"}, "time_mode"), ({"cost_table": {"d2co": float("nan")}}, "cost_table"),
    ({"min_visib_fract": 1.5}, "min_visib_fract"), ({"lambda_range": (0.5, 0.1)}, "low <= high"),
    ({"lambda_range": (0.0, 9.0)}, "lambda_range high"), ({"loop_mask": "yes"}, "loop_mask"),
    ({"final_pick": 1}, "final_pick"), ({"final_pick_best": "on"}, "final_pick_best"),
    ({"converge_tol": -0.1}, "converge_tol"),
    ({"converge_tol": float("nan")}, "converge_tol"),
    ({"cost_table": {"action:icp_fine@3": -0.1}}, "action:icp_fine@3"),
])
def test_bad_settings_are_refused_naming_the_field(bad, message):
    with pytest.raises(ValueError, match=message):
        EnvSettings(**bad)


def test_unknown_settings_name_the_source():
    with pytest.raises(ValueError, match="policy p.json: unknown environment settings \\['speed'\\]"):
        EnvSettings.from_json({"speed": 2}, "policy p.json")
    with pytest.raises(ValueError, match="unknown environment settings \\['speed'\\]"):
        EnvSettings().replace(speed=2)
    assert settings_from_policy_meta({"extra": {}}) is None


def test_atomic_write_replaces_whole_files(tmp_path):
    path = tmp_path / "sub" / "results.json"
    atomic_write(path, "first\n")
    atomic_write(path, b"second\n")
    assert path.read_text() == "second\n"
    assert os.listdir(path.parent) == ["results.json"]  # no temporary left


def test_atomic_write_gives_the_mode_a_plain_open_gives(tmp_path):
    """Not mkstemp's 0600: results and policies are readable by whoever the umask lets read them."""
    old = os.umask(0o022)
    try:
        path = atomic_write(tmp_path / "results.json", "{}")
        plain = tmp_path / "plain.json"
        plain.write_text("{}")
    finally:
        os.umask(old)
    assert (path.stat().st_mode & 0o777) == (plain.stat().st_mode & 0o777) == 0o644


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    path = tmp_path / "plot.png"
    atomic_write(path, b"old")
    with pytest.raises(RuntimeError):
        with atomic_output(path) as tmp:
            assert tmp.parent == path.parent and tmp.suffix == ".png"  # writers pick the format from it
            tmp.write_bytes(b"half")
            raise RuntimeError("the writer failed")
    assert path.read_bytes() == b"old" and os.listdir(tmp_path) == ["plot.png"]
    with pytest.raises(KeyboardInterrupt):
        with atomic_output(path) as tmp:
            raise KeyboardInterrupt
    assert os.listdir(tmp_path) == ["plot.png"]


def test_cost_table_lookup_order():
    """action:<name>@<obj> before action:<name> before the block's name before its default_cost;
    scoring@<obj> before scoring before the sum of the scoring blocks."""
    from perception_config.blocks.pipeline import load_pipeline

    pipe = load_pipeline("default")
    fine = pipe.action("icp_fine").block  # an icp_point_to_plane block, as icp_coarse's
    table = {"action:icp_fine@3": 0.5, "action:icp_fine": 0.25, "icp_point_to_plane": 0.125,
             "scoring@3": 0.0625, "scoring": 0.03125}
    s = EnvSettings(cost_table=table)
    assert s.block_cost(fine, "icp_fine", 3) == 0.5
    assert s.block_cost(fine, "icp_fine", 4) == 0.25  # an object without its own entry: the pooled one
    assert s.block_cost(fine, "icp_coarse", 3) == 0.125  # no action entry: the block's name
    assert s.block_cost(fine) == 0.125
    assert EnvSettings().block_cost(fine, "icp_fine", 3) == fine.default_cost
    assert s.scoring_cost(pipe.scoring, 3) == 0.0625 and s.scoring_cost(pipe.scoring, 4) == 0.03125
    assert EnvSettings().scoring_cost(pipe.scoring) == sum(b.default_cost for b in pipe.scoring)
