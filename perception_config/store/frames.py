"""The camera frames of learned estimates, kept so that the learner can replay them in-process.

Through ROS the images live in the operator nodes; the episode store has only a frame's stamp.
With online learning the configurator also keeps each estimated frame here
(`<learn_dir>/frames/<stamp_ns>.npz`, compressed): rgb, depth (absent for an RGB-only camera),
K, the stamp and, when the frame came with replayed ground truth (a test bench, a recorded bag
with annotations), the ground-truth poses of its objects. The learner replays the store's
episodes on these frames with the same operators in-process; the simulated initialisation and
the simulated pick need the ground truth, so a frame without it (a real robot cell) is kept for
the record but cannot be replayed (`load_frame` returns no poses; the learner skips it).

Writes are atomic (a reader never sees half a file); the folder is a bounded ring: beyond
`keep` files the oldest (by stamp) are removed, so disk use stays bounded (a 640x480 RGB-D
frame is about 0.3-1 MB compressed). npz is read with allow_pickle=False: no code in a frame file.

Frames are read, written and pruned only inside the learn directory (`root`; default: the frames
folder's parent): a frames folder or a frame file that is a symbolic link leading out of it is
refused (util/confine.py: a ConfinementError, a ValueError naming the path and where it leads)
before anything is read, written or removed; links that stay inside are allowed.
"""
from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from ..core.geometry import Pose
from ..core.scene import Frame
from ..util.atomic_file import atomic_output
from ..util.confine import confined

FRAME_RING = 300  # frames kept


def frame_path(folder: str | Path, stamp_ns: int) -> Path:
    return Path(folder) / f"{int(stamp_ns)}.npz"


def _frames_folder(folder: str | Path, root: str | Path | None) -> Path:
    """The frames folder resolved, when it stays inside `root` (default: its parent)."""
    folder = Path(folder)
    return confined(folder, folder.parent if root is None else root, "frames folder")


def save_frame(folder: str | Path, stamp_ns: int, frame: Frame, ground_truth: dict[int, Pose] | None,
               keep: int = FRAME_RING, root: str | Path | None = None) -> Path:
    """Write one frame (and its objects' ground truth, when known) atomically; prune the ring.
    Raises OSError (a full disk ...) with nothing half-written left behind; ConfinementError (a
    ValueError) when the folder or the file leads out of `root` (module docstring)."""
    top = Path(folder).parent if root is None else Path(root)
    real = _frames_folder(folder, top)
    real.mkdir(parents=True, exist_ok=True)
    path = frame_path(folder, stamp_ns)
    target = confined(path, top, "frame file")
    gt = ground_truth or {}
    ids = sorted(gt)
    arrays = {"rgb": np.ascontiguousarray(frame.rgb, np.uint8), "K": np.asarray(frame.K, np.float64),
              "stamp_ns": np.int64(stamp_ns), "gt_ids": np.asarray(ids, np.int64),
              "gt_R": np.asarray([gt[i].R for i in ids], np.float64).reshape(len(ids), 3, 3),
              "gt_t": np.asarray([gt[i].t for i in ids], np.float64).reshape(len(ids), 3)}
    if frame.depth is not None:
        arrays["depth"] = np.ascontiguousarray(frame.depth, np.float32)
    with atomic_output(target) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)
    prune_frames(real, keep, top)
    return path


def prune_frames(folder: str | Path, keep: int, root: str | Path | None = None) -> int:
    """Remove the oldest frames beyond `keep` (the folder confined to `root`, default its
    parent; a frame file that is a link loses the link only); how many were removed."""
    files = sorted(_frames_folder(folder, root).glob("*.npz"), key=lambda p: int(p.stem) if p.stem.isdigit() else -1)
    removed = 0
    for p in files[: max(0, len(files) - keep)]:
        p.unlink(missing_ok=True)
        removed += 1
    return removed


def load_frame(path: str | Path, root: str | Path | None = None) -> tuple[Frame, dict[int, Pose]]:
    """A saved frame and its ground truth ({} when it had none). ValueError naming the file when
    it is not a frame file (corrupt, truncated, foreign) or when it leads out of `root` (default:
    its frames folder's parent, the learn directory)."""
    path = Path(path)
    real = confined(path, path.parent.parent if root is None else root, "frame file")
    try:
        with np.load(real, allow_pickle=False) as z:
            rgb, K, stamp = z["rgb"], z["K"], int(z["stamp_ns"])
            depth = z["depth"] if "depth" in z.files else None
            ids, R, t = z["gt_ids"], z["gt_R"], z["gt_t"]
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise ValueError(f"frame file {path} cannot be read: {type(exc).__name__}: {exc}") from None
    try:
        frame = Frame(rgb=rgb, depth=depth, K=K, stamp=stamp * 1e-9)
        gt = {int(i): Pose(np.asarray(r, np.float64), np.asarray(tt, np.float64)) for i, r, tt in zip(ids, R, t)}
    except (ValueError, TypeError) as exc:
        raise ValueError(f"frame file {path} is not a frame: {exc}") from None
    return frame, gt
