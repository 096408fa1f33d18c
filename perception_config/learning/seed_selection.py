"""Training several seeds and shipping the one that validates best.

A policy-gradient run's outcome depends on its seed: on the cell pipeline two runs trained the
same way reached 92.6 % and 83.8 % success on the test images (docs/results/cell_agent.md);
the weaker had learned to give up after a refused generator call. Their held-out validation
costs (0.77 s against 1.71 s) told them apart without looking at the test images. So
`train_seeds` trains one run per seed, each with its own validation-based selection
(learning/training.py), in `out/seed-<s>/`, and ships the policy whose selected checkpoint has the lowest
mean validation cost as `out/policy.safetensors`, with `out/seeds.csv` (one row per seed) and
the chosen run's learning curve. Every run's validation uses the same held-out images and
episode seeds (learning/validation.py), so their costs compare. Ties go to the earlier seed.

Each run is an ordinary training run: `resume` continues the runs that have a checkpoint and
starts the others; `overwrite` starts them again (and over a single run's folder, drops its
checkpoint, history and validation files, as retraining it would); a stop signal ends the
seed in progress as `train` does (its work saved) and leaves the selection to the resumed call.
"""
from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any

from ..agents.policy_io import read_file
from ..util.atomic_file import atomic_write
from .training import CHECKPOINT, CURVE, HISTORY_CSV, VALIDATION_CSV, train

SEEDS_CSV = "seeds.csv"
SEEDS_FIELDS = ("seed", "run", "validation_cost", "validation_success", "validation_first_pick", "selected_episode",
                "shipped")


def seed_run(out: Path, seed: int) -> Path:
    """The run folder of one seed."""
    return out / f"seed-{seed}"


def validated(policy: Path) -> dict[str, Any]:
    """The validation record of the checkpoint a run shipped (its policy's `extra.selected`)."""
    meta, _ = read_file(policy)
    selected = meta.get("extra", {}).get("selected")
    if not selected or "validation" not in selected:
        raise ValueError(f"{policy}: the run has no validation record (train with validation_fraction > 0)")
    return {"episode": int(selected["episode"]), **selected["validation"]}


def train_seeds(dataset: str | Path, agent: str, out: str | Path, episodes: int, seeds: list[int],
                *, resume: bool = False, overwrite: bool = False, validation_fraction: float = 0.2,
                **train_kwargs: Any) -> Path:
    """Train `agent` once per seed in `seeds` (training.train's arguments otherwise) and ship
    the policy of lowest validation cost as out/<policy file>; returns that file."""
    seeds = list(dict.fromkeys(int(s) for s in seeds))
    if len(seeds) < 2:
        raise ValueError(f"seed selection needs at least two seeds, got {seeds}")
    if not validation_fraction > 0:
        raise ValueError("seed selection compares the runs' validation costs: validation_fraction must be > 0")
    out = Path(out)
    if (out / CHECKPOINT).exists():  # a single run's folder: its files would sit beside the seeds' as if shipped
        if not overwrite:
            raise FileExistsError(f"{out} already holds a single training run ({CHECKPOINT}): pass overwrite=True "
                                  "to train the seeds there instead, or choose another folder")
        for name in (CHECKPOINT, HISTORY_CSV, VALIDATION_CSV):
            (out / name).unlink(missing_ok=True)
    runs = []
    for k, seed in enumerate(seeds):
        run = seed_run(out, seed)
        if train_kwargs.get("progress", True):
            print(f"seed {seed} ({k + 1} of {len(seeds)}): {run}", flush=True)
        again = resume and (run / CHECKPOINT).exists()
        policy = train(dataset, agent, run, episodes, seed=seed, resume=again, overwrite=overwrite and not again,
                       validation_fraction=validation_fraction, **train_kwargs)
        runs.append((seed, run, policy, validated(policy)))
    best = min(range(len(runs)), key=lambda i: (runs[i][3]["cost"], i))
    _, run, policy, _ = runs[best]
    shipped = out / policy.name
    atomic_write(shipped, policy.read_bytes())
    if (run / CURVE).exists():
        atomic_write(out / CURVE, (run / CURVE).read_bytes())
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(SEEDS_FIELDS)
    for i, (seed, run, _, v) in enumerate(runs):
        writer.writerow([seed, run.name, f"{v['cost']:.6g}", f"{v['success']:.6g}", f"{v['first_pick']:.6g}",
                         v["episode"], int(i == best)])
    atomic_write(out / SEEDS_CSV, text.getvalue())
    return shipped


__all__ = ["train_seeds", "seed_run", "validated", "SEEDS_CSV", "SEEDS_FIELDS"]
