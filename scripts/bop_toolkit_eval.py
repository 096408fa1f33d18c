"""bop_toolkit's BOP19 pose evaluation (eval_bop19_pose.py) on the BOP results `evaluate` writes.

Run it with a Python that has bop_toolkit's dependencies (numpy < 2, scipy, imageio, pypng; for
VSD vispy and PyOpenGL), not the project's: this file imports nothing from perception_config.

    <bop_toolkit python> scripts/bop_toolkit_eval.py --toolkit ../shared/tools/bop_toolkit \\
        --dataset data/default --results outputs/demo/evaluation/bop --eval-path /tmp/bop_eval [--vsd]

What runs, by default: the MSSD and MSPD entries of `p["errors"]` of bop_toolkit's
scripts/eval_bop19_pose.py (read from that script), each as eval_bop19_pose.py runs it:
scripts/eval_calc_errors.py with its arguments (all result files in one call), then
scripts/eval_calc_scores.py once per correctness threshold (and per tau for VSD), and the mean of
the recalls (its "Average recall"). The scripts run unmodified, one after the other in this
process (runpy, as `python script args`; eval_bop19_pose.py starts a process for each, 121 per
result file with VSD, which costs about a minute). `--vsd` adds the VSD entry (bop_toolkit's vispy
renderer) and the overall AR, the mean of the three. `--eval-bop19-pose` runs eval_bop19_pose.py
itself instead. VSD renders with OpenGL through EGL: without a GPU, Mesa's llvmpipe on EGL's
surfaceless platform (apt: libegl1 libegl-mesa0 libgl1-mesa-dri libgl1 libopengl0; `headless_gl_env`).

bop_toolkit is not modified. Its dataset_params knows the BOP datasets by name; a dataset it does
not know (the synthetic default) is described to it, in this process, from its
folder: object ids from models_eval/models_info.json, scene ids from the split's folders, the
image size from camera.json, the file layout of the classic BOP datasets. The dataset is linked
into <eval-path>/datasets under the name the result files carry.
"""
from __future__ import annotations

import argparse
import ast
import json
import os
import runpy
import sys
from pathlib import Path
from typing import Any

ERROR_TYPES = ("mssd", "mspd")  # eval_bop19_pose.py's errors that need no renderer (VSD: --vsd)
VSD_DELTA_MM = 15  # VSD delta for a dataset bop_toolkit does not know: its classic datasets' (metrics.VSD_DELTA)
_TEMPLATE_DATASET = "lm"  # a classic-layout BOP dataset whose path templates are reused


# --------------------------------------------------------------------------- bop_toolkit's dataset list


def describe_dataset(dataset_params: Any, name: str) -> None:
    """Teach bop_toolkit's dataset_params (the module, in this process) the dataset `name` found
    under the datasets path, when bop_toolkit does not know it."""
    orig_split, orig_model = dataset_params.get_split_params, dataset_params.get_model_params

    def get_model_params(datasets_path: str, dataset_name: str, model_type: str | None = None) -> dict:
        if dataset_name != name:
            return orig_model(datasets_path, dataset_name, model_type)
        models = Path(datasets_path) / dataset_name / ("models" + (f"_{model_type}" if model_type else ""))
        info_path = models / "models_info.json"
        if not info_path.is_file():
            raise FileNotFoundError(f"{info_path} not found: bop_toolkit evaluates on the dataset's "
                                    f"{models.name}/ (perception-config synth writes it; for an older "
                                    "dataset copy models/ to models_eval/)")
        info = json.loads(info_path.read_text())
        return {
            "obj_ids": sorted(int(k) for k in info),
            "symmetric_obj_ids": sorted(int(k) for k, v in info.items()
                                        if v.get("symmetries_discrete") or v.get("symmetries_continuous")),
            "model_tpath": str(models / "obj_{obj_id:06d}.ply"),
            "models_info_path": str(info_path),
        }

    def get_split_params(datasets_path: str, dataset_name: str, split: str, split_type: str | None = None) -> dict:
        if dataset_name != name:
            return orig_split(datasets_path, dataset_name, split, split_type)
        p = orig_split(datasets_path, _TEMPLATE_DATASET, split, split_type)
        old, new = os.path.join(datasets_path, _TEMPLATE_DATASET), os.path.join(datasets_path, dataset_name)
        p = {k: (new + v[len(old):] if isinstance(v, str) and v.startswith(old) else v) for k, v in p.items()}
        cam = json.loads((Path(new) / "camera.json").read_text())
        split_dir = Path(p["split_path"])
        p.update(name=dataset_name, im_size=(int(cam["width"]), int(cam["height"])),
                 scene_ids=sorted(int(d.name) for d in split_dir.iterdir() if d.is_dir() and d.name.isdigit()),
                 depth_range=None, azimuth_range=None, elev_range=None)
        return p

    dataset_params.get_model_params = get_model_params
    dataset_params.get_split_params = get_split_params


# --------------------------------------------------------------------------- the evaluation


def bop19_errors(toolkit: Path) -> dict[str, Any]:
    """eval_bop19_pose.py's parameter dict `p`, evaluated from the script's source (its first
    assignment to `p`), without running the script."""
    import numpy as np
    from bop_toolkit_lib import config  # noqa: F401  (used by the evaluated expression)

    src = (toolkit / "scripts" / "eval_bop19_pose.py").read_text()
    node = next(n for n in ast.parse(src).body if isinstance(n, ast.Assign)
                and any(isinstance(t, ast.Name) and t.id == "p" for t in n.targets))
    return eval(compile(ast.Expression(node.value), "eval_bop19_pose.py", "eval"), {"np": np, "config": config})


def _run(script: Path, args: list[str]) -> None:
    """Run one bop_toolkit script as `python script args` would (in this process)."""
    print("Running: " + " ".join([script.name, *args]), flush=True)
    argv = sys.argv
    sys.argv = [str(script), *args]
    try:
        runpy.run_path(str(script), run_name="__main__")
    except SystemExit as e:
        if e.code not in (None, 0):
            raise RuntimeError(f"bop_toolkit's {script.name} failed (exit {e.code})") from None
    finally:
        sys.argv = argv


def _prepare(toolkit: Path, dataset: Path, results: Path, eval_path: Path, result_filenames: list[str] | None,
             targets: Path | None) -> tuple[list[str], str, Path, Path]:
    """Check the inputs, set BOP_PATH, link the dataset under <eval-path>/datasets by the name the
    result files carry: (result files, dataset name, targets file, datasets folder)."""
    if not (toolkit / "scripts" / "eval_bop19_pose.py").is_file():
        raise FileNotFoundError(f"not bop_toolkit's folder (no scripts/eval_bop19_pose.py): {toolkit}")
    if not (dataset / "camera.json").is_file():
        raise FileNotFoundError(f"not a BOP dataset folder (no camera.json): {dataset}")
    if not results.is_dir():
        raise FileNotFoundError(f"results folder not found: {results}")
    datasets = eval_path / "datasets"
    os.environ["BOP_PATH"] = str(datasets)  # before bop_toolkit_lib.config reads it
    sys.path.insert(0, str(toolkit))
    from bop_toolkit_lib import inout

    files = result_filenames or sorted(p.name for p in results.glob("*.csv"))
    if not files:
        raise FileNotFoundError(f"no BOP result file (*.csv) in {results}")
    names = {inout.parse_result_filename(f)[2] for f in files}
    if len(names) != 1:
        raise ValueError(f"the result files name several datasets {sorted(names)}: evaluate one dataset at a time")
    name = names.pop()
    if targets is None:
        found = sorted(results.glob("targets_*.json"))
        if len(found) != 1:
            raise FileNotFoundError(f"expected one targets_*.json next to the result files in {results}, "
                                    f"found {[p.name for p in found]}: give --targets")
        targets = found[0]
    datasets.mkdir(parents=True, exist_ok=True)
    link = datasets / name
    if link.is_symlink() or link.exists():
        if link.resolve() != dataset.resolve():
            raise ValueError(f"{link} already points at {link.resolve()}, not at {dataset}")
    else:
        link.symlink_to(dataset, target_is_directory=True)

    return files, name, targets, datasets


def evaluate(toolkit: Path, dataset: Path, results: Path, eval_path: Path, result_filenames: list[str] | None = None,
             targets: Path | None = None, num_workers: int = 1, vsd: bool = False) -> dict[str, dict[str, float]]:
    """AR_MSSD and AR_MSPD of bop_toolkit per result file: {file name: {"mssd": ar, "mspd": ar,
    "time": average time per image}}; also written to <eval-path>/<result>/scores_bop19_mssd_mspd.json.
    With `vsd` also eval_bop19_pose.py's VSD step (its vispy renderer, see `headless_gl_env`):
    "vsd" and "ar" (bop19_average_recall, the mean of the three), written to
    scores_bop19_vsd_mssd_mspd.json."""
    toolkit, dataset, results, eval_path = (Path(x).resolve() for x in (toolkit, dataset, results, eval_path))
    files, name, targets, datasets = _prepare(toolkit, dataset, results, eval_path, result_filenames, targets)
    import numpy as np
    from bop_toolkit_lib import dataset_params, inout, misc

    p = bop19_errors(toolkit)
    types = ("vsd", *ERROR_TYPES) if vsd else ERROR_TYPES
    errors = [e for e in p["errors"] if e["type"] in types]
    if vsd:
        os.environ.update(headless_gl_env())  # before bop_toolkit's renderer imports vispy
    try:
        dataset_params.get_model_params(str(datasets), name)
    except KeyError:  # not a BOP dataset bop_toolkit knows
        describe_dataset(dataset_params, name)
    scripts = toolkit / "scripts"
    out: dict[str, dict[str, float]] = {f: {} for f in files}
    for error in errors:
        vsd_args: list[str] = []
        if error["type"] == "vsd":  # eval_bop19_pose.py's VSD arguments (its delta, or 15 mm for a new dataset)
            deltas = {**error["vsd_deltas"], name: error["vsd_deltas"].get(name, VSD_DELTA_MM)}
            delta = deltas[name]
            vsd_args = [f"--vsd_deltas={','.join(f'{k}:{v}' for k, v in deltas.items())}",
                        f"--vsd_taus={','.join(map(str, error['vsd_taus']))}",
                        f"--vsd_normalized_by_diameter={error['vsd_normalized_by_diameter']}"]
        _run(scripts / "eval_calc_errors.py", [f"--n_top={error['n_top']}",
                     f"--error_type={error['type']}", f"--result_filenames={','.join(files)}",
                     f"--renderer_type={p['renderer_type']}", f"--results_path={results}",
                     f"--eval_path={eval_path}", f"--targets_filename={targets}",
                     f"--max_sym_disc_step={p['max_sym_disc_step']}", "--skip_missing=1",
                     f"--num_workers={num_workers}", f"--datasets_path={datasets}", *vsd_args])
        signs = ([misc.get_error_signature("vsd", error["n_top"], vsd_delta=delta, vsd_tau=tau)
                  for tau in error["vsd_taus"]] if error["type"] == "vsd"
                 else [misc.get_error_signature(error["type"], error["n_top"])])
        for sign in signs:  # one error folder per tau for VSD, as eval_bop19_pose.py
            dirs = [os.path.join(inout.parse_result_filename(f)[0], sign) for f in files]
            for correct_th in error["correct_th"]:
                _run(scripts / "eval_calc_scores.py", [f"--error_dir_paths={','.join(dirs)}",
                             f"--eval_path={eval_path}", f"--targets_filename={targets}",
                             f"--visib_gt_min={p['visib_gt_min']}",
                             f"--correct_th_{error['type']}={','.join(map(str, correct_th))}",
                             f"--datasets_path={datasets}"])
        for f in files:
            result_name = inout.parse_result_filename(f)[0]
            recalls = [inout.load_json(str(eval_path / result_name / sign /
                                           f"scores_{misc.get_score_signature(th, p['visib_gt_min'])}.json"))["recall"]
                       for sign in signs for th in error["correct_th"]]
            out[f][error["type"]] = float(np.mean(recalls))
    for f in files:
        ests = inout.load_bop_results(str(results / f), version="bop19")
        ok, msg, times, available = inout.check_consistent_timings(ests, "im_id")
        if not ok:
            raise ValueError(f"{f}: {msg}")
        out[f]["time"] = float(np.mean(list(times.values()))) if available else -1.0
        scores = {f"bop19_average_recall_{k}": out[f][k] for k in types}
        if vsd:  # eval_bop19_pose.py's final score
            out[f]["ar"] = scores["bop19_average_recall"] = float(np.mean([out[f][k] for k in types]))
        scores["bop19_average_time_per_image"] = out[f]["time"]
        inout.save_json(str(eval_path / inout.parse_result_filename(f)[0] /
                            f"scores_bop19_{'_'.join(types)}.json"), scores)
    return out


# --------------------------------------------------------------------------- eval_bop19_pose.py itself

# Started by Python in every process of eval_bop19_pose.py's run (its eval_calc_errors.py and
# eval_calc_scores.py are `python script ...` subprocesses): describes the dataset to
# bop_toolkit's dataset_params there too, when bop_toolkit does not know it.
_SITECUSTOMIZE = """import os
if os.environ.get("PERCEPTION_CONFIG_BOP_DATASET"):
    import bop_toolkit_eval
    from bop_toolkit_lib import dataset_params
    bop_toolkit_eval.describe_dataset(dataset_params, os.environ["PERCEPTION_CONFIG_BOP_DATASET"])
"""


def headless_gl_env() -> dict[str, str]:
    """The environment bop_toolkit's vispy renderer needs without a display or GPU: EGL (the
    renderer sets PYOPENGL_PLATFORM=egl itself and vispy's EGL app) on Mesa's surfaceless
    platform, i.e. llvmpipe software rendering (apt: libegl1 libegl-mesa0 libgl1-mesa-dri libgl1 libopengl0)."""
    return {"PYOPENGL_PLATFORM": "egl", "EGL_PLATFORM": os.environ.get("EGL_PLATFORM", "surfaceless")}


def eval_bop19_pose(toolkit: Path, dataset: Path, results: Path, eval_path: Path,
                    result_filenames: list[str] | None = None, targets: Path | None = None,
                    num_workers: int = 1) -> dict[str, dict[str, float]]:
    """bop_toolkit's scripts/eval_bop19_pose.py itself (VSD with its vispy renderer, MSSD, MSPD,
    the overall AR): {file name: its scores_bop19.json}. The script's source runs unmodified
    but for one entry, when bop_toolkit does not know the dataset: its VSD delta ({dataset}: 15
    mm) added to the hard-coded `vsd_deltas` of its parameters. Its subprocesses run with this
    Python first on PATH (it calls `python`), bop_toolkit on PYTHONPATH and a sitecustomize that
    describes the dataset to dataset_params (see `describe_dataset`)."""
    toolkit, dataset, results, eval_path = (Path(x).resolve() for x in (toolkit, dataset, results, eval_path))
    files, name, targets, datasets = _prepare(toolkit, dataset, results, eval_path, result_filenames, targets)
    from bop_toolkit_lib import dataset_params, inout

    script = toolkit / "scripts" / "eval_bop19_pose.py"
    tree = ast.parse(script.read_text())
    known = True
    try:
        dataset_params.get_model_params(str(datasets), name)
    except KeyError:
        known = False
    if not known:
        deltas = [n for n in ast.walk(tree) if isinstance(n, ast.Dict)
                  and any(isinstance(k, ast.Constant) and k.value == "vsd_deltas" for k in n.keys)]
        if len(deltas) != 1:
            raise RuntimeError(f"cannot find the vsd_deltas of {script}'s parameters")
        d = deltas[0].values[[k.value for k in deltas[0].keys].index("vsd_deltas")]
        d.keys.append(ast.Constant(name))
        d.values.append(ast.Constant(VSD_DELTA_MM))
        ast.fix_missing_locations(tree)
        hook = eval_path / "_sitecustomize"
        hook.mkdir(parents=True, exist_ok=True)
        (hook / "sitecustomize.py").write_text(_SITECUSTOMIZE)
        os.environ["PERCEPTION_CONFIG_BOP_DATASET"] = name
        paths = [str(hook), str(Path(__file__).resolve().parent)]
    else:
        paths = []
    os.environ["PYTHONPATH"] = os.pathsep.join([*paths, str(toolkit), *filter(None, [os.environ.get("PYTHONPATH")])])
    os.environ["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])
    os.environ.update(headless_gl_env())
    args = [f"--result_filenames={','.join(files)}", f"--results_path={results}", f"--eval_path={eval_path}",
            f"--targets_filename={targets}", f"--num_workers={num_workers}"]
    print("Running: " + " ".join([script.name, *args]), flush=True)
    argv = sys.argv
    sys.argv = [str(script), *args]
    try:
        exec(compile(tree, str(script), "exec"), {"__name__": "__main__", "__file__": str(script)})
    except SystemExit as e:
        if e.code not in (None, 0):
            raise RuntimeError(f"bop_toolkit's {script.name} failed (exit {e.code})") from None
    finally:
        sys.argv = argv
    return {f: inout.load_json(str(eval_path / inout.parse_result_filename(f)[0] / "scores_bop19.json"))
            for f in files}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--toolkit", type=Path, required=True,
                    help="bop_toolkit's folder (its scripts/ and bop_toolkit_lib/)")
    ap.add_argument("--dataset", type=Path, required=True, help="the evaluated BOP dataset's folder")
    ap.add_argument("--results", type=Path, required=True, help="folder of the result CSVs (evaluate's bop/)")
    ap.add_argument("--eval-path", type=Path, required=True, help="bop_toolkit's output folder (errors, scores)")
    ap.add_argument("--result-filenames", default=None, help="comma-separated CSV names (default: all in --results)")
    ap.add_argument("--targets", type=Path, default=None,
                    help="targets file (default: the targets_*.json in --results)")
    ap.add_argument("--num-workers", type=int, default=1)
    ap.add_argument("--eval-bop19-pose", action="store_true",
                    help="run bop_toolkit's eval_bop19_pose.py itself: VSD (its vispy renderer over EGL; without a "
                         "GPU Mesa's llvmpipe, apt libegl1 libegl-mesa0 libgl1-mesa-dri libgl1 libopengl0; the venv "
                         "needs vispy and PyOpenGL), MSSD, MSPD and the overall AR")
    ap.add_argument("--vsd", action="store_true",
                    help="also eval_bop19_pose.py's VSD step (its vispy renderer, headless as for --eval-bop19-pose) "
                         "and the overall AR")
    a = ap.parse_args(argv)
    if a.eval_bop19_pose:
        try:
            full = eval_bop19_pose(a.toolkit, a.dataset, a.results, a.eval_path,
                                   a.result_filenames.split(",") if a.result_filenames else None, a.targets,
                                   a.num_workers)
        except (OSError, ValueError, RuntimeError, ImportError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        print("bop_toolkit (eval_bop19_pose.py):")
        for f, s in full.items():
            print(f"  {f}: AR {s['bop19_average_recall']:.4f}  AR_VSD {s['bop19_average_recall_vsd']:.4f}  "
                  f"AR_MSSD {s['bop19_average_recall_mssd']:.4f}  AR_MSPD {s['bop19_average_recall_mspd']:.4f}  "
                  f"time/image {s['bop19_average_time_per_image']:.3f} s")
        return 0
    try:
        out = evaluate(a.toolkit, a.dataset, a.results, a.eval_path,
                       a.result_filenames.split(",") if a.result_filenames else None, a.targets, a.num_workers,
                       a.vsd)
    except (OSError, ValueError, RuntimeError, ImportError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"bop_toolkit (eval_bop19_pose.py's {'VSD, ' if a.vsd else ''}MSSD and MSPD steps):")
    for f, s in out.items():
        head = f"AR {s['ar']:.4f}  AR_VSD {s['vsd']:.4f}  " if a.vsd else ""
        print(f"  {f}: {head}AR_MSSD {s['mssd']:.4f}  AR_MSPD {s['mspd']:.4f}  time/image {s['time']:.3f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
