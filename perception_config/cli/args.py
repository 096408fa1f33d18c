"""Options and set-up shared by the commands."""
from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any


def add_dataset_args(parser: argparse.ArgumentParser, **kw: Any) -> None:
    """--dataset DIR and --no-depth (read the dataset as RGB-only: BopDataset(use_depth=False))."""
    parser.add_argument("--dataset", type=Path, required=True, **kw)
    parser.add_argument("--no-depth", dest="use_depth", action="store_false",
                        help="read the dataset as RGB-only (its depth images ignored): the actions and blocks that "
                             "need depth are left out")


def add_ray_args(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help=f"play {what} as tasks on a local Ray with N worker processes (bound to 127.0.0.1, "
                             "no dashboard); default and 1: in this process, without Ray")
    parser.add_argument("--ray-address", default=None, metavar="ADDR",
                        help="join a running Ray cluster instead (e.g. 127.0.0.1:6379 of `ray start --head`, or "
                             "auto); the dataset path must exist on every node")


def one_core() -> None:
    """Benchmarks measure one core: pin the numeric libraries before they load."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
