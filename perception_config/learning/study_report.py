"""The statistics of an evaluation folder (results.json + episodes.jsonl of learning/evaluation.py):
every agent's figures with bootstrap intervals (learning/study_stats.py), the learned seeds pooled,
each seed against the bar and the oracle, the table and the verdict lines.

The bar: `best_static` (kind "best_static": the best fixed sequence found on the train images,
per lambda), else the best fixed pipeline (the `fixed` record flagged `best_fixed`), and the
report says it fell back. Beside it, where the evaluation has it, `best_static_single` (one
sequence for every lambda: the static reference of Dynamic Algorithm Configuration, not told
the noise level, as the learned agent is not) gets its own k of N (`comparisons[i]["single"]`,
and the verdict line), and so does `best_threshold` (the searched threshold rule: it reads the
pick-success score as the learned agent reads the scores; `comparisons[i]["threshold"]`).
A seed beats the bar at a lambda when its mean episode cost is lower
and its success not lower (point estimates, `study_stats.beats`); it beats it surely when, in
addition, the 95 % interval of the paired cost difference (seed minus bar, episode by episode)
lies below 0. The oracle comparison is the time ratio on the episodes both picked (the mean of
the agent's time over the oracle's, the first generator call included, as evaluation's
`oracle_ratio`).

Episodes are paired by (lambda, episode, episode seed): an evaluation plays the same plan for
every agent, and an agent missing one of them is an error.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from . import study_stats as st

BASELINE_KINDS = ("oracle", "fixed", "random", "best_static", "best_static_single", "best_threshold")
FIGURES = ("success", "first_pick_success", "episode_cost", "time_to_success")


def load_evaluation(eval_dir: str | Path) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """(records of results.json, episodes of episodes.jsonl) of an evaluation folder."""
    eval_dir = Path(eval_dir)
    for name in ("results.json", "episodes.jsonl"):
        if not (eval_dir / name).is_file():
            raise FileNotFoundError(f"{eval_dir / name} does not exist: give the output folder of an evaluation")
    records = json.loads((eval_dir / "results.json").read_text())
    episodes = [json.loads(line) for line in (eval_dir / "episodes.jsonl").read_text().splitlines() if line.strip()]
    return records, episodes


class Episodes:
    """The per-episode figures of an evaluation, paired: `arrays(agent, lambdas)` gives every
    agent's episodes at those lambdas in the same order."""

    def __init__(self, episodes: Sequence[dict[str, Any]]) -> None:
        self.by: dict[tuple[str, float], dict[tuple[int, int], dict[str, Any]]] = {}
        for e in episodes:
            self.by.setdefault((e["agent"], float(e["lambda"])), {})[(int(e["episode"]), int(e["episode_seed"]))] = e

    def agents(self) -> list[str]:
        return list(dict.fromkeys(a for a, _ in self.by))

    def arrays(self, agent: str, lambdas: Sequence[float], keys_of: str | None = None) -> dict[str, np.ndarray]:
        """success, first_pick, cost, time, time_gen (time + the first generator call) per episode
        of `agent` at `lambdas`, in the order of `keys_of`'s episodes (default: the agent's own)."""
        cols: dict[str, list[float]] = {k: [] for k in ("success", "first_pick", "cost", "time", "time_gen")}
        for lam in lambdas:
            mine = self.by.get((agent, float(lam)))
            if mine is None:
                raise ValueError(f"the evaluation has no episodes of {agent!r} at lambda {lam:g}")
            order = self.by.get((keys_of or agent, float(lam)), mine)
            for key in order:
                e = mine.get(key)
                if e is None:
                    raise ValueError(f"{agent!r} did not play episode {key[0]} (seed {key[1]}) at lambda {lam:g}: "
                                     "the agents of one evaluation must play the same episodes")
                cols["success"].append(float(bool(e["success"])))
                cols["first_pick"].append(float(bool(e["first_pick_success"])))
                cols["cost"].append(float(e["cost"]))
                cols["time"].append(float(e["time"]))
                cols["time_gen"].append(float(e["time"]) + float(e.get("generation_time", 0.0)))
        return {k: np.asarray(v, np.float64) for k, v in cols.items()}


def figures(a: dict[str, np.ndarray], **kw: Any) -> dict[str, st.Estimate]:
    """The four figures with intervals from `Episodes.arrays` output ((n,), or (S, n) pooled)."""
    return {"success": st.mean_interval(a["success"], **kw),
            "first_pick_success": st.mean_interval(a["first_pick"], **kw),
            "episode_cost": st.mean_interval(a["cost"], **kw),
            "time_to_success": st.success_time_interval(a["time"], a["success"], **kw)}


def choose_bar(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The bar to beat: {"name", "kind": "best_static" | "best_fixed" | None, "note", "sequences"}."""
    static = [r for r in records if r.get("kind") == "best_static"]
    if static:
        return {"name": static[0]["agent"], "kind": "best_static", "note": None,
                "sequences": {str(r["lambda"]): r.get("sequence") for r in static}}
    best = [r for r in records if r.get("best_fixed")]
    if best:
        return {"name": best[0]["agent"], "kind": "best_fixed", "sequences": None,
                "note": f"no best_static in this evaluation: compared with the best fixed pipeline {best[0]['agent']} "
                        "instead"}
    return {"name": None, "kind": None, "sequences": None,
            "note": "no best_static and no fixed pipeline in this evaluation: no bar to compare with"}


def single_bar_name(records: Sequence[dict[str, Any]]) -> str | None:
    """The evaluation's `best_static_single` agent (one sequence for every lambda), None without it."""
    return next((r["agent"] for r in records if r.get("kind") == "best_static_single"), None)


def threshold_name(records: Sequence[dict[str, Any]]) -> str | None:
    """The evaluation's `best_threshold` agent (the searched threshold rule), None without it."""
    return next((r["agent"] for r in records if r.get("kind") == "best_threshold"), None)


def best_fixed_name(records: Sequence[dict[str, Any]]) -> str | None:
    return next((r["agent"] for r in records if r.get("best_fixed")), None)


def compare(cand: dict[str, np.ndarray], bar: dict[str, np.ndarray] | None, oracle: dict[str, np.ndarray] | None,
            **kw: Any) -> dict[str, Any]:
    """A candidate against the bar and the oracle on paired episodes ((n,), or (S, n) pooled)."""
    out: dict[str, Any] = {}
    if bar is not None:
        diff = st.paired_difference_interval(cand["cost"], bar["cost"], **kw)
        won = st.beats({"cost": cand["cost"].mean(), "success": cand["success"].mean()},
                       {"cost": bar["cost"].mean(), "success": bar["success"].mean()})
        out.update(beats=won, cost_difference=diff,
                   beats_surely=bool(won and diff.hi is not None and diff.hi < 0))
    if oracle is not None:
        out["oracle_ratio"] = st.oracle_ratio_interval(cand["time_gen"], cand["success"], oracle["time_gen"],
                                                       oracle["success"], **kw)
    return out


def _json(d: dict[str, Any]) -> dict[str, Any]:
    return {k: v.to_json() if isinstance(v, st.Estimate) else v for k, v in d.items()}


def analyse(records: Sequence[dict[str, Any]], episodes: Sequence[dict[str, Any]], learned: Sequence[str],
            label: str = "pg", seeds: Sequence[int] | None = None, **kw: Any) -> dict[str, Any]:
    """The study's statistics: `learned` are the agent names of the seeds (in the evaluation),
    `label` their agent (pg), `seeds` their seeds; `kw`: bootstrap settings (resamples, level,
    seed). JSON-ready (Estimates as {mean, lo, hi, n, n_den})."""
    eps = Episodes(episodes)
    names = eps.agents()
    missing = [a for a in learned if a not in names]
    if missing:
        raise ValueError(f"the evaluation has no episodes of {missing}; agents: {names}")
    kinds = {r["agent"]: r.get("kind", "") for r in records}
    lambdas = sorted({float(r["lambda"]) for r in records})
    bar = choose_bar(records)
    single = single_bar_name(records)
    seeds = list(seeds) if seeds is not None else list(range(len(learned)))
    rows, pooled, comparisons = [], [], []
    for lam in lambdas:
        ref = learned[0]
        arr = {a: eps.arrays(a, [lam], keys_of=ref) for a in names}
        for a in names:
            rows.append({"agent": a, "kind": kinds.get(a, ""), "lambda": lam, "episodes": int(arr[a]["cost"].size),
                         **_json(figures(arr[a], **kw))})
        stacked = {k: np.stack([arr[a][k] for a in learned]) for k in arr[ref]}
        bar_arr = arr.get(bar["name"]) if bar["name"] else None
        oracle = arr.get("oracle")
        bar_tiled = {k: np.tile(v, (len(learned), 1)) for k, v in bar_arr.items()} if bar_arr is not None else None
        oracle_tiled = {k: np.tile(v, (len(learned), 1)) for k, v in oracle.items()} if oracle is not None else None
        pooled_fig = figures(stacked, **kw)
        pooled_cmp = compare(stacked, bar_tiled, oracle_tiled, **kw)
        name = f"{label} ({len(learned)} seed{'s' if len(learned) > 1 else ''} pooled)"
        pooled.append({"agent": name, "lambda": lam, "seeds": len(learned),
                       "episodes": int(stacked["cost"].size), **_json(pooled_fig),
                       **_json({k: v for k, v in pooled_cmp.items() if k != "beats"})})
        per_seed = []
        for s, a in zip(seeds, learned):
            c = compare(arr[a], bar_arr, oracle, **kw)
            per_seed.append({"seed": int(s), "agent": a, "cost": float(arr[a]["cost"].mean()),
                             "success": float(arr[a]["success"].mean()), **_json(c)})
        comp: dict[str, Any] = {"lambda": lam, "bar": bar["name"], "bar_kind": bar["kind"], "n_seeds": len(learned),
                                "seeds": per_seed}
        if bar_arr is not None:
            comp["bar_cost"] = st.mean_interval(bar_arr["cost"], **kw).to_json()
            comp["bar_success"] = float(bar_arr["success"].mean())
            comp["k_beats"] = sum(1 for p in per_seed if p["beats"])
            comp["k_beats_surely"] = sum(1 for p in per_seed if p["beats_surely"])
        if single and single in arr:
            comp["single"] = _single_comparison(arr, learned, single, records, lam, **kw)
        rule = threshold_name(records)
        if rule and rule in arr:
            comp["threshold"] = _single_comparison(arr, learned, rule, records, lam, **kw)
        comp["pooled_cost"] = pooled_fig["episode_cost"].to_json()
        comp["pooled_success"] = pooled_fig["success"].value
        if "oracle_ratio" in pooled_cmp:
            comp["pooled_oracle_ratio"] = pooled_cmp["oracle_ratio"].to_json()
        comp["verdict"] = verdict_line(comp, label, bar)
        comparisons.append(comp)
    return {"lambdas": lambdas, "learned": list(learned), "label": label, "bar": bar,
            "best_fixed": best_fixed_name(records), "agents": rows, "pooled": pooled, "comparisons": comparisons,
            "bootstrap": {"method": st.METHOD, "resamples": kw.get("resamples", st.RESAMPLES),
                          "level": kw.get("level", st.LEVEL), "seed": kw.get("seed", st.BOOTSTRAP_SEED)}}


def _single_comparison(arr: dict[str, dict[str, np.ndarray]], learned: Sequence[str], single: str,
                       records: Sequence[dict[str, Any]], lam: float, **kw: Any) -> dict[str, Any]:
    """The seeds against `best_static_single` at one lambda (one sequence for every lambda, not told
    the noise level, as the learned agent is not: learning/evaluation_best_static.py)."""
    per_seed = [compare(arr[a], arr[single], None, **kw) for a in learned]
    sequence = next((r.get("sequence") or r.get("rule") for r in records
                     if r["agent"] == single and float(r["lambda"]) == lam), None)
    return {"bar": single, "sequence": sequence, "k_beats": sum(1 for c in per_seed if c["beats"]),
            "k_beats_surely": sum(1 for c in per_seed if c["beats_surely"]),
            "bar_cost": st.mean_interval(arr[single]["cost"], **kw).to_json(),
            "bar_success": float(arr[single]["success"].mean())}


def format_estimate(d: dict[str, Any] | None, fmt: str = ".2f", unit: str = "", scale: float = 1.0) -> str:
    """'mean [lo, hi]' of an Estimate's JSON (`unit` after the mean), the mean alone without an
    interval, '-' without a mean."""
    if not d or d.get("mean") is None:
        return "-"
    e = st.Estimate(d["mean"], d.get("lo"), d.get("hi"), d.get("n", 0))
    text = e.format(fmt, scale)
    return text.replace(" [", f"{unit} [", 1) if unit and " [" in text else text + unit


def verdict_line(comp: dict[str, Any], label: str, bar: dict[str, Any]) -> str:
    """`lambda 0.5: pg beats best_static in 4 of 5 seeds (...); 1.31x the oracle's time [1.22, 1.41]`."""
    head = f"lambda {comp['lambda']:g}: "
    if comp.get("k_beats") is None:
        text = head + f"{label}: no bar to compare with (cost {format_estimate(comp['pooled_cost'], '.3g', unit=' s')})"
    else:
        name = bar["name"] if bar["kind"] == "best_static" else f"the best fixed pipeline ({bar['name']})"
        text = (head + f"{label} beats {name} in {comp['k_beats']} of {comp['n_seeds']} seeds "
                f"({comp['k_beats_surely']} with the paired cost difference's interval below 0; cost "
                f"{format_estimate(comp['pooled_cost'], '.3g', unit=' s')} vs "
                f"{format_estimate(comp['bar_cost'], '.3g')}; success "
                f"{100 * comp['pooled_success']:.1f} % vs {100 * comp['bar_success']:.1f} %)")
    single = comp.get("single")
    if single:
        seq = "+".join(single.get("sequence") or [])
        text += (f"; beats {single['bar']} ({seq}, one sequence for every lambda) in {single['k_beats']} of "
                 f"{comp['n_seeds']} ({single['k_beats_surely']} surely; its cost "
                 f"{format_estimate(single['bar_cost'], '.3g')})")
    rule = comp.get("threshold")
    if rule:
        text += (f"; beats {rule['bar']} ({rule.get('sequence')}) in {rule['k_beats']} of {comp['n_seeds']} "
                 f"({rule['k_beats_surely']} surely; its cost {format_estimate(rule['bar_cost'], '.3g')}, success "
                 f"{100 * rule['bar_success']:.1f} %)")
    ratio = comp.get("pooled_oracle_ratio")
    if ratio and ratio.get("mean") is not None:
        text += "; " + _oracle_text(ratio["mean"], ratio.get("lo"), ratio.get("hi"))
    return text


def _oracle_text(mean: float, lo: float | None, hi: float | None) -> str:
    """'1.31x the oracle's time [1.22, 1.41]'."""
    return f"{mean:.2f}x the oracle's time" + (f" [{lo:.2f}, {hi:.2f}]" if lo is not None and hi is not None else "")


def format_table(analysis: dict[str, Any]) -> str:
    """Per lambda: every agent's figures with 95 % intervals, the seeds pooled, then the verdicts."""
    head = ("lambda", "agent", "success %", "1st pick %", "cost s", "time to success s", "vs bar: cost diff s",
            "x oracle time")
    cmp = {(c["lambda"], p["agent"]): p for c in analysis["comparisons"] for p in c["seeds"]}
    pooled = {p["lambda"]: p for p in analysis["pooled"]}
    lines: list[tuple[str, ...]] = []
    for lam in analysis["lambdas"]:
        rows = [r for r in analysis["agents"] if r["lambda"] == lam]
        rows.sort(key=lambda r: (r["agent"] not in analysis["learned"], r["agent"]))
        for r in rows + [pooled[lam]]:
            c = cmp.get((lam, r["agent"]), r)
            name = r["agent"] + (" (bar)" if r["agent"] == analysis["bar"]["name"] else "") \
                + (" *" if r["agent"] == analysis["best_fixed"] else "")
            lines.append((f"{lam:.2f}", name, format_estimate(r["success"], ".1f", scale=100),
                          format_estimate(r["first_pick_success"], ".1f", scale=100),
                          format_estimate(r["episode_cost"], ".3f"), format_estimate(r["time_to_success"], ".3f"),
                          format_estimate(c.get("cost_difference"), "+.3f"),
                          format_estimate(c.get("oracle_ratio"), ".2f")))
    widths = [max(len(x[i]) for x in [head, *lines]) for i in range(len(head))]
    out = ["  ".join(h.ljust(w) for h, w in zip(head, widths)), "-" * (sum(widths) + 2 * (len(widths) - 1))]
    out += ["  ".join(x.ljust(w) for x, w in zip(row, widths)).rstrip() for row in lines]
    bs = analysis["bootstrap"]
    out += ["", f"means [{100 * bs['level']:g} % interval: {bs['method']}, {bs['resamples']} resamples]; time to "
                "success over the successful episodes; cost = time + truncation penalty, all episodes; vs bar: "
                "paired episode cost difference; x oracle time: on the episodes both picked; * best fixed pipeline"]
    if analysis["bar"]["note"]:
        out.append(f"note: {analysis['bar']['note']}")
    out += [c["verdict"] for c in analysis["comparisons"]]
    return "\n".join(out)


def verdict(eval_dir: str | Path, agent: str | None = None, lam: float | None = None, **kw: Any) -> str:
    """One line: `agent` of the evaluation in `eval_dir` against best_static (else the best fixed
    pipeline) and the oracle, with 95 % intervals, over every lambda's episodes together (or at
    `lam`). `agent` None: the evaluation's only learned agent (not a baseline)."""
    records, episodes = load_evaluation(eval_dir)
    eps = Episodes(episodes)
    if agent is None:
        learned = [r["agent"] for r in records if r.get("kind") not in BASELINE_KINDS]
        learned = list(dict.fromkeys(learned))
        if len(learned) != 1:
            raise ValueError(f"{eval_dir}: name the agent, the evaluation has {len(learned)} learned agents "
                             f"{learned}; all: {eps.agents()}")
        agent = learned[0]
    if agent not in eps.agents():
        raise ValueError(f"{eval_dir}: no agent {agent!r}; agents: {eps.agents()}")
    lambdas = sorted({float(r["lambda"]) for r in records if r["agent"] == agent})
    if lam is not None:
        if float(lam) not in lambdas:
            raise ValueError(f"{eval_dir}: {agent} was not evaluated at lambda {lam:g}; lambdas: {lambdas}")
        lambdas = [float(lam)]
    bar = choose_bar(records)
    mine = eps.arrays(agent, lambdas)
    bar_arr = eps.arrays(bar["name"], lambdas, keys_of=agent) if bar["name"] and bar["name"] != agent else None
    oracle = eps.arrays("oracle", lambdas, keys_of=agent) if "oracle" in eps.agents() and agent != "oracle" else None
    c = compare(mine, bar_arr, oracle, **kw)
    cost = st.mean_interval(mine["cost"], **kw)
    where = f"lambda {lambdas[0]:g}" if len(lambdas) == 1 else f"{len(lambdas)} lambdas"
    text = f"{agent} ({where}, {mine['cost'].size} episodes): "
    if bar_arr is not None:
        name = bar["name"] if bar["kind"] == "best_static" else f"the best fixed pipeline {bar['name']}"
        diff = c["cost_difference"]
        text += (f"{'beats' if c['beats'] else 'does not beat'} {name}: cost {cost.format('.3f')} s vs "
                 f"{st.mean_interval(bar_arr['cost'], **kw).format('.3f')}, paired difference {diff.format('+.3f')}"
                 f"{' (below 0)' if c['beats_surely'] else ''}; success {100 * mine['success'].mean():.1f} % vs "
                 f"{100 * bar_arr['success'].mean():.1f} %")
        if bar["kind"] != "best_static":
            text += " (no best_static in this evaluation)"
        single = single_bar_name(records)
        if single and single != agent and single in eps.agents():
            s_arr = eps.arrays(single, lambdas, keys_of=agent)
            s_won = compare(mine, s_arr, None, **kw)["beats"]
            text += (f"; {'beats' if s_won else 'does not beat'} {single} (one sequence for every lambda): cost "
                     f"{st.mean_interval(s_arr['cost'], **kw).format('.3f')} s, success "
                     f"{100 * s_arr['success'].mean():.1f} %")
    else:
        text += f"cost {cost.format('.3f')} s, success {100 * mine['success'].mean():.1f} % (no bar to compare with)"
    ratio = c.get("oracle_ratio")
    if ratio is not None and ratio.value is not None and oracle is not None:
        both = int(((mine["success"] > 0) & (oracle["success"] > 0)).sum())
        text += f"; {_oracle_text(ratio.value, ratio.lo, ratio.hi)} ({both} episodes both picked)"
    return text


__all__ = ["analyse", "format_table", "verdict", "verdict_line", "load_evaluation", "choose_bar", "compare",
           "figures", "Episodes", "BASELINE_KINDS"]
