"""One-line warnings of the commands: a degradation the run would otherwise go through silently
(the depth actions masked on an RGB-only dataset) is said once per command, on stderr, in the
format of the data warnings (`warning: ...`, cli/__init__.py)."""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Any


def warn(text: str) -> None:
    """One warning line on stderr."""
    print(f"warning: {text}", file=sys.stderr, flush=True)


def rgb_only_warning(dataset: str | Path, pipeline: Any = None, *, split: str = "test",
                     use_depth: bool = True) -> str | None:
    """What an RGB-only dataset (no depth/ folder, or read with --no-depth) takes from `pipeline`
    (a YAML path or a shipped name; None = default): the actions masked on its frames (rl/env.py)
    and the scores missing there, with the reason, as one line; None when nothing is taken (every
    scene has depth, or the pipeline needs none)."""
    from ..blocks.pipeline import load_pipeline
    from ..datasets.bop import BopDataset
    from ..datasets.bop_json import short_ids

    pipe = load_pipeline(pipeline)
    actions, scores = pipe.depth_actions, pipe.depth_scoring
    if not actions and not scores:
        return None
    ds = BopDataset(dataset, split=split, use_depth=use_depth)
    scenes = ds.scene_ids()
    lacking = sorted({s for s, i in ds.image_keys() if not ds.has_depth(s, i)})
    if not lacking:
        return None
    if not use_depth:
        reason = f"--no-depth reads dataset {ds.root} as RGB-only"
    elif len(lacking) == len(scenes):
        reason = f"dataset {ds.root} has no depth images"
    else:
        reason = (f"{len(lacking)} of {len(scenes)} scenes of dataset {ds.root} have no depth images "
                  f"(scenes {short_ids(lacking)})")
    lost = []
    if actions:
        lost.append(f"the depth actions {', '.join(actions)} are masked out")
    if scores:
        lost.append(f"the depth scores {', '.join(scores)} are missing")
    where = " on those scenes' frames" if len(lacking) < len(scenes) else ""
    return f"{reason}: {' and '.join(lost)}{where}; use --pipeline rgb for an RGB pipeline"
