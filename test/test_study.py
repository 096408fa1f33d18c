"""Multi-seed studies: the bootstrap intervals (learning/study_stats.py), the k-of-N counting and
the verdict on hand-made evaluations (learning/study_report.py), and `perception-config study` end
to end on the tiny dataset, stopped nowhere and run again (nothing retrained, nothing re-evaluated)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from perception_config.learning import study_stats as st
from perception_config.learning.study_report import analyse, verdict
from rl_helpers import pipeline_file, tiny_dataset


# -- the bootstrap ---------------------------------------------------------------------------------
def test_constant_data_gives_a_zero_width_interval():
    e = st.mean_interval(np.full(40, 0.37))
    assert e.value == pytest.approx(0.37) and e.lo == pytest.approx(0.37) and e.hi == pytest.approx(0.37)
    same = np.linspace(0.1, 2.0, 30)
    d = st.paired_difference_interval(same, same)
    assert (d.value, d.lo, d.hi) == (0.0, 0.0, 0.0)


def test_coin_interval_contains_its_mean_and_shrinks_with_n():
    rng = np.random.default_rng(3)
    widths = []
    for n in (20, 200, 2000):
        coin = (rng.random(n) < 0.6).astype(float)
        e = st.mean_interval(coin)
        assert e.lo < e.value < e.hi and e.value == coin.mean() and e.n == n
        widths.append(e.hi - e.lo)
    assert widths[0] > widths[1] > widths[2]
    # about the normal approximation's 2 x 1.96 x sqrt(p (1 - p) / n) at n = 2000
    assert widths[2] == pytest.approx(2 * 1.96 * np.sqrt(0.24 / 2000), rel=0.2)
    # seeded: the same data, the same interval
    assert st.mean_interval(coin) == st.mean_interval(coin)


def test_time_to_success_counts_only_the_successful_episodes():
    time = np.array([1.0, 2.0, 3.0, 100.0])
    success = np.array([1, 1, 1, 0])
    e = st.success_time_interval(time, success)
    assert e.value == pytest.approx(2.0) and 1.0 <= e.lo <= 2.0 <= e.hi <= 3.0 and e.n_den == 3
    none = st.success_time_interval(time, np.zeros(4))
    assert none.value is None and none.lo is None


def test_oracle_ratio_pairs_the_episodes_both_picked():
    e = st.oracle_ratio_interval([2.0, 4.0, 9.0], [1, 1, 0], [1.0, 2.0, 1.0], [1, 1, 1])
    assert e.value == pytest.approx(2.0) and e.lo == pytest.approx(2.0) and e.hi == pytest.approx(2.0)


def test_pooled_interval_resamples_seeds_too():
    # two seeds, each constant: within a seed no spread, between them a lot
    values = np.array([[1.0] * 30, [3.0] * 30])
    pooled = st.mean_interval(values)
    assert pooled.value == pytest.approx(2.0) and pooled.lo == pytest.approx(1.0) and pooled.hi == pytest.approx(3.0)
    with pytest.raises(ValueError, match="same shape"):
        st.ratio_interval(np.ones(3), np.ones(4))


def test_beats_needs_a_lower_cost_and_a_success_not_lower():
    bar = {"cost": 0.5, "success": 0.9}
    assert st.beats({"cost": 0.4, "success": 0.9}, bar)  # tie in success, lower cost
    assert not st.beats({"cost": 0.5, "success": 1.0}, bar)  # same cost
    assert not st.beats({"cost": 0.6, "success": 1.0}, bar)  # higher cost
    assert not st.beats({"cost": 0.1, "success": 0.85}, bar)  # lower success
    assert st.count_beats([{"cost": 0.4, "success": 0.9}, {"cost": 0.6, "success": 0.9},
                           {"cost": 0.45, "success": 0.95}], bar) == 2


# -- the report on hand-made evaluations -------------------------------------------------------------
def _episodes(agent: str, lam: float, costs, success, times=None, kind: str = "pg") -> list[dict]:
    times = costs if times is None else times
    return [{"agent": agent, "lambda": lam, "episode": j, "episode_seed": 100 + j, "success": bool(s),
             "first_pick_success": bool(s), "cost": float(c), "time": float(t), "generation_time": 0.0}
            for j, (c, s, t) in enumerate(zip(costs, success, times))]


def _records(episodes: list[dict], kinds: dict[str, str], best_fixed: str | None = None) -> list[dict]:
    out = []
    for agent, kind in kinds.items():
        for lam in sorted({e["lambda"] for e in episodes}):
            rec = {"agent": agent, "lambda": lam, "kind": kind}
            if kind == "fixed":
                rec["best_fixed"] = agent == best_fixed
            out.append(rec)
    return out


def _evaluation(with_best_static: bool = True) -> tuple[list[dict], list[dict]]:
    n = 20
    ones = [1] * n
    eps = _episodes("pg:seed-0", 0.5, [0.40] * n, ones)  # beats: lower cost, same success
    eps += _episodes("pg:seed-1", 0.5, [0.55] * n, ones)  # higher cost
    eps += _episodes("pg:seed-2", 0.5, [0.30] * n, [1] * (n - 1) + [0])  # lower cost, lower success
    eps += _episodes("pg:seed-3", 0.5, [0.47, 0.52] * (n // 2), ones)  # lower on average, not surely
    eps += _episodes("oracle", 0.5, [0.20] * n, ones)
    eps += _episodes("fixed:a", 0.5, [0.60] * n, ones)
    kinds = {f"pg:seed-{s}": "pg" for s in range(4)} | {"oracle": "oracle", "fixed:a": "fixed"}
    if with_best_static:
        eps += _episodes("best_static", 0.5, [0.50] * n, ones)
        kinds["best_static"] = "best_static"
    return _records(eps, kinds, best_fixed="fixed:a"), eps


def test_k_of_n_counts_seeds_that_beat_best_static():
    records, eps = _evaluation()
    a = analyse(records, eps, [f"pg:seed-{s}" for s in range(4)], seeds=range(4), resamples=500)
    (c,) = a["comparisons"]
    assert a["bar"]["kind"] == "best_static" and a["bar"]["note"] is None
    assert [p["beats"] for p in c["seeds"]] == [True, False, False, True]
    assert c["k_beats"] == 2 and c["n_seeds"] == 4
    # seed 0 is 0.1 s below on every episode; seed 3 only 0.005 s on average (-0.03, +0.02): not surely
    assert [p["beats_surely"] for p in c["seeds"]] == [True, False, False, False] and c["k_beats_surely"] == 1
    assert c["seeds"][0]["cost_difference"]["mean"] == pytest.approx(-0.1)
    assert c["seeds"][0]["oracle_ratio"]["mean"] == pytest.approx(2.0)
    assert c["verdict"].startswith("lambda 0.5: pg beats best_static in 2 of 4 seeds (1 with")
    assert "x the oracle's time [" in c["verdict"] and "single" not in c and "best_static_single" not in c["verdict"]


def test_the_single_sequence_bar_is_counted_beside_best_static():
    """best_static_single (one sequence for every lambda): its own k of N, in the verdict too; the
    bar stays best_static."""
    records, eps = _evaluation()
    eps += _episodes("best_static_single", 0.5, [0.56] * 20, [1] * 20)
    records += [{"agent": "best_static_single", "lambda": 0.5, "kind": "best_static_single",
                 "sequence": ["icp_fine", "pick"]}]
    a = analyse(records, eps, [f"pg:seed-{s}" for s in range(4)], seeds=range(4), resamples=500)
    (c,) = a["comparisons"]
    assert a["bar"]["name"] == "best_static" and c["k_beats"] == 2
    # seeds 0, 1 and 3 are below 0.56 s with every pick; seed 2 is cheaper but misses one
    assert c["single"]["k_beats"] == 3 and c["single"]["bar"] == "best_static_single"
    assert c["single"]["bar_cost"]["mean"] == pytest.approx(0.56) and c["single"]["sequence"] == ["icp_fine", "pick"]
    assert "beats best_static_single (icp_fine+pick, one sequence for every lambda) in 3 of 4" in c["verdict"]
    assert "best_static_single" not in a["learned"]


def test_the_threshold_rule_is_counted_beside_best_static():
    """best_threshold (the searched threshold rule): its own k of N, its rule in the verdict; a
    baseline, not a learned seed; the bar stays best_static."""
    records, eps = _evaluation()
    eps += _episodes("best_threshold", 0.5, [0.42] * 20, [1] * 20)
    rule = "pick at pick_success >= 0.7, else regenerate > icp_point"
    records += [{"agent": "best_threshold", "lambda": 0.5, "kind": "best_threshold", "rule": rule}]
    a = analyse(records, eps, [f"pg:seed-{s}" for s in range(4)], seeds=range(4), resamples=500)
    (c,) = a["comparisons"]
    assert a["bar"]["name"] == "best_static" and c["k_beats"] == 2
    # only seed 0 (0.40 s, every pick) is below 0.42 s without missing a pick
    assert c["threshold"]["k_beats"] == 1 and c["threshold"]["sequence"] == rule
    assert f"beats best_threshold ({rule}) in 1 of 4" in c["verdict"] and "best_threshold" not in a["learned"]


def test_without_best_static_the_best_fixed_pipeline_is_the_bar_and_the_report_says_so():
    records, eps = _evaluation(with_best_static=False)
    a = analyse(records, eps, [f"pg:seed-{s}" for s in range(4)], resamples=200)
    assert a["bar"]["kind"] == "best_fixed" and a["bar"]["name"] == "fixed:a"
    assert "no best_static" in a["bar"]["note"]
    assert a["comparisons"][0]["k_beats"] == 3  # seeds 0, 1 and 3 are below 0.60 s with all picked


def test_verdict_of_an_evaluation_folder(tmp_path):
    records, eps = _evaluation()
    (tmp_path / "results.json").write_text(json.dumps(records))
    (tmp_path / "episodes.jsonl").write_text("".join(json.dumps(e) + "\n" for e in eps))
    line = verdict(tmp_path, "pg:seed-0")
    assert "\n" not in line and line.startswith("pg:seed-0 (lambda 0.5, 20 episodes): beats best_static")
    assert "paired difference -0.100" in line and "2.00x the oracle's time [2.00, 2.00]" in line
    assert "best_static_single" not in line
    eps += _episodes("best_static_single", 0.5, [0.45] * 20, [1] * 20)
    records += [{"agent": "best_static_single", "lambda": 0.5, "kind": "best_static_single"}]
    (tmp_path / "results.json").write_text(json.dumps(records))
    (tmp_path / "episodes.jsonl").write_text("".join(json.dumps(e) + "\n" for e in eps))
    line = verdict(tmp_path, "pg:seed-0")  # 0.40 s against 0.45 s, every pick: beats it too
    assert "; beats best_static_single (one sequence for every lambda): cost 0.450" in line, line
    assert "does not beat best_static_single" in verdict(tmp_path, "pg:seed-1")  # 0.55 s
    with pytest.raises(ValueError, match="name the agent"):
        verdict(tmp_path)  # four learned agents
    with pytest.raises(ValueError, match="no agent 'pg:seed-9'"):
        verdict(tmp_path, "pg:seed-9")
    with pytest.raises(FileNotFoundError, match="results.json"):
        verdict(tmp_path / "none")


# -- the command -------------------------------------------------------------------------------------
def test_study_runs_end_to_end_and_resumes_without_retraining(tmp_path_factory, tmp_path, capsys):
    from perception_config.cli import main

    table = tmp_path / "cost_model.json"
    table.write_text(json.dumps({"cost_table": {"action:pick": 0.3}}))
    out = tmp_path / "study"
    argv = ["study", "--dataset", str(tiny_dataset(tmp_path_factory)), "--pipeline",
            str(pipeline_file(tmp_path_factory)), "--out", str(out), "--seeds", "2", "--episodes", "16",
            "--eval-episodes", "3", "--lambdas", "0.5", "--cost-table", str(table),
            "--agent-param", "batch_episodes=8", "--quiet"]
    import inspect

    from perception_config.learning.evaluation import evaluate

    if "best_static_episodes" in inspect.signature(evaluate).parameters:  # a small search: the mechanics only
        argv += ["--best-static-episodes", "2", "--best-static-length", "2"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "lambda 0.5: pg beats" in printed and "of 2 seeds" in printed
    study = json.loads((out / "study.json").read_text())
    assert study["seeds"] == [0, 1] and study["cost_model"] == str(table.resolve())
    assert set(study["training_seconds"]) == {"0", "1"} and all(v > 0 for v in study["training_seconds"].values())
    assert study["learned"] == ["pg:seed-0", "pg:seed-1"] and study["command"][:2] == ["perception-config", "study"]
    (c,) = study["comparisons"]
    assert c["bar_kind"] in ("best_static", "best_fixed") and 0 <= c["k_beats"] <= 2
    rows = {r["agent"] for r in study["agents"]}
    assert {"pg:seed-0", "pg:seed-1", "oracle", "random"} <= rows
    for r in study["agents"]:
        e = r["episode_cost"]
        assert e["lo"] <= e["mean"] <= e["hi"] and r["episodes"] == 3
    assert (out / "study.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the seeds trained with the one cost table
    from perception_config.agents.policy_io import read_file

    for s in (0, 1):
        meta, _ = read_file(out / f"seed-{s}" / "policy.safetensors")
        assert meta["extra"]["env_settings"]["cost_table"] == {"action:pick": 0.3}

    # Run again: nothing trained, nothing evaluated again; the statistics are the same.
    kept = [out / f"seed-{s}" / n for s in (0, 1) for n in ("policy.safetensors", "checkpoint.safetensors")]
    kept += [out / "evaluation" / "results.json"]
    before = [p.stat().st_mtime_ns for p in kept]
    assert main([a for a in argv if a != "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert printed.count("is trained already, kept") == 2 and "evaluation already, kept" in printed
    assert [p.stat().st_mtime_ns for p in kept] == before
    again = json.loads((out / "study.json").read_text())
    assert again["comparisons"] == study["comparisons"]

    # The one-line verdict of the study's evaluation, from the shell.
    assert main(["study", "--verdict", str(out / "evaluation"), "--verdict-agent", "pg:seed-1"]) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith("pg:seed-1 (lambda 0.5, 3 episodes):") and "oracle's time" in line

    # Another cost table over the same study folder: refused, naming the seed.
    table.write_text(json.dumps({"cost_table": {"action:pick": 0.4}}))
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "seed-0" in err and "trained with other settings" in err and "cost_table" in err


def test_a_study_seed_can_be_the_validation_best_of_restarts(tmp_path_factory, tmp_path, capsys):
    """--restarts 2: each study seed trains two runs (seeds s and s + 1000) in its folder and its
    policy is the one of lower validation cost (seeds.csv says which); the study kept that way is
    refused under another restarts count."""
    from perception_config.cli import main
    from perception_config.learning.seed_selection import SEEDS_CSV

    out = tmp_path / "study"
    argv = ["study", "--dataset", str(tiny_dataset(tmp_path_factory)), "--pipeline",
            str(pipeline_file(tmp_path_factory)), "--out", str(out), "--seeds", "1", "--restarts", "2",
            "--episodes", "8", "--eval-episodes", "2", "--lambdas", "0.5", "--cost-table", "blocks",
            "--best-static-episodes", "0", "--agent-param", "batch_episodes=8", "--quiet"]
    assert main(argv) == 0
    study = json.loads((out / "study.json").read_text())
    assert study["restarts"] == 2 and study["learned"] == ["pg:seed-0"]
    rows = (out / "seed-0" / SEEDS_CSV).read_text().splitlines()
    assert [r.split(",")[0] for r in rows[1:]] == ["0", "1000"]
    shipped = next(r.split(",")[1] for r in rows[1:] if r.endswith(",1"))
    assert (out / "seed-0" / "policy.safetensors").read_bytes() == \
        (out / "seed-0" / shipped / "policy.safetensors").read_bytes()
    capsys.readouterr()
    assert main([a if a != "2" else "1" for a in argv]) == 2  # restarts 1 over it (eval episodes 1)
    assert "the best of 2 runs, this study has restarts 1" in capsys.readouterr().err
