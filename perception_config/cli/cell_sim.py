"""`perception-config cell-sim`: a simulated robot cell learning online (ros/cell_sim_run.py)."""
from __future__ import annotations

import argparse
from pathlib import Path


def _cmd_cell_sim(args: argparse.Namespace) -> int:
    from ..ros import cell_sim_run  # imports rclpy: only for this command

    return cell_sim_run.run_cli(args)


def add_parser(sub: argparse._SubParsersAction) -> None:
    cs = sub.add_parser(
        "cell-sim", help="a simulated robot cell: a bag replayed in a loop through the nodes, every object estimated "
                         "and picked (simulated) while the configurator learns; plotted against a reference policy",
        description="Replay a bag in a loop through the operator nodes and the configurator (separate processes, "
                    "loopback), estimate every object of each frame the cell sees with estimate_pose, one after "
                    "the other, while the configurator learns (learn:=true; --no-learn: it serves the start as "
                    "it is). The reference policy is run through the same nodes for one round first. Writes "
                    "OUT/estimates.csv (per estimate), OUT/reference.csv, OUT/cell_sim.png, OUT/summary.json and "
                    "prints when the rolling window came within the tolerance of the reference and every "
                    "promotion's replay-check cost against its predecessor. Ctrl-C keeps what ran (exit 130).",
    )
    source = cs.add_mutually_exclusive_group(required=True)
    source.add_argument("--bag", type=Path, help="a bag with ground truth (perception-config bag write)")
    source.add_argument("--dataset", type=Path,
                        help="BOP dataset: its test images (the reference policy's split) go to OUT/cell.mcap")
    cs.add_argument("--models", type=Path, default=None,
                    help="BOP models folder with --bag (default: data/default/models); --dataset brings its own")
    cs.add_argument("--images", type=int, default=None, help="with --dataset: record only the first N test images")
    cs.add_argument("--all-images", action="store_true",
                    help="with --dataset: every image of the dataset, not only the reference policy's test images "
                         "(the learner holds out about 30 %% of the frames for its checks and needs 5 of them)")
    cs.add_argument("--start", default="fixed", metavar="fixed|untrained|POLICY",
                    help="what serves first: the fixed sequence, an untrained pg policy (learning only) or a policy "
                         "file (default fixed)")
    cs.add_argument("--fixed-sequence", default=None, metavar="A,B,...",
                    help="the fixed sequence of --start fixed (default: the configurator's, icp_coarse,icp_fine,pick; "
                         "the best on the demo dataset is d2co,icp_fine,pick)")
    cs.add_argument("--reference", type=Path, required=True, metavar="POLICY",
                    help="the offline-trained policy whose success and time are the reference lines")
    cs.add_argument("--reference-from", type=Path, default=None, metavar="CSV",
                    help="reuse a previous run's reference.csv instead of measuring the reference again")
    cs.add_argument("--reference-rounds", type=int, default=1, metavar="R",
                    help="rounds over the bag (every object of every frame once each) for the reference (1)")
    cs.add_argument("--estimates", type=int, default=200, help="estimates of the cell (200)")
    cs.add_argument("--out", type=Path, required=True, help="output folder")
    cs.add_argument("--no-learn", dest="learn", action="store_false",
                    help="serve the start without learning (a baseline; the configurator gets no learn parameters)")
    cs.add_argument("--learn-every", type=int, default=None, metavar="K",
                    help="new estimates between two candidate trainings (the configurator's learn_every)")
    cs.add_argument("--learn-margin", type=float, default=None, metavar="M",
                    help="a candidate is promoted only if, besides passing the 95 %% paired test on held-out "
                         "frames, its replay-check cost is lower by this fraction (learn_margin)")
    cs.add_argument("--lockstep", action="store_true",
                    help="hold the next estimate while the learner trains a candidate: a real cell's robot takes "
                         "seconds per pick, so the learner keeps up with it; the simulated robot takes none, and "
                         "without this a run of a few hundred estimates ends before the learner's second cycle "
                         "(summary.json: lockstep holds and seconds)")
    cs.add_argument("--lambda", dest="noise_lambda", type=float, default=0.5,
                    help="noise level of the simulated initial hypotheses (0.5)")
    cs.add_argument("--seed", type=int, default=0, help="the estimates' seeds")
    cs.add_argument("--rate", type=float, default=1.0, help="replay rate, x the recorded timing (1.0)")
    cs.add_argument("--window", type=int, default=200, help="estimates in the rolling window (200)")
    cs.add_argument("--labels", choices=("ground_truth", "robot"), default="ground_truth",
                    help="what the cell's learner sees: ground_truth (replayed to the nodes and kept with the frames, "
                         "the default) or robot (a cell without ground truth: only this process knows it; its "
                         "simulated robot answers each pick and reports it with report_pick_outcome; needs --dataset "
                         "and a generator without ground truth, the cell pipeline)")
    cs.add_argument("--robot-reports", choices=("truth", "flipped", "all-failed", "all-success"), default="truth",
                    help="with --labels robot: a robot program that reports the truth (default), flips outcomes at "
                         "random (--flip-share), reports every pick failed, or every pick successful")
    cs.add_argument("--flip-share", type=float, default=0.3, help="share of outcomes flipped by --robot-reports "
                                                                   "flipped (0.3)")
    cs.add_argument("--hidden-seeds", type=int, default=1, metavar="N",
                    help="after the run, every kept version plays every object of the bag's images N times with the "
                         "hidden ground truth (summary: hidden_success_start/end, worse_promotions); 0: skip (1)")
    cs.add_argument("--quiet", action="store_true", help="no progress bar")
    cs.set_defaults(func=_cmd_cell_sim)
