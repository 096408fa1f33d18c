"""`perception-config cell-sim`: a simulated robot cell through the nodes (the record, figures
and verdict are perception_config/bench/cell_sim.py).

    perception-config cell-sim --dataset data/default --start fixed \\
        --reference runs/demo-pg/policy.safetensors --estimates 300 --out outputs/cell

1. The bag: `--bag` as given, or `--dataset`'s test images of the reference policy (its split
   seed and test fraction; `--all-images`: every image) recorded to `<out>/cell.mcap`
   (replay-check's recording). The learner holds out about 30 % of the frames for its checks and
   needs 5 of them (online/promotion_gate.py); a bag of fewer is warned about.
2. The reference: the reference policy through the same nodes for `--reference-rounds` rounds
   (a round: every object of every frame of the bag once; 1 by default), no learning, into
   `<out>/reference.csv` (or a previous run's with `--reference-from`). Through the nodes rather
   than in-process (evaluation): the cell's time is the time through ROS on this machine, under
   the same load, which docs/results/ros.md measures at 1.14-1.24x the in-process operator time; an
   in-process reference would hold the cell to a time no learning through the nodes can reach,
   and its frames, lambda and charged time would not be the cell's.
3. The cell: generation/refinement/scoring/pick nodes, the configurator serving the start
   (`fixed`: the fixed sequence, `untrained`: a fresh pg policy (learning only), or a policy
   file) with `learn:=true` (the online learner, its state in `<out>/learn`) unless
   `--no-learn`, and bag_replay_node with `loop:=true`, each its own process (the launcher,
   loopback ROS defaults). This process sees every replayed frame's ground truth and, whenever
   the previous frame's estimates are done, takes the next frame that arrives which it has not
   estimated in this round (a round = every frame of the bag once, so the cell's frames and the
   reference's are the same mix), and calls estimate_pose for each of its objects (an object id
   that occurs twice in a frame is skipped: the simulated pick cannot tell the two apart) with
   `--lambda` and a fresh seed per estimate, until `--estimates` are done.
4. Per estimate, a row of `<out>/estimates.csv` (cell_sim.ESTIMATE_COLUMNS); the operator trace
   (perception/trace) gives the ok flags the charged time needs, and the serving policy version
   (the trace's, perception/policy_version, or the start's). The learner's lines are read from
   the configurator's log; `<out>/cell_sim.png`, `<out>/summary.json` and the printed summary.

Ctrl-C stops the cell: the rows so far are kept (estimates.csv.part is flushed per row) and the
summary and plot cover them (exit code 130).
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import sqlite3
import sys
from pathlib import Path
from typing import Any, Callable

import numpy as np
import rclpy

from ..agents.fixed import DEFAULT_SEQUENCE
from ..agents.policy_settings import is_policy_file, policy_settings
from ..bench.cell_sim import (
    DEFAULT_TOLERANCE,
    DEFAULT_WINDOW,
    EstimateLog,
    format_summary,
    learner_events,
    plot_cell_sim,
    read_estimates,
    reference_figures,
    summarise,
)
from ..blocks.base import GROUND_TRUTH, Kind
from ..blocks.pipeline import load_pipeline
from ..datasets.bag import bag_info
from ..datasets.bop import BopDataset
from ..datasets.bop_models import ModelFolder
from ..launcher.resolution import default_models
from ..launcher.ros_environment import configure_ros_environment
from ..launcher.supervisor import Launcher
from ..learning.hidden_evaluation import evaluate_versions, hidden_summary
from ..online.learner_state import LearnerPace
from ..online.pick_labels import label_counts
from ..online.promotion_gate import MIN_CHECK_FRAMES, is_check_frame
from ..online.score_learner import SCORES
from ..rl.episodes import split_image_keys
from ..store.episode_store import STORE_NAME, policy_version
from ..util.atomic_file import atomic_write
from ..util.stop_signals import StopRequested, StopSignals, signal_name
from ..util.versions import PolicyVersions
from .cell_sim_drive import CellNode, drive, running_elsewhere
from .cell_sim_robot import FRAME_INFO, REPORTS, ROBOT_SERVICE, SimulatedRobot
from .estimate_client import EstimateClient
from .replay_check import record_images, replay_spec, service_specs

STARTS = ("fixed", "untrained")
LABELS = ("ground_truth", "robot")  # what the cell's learner may see: replayed ground truth, or the robot's picks
SERVICE_NODES = ("generation_node", "refinement_node", "scoring_node", "pick_node", "configurator_node")


def _alive(launcher: Launcher, log_dir: Path) -> Callable[[], None]:
    def check() -> None:
        dead = [n for n in SERVICE_NODES + ("bag_replay_node",) if launcher.returncode(n) is not None]
        if dead:
            raise RuntimeError(f"{', '.join(dead)} stopped (see {log_dir})")
    return check


def run_phase(specs: list, out: Path, name: str, log: EstimateLog, *, quiet: bool = True,
              hidden: dict[tuple[int, int], list[str]] | None = None,
              robot: Callable[[Any], SimulatedRobot] | None = None, **drive_args: Any) -> tuple[bool, list[str]]:
    """Start `specs`, drive the cell, stop them; (completed, the configurator's log lines).
    `hidden` and `robot` (a factory on this process's node): a cell without ground truth."""
    log_dir = out / "logs" / name
    node = rclpy.create_node(f"cell_sim_{name}_{os.getpid()}")
    try:
        clash = running_elsewhere(SERVICE_NODES)
        if clash:
            raise RuntimeError(f"{', '.join(clash)} already run on ROS_DOMAIN_ID {os.environ.get('ROS_DOMAIN_ID')}: "
                               "another cell (a launch, a replay-check, a cell-sim) would answer this one's requests; "
                               "stop it, or run this one with another ROS_DOMAIN_ID")
        with open(out / f"launch-{name}.log", "w") as launch_log:
            launcher = Launcher(specs, log_dir=log_dir, out=launch_log if quiet else None)
            with launcher:
                cell = CellNode(node, hidden)
                the_robot = robot(node) if robot is not None else None
                launcher.wait_for_line("configurator_node", "serving", timeout=120.0)
                cell.wait_for_trace_publisher(30.0, _alive(launcher, log_dir))
                client = EstimateClient(node)
                completed = drive(cell, client, log, alive=_alive(launcher, log_dir), robot=the_robot, **drive_args)
                if the_robot is not None and the_robot.refused_reports:
                    print(f"cell-sim: {len(the_robot.refused_reports)} pick reports refused, the first: "
                          f"{the_robot.refused_reports[0]}", file=sys.stderr, flush=True)
    finally:
        node.destroy_node()
    lines = (log_dir / "configurator_node.log").read_text(errors="replace").splitlines() \
        if (log_dir / "configurator_node.log").is_file() else []
    return completed, lines


def cell_sim(out: str | Path, reference: str | Path, *, bag: str | Path | None = None,
             dataset: str | Path | None = None, models: str | Path | None = None, start: str = "fixed",
             estimates: int = 200, learn: bool = True, learn_every: int | None = None,
             learn_margin: float | None = None, noise_lambda: float = 0.5, seed: int = 0, rate: float = 1.0,
             images: int | None = None, window: int = DEFAULT_WINDOW, tolerance: float = DEFAULT_TOLERANCE,
             reference_from: str | Path | None = None, reference_rounds: int = 1,
             fixed_sequence: list[str] | None = None, quiet: bool = True, progress: bool = True,
             stop: StopSignals | None = None, all_images: bool = False, labels: str = "ground_truth",
             robot_reports: str = "truth", flip_share: float = 0.3, hidden_seeds: int = 1,
             lockstep: bool = False) -> dict[str, Any]:
    """Run the cell (module docstring); returns the summary also written to `<out>/summary.json`.
    `lockstep`: hold each estimate while the learner's cycle runs (online/learner_state.LearnerPace)."""
    out = Path(out).resolve()
    if (bag is None) == (dataset is None):
        raise ValueError("give exactly one of --bag and --dataset")
    if labels not in LABELS:
        raise ValueError(f"--labels must be one of {LABELS}, got {labels!r}")
    if labels == "robot" and dataset is None:
        raise ValueError("--labels robot needs --dataset: the simulated robot reads the ground truth from it "
                         "(a bag's ground truth would be replayed to the nodes)")
    if robot_reports not in REPORTS:
        raise ValueError(f"--robot-reports must be one of {REPORTS}, got {robot_reports!r}")
    if not 0.0 <= flip_share <= 1.0:
        raise ValueError(f"--flip-share must be in [0, 1], got {flip_share}")
    if robot_reports != "truth" and labels != "robot":
        raise ValueError("--robot-reports other than truth needs --labels robot")
    if hidden_seeds < 0:
        raise ValueError(f"--hidden-seeds must be >= 0, got {hidden_seeds}")
    if estimates < 1:
        raise ValueError(f"--estimates must be >= 1, got {estimates}")
    if not 1 <= window:
        raise ValueError(f"--window must be >= 1, got {window}")
    if not 1 <= reference_rounds:
        raise ValueError(f"--reference-rounds must be >= 1, got {reference_rounds}")
    reference = Path(reference).resolve()
    if not reference.is_file():
        raise FileNotFoundError(f"reference policy {reference} does not exist")
    start_policy = None
    if start not in STARTS:
        start_policy = Path(start).resolve()
        if not is_policy_file(start_policy):
            raise FileNotFoundError(f"--start {start}: neither fixed, untrained nor a policy file")
    if start == "untrained" and not learn:
        raise ValueError("--start untrained needs learning (the configurator makes the untrained policy): "
                         "drop --no-learn, or start from fixed or a policy file")
    settings = policy_settings([p for p in (reference, start_policy) if p is not None])
    pipeline = load_pipeline(settings.pipeline)
    pick_actions = [a.name for a in pipeline.actions if a.block.kind == Kind.PICK]
    if labels == "robot" and GROUND_TRUTH in pipeline.generator.inputs:
        raise ValueError(f"--labels robot: the pipeline's generator {pipeline.generator.name} needs the ground truth, "
                         "which the nodes do not see there; use a policy of the cell pipeline (--pipeline cell)")
    sequence = list(fixed_sequence or DEFAULT_SEQUENCE)
    unknown = [a for a in sequence if a not in pipeline.action_names]
    if unknown:
        raise ValueError(f"--fixed-sequence: {unknown} are not actions of the pipeline ({pipeline.action_names})")
    out.mkdir(parents=True, exist_ok=True)

    if dataset is not None:
        ds = BopDataset(Path(dataset), split="test")
        keys = sorted(ds.image_keys()) if all_images else \
            sorted(split_image_keys(ds.image_keys(), settings.test_fraction, settings.split_seed)[1])
        keys = keys[: images] if images else keys
        bag_path = out / "cell.mcap"
        stamps, _ = record_images(ds, keys, bag_path, quiet=not progress)
        models_dir = Path(ds.models_dir)
        hidden_truth = {stamp: {int(o): pose for o, pose in ds.gt(*key)} for key, stamp in stamps.items()}
        hidden_ids = {key: [str(o) for o, _ in ds.gt(*key)] for key in stamps}
        held_out = sum(is_check_frame(stamp) for stamp in stamps.values())
        if learn and held_out < MIN_CHECK_FRAMES:
            print(f"cell-sim: warning: of the bag's {len(stamps)} frames (their stamps repeat every pass) {held_out} "
                  f"are the learner's held-out check frames, and a candidate needs {MIN_CHECK_FRAMES}: nothing "
                  "will be promoted. Replay more images (--all-images, or a larger dataset).", file=sys.stderr,
                  flush=True)
    else:
        bag_path = Path(bag).resolve()
        models_dir = Path(models).resolve() if models else default_models(Path.cwd(), print)
    if not (models_dir / "models_info.json").is_file():
        raise FileNotFoundError(f"models folder {models_dir} has no models_info.json")
    info = bag_info(bag_path)
    frames = int(info["frames"])
    truth = sum(t["count"] for t in info["topics"] if t["topic"].lstrip("/") == "perception/ground_truth")
    if frames < 1 or truth < 1:
        raise ValueError(f"bag {bag_path} has {frames} frames and {truth} ground truth messages: the simulated "
                         "cell needs both (record one with `perception-config bag write` or give --dataset)")
    rgb_only = isinstance(info.get("frame_topics"), dict) and "depth" not in info["frame_topics"]
    # The frame's stamps repeat every pass; a frame not seen for a whole pass plus start-up is lost.
    frame_timeout = 90.0 + 2.0 * info.get("duration_s", 0.0) / (rate if rate > 0 else 1.0)
    base = {"noise_lambda": float(noise_lambda), "max_ops": settings.env.max_ops}
    drive_common = {"stop": stop, "noise_lambda": noise_lambda, "pick_actions": pick_actions,
                    "failed_pick_cost": settings.env.failed_pick_cost, "frame_timeout": frame_timeout,
                    "frames_per_round": truth,
                    "window": window, "progress": progress}

    # The reference: `reference_rounds` rounds through the same nodes, without learning.
    if reference_from is not None:
        ref_rows = read_estimates(reference_from)
        measured = f"from {reference_from}"
    else:
        specs = service_specs(models_dir, settings.pipeline, frames, rgb_only,
                              {**base, "policy": str(reference),
                               "episode_store": str(out / "reference" / STORE_NAME)})
        specs.append(replay_spec(bag_path, rate, rgb_only, 3, loop=True))
        (out / "reference").mkdir(exist_ok=True)
        with EstimateLog(out / "reference.csv") as ref_log:
            completed, _ = run_phase(specs, out, "reference", ref_log, quiet=quiet, estimates=None,
                                     rounds=reference_rounds,
                                     seed=seed + 1, start_version=policy_version(reference),
                                     desc="reference", **drive_common)
        if not completed:
            raise StopRequested(stop.received[0] if stop is not None and stop.received else signal.SIGINT,
                                f"stopped during the reference pass; {len(ref_log.rows)} reference estimates in "
                                f"{out / 'reference.csv'}")
        ref_rows = ref_log.rows
        measured = f"{reference_rounds} round{'s' if reference_rounds > 1 else ''} through the nodes"
    ref = {**reference_figures(ref_rows), "name": _policy_name(reference), "measured": measured}

    # The cell.
    conf: dict[str, Any] = {**base, "policy": str(start_policy or ""), "fixed_sequence": sequence}
    operators: dict[str, Any] = {}
    robot = None
    if labels == "robot":  # the nodes never see the ground truth; the simulated robot answers the picks
        conf["pick_source"] = "robot"

        def robot(node: Any) -> SimulatedRobot:
            return SimulatedRobot(node, hidden_truth, ModelFolder(models_dir), pipeline.action(pick_actions[0]).block,
                                  reports=robot_reports, flip_share=flip_share, seed=seed + 17)
    if learn:
        operators["pick_success_versions"] = str(out / "learn" / SCORES)  # the learned score, when the pipeline has it
        conf.update({"learn": True, "learn_dir": str(out / "learn"),
                     "learn_start": "policy" if start_policy else start})
        if learn_every is not None:
            conf["learn_every"] = int(learn_every)
        if learn_margin is not None:
            conf["learn_margin"] = float(learn_margin)
    else:
        conf["episode_store"] = str(out / STORE_NAME)
    specs = service_specs(models_dir, settings.pipeline, frames, rgb_only, conf, operators)
    if labels == "robot":
        next(s for s in specs if s.name == "pick_node").params["robot_service"] = ROBOT_SERVICE
        cameras = [t["topic"].lstrip("/") for t in info["topics"] if "ground_truth" not in t["topic"]]
        specs.append(replay_spec(bag_path, rate, rgb_only, 3, loop=True, topics=cameras,
                                 wait_for=[f"{t}:4" for t in cameras if t.startswith("camera/")]
                                 + [f"{FRAME_INFO}:1"]))
    else:
        specs.append(replay_spec(bag_path, rate, rgb_only, 3, loop=True))
    start_version = policy_version(start_policy) if start_policy else \
        "fixed:" + "+".join(sequence) if start == "fixed" else start  # as the episode store names the agent
    with EstimateLog(out / "estimates.csv") as log:
        pace = LearnerPace(out / "learn") if learn and lockstep else None
        completed, lines = run_phase(specs, out, "cell", log, quiet=quiet, estimates=estimates, rounds=None,
                                     seed=seed, start_version=start_version, desc="cell",
                                     hidden=hidden_ids if labels == "robot" else None, robot=robot, pace=pace,
                                     **drive_common)
    events = learner_events(lines)
    summary = summarise(log.rows, ref, events, window, tolerance, requested=estimates)
    summary["learner_failures"] = [line.strip() for line in lines if "learner: no candidate:" in line]
    summary.update({"start": start if start_policy is None else str(start_policy), "learn": learn,
                    "bag": str(bag_path), "frames": frames, "noise_lambda": noise_lambda, "interrupted": not completed,
                    "learner_lines": [e.line for e in events], "labels": labels, "robot_reports": robot_reports,
                    "flip_share": flip_share if robot_reports == "flipped" else None,
                    "lockstep": pace.record() if pace is not None else None,
                    "reported_success": float(np.mean([r["reported_success"] for r in log.rows]))
                    if log.rows else None})
    if learn:
        with contextlib.suppress(OSError, ValueError, sqlite3.Error):
            summary["stored_labels"] = label_counts(out / "learn" / STORE_NAME)
    if learn and dataset is not None and hidden_seeds > 0 and (out / "learn" / "policies").is_dir():
        figures = evaluate_versions(out / "learn" / "policies", dataset, keys, settings.pipeline, settings.env,
                                    noise_lambda, hidden_seeds, progress)
        served = summary["versions"] + [PolicyVersions(out / "learn" / "policies").current()]
        summary.update(hidden_summary(figures, [v for v in served if v]))
    marks = [(p["first_estimate"], p["version"]) for p in summary["promotions"] if p["first_estimate"] is not None]
    start_name = _policy_name(start_policy) if start_policy else \
        f"fixed {' -> '.join(sequence)}" if start == "fixed" else start
    plot_cell_sim(out / "cell_sim.png", log.rows, ref, window, marks, tolerance=tolerance,
                  reached=summary["reached_within"],
                  title=f"cell from {start_name}, {'learning' if learn else 'no learning'}, "
                        f"{frames} frames in a loop, lambda {noise_lambda:g}")
    atomic_write(out / "summary.json", json.dumps(_finite(summary), indent=2) + "\n")
    return summary


def _policy_name(path: Path) -> str:
    """A policy file as people know it: runs/<run>/policy.safetensors by its run folder."""
    return f"{path.parent.name}/{path.name}" if path.stem == "policy" else path.name


def _finite(x: Any) -> Any:
    """JSON without NaN/inf (null instead)."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def run_cli(args: Any) -> int:
    """`perception-config cell-sim`: exit 0 when the run completed; stopped by SIGINT, SIGTERM or
    SIGHUP: what ran is written and summarised, exit 128 + the signal number."""
    configure_ros_environment()  # loopback defaults before rclpy starts
    rclpy.init()
    try:
        with StopSignals().installed() as stop:
            s = cell_sim(args.out, args.reference, bag=args.bag, dataset=args.dataset, models=args.models,
                         start=args.start, estimates=args.estimates, learn=args.learn, learn_every=args.learn_every,
                         learn_margin=args.learn_margin, noise_lambda=args.noise_lambda, seed=args.seed,
                         rate=args.rate, images=args.images, window=args.window, reference_from=args.reference_from,
                         all_images=args.all_images, labels=args.labels, robot_reports=args.robot_reports,
                         flip_share=args.flip_share, hidden_seeds=args.hidden_seeds,
                         reference_rounds=args.reference_rounds, progress=not args.quiet, stop=stop,
                         lockstep=args.lockstep,
                         fixed_sequence=[a for a in args.fixed_sequence.split(",") if a] if args.fixed_sequence
                         else None)
    except RuntimeError as exc:  # a node died, no frames came: the rows that ran are in estimates.csv
        print(f"perception-config cell-sim: {exc}; the estimates made so far are in {Path(args.out)}",
              file=sys.stderr)
        return 1
    finally:
        rclpy.try_shutdown()
    print(format_summary(s))
    print(f"wrote {Path(args.out) / 'estimates.csv'}, {Path(args.out) / 'cell_sim.png'} and "
          f"{Path(args.out) / 'summary.json'}")
    if stop.received:
        print(f"perception-config cell-sim: stopped by {signal_name(stop.received[0])} after {s['estimates']} "
              "estimates", file=sys.stderr)
        return 128 + stop.received[0]
    return 0
