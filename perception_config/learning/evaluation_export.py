"""The reports of an evaluation (learning/evaluation.py) besides its JSON: the BOP results CSVs
and targets file bop_toolkit reads (`write_bop_csvs`), the plots (`make_plots`) and the
plain-text table (`format_table`)."""
from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any, Sequence

from ..core.pose_json import pose_from_json
from ..datasets.bop_results import BopResult, write_results_csv
from ..rl.env import PerceptionConfigEnv
from ..util.atomic_file import atomic_write


def _slug(name: str) -> str:
    """A bop_toolkit method name: letters, digits, '+' and '-' only (its parser cuts the file
    name at the first '.' and splits it at '_')."""
    return re.sub(r"[^A-Za-z0-9+-]+", "-", name).strip("-") or "agent"


def bop_dataset_name(name: str) -> str:
    """The dataset part of a bop_toolkit file name: the dataset folder's name without '_', '-'
    and '.' (bop_toolkit reads `{method}_{dataset}-{split}` and finds the dataset at
    BOP_PATH/<dataset>: a folder whose name has those characters must be linked under this one)."""
    return re.sub(r"[^A-Za-z0-9]+", "", name) or "dataset"


def bop_results(episodes: Sequence[dict[str, Any]]) -> list[BopResult]:
    """BOP results rows of the final poses. bop_toolkit wants one time per image: the time of an
    image is the sum of the times of its episodes (the objects are handled one after another)."""
    image_time: dict[tuple[int, int], float] = {}
    for e in episodes:
        key = (e["scene_id"], e["im_id"])
        image_time[key] = image_time.get(key, 0.0) + e["time"]
    rows = []
    for e in episodes:
        pose = pose_from_json(e["final_pose"])
        if pose is None:
            continue
        rows.append(BopResult(e["scene_id"], e["im_id"], e["obj_id"], e["confidence"], pose,
                              image_time[(e["scene_id"], e["im_id"])]))
    return rows


def bop_csv_name(agent: str, lam: float, dataset_name: str, split: str = "test") -> str:
    """`<method>_<dataset>-<split>.csv` with method = <agent>-lam<lambda, '.' written 'p'>
    (e.g. `oracle-lam0p5_default-test.csv`), as bop_toolkit's inout.parse_result_filename reads it."""
    return f"{_slug(agent)}-lam{format(lam, 'g').replace('.', 'p')}_{bop_dataset_name(dataset_name)}-{_slug(split)}.csv"


def bop_targets_name(dataset_name: str, split: str = "test") -> str:
    """The targets file of the BOP CSVs: `targets_<dataset>-<split>.json`."""
    return f"targets_{bop_dataset_name(dataset_name)}-{_slug(split)}.json"


def first_pass(per_episode: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The episodes of each (agent, lambda) with the first occurrence of every (scene, image,
    object instance) only: what a BOP results file can hold (one estimate per target)."""
    seen: set[tuple[Any, ...]] = set()
    out = []
    for e in per_episode:
        key = (e["agent"], e["lambda"], e["scene_id"], e["im_id"], e["obj_id"], e["instance"])
        if key not in seen:
            seen.add(key)
            out.append(e)
    return out


def bop_targets(episodes: Sequence[dict[str, Any]]) -> list[dict[str, int]]:
    """bop_toolkit's test_targets_bop19.json entries for the evaluated episodes of one (agent,
    lambda): one per (scene, image, object), inst_count = its distinct evaluated instances."""
    instances: dict[tuple[int, int, int], set[int]] = {}
    for e in episodes:
        instances.setdefault((e["scene_id"], e["im_id"], e["obj_id"]), set()).add(e["instance"])
    return [{"im_id": im, "inst_count": len(inst), "obj_id": obj, "scene_id": sc}
            for (sc, im, obj), inst in sorted(instances.items())]


def write_bop_csvs(folder: Path, per_episode: Sequence[dict[str, Any]], dataset_name: str,
                   split: str = "test") -> list[Path]:
    """One BOP results CSV per (agent, lambda) of the final poses (first pass of each episode),
    and the targets file of those episodes (the same for every agent and lambda: one plan);
    returns the CSV paths."""
    groups: dict[tuple[str, float], list[dict[str, Any]]] = {}
    for e in first_pass(per_episode):
        groups.setdefault((e["agent"], e["lambda"]), []).append(e)
    paths = []
    targets: list[dict[str, int]] | None = None
    for (agent, lam), eps in groups.items():
        path = folder / bop_csv_name(agent, lam, dataset_name, split)
        folder.mkdir(parents=True, exist_ok=True)
        write_results_csv(path, bop_results(eps))
        paths.append(path)
        mine = bop_targets(eps)
        if targets is not None and mine != targets:
            raise ValueError(f"{agent} at lambda {lam:g} was evaluated on other episodes than the first agent")
        targets = mine
    if targets is not None:
        atomic_write(folder / bop_targets_name(dataset_name, split), json.dumps(targets, indent=1) + "\n")
    return paths


def make_plots(
    out: Path, records: list[dict[str, Any]], per_episode: list[dict[str, Any]], env: PerceptionConfigEnv,
    lams: Sequence[float], plan: Sequence[tuple[int, int]], n_examples: int = 2,
) -> list[Path]:
    """fig5.png, lambda_grid.png (the first planned episode) and a few Fig. 2-style episodes."""
    from ..core import plots

    paths = [plots.plot_fig5(records, out / "fig5.png")]
    index, ep_seed = plan[0]
    hyps = []
    for lam in lams:
        _obs, info = env.reset(options={"episode": index, "lambda": lam, "episode_seed": ep_seed})
        hyps.append((lam, info["pose"]))
    ep = env.episode
    assert ep is not None
    if ep.ground_truth is not None:
        paths.append(plots.plot_lambda_grid(ep.frame, ep.model, ep.ground_truth, hyps, out / "lambda_grid.png"))
    for i, e in enumerate(example_episodes(per_episode, n_examples)):
        frame = env.source.frame(e["scene_id"], e["im_id"])
        obj = frame.objects[e["instance"]]
        title = (f"{e['agent']}  lambda={e['lambda']:g}  scene {e['scene_id']} image {e['im_id']} obj {e['obj_id']}\n"
                 f"{' > '.join(e['actions'])}  ({e['time']:.2f} s, {'picked' if e['success'] else 'not picked'})")
        paths.append(plots.plot_episode(frame, obj.model, obj.gt, pose_from_json(e["initial_pose"]),
                                        pose_from_json(e["final_pose"]), title, out / f"episode_{i}.png"))
    return paths


def example_episodes(per_episode: Sequence[dict[str, Any]], n: int = 2) -> list[dict[str, Any]]:
    """Episodes worth a Fig. 2 picture, of the first agent under evaluation that is not a
    baseline (else the oracle), at the middle lambda: the successful one that started furthest
    from the ground truth (MSSD / diameter), then failures. Without a success there, the
    success comes from the nearest lambda with one, else from the oracle."""
    if n <= 0 or not per_episode:
        return []
    names = list(dict.fromkeys(e["agent"] for e in per_episode))
    agent = next((a for a in names if a not in ("random", "oracle") and not a.startswith("fixed:")),
                 "oracle" if "oracle" in names else names[0])
    lams = sorted({e["lambda"] for e in per_episode})
    mid = lams[len(lams) // 2]
    drawable = [e for e in per_episode if e["initial_pose"] and e["final_pose"]]

    def rel_init(e: dict[str, Any]) -> float:
        v = (e.get("initial_errors") or {}).get("mssd_mm")
        return -1.0 if v is None else v / e["diameter_mm"]

    def successes(name: str) -> list[dict[str, Any]]:
        by_lam = sorted(lams, key=lambda lam: abs(lam - mid))
        for lam in by_lam:
            ok = [e for e in drawable if e["agent"] == name and e["lambda"] == lam and e["success"]]
            if ok:
                return sorted(ok, key=rel_init, reverse=True)
        return []

    ok = successes(agent) or successes("oracle")
    failed = [e for e in drawable if e["agent"] == agent and e["lambda"] == mid and not e["success"]]
    chosen = ok[:1] + failed[: n - 1] if failed else ok[:n]
    return (chosen + [e for e in ok if e not in chosen])[:n]


def format_table(records: Sequence[dict[str, Any]]) -> str:
    """A plain-text table, grouped by lambda: mean time and ops to success (successful episodes),
    first-pick share, success share and mean episode time (all episodes). '*' marks the best
    fixed pipeline. With a ground-truth-free generator (its first call takes measurable time),
    'gen+time' adds it; 'vs oracle' is the time ratio to the oracle on the episodes both solved."""
    def gen_time(r: dict[str, Any]) -> float | None:
        return (r.get("time_to_success_with_generation") or {}).get("mean")

    show_gen = any(gen_time(r) is not None and r["time_to_success"]["mean"] is not None
                   and gen_time(r) - r["time_to_success"]["mean"] > 0.005 for r in records)
    show_ratio = any(r.get("oracle_ratio") is not None for r in records)
    show_wall = any("measured_time_to_success" in r for r in records)

    def wall(r: dict[str, Any]) -> float | None:
        return (r.get("measured_time_to_success") or {}).get("mean")

    width = min(60, max([34] + [len(r["agent"]) + 2 for r in records]))
    header = (f"{'lambda':>6}  {'agent':<{width}} {'time s':>8}" + (f" {'wall s':>8}" if show_wall else "")
              + f" {'ops':>6} {'1st pick':>8} {'success':>8} "
              f"{'ep. time':>9} {'n':>5}" + (f" {'gen+time':>9}" if show_gen else "")
              + (f" {'vs oracle':>9}" if show_ratio else ""))
    lines = [header, "-" * len(header)]

    def num(x: float | None, fmt: str) -> str:
        return format(x, fmt) if x is not None else "-".rjust(int(fmt.split(".")[0]))

    last = None
    for r in sorted(records, key=lambda r: (r["lambda"],)):
        if last is not None and r["lambda"] != last:
            lines.append("")
        last = r["lambda"]
        name = r["agent"] + (" *" if r.get("best_fixed") else "")
        lines.append(
            f"{r['lambda']:>6.2f}  {name[:width]:<{width}} {num(r['time_to_success']['mean'], '8.3f')}"
            + (f" {num(wall(r), '8.3f')}" if show_wall else "")
            + f" {num(r['ops_to_success']['mean'], '6.2f')} {100 * r['first_pick_success']:>7.1f}% "
            f"{100 * r['success']:>7.1f}% {num(r['episode_time']['mean'], '9.3f')} {r['episodes']:>5d}"
            + (f" {num(gen_time(r), '9.3f')}" if show_gen else "")
            + (f" {num(r.get('oracle_ratio'), '8.2f')}x" if show_ratio and r.get("oracle_ratio") is not None
               else f" {'-':>9}" if show_ratio else "")
        )
    lines.append("")
    lines.append("time s / ops: means over successful episodes (time s: the seconds charged, the cost model's in "
                 "cost-table time; wall s: the same episodes' measured wall time); ep. time: mean over all episodes; "
                 "* best fixed pipeline")
    statics = sorted({(r["lambda"], " > ".join(r["sequence"])) for r in records if r.get("sequence")})
    if statics:
        lines.append("best_static (the fixed sequence of lowest mean cost on the train images, searched per lambda): "
                     + "; ".join(f"{lam:g}: {seq}" for lam, seq in statics))
    if show_gen or show_ratio:
        lines.append("gen+time: time s with the first generator call; vs oracle: time (with the first call) "
                     "over the oracle's on the episodes both picked")
    return "\n".join(lines)
