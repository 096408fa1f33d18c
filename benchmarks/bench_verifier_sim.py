"""The pick-success score trained in simulation on a real dataset's own meshes, judged on its real frames.

    .venv/bin/python benchmarks/bench_verifier_sim.py [--sets lmo ycbv-rgbd] [--variants clean realism]
        [--scenes 4] [--episodes 1500] [--work outputs/bench_verifier_sim]

Per real RGB-D set of ../shared/data (skipped when absent) and per variant:
1. `perception-config synth --models <set>/models --camera <set> [--realism] --scenes N`: scenes
   of the set's meshes seen by the set's camera; `realism` adds the calibration and annotation
   errors of a real cell (datasets/realism.py), `clean` does not;
2. `perception-config fit-score` on every image of it (random masked-policy episodes, lambdas
   0.1-1.0; the fit's own held-out figures are synthetic). Variants:
   - `clean`, `realism`: those episodes' hypotheses, labelled with the declared symmetries;
   - `recipe`: realism, plus the ranked candidates of the cell's generators on `--candidates`
     images (their own mistakes: flips, a neighbouring part), labelled with the declared or
     derived symmetries (`--candidates N --symmetries derived`);
   - `recipe-crops`: the same with the crop branch (`--crops`: a small CNN on the rendered-
     against-observed crop beside the features);
3. `benchmarks/bench_pick_success.py --model <fit> --sets <set>` (and `lmo-rgb` for lmo): AUC,
   Brier and ECE on the real frames' hypotheses (perturbed from the annotated ground truth at
   lambda 0.1, 0.3, 0.5), RGB-D and as RGB-only;
4. `perception-config bench generators --dataset <set> --pipeline cell --verifier <fit>`: the
   model on the cell generators' own candidates of the real frames (AUC, Brier, ECE; labels
   under the declared or derived symmetries), and each generator ranked by it and refusing
   below 0.5 (offered, top-1, confident wrong).
The real frames are never trained on. A step whose output exists is not run again. Writes
results/verifier_sim.json (one entry per set and variant), copies step 4's files to
results/generators_<set>_<variant>.{json,png}, and prints one line each.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
CLI = [sys.executable, "-m", "perception_config.cli"]  # this checkout's code (run from REPO)
SET_NAMES = {"lmo": "lmo RGB-D", "ycbv-rgbd": "ycbv-rgbd RGB-D"}  # bench_pick_success.py's set names
VARIANTS = ("clean", "realism", "recipe", "recipe-crops")


def run(cmd: list[str], log: Path) -> None:
    with open(log, "w") as f:
        subprocess.run(cmd, check=True, stdout=f, stderr=subprocess.STDOUT, cwd=REPO,
                       env={**os.environ, "OMP_NUM_THREADS": "1"})


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sets", nargs="+", choices=sorted(SET_NAMES), default=sorted(SET_NAMES))
    ap.add_argument("--variants", nargs="+", choices=VARIANTS, default=["recipe", "recipe-crops"])
    ap.add_argument("--candidates", type=int, default=30, help="images whose generator candidates are added (recipe)")
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
            realism = variant != "clean"
            synth = args.work / f"{name}-{'realism' if realism else 'clean'}-synth"
            fit, scored = args.work / f"{tag}-fit", args.work / f"{tag}-real.json"
            generators = args.work / f"{tag}-generators"
            if not (synth / "dataset_info.json").is_file():
                run(CLI + ["synth", "--models", str(real / "models"), "--camera", str(real), "--scenes",
                           str(args.scenes), "--out", str(synth), "--quiet"]
                    + (["--realism"] if realism else []), args.work / f"{tag}-synth.log")
            t0 = time.perf_counter()
            if not (fit / "pick_success.safetensors").is_file():
                recipe = (["--candidates", str(args.candidates), "--symmetries", "derived"]
                          if "recipe" in variant else [])
                crops = ["--crops"] if variant.endswith("crops") else ["--hidden", "32,16", "--epochs", "300"]
                run(CLI + ["fit-score", "--dataset", str(synth), "--all-images", "--episodes", str(args.episodes),
                           "--lambdas", "0.1,0.3,0.5,0.7,1.0", "--max-steps", "8", *recipe, *crops,
                           "--seed", "0", "--out", str(fit), "--quiet"], args.work / f"{tag}-fit.log")
                (fit / "seconds.txt").write_text(f"{time.perf_counter() - t0:.0f}\n")
            if not scored.is_file():
                sets = [name] + (["lmo-rgb"] if name == "lmo" and (SHARED / "lmo-rgb").is_dir() else [])
                run([sys.executable, str(REPO / "benchmarks" / "bench_pick_success.py"), "--model", str(fit),
                     "--sets", *sets, "--out", str(scored)], args.work / f"{tag}-real.log")
            if "recipe" in variant and not (generators / "generators.json").is_file():
                run(CLI + ["bench", "generators", "--dataset", str(real), "--pipeline", "cell", "--verifier", str(fit),
                           "--out", str(generators), "--quiet"], args.work / f"{tag}-generators.log")
            sets = json.loads(scored.read_text())["sets"]
            s = sets[SET_NAMES[name]]
            synthetic = json.loads((fit / "metrics.json").read_text()).get("test", {}).get("rgbd", {})
            results[tag] = {"set": name, "variant": variant, "scenes": args.scenes, "episodes": args.episodes,
                            "real": {k: s[k] for k in ("n", "base_rate", "auc", "brier", "ece")},
                            "real_per_lambda": s["per_lambda"], "synthetic_held_out": synthetic,
                            "rgb_only": {k: {m: v[m] for m in ("n", "auc", "brier", "ece")}
                                         for k, v in sets.items() if "RGB-only" in k}}
            if (fit / "seconds.txt").is_file():
                results[tag]["fit_seconds"] = float((fit / "seconds.txt").read_text())
            line = (f"{tag:22s} perturbed: AUC {s['auc']:.3f} Brier {s['brier']:.3f} ECE {s['ece']:.3f}  "
                    f"(synthetic held-out AUC {synthetic.get('auc', float('nan')):.3f})")
            if (generators / "generators.json").is_file():
                g = json.loads((generators / "generators.json").read_text())
                keep = args.out.parent / f"generators_{name.replace('-', '_')}_{variant.replace('-', '_')}"
                for ext in ("json", "png"):  # beside the other generator results (docs: Results, generators)
                    shutil.copyfile(generators / f"generators.{ext}", keep.with_suffix(f".{ext}"))
                v = g["verifier_all"]
                results[tag]["candidates"] = {"all": v, "per_generator": {
                    n: {"own": {"refused": r["summary"]["refused"], **r["summary"]["derived"]},
                        "ranked": r["summary"].get("verifier")} for n, r in g["generators"].items()}}
                line += f"; candidates: AUC {v['auc']:.3f} Brier {v['brier']:.3f} ECE {v['ece']:.3f}"
            print(line)
            args.out.write_text(json.dumps(results, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
