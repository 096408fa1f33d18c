"""The pick-success score trained in simulation on a real dataset's own meshes, judged on its real frames.

    .venv/bin/python benchmarks/bench_verifier_sim.py [--sets lmo ycbv-rgbd] [--variants clean realism]
        [--scenes 4] [--episodes 1500] [--work outputs/bench_verifier_sim]

Per real RGB-D set of ../shared/data (skipped when absent) and per variant of the synthetic data:
1. `perception-config synth --models <set>/models --camera <set> [--realism] --scenes N`: scenes
   of the set's meshes seen by the set's camera; `realism` adds the calibration and annotation
   errors of a real cell (datasets/realism.py), `clean` does not;
2. `perception-config fit-score` on every image of it (random masked-policy episodes, lambdas
   0.1-1.0; the fit's own held-out figures are synthetic);
3. `benchmarks/bench_pick_success.py --model <fit> --sets <set>`: AUC, Brier and ECE on the real
   frames' hypotheses (perturbed from the annotated ground truth at lambda 0.1, 0.3, 0.5).
The real frames are never trained on. A step whose output exists is not run again. Writes
results/verifier_sim.json (one entry per set and variant) and prints one line each.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
CLI = [str(Path(sys.executable).parent / "perception-config")]
SET_NAMES = {"lmo": "lmo RGB-D", "ycbv-rgbd": "ycbv-rgbd RGB-D"}  # bench_pick_success.py's set names


def run(cmd: list[str], log: Path) -> None:
    with open(log, "w") as f:
        subprocess.run(cmd, check=True, stdout=f, stderr=subprocess.STDOUT, cwd=REPO,
                       env={**os.environ, "OMP_NUM_THREADS": "1"})


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sets", nargs="+", choices=sorted(SET_NAMES), default=sorted(SET_NAMES))
    ap.add_argument("--variants", nargs="+", choices=("clean", "realism"), default=["clean", "realism"])
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--episodes", type=int, default=1500)
    ap.add_argument("--work", type=Path, default=REPO / "outputs" / "bench_verifier_sim")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "verifier_sim.json")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    results = json.loads(args.out.read_text()) if args.out.is_file() else {}
    for name in args.sets:
        real = SHARED / name
        if not (real / "models").is_dir():
            print(f"{name}: no {real}: skipped")
            continue
        for variant in args.variants:
            tag = f"{name}-{variant}"
            synth, fit, scored = args.work / f"{tag}-synth", args.work / f"{tag}-fit", args.work / f"{tag}-real.json"
            if not (synth / "dataset_info.json").is_file():
                run(CLI + ["synth", "--models", str(real / "models"), "--camera", str(real), "--scenes",
                           str(args.scenes), "--out", str(synth), "--quiet"]
                    + (["--realism"] if variant == "realism" else []), args.work / f"{tag}-synth.log")
            if not (fit / "pick_success.safetensors").is_file():
                run(CLI + ["fit-score", "--dataset", str(synth), "--all-images", "--episodes", str(args.episodes),
                           "--lambdas", "0.1,0.3,0.5,0.7,1.0", "--max-steps", "8", "--hidden", "32,16",
                           "--epochs", "300", "--seed", "0", "--out", str(fit), "--quiet"],
                    args.work / f"{tag}-fit.log")
            if not scored.is_file():
                run([sys.executable, str(REPO / "benchmarks" / "bench_pick_success.py"), "--model", str(fit),
                     "--sets", name, "--out", str(scored)], args.work / f"{tag}-real.log")
            s = json.loads(scored.read_text())["sets"][SET_NAMES[name]]
            synthetic = json.loads((fit / "metrics.json").read_text()).get("test", {}).get("rgbd", {})
            results[tag] = {"set": name, "variant": variant, "scenes": args.scenes, "episodes": args.episodes,
                            "real": {k: s[k] for k in ("n", "base_rate", "auc", "brier", "ece")},
                            "real_per_lambda": s["per_lambda"], "synthetic_held_out": synthetic}
            print(f"{tag:22s} real AUC {s['auc']:.3f} Brier {s['brier']:.3f} ECE {s['ece']:.3f}  "
                  f"(synthetic held-out AUC {synthetic.get('auc', float('nan')):.3f})")
            args.out.write_text(json.dumps(results, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
