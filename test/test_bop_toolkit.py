"""bop_toolkit (upstream, unmodified, ../shared/tools/bop_toolkit) on a small evaluation's output:
its AR_MSSD and AR_MSPD (eval_bop19_pose.py's MSSD and MSPD steps, through
scripts/bop_toolkit_eval.py) equal the project's, and its recall at 0.1 x diameter equals
recall_mssd.

bop_toolkit needs numpy < 2 (the project has numpy 2): it runs in a venv of its own, built once
from PyPI in ~/.cache/perception_config/bop_toolkit_venv (PERCEPTION_CONFIG_BOP_VENV overrides),
with only what its evaluation scripts import for MSSD / MSPD. Skipped, saying why, without
../shared or when that venv cannot be built (no network, no venv module).
"""
from __future__ import annotations

import fcntl
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from perception_config.evaluation import bop_csv_name, evaluate
from rl_helpers import pipeline_file, tiny_dataset

REPO = Path(__file__).resolve().parents[1]
TOOLKIT = REPO.parent / "shared" / "tools" / "bop_toolkit"
# What bop_toolkit's eval_calc_errors.py / eval_calc_scores.py import for MSSD and MSPD (its
# pyproject lists the renderer, OpenCV, scikit-image... for the rest), at its uv.lock's versions.
REQUIREMENTS = ("numpy==1.26.4", "scipy==1.15.2", "imageio==2.37.0", "pypng==0.20220715.0")
LAMBDAS = (0.3, 1.0)


def bop_venv() -> Path:
    """The python of the bop_toolkit venv, built once (under a lock: parallel sessions share it)."""
    root = Path(os.environ.get("PERCEPTION_CONFIG_BOP_VENV",
                               Path.home() / ".cache" / "perception_config" / "bop_toolkit_venv"))
    python, stamp = root / "bin" / "python", root / "perception_config_requirements.txt"
    wanted = "\n".join(REQUIREMENTS) + "\n"
    root.parent.mkdir(parents=True, exist_ok=True)
    with open(root.parent / f".{root.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if python.exists() and stamp.is_file() and stamp.read_text() == wanted:
            return python
        steps = ([sys.executable, "-m", "venv", "--clear", str(root)],
                 [str(python), "-m", "pip", "install", "-q", "--disable-pip-version-check", *REQUIREMENTS])
        for cmd in steps:
            try:
                done = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
            except (OSError, subprocess.TimeoutExpired) as e:
                pytest.skip(f"cannot build the bop_toolkit venv: {' '.join(cmd[:4])}: {e}")
            if done.returncode != 0:
                pytest.skip(f"cannot build the bop_toolkit venv: {' '.join(cmd[:4])} failed: "
                            f"{(done.stderr or done.stdout).strip()[-600:]}")
        stamp.write_text(wanted)
    return python


@pytest.fixture(scope="module")
def evaluation(tmp_path_factory) -> dict:
    if not (TOOLKIT / "scripts" / "eval_bop19_pose.py").is_file():
        pytest.skip(f"bop_toolkit not found at {TOOLKIT} (../shared/tools/bop_toolkit next to the repository)")
    python = bop_venv()
    dataset = tiny_dataset(tmp_path_factory)
    out = tmp_path_factory.mktemp("bop_eval")
    results = evaluate(dataset, ["random"], LAMBDAS, out / "evaluation", include_baselines=False, seed=3,
                       pipeline=pipeline_file(tmp_path_factory), test_fraction=0.5, time_mode="cost_table",
                       progress=False, plots=False)
    run = subprocess.run(
        [str(python), str(REPO / "scripts" / "bop_toolkit_eval.py"), "--toolkit", str(TOOLKIT),
         "--dataset", str(dataset), "--results", str(out / "evaluation" / "bop"), "--eval-path", str(out / "bop_eval")],
        capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, (run.stdout[-3000:], run.stderr[-3000:])
    return {"records": json.loads(results.read_text()), "eval_path": out / "bop_eval", "dataset": dataset,
            "stdout": run.stdout}


def _bop_scores(evaluation: dict, agent: str, lam: float) -> tuple[dict, Path]:
    result_name = bop_csv_name(agent, lam, evaluation["dataset"].name).removesuffix(".csv")
    folder = evaluation["eval_path"] / result_name
    return json.loads((folder / "scores_bop19_mssd_mspd.json").read_text()), folder


def test_bop_toolkit_average_recalls_equal_the_projects(evaluation):
    for r in evaluation["records"]:
        scores, _ = _bop_scores(evaluation, r["agent"], r["lambda"])
        assert scores["bop19_average_recall_mssd"] == pytest.approx(r["ar_mssd"], abs=1e-12), r["lambda"]
        assert scores["bop19_average_recall_mspd"] == pytest.approx(r["ar_mspd"], abs=1e-12), r["lambda"]
    # not a trivial agreement: the random agent's poses are not all right or all wrong
    assert any(0.0 < r["ar_mssd"] < 1.0 for r in evaluation["records"])
    assert "AR_MSSD" in evaluation["stdout"]


def test_bop_toolkit_recall_at_a_tenth_of_the_diameter_is_recall_mssd(evaluation):
    for r in evaluation["records"]:
        _, folder = _bop_scores(evaluation, r["agent"], r["lambda"])
        scores = json.loads((folder / "error=mssd_ntop=-1" / "scores_th=0.100_min-visib=-1.000.json").read_text())
        assert scores["recall"] == pytest.approx(r["recall_mssd"], abs=1e-12)
        assert scores["targets_count"] == r["episodes"]  # the targets file: exactly the evaluated episodes


def test_bad_input_is_named(evaluation, tmp_path):
    """No result file, or no targets file next to them: an error naming what is missing, exit 2."""
    script = str(REPO / "scripts" / "bop_toolkit_eval.py")
    base = [str(bop_venv()), script, "--toolkit", str(TOOLKIT), "--dataset", str(evaluation["dataset"]),
            "--eval-path", str(tmp_path / "e")]
    (tmp_path / "empty").mkdir()
    run = subprocess.run(base + ["--results", str(tmp_path / "empty")], capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and "no BOP result file (*.csv) in" in run.stderr, run.stderr[-2000:]
    (tmp_path / "no_targets").mkdir()
    (tmp_path / "no_targets" / "random-lam1_tiny-test.csv").write_text("scene_id,im_id,obj_id,score,R,t,time\n")
    run = subprocess.run(base + ["--results", str(tmp_path / "no_targets")], capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 2 and "expected one targets_*.json" in run.stderr, run.stderr[-2000:]
    run = subprocess.run(base[:4] + ["--dataset", str(tmp_path), "--eval-path", str(tmp_path / "e"), "--results",
                                     str(tmp_path / "empty")], capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and "not a BOP dataset folder (no camera.json)" in run.stderr, run.stderr[-2000:]
