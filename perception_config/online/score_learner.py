"""The learner's pick-success score: refit from the cell's own estimates, promote only a better one.

The pick_success score (blocks/pick_success.py) ships fitted on synthetic parts; a cell's camera,
parts and gripper differ. With online learning (online/policy_learner.py) the learner also refits the
score, from what the configurator stored (`<learn_dir>/episodes.sqlite`, the kept frames in
`<learn_dir>/frames/`): every hypothesis of a frame that came with ground truth is labelled by
the pick criterion, and a hypothesis the robot picked by the robot's reported outcome
(`report_pick_outcome`), which wins over the simulation. A cell without ground truth learns from
its pick outcomes alone (pick_success_data.featurise).

One cycle (`refit_score_once`):
1. the labelled hypotheses, split by frame (pick_success_fit.split_images: the frames of the
   held-out share are never fitted on);
2. candidates: the serving model recalibrated (its network kept, Platt scaling fitted again:
   cheap, safe with few frames) and, from `REFIT_ROWS` labelled hypotheses on, a model fitted
   anew on the cell's rows alone (not for a model with a crop branch: its convolutions are
   trained offline on synthetic images, `fit-score --crops`; the cell recalibrates it);
3. the check: the Brier score (mean squared error of the probability) of the serving model and
   of each candidate on the held-out frames; the best candidate is promoted only if its Brier is
   below (1 - margin) x the serving one's AND the gain holds across the held-out frames: the
   policy's gate (online/promotion_gate.per_frame_bound), one-sided Student-t over the frames'
   mean gains (frames are the independent unit: hypotheses of one frame are alike), its lower
   bound at 95 % above zero; else discarded. Without the second test a handful of held-out
   frames promote noise (measured: a "better" Brier on 2 frames that was worse on images the
   cell never saw).
Versions live in `<learn_dir>/pick_success/` (util/versions.PolicyVersions, the same index as
the policies): version 0 is the pipeline's model, written at the configurator's start
(`initial_score_version`). The operator nodes follow the folder (their parameter
`pick_success_versions`), so a promotion or a rollback (the configurator's `score_version`)
serves from the next scoring on; the learner's own environment follows it too, so its policy
candidates are trained and checked on the score that serves.

Every file a cycle reads or writes (the store, the frames, the versions, the candidate) stays in
`learn_dir`: a symbolic link leading out of it is refused (util/confine.py) and the cycle fails
with the path named.
"""
from __future__ import annotations

import sqlite3
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..blocks.pick_success import PickSuccess, load_model, resolve_model_path
from ..core.score_metrics import score_metrics
from ..learning.pick_success_data import featurise, load_step_rows
from ..learning.pick_success_fit import fit_model, split_images
from ..store.episode_store import STORE_NAME, EpisodeStoreError
from ..util.confine import confined
from ..util.versions import PolicyVersionError, PolicyVersions
from ..vision.pick_success_model import MODEL_FILE, PickSuccessModelError
from .promotion_gate import CONFIDENCE, per_frame_bound

SCORES = "pick_success"  # the versions folder in learn_dir
MIN_FRAMES = 10  # labelled frames a cycle needs at least (fit, calibration and held-out ones)
MIN_HELD_OUT_FRAMES = 3  # held-out frames the gain is tested over
REFIT_ROWS = 400  # labelled hypotheses from which a model fitted anew is a candidate too
SPLIT_SEED = 0


class ScoreLearnError(RuntimeError):
    """A cycle without a score candidate; the message says why."""


def score_versions(learn_dir: str | Path) -> PolicyVersions:
    """The score versions of `learn_dir`, confined to it (PolicyVersionError when its
    pick_success/ folder leads out of it)."""
    return PolicyVersions(Path(learn_dir) / SCORES, "pick_success", root=learn_dir)


def pick_success_block(pipeline: Any) -> PickSuccess | None:
    """The pipeline's pick_success scoring block (None: the pipeline has no learned score)."""
    return next((b for b in pipeline.scoring if isinstance(b, PickSuccess)), None)


def initial_score_version(learn_dir: str | Path, pipeline: Any) -> str | None:
    """Write version 0 (the pipeline's model) when the folder has none and the pipeline scores
    pick_success; the version written (None: nothing to write)."""
    block = pick_success_block(pipeline)
    if block is None:
        return None
    versions = score_versions(learn_dir)
    if versions.newest() is not None:
        return None
    path = resolve_model_path(str(block.config["model"]))
    path = path / MODEL_FILE if path.is_dir() else path
    return versions.promote(path, {"start": str(path)})


def labelled_rows(learn_dir: Path, models_dir: str | Path, crops: bool = False) -> Any:
    """The FeatureTable of the stored hypotheses that carry a label (module docstring); `crops`:
    with each hypothesis' crop (a serving model with a crop branch needs them)."""
    try:
        rows = load_step_rows(confined(learn_dir / STORE_NAME, learn_dir, "episode store"), busy_timeout=2.0)
    except (sqlite3.Error, OSError, EpisodeStoreError) as exc:
        raise ScoreLearnError(f"episode store {learn_dir / STORE_NAME} cannot be read: {exc}") from None
    if not rows:
        raise ScoreLearnError("no stored hypothesis yet")
    try:
        # the cell's own camera only (no RGB-only copies of RGB-D frames: the cell's frames are what they are)
        return featurise(rows, with_rgb_only=False, progress=False, frames_dir=learn_dir / "frames",
                         models_dir=models_dir, crops=crops)
    except ValueError as exc:
        raise ScoreLearnError(str(exc)) from None


def refit_score_once(learn_dir: str | Path, models_dir: str | Path, margin: float = 0.05,
                     seed: int = 0) -> dict[str, Any]:
    """One cycle (module docstring); the result: outcome "promoted" | "discarded" | "failed",
    rows, frames, brier, serving_brier, candidate ("recalibrated" | "refit"), serving, version."""
    learn_dir = Path(learn_dir)
    serving = None
    try:
        versions = score_versions(learn_dir)
        serving = versions.current()
        if serving is None:
            raise ScoreLearnError(f"no pick_success version in {versions.folder}")
        serving_model = load_model(str(versions.path(serving)))
        started = time.perf_counter()
        table = labelled_rows(learn_dir, models_dir, crops=serving_model.uses_crop)
        frames = len(set(table.images))
        if frames < MIN_FRAMES:
            raise ScoreLearnError(f"{frames} labelled frames ({len(table)} hypotheses); at least {MIN_FRAMES} needed")
        held_out = split_images(table, seed=SPLIT_SEED)["test"]
        held_frames = [table.images[i] for i in np.flatnonzero(held_out)]
        if len(set(held_frames)) < MIN_HELD_OUT_FRAMES:
            raise ScoreLearnError(f"{len(set(held_frames))} held-out frames; at least {MIN_HELD_OUT_FRAMES} needed")
        y = table.y[held_out]
        serving_err = (serving_model.predict(*table.inputs(held_out)) - y) ** 2
        serving_brier = float(np.mean(serving_err))
        candidates: list[tuple[str, Any]] = []
        problems: list[str] = []
        for kind, base in (("recalibrated", serving_model), ("refit", None)):
            if kind == "refit" and (len(table) < REFIT_ROWS or serving_model.uses_crop):
                continue  # a model with a crop branch is recalibrated in the cell, its network refitted offline
            try:
                model, _, _ = fit_model(table, seed=seed, split_seed=SPLIT_SEED, base=base)
            except (ValueError, RuntimeError) as exc:
                problems.append(f"{kind}: {exc}")
                continue
            candidates.append((kind, model))
        if not candidates:
            raise ScoreLearnError("no candidate could be fitted (" + "; ".join(problems) + ")")
        scored = [((m.predict(*table.inputs(held_out)) - y) ** 2, kind, m) for kind, m in candidates]
        err, kind, best = min(scored, key=lambda s: float(np.mean(s[0])))
        brier = float(np.mean(err))
        gain, lower, _ = per_frame_bound(serving_err - err, held_frames, CONFIDENCE, "lower")
        held = score_metrics(best.predict(*table.inputs(held_out)), y)
        result: dict[str, Any] = {
            "outcome": "discarded", "what": "pick_success", "candidate": kind, "rows": len(table), "frames": frames,
            "held_out": int(held_out.sum()), "held_out_frames": len(set(held_frames)), "brier": brier,
            "serving_brier": serving_brier, "gain": gain, "gain_lower": lower, "confidence": CONFIDENCE,
            "auc": held["auc"], "serving": serving, "margin": margin,
            "seconds": time.perf_counter() - started}
        if brier < (1.0 - margin) * serving_brier and lower > 0.0:
            folder = confined(learn_dir / "candidates", learn_dir, "candidates folder")
            folder.mkdir(parents=True, exist_ok=True)
            best.record["learned_from"] = serving
            path = best.save(folder / MODEL_FILE)
            try:
                result["version"] = versions.promote(path, {k: v for k, v in result.items() if k != "outcome"})
            finally:
                path.unlink(missing_ok=True)
            result["outcome"] = "promoted"
        return result
    except (ScoreLearnError, PolicyVersionError, PickSuccessModelError, OSError, ValueError, RuntimeError) as exc:
        return {"outcome": "failed", "what": "pick_success", "serving": serving,
                "reason": f"{type(exc).__name__}: {exc}"[:500]}


def format_score_result(r: dict[str, Any]) -> str:
    """The learner's line for a score cycle (the configurator logs it)."""
    if r["outcome"] == "failed":
        return f"learner: no pick_success candidate: {r['reason']}; serving {r.get('serving') or 'nothing'} unchanged"
    verdict = f"promoted {r['version']}" if r["outcome"] == "promoted" else "discarded"
    return (f"learner: pick_success candidate ({r['candidate']}) from {r['rows']} hypotheses of {r['frames']} frames: "
            f"held-out Brier {r['brier']:.4f} vs serving {r['serving_brier']:.4f} (gain {r['gain']:+.4f}, "
            f"{r['confidence']:.0%} lower bound {r['gain_lower']:+.4f} over {r['held_out_frames']} frames) "
            f"-> {verdict}")


__all__ = ["SCORES", "score_versions", "initial_score_version", "refit_score_once", "format_score_result",
           "pick_success_block", "ScoreLearnError"]
