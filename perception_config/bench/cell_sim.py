"""`perception-config cell-sim`: a simulated robot cell, its record and its verdict (no rclpy here;
the run through the nodes is perception_config/ros/cell_sim_run.py).

A cell replays a bag in a loop through the nodes and estimates every object of the frames it
sees, one estimate after the other, with the simulated pick; the configurator may learn while
it serves (`learn`, online/policy_learner.py). This module holds what does not need ROS:

- the per-estimate record (`ESTIMATE_COLUMNS`) and its CSV (`EstimateLog`: each row flushed to
  `estimates.csv.part` as it comes, so Ctrl-C or a crash keeps what ran; the finished file
  `estimates.csv` is written atomically at the end);
- the charged time of an estimate from its operator trace (`charged_time`: the operators'
  measured seconds plus the robot's attempt time for every pick that ran and failed, the
  environment's `episode_time`) and its first-pick outcome;
- the learner's log lines (`parse_learner_line`: `learner: candidate from N episodes: cost X vs
  serving Y -> promoted vN | discarded`) and the check that no promoted version is worse than
  its predecessor on the learner's replay check (`check_promotions`);
- the rolling window figures and `reached_within`: the first estimate count after which the
  rolling success share and mean time stay within a tolerance of the reference;
- the plot (`plot_cell_sim`) and the summary.
"""
from __future__ import annotations

import csv
import io
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from ..util.atomic_file import atomic_write

ESTIMATE_COLUMNS = (
    "index",  # 0, 1, ... in the order estimated
    "round",  # 0, 1, ...: every frame of the bag once per round
    "wall_time",  # unix seconds when the answer came
    "frame_stamp_ns", "obj_id", "seed",
    "answered",  # 1: the configurator made an estimate (0: refused, a node down; see message)
    "success",  # 1: a pick succeeded
    "time_s",  # seconds charged: operators measured + failed picks at the robot's attempt cost
    "operator_s",  # the operators' measured seconds
    "estimate_wall_s",  # request to answer, as the robot program waits
    "first_pick_success", "operations",
    "policy_version",  # the serving version: the trace's / perception/policy_version, else the file's
    "estimate_id",  # the configurator's episode store id (0: none given)
    "trace",  # 1: the operator trace (ok flags) was received; 0: time and first pick from the answer alone
    "message",
    "reported_success",  # 1: the pick outcome as the robot reported it (== success unless the robot lies)
)
OPTIONAL_COLUMNS = ("reported_success",)  # absent from files written before it: taken as `success`
LEARNER_LINE = re.compile(
    r"learner: candidate from (?P<episodes>\d+) episodes: cost (?P<cost>\S+) vs serving (?P<serving>\S+)"
    r" -> (?:(?P<promoted>promoted) (?P<version>[^\s,;]+)|(?P<discarded>discarded))")
ROS_LOG_TIME = re.compile(r"\[(\d{9,}\.\d+)\]")  # rcutils' default format: [INFO] [1733100000.123] [node]: ...
DEFAULT_TOLERANCE = 0.10
# estimates: the rolling mean time of a fixed policy varies by +-10 % over 200 (docs/results/cell_sim.md)
DEFAULT_WINDOW = 200


# --------------------------------------------------------------------------- one estimate


def charged_time(operations: Sequence[str], seconds: Sequence[float], oks: Sequence[bool] | None,
                 picked: bool, pick_actions: Iterable[str], failed_pick_cost: float) -> float:
    """The seconds the environment charges an episode (`env.episode_time`): every operator's
    measured seconds plus `failed_pick_cost` for each pick that ran (ok) and did not succeed.
    A successful pick ends the episode, so only the last operation can be one. Without the ok
    flags (`oks` None) every pick is taken to have run."""
    picks = set(pick_actions)
    oks = list(oks) if oks is not None else [True] * len(operations)
    total = float(sum(seconds))
    last = len(operations) - 1
    for i, (name, ok) in enumerate(zip(operations, oks)):
        if name in picks and ok and not (picked and i == last):
            total += failed_pick_cost
    return total


def first_pick_success(operations: Sequence[str], oks: Sequence[bool] | None, picked: bool,
                       pick_actions: Iterable[str]) -> bool:
    """Whether the first pick that ran succeeded (an episode without one: False), as the
    evaluation counts it."""
    picks = set(pick_actions)
    oks = list(oks) if oks is not None else [True] * len(operations)
    for i, (name, ok) in enumerate(zip(operations, oks)):
        if name in picks and ok:
            return bool(picked and i == len(operations) - 1)
    return False


# --------------------------------------------------------------------------- the CSV


class EstimateLog:
    """estimates.csv of a run: rows appended to `<path>.part` and flushed one by one (what ran
    survives Ctrl-C and a crash); `close()` writes `path` atomically and removes the part file."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.part = self.path.with_name(self.path.name + ".part")
        self.rows: list[dict[str, Any]] = []
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.part, "w", newline="", encoding="utf-8")
        self._writer = csv.DictWriter(self._file, fieldnames=ESTIMATE_COLUMNS, extrasaction="ignore")
        self._writer.writeheader()
        self._file.flush()

    def append(self, row: dict[str, Any]) -> None:
        missing = [c for c in ESTIMATE_COLUMNS if c not in row]
        if missing:
            raise ValueError(f"estimate row lacks {missing}")
        self.rows.append(dict(row))
        self._writer.writerow(row)
        self._file.flush()

    def close(self) -> Path:
        if not self._file.closed:
            self._file.close()
        atomic_write(self.path, rows_to_csv(self.rows))
        self.part.unlink(missing_ok=True)
        return self.path

    def __enter__(self) -> "EstimateLog":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def rows_to_csv(rows: Sequence[dict[str, Any]]) -> str:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=ESTIMATE_COLUMNS, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()


INT_COLUMNS = ("index", "round", "frame_stamp_ns", "obj_id", "seed", "answered", "success", "first_pick_success",
               "operations", "estimate_id", "trace", "reported_success")
FLOAT_COLUMNS = ("wall_time", "time_s", "operator_s", "estimate_wall_s")


def read_estimates(path: str | os.PathLike) -> list[dict[str, Any]]:
    """The rows of an estimates.csv (or reference.csv) with their numbers parsed; ValueError
    naming the file and row when it is not one."""
    path = Path(path)
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        missing = [c for c in ESTIMATE_COLUMNS if c not in (reader.fieldnames or []) and c not in OPTIONAL_COLUMNS]
        if missing:
            raise ValueError(f"{path} is not an estimates CSV of cell-sim: it lacks the columns {missing}")
        rows = []
        for n, raw in enumerate(reader, start=2):
            try:
                row: dict[str, Any] = dict(raw)
                row["reported_success"] = raw.get("reported_success") or raw["success"]
                row.update({c: int(row[c]) for c in INT_COLUMNS})
                row.update({c: float(raw[c]) for c in FLOAT_COLUMNS})
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{path} line {n}: {exc}") from None
            rows.append(row)
    return rows


# --------------------------------------------------------------------------- the learner's lines


@dataclass
class LearnerEvent:
    """One candidate of the learner as the configurator logged it."""

    episodes: int
    cost: float  # the candidate's mean cost on the replay check
    serving: float  # the serving version's mean cost on the same check
    promoted: bool
    version: str | None  # the promoted version (None: discarded)
    log_time: float | None  # unix seconds from the ROS log line, when it carries them
    line: str

    @property
    def not_worse(self) -> bool:
        """The candidate's replay-check cost is no higher than its predecessor's."""
        return math.isfinite(self.cost) and (not math.isfinite(self.serving) or self.cost <= self.serving)


def parse_learner_line(line: str) -> LearnerEvent | None:
    """A learner line of the configurator's log (any prefix: the launcher's `[node]`, ROS's
    `[INFO] [time] [name]:`), or None for any other line."""
    m = LEARNER_LINE.search(line)
    if m is None:
        return None
    try:
        cost, serving = float(m["cost"]), float(m["serving"])
    except ValueError:
        return None
    t = ROS_LOG_TIME.search(line[: m.start()])
    return LearnerEvent(episodes=int(m["episodes"]), cost=cost, serving=serving, promoted=bool(m["promoted"]),
                        version=m["version"], log_time=float(t.group(1)) if t else None, line=line.strip())


def learner_events(lines: Iterable[str]) -> list[LearnerEvent]:
    return [e for e in (parse_learner_line(line) for line in lines) if e is not None]


def check_promotions(events: Sequence[LearnerEvent]) -> dict[str, Any]:
    """Every promotion with its cost against its predecessor's (the version serving when it was
    trained); `all_not_worse` is the issue's target "no promoted version is worse than its
    predecessor on the replay check"."""
    promotions = []
    previous = None
    for e in events:
        if not e.promoted:
            continue
        promotions.append({"version": e.version, "previous": previous, "cost": e.cost, "previous_cost": e.serving,
                           "change": (e.cost / e.serving - 1.0) if e.serving and math.isfinite(e.serving) else None,
                           "episodes": e.episodes, "not_worse": e.not_worse, "log_time": e.log_time})
        previous = e.version
    return {"promotions": promotions, "candidates": len(events),
            "discarded": sum(not e.promoted for e in events),
            "all_not_worse": all(p["not_worse"] for p in promotions)}


def promotion_indices(rows: Sequence[dict[str, Any]], promotions: Sequence[dict[str, Any]]) -> list[int | None]:
    """The estimate index at which each promoted version began to serve: its first estimate
    (policy_version column), else the first estimate answered after its log line, else None."""
    out: list[int | None] = []
    for p in promotions:
        first = next((r["index"] for r in rows if r["policy_version"] == p["version"]), None)
        if first is None and p.get("log_time") is not None:
            first = next((r["index"] for r in rows if r["wall_time"] >= p["log_time"]), None)
        out.append(first)
    return out


# --------------------------------------------------------------------------- figures


def rolling_mean(values: Sequence[float], window: int) -> np.ndarray:
    """Mean of the last `window` values at every index (fewer at the start)."""
    v = np.asarray(values, np.float64)
    if v.size == 0:
        return v
    c = np.concatenate([[0.0], np.cumsum(v)])
    idx = np.arange(1, v.size + 1)
    lo = np.maximum(idx - int(window), 0)
    return (c[idx] - c[lo]) / (idx - lo)


def within_reference(success: float, time_s: float, ref_success: float, ref_time: float,
                     tolerance: float = DEFAULT_TOLERANCE) -> bool:
    """Success at least (1 - tolerance) x the reference's and mean time at most (1 + tolerance)
    x the reference's (better than the reference counts as within)."""
    return success >= (1.0 - tolerance) * ref_success and time_s <= (1.0 + tolerance) * ref_time


def reached_within(success: Sequence[float], times: Sequence[float], ref_success: float, ref_time: float,
                   window: int = DEFAULT_WINDOW, tolerance: float = DEFAULT_TOLERANCE) -> int | None:
    """The number of estimates after which the rolling window (full windows only) stays within
    `tolerance` of the reference on both success and mean time to the end of the run; None when
    the last window is not within (or the run is shorter than one window)."""
    n = len(success)
    if len(times) != n:
        raise ValueError(f"{n} success values but {len(times)} times")
    window = int(window)
    if window < 1:
        raise ValueError(f"window must be >= 1, got {window}")
    if n < window:
        return None
    rs, rt = rolling_mean(success, window), rolling_mean(times, window)
    ok = [within_reference(s, t, ref_success, ref_time, tolerance) for s, t in zip(rs, rt)]
    first = None
    for i in range(n - 1, window - 2, -1):
        if not ok[i]:
            break
        first = i
    return None if first is None else first + 1


def reference_figures(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Success share and mean charged time of the reference's estimates, with their standard
    errors: the time per estimate is heavy-tailed (a failed estimate is charged its failed picks
    at the robot's cost, ~100x a quick success), so its mean needs many estimates."""
    if not rows:
        raise ValueError("the reference has no estimates")
    success = np.array([r["success"] for r in rows], np.float64)
    times = np.array([r["time_s"] for r in rows], np.float64)
    return {"estimates": len(rows), "success": float(success.mean()), "time_s": float(times.mean()),
            "success_se": float(success.std() / math.sqrt(len(rows))),
            "time_se": float(times.std() / math.sqrt(len(rows))),
            "time_median_s": float(np.median(times)),
            "first_pick_success": float(np.mean([r["first_pick_success"] for r in rows])),
            "policy_version": rows[0]["policy_version"]}


def plot_cell_sim(path: str | os.PathLike, rows: Sequence[dict[str, Any]], reference: dict[str, Any],
                  window: int, marks: Sequence[tuple[int, str]] = (), title: str = "",
                  tolerance: float = DEFAULT_TOLERANCE, reached: int | None = None) -> Path:
    """Rolling success share and rolling mean time per estimate over the estimate index, the
    reference as horizontal lines with its tolerance band, promotions as vertical lines."""
    from ..core.plots import plt, save_figure  # lazy: matplotlib (Agg) only when plotting

    x = np.array([r["index"] for r in rows]) + 1
    success = rolling_mean([r["success"] for r in rows], window)
    times = rolling_mean([r["time_s"] for r in rows], window)
    fig, axes = plt.subplots(2, 1, figsize=(10, 7), sharex=True, constrained_layout=True)
    panels = ((axes[0], success, reference["success"], "success share", (1 - tolerance), "tab:green"),
              (axes[1], times, reference["time_s"], "mean time per estimate [s]", (1 + tolerance), "tab:blue"))
    for ax, y, ref, label, bound, colour in panels:
        full = x >= window
        ax.plot(x[: window], y[: window], color=colour, lw=1.0, alpha=0.4)  # fewer than `window` estimates
        ax.plot(x[full], y[full], color=colour, lw=1.8, label=f"cell, rolling {window} estimates")
        ax.axhline(ref, color="black", ls="--", lw=1.2, label=f"reference {reference.get('name', 'offline pg')}")
        ax.axhspan(min(ref, ref * bound), max(ref, ref * bound), color="0.85", alpha=0.6,
                   label=f"within {tolerance:.0%}")
        for index, version in marks:
            ax.axvline(index + 1, color="tab:red", ls=":", lw=1.0)
            if ax is axes[0]:
                ax.annotate(version, (index + 1, 1.0), xycoords=("data", "axes fraction"), rotation=90,
                            va="top", ha="right", fontsize=8, color="tab:red")
        if reached is not None:
            ax.axvline(reached, color="black", lw=0.8, label=f"within {tolerance:.0%} from here on")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].set_ylim(0, 1.05)
    axes[0].legend(loc="lower right", fontsize=8)
    axes[1].set_xlabel("estimate")
    if title:
        axes[0].set_title(title)
    return save_figure(fig, path)


# --------------------------------------------------------------------------- summary


def summarise(rows: Sequence[dict[str, Any]], reference: dict[str, Any], events: Sequence[LearnerEvent],
              window: int = DEFAULT_WINDOW, tolerance: float = DEFAULT_TOLERANCE,
              requested: int | None = None) -> dict[str, Any]:
    """The run's figures: overall and last-window success and time, the reference, when the
    window came within `tolerance` of it (`reached_within`), the promotions and their check."""
    succ = [float(r["success"]) for r in rows]
    times = [float(r["time_s"]) for r in rows]
    promo = check_promotions(events)
    if promo["promotions"] and promo["promotions"][0]["previous"] is None and rows:
        promo["promotions"][0]["previous"] = rows[0]["policy_version"]  # what served first (learning's v0000)
    indices = promotion_indices(rows, promo["promotions"])
    for p, i in zip(promo["promotions"], indices):
        p["first_estimate"] = i
    last = slice(max(0, len(rows) - window), len(rows))
    return {
        "estimates": len(rows), "requested": requested, "window": window, "tolerance": tolerance,
        "success": float(np.mean(succ)) if rows else None, "time_s": float(np.mean(times)) if rows else None,
        "last_window_success": float(np.mean(succ[last])) if rows else None,
        "last_window_time_s": float(np.mean(times[last])) if rows else None,
        "reference": dict(reference),
        "reached_within": reached_within(succ, times, reference["success"], reference["time_s"], window, tolerance)
        if rows else None,
        "versions": list(dict.fromkeys(r["policy_version"] for r in rows)),
        "unanswered": sum(1 - int(r["answered"]) for r in rows),
        "without_trace": sum(1 - int(r["trace"]) for r in rows),
        **promo,
    }


def format_summary(s: dict[str, Any]) -> str:
    ref = s["reference"]
    lines = [f"{s['estimates']} estimates"
             + (f" of {s['requested']} requested" if s.get("requested") and s["requested"] != s["estimates"] else "")
             + f": success {s['success']:.1%}, mean time {s['time_s']:.3f} s; last {min(s['window'], s['estimates'])}: "
             f"success {s['last_window_success']:.1%}, mean time {s['last_window_time_s']:.3f} s"
             if s["estimates"] else "no estimates",
             f"reference {ref.get('name', '')} ({ref['estimates']} estimates, "
             f"{ref.get('measured', 'through the nodes')}): "
             f"success {ref['success']:.1%}" + (f" +- {ref['success_se']:.1%}" if "success_se" in ref else "")
             + f", mean time {ref['time_s']:.3f} s" + (f" +- {ref['time_se']:.3f} s (standard errors)"
                                                       if "time_se" in ref else "")]
    if ref.get("time_se") and ref["time_se"] > 0.5 * s["tolerance"] * ref["time_s"]:
        lines.append(f"  the reference's mean time is known to {ref['time_se'] / ref['time_s']:.0%} only (one standard "
                     f"error), more than half the {s['tolerance']:.0%} tolerance: measure it over more rounds")
    if s["reached_within"] is not None:
        lines.append(f"within {s['tolerance']:.0%} of the reference on success and time (rolling {s['window']}) "
                     f"from estimate {s['reached_within']} to the end")
    else:
        lines.append(f"not within {s['tolerance']:.0%} of the reference on success and time (rolling "
                     f"{s['window']}) by the end: not reached within {s['estimates']}")
    if s["candidates"]:
        lines.append(f"learner: {s['candidates']} candidates, {len(s['promotions'])} promoted, "
                     f"{s['discarded']} discarded")
    for p in s["promotions"]:
        change = f" ({p['change']:+.1%})" if p["change"] is not None else ""
        where = f", serving from estimate {p['first_estimate'] + 1}" if p.get("first_estimate") is not None else ""
        lines.append(f"  {p['version']}: replay-check cost {p['cost']:.3f} vs {p['previous'] or 'start'} "
                     f"{p['previous_cost']:.3f}{change}{where}: {'not worse' if p['not_worse'] else 'WORSE'}")
    if s["promotions"]:
        lines.append("no promoted version worse than its predecessor" if s["all_not_worse"]
                     else "a promoted version is WORSE than its predecessor on the replay check")
    if s.get("learner_failures"):
        lines.append(f"learner: {len(s['learner_failures'])} cycles without a candidate, the last: "
                     f"{s['learner_failures'][-1].split('learner: ', 1)[-1]}")
    if s.get("labels") == "robot":
        lines.append(f"labels: the robot's picks only (reports: {s.get('robot_reports')}); reported success "
                     f"{s['reported_success']:.1%}, true {s['success']:.1%}" if s.get("reported_success") is not None
                     else "labels: the robot's picks only")
    if s.get("hidden_success_start") is not None:
        lines.append(f"hidden evaluation (ground truth, the same episodes for every version): first served success "
                     f"{s['hidden_success_start']:.1%}, cost {s['hidden_cost_start']:.3f} s; last "
                     f"{s['hidden_success_end']:.1%}, cost {s['hidden_cost_end']:.3f} s; "
                     f"{s['worse_promotions']} of {len(s.get('promotion_checks', []))} promotions truly worse")
    if s["unanswered"]:
        lines.append(f"{s['unanswered']} estimates not answered (counted as failures; see the message column)")
    if s["without_trace"]:
        lines.append(f"{s['without_trace']} estimates without their operator trace (time from the answer alone)")
    return "\n".join(lines)
