"""The BOP results CSV (bop_toolkit's inout.save_bop_results / load_bop_results): one pose estimate
per line, R row-major, t in mm (metres in the code).
"""
from __future__ import annotations

import csv
import io
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from ..core.geometry import MM, Pose
from ..util.atomic_file import atomic_write
from ..util.safe_json import JsonLimitError, read_limited
from .bop_json import MAX_JSON_BYTES
from .errors import BopFormatError

RESULTS_HEADER = ["scene_id", "im_id", "obj_id", "score", "R", "t", "time"]


@dataclass(frozen=True)
class BopResult:
    """One pose estimate for the BOP results CSV; pose in metres, time in seconds (-1 unknown;
    bop_toolkit wants the same time for all estimates of an image)."""

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    pose: Pose
    time: float = -1.0


def write_results_csv(path: str | os.PathLike, rows: Iterable[BopResult]) -> None:
    """Write `scene_id,im_id,obj_id,score,R,t,time` (R row-major, t in mm, space-separated)
    as bop_toolkit's inout.save_bop_results; atomic."""
    buf = io.StringIO()
    buf.write(",".join(RESULTS_HEADER) + "\n")
    for r in rows:
        R = " ".join(repr(float(x)) for x in r.pose.R.reshape(-1))
        t = " ".join(repr(float(x)) for x in r.pose.t / MM)
        buf.write(f"{int(r.scene_id)},{int(r.im_id)},{int(r.obj_id)},{float(r.score)!r},{R},{t},{float(r.time)!r}\n")
    atomic_write(Path(path), buf.getvalue().encode("utf-8"))


def read_results_csv(path: str | os.PathLike) -> list[BopResult]:
    """Read a BOP results CSV (t in mm -> metres); BopFormatError naming file and line."""
    path = Path(path)
    try:
        text = read_limited(path, MAX_JSON_BYTES, "BOP results file").decode("utf-8")
    except FileNotFoundError:
        raise FileNotFoundError(f"BOP results file not found: {path}") from None
    except JsonLimitError as e:
        raise BopFormatError(str(e)) from None
    except UnicodeDecodeError as e:
        raise BopFormatError(f"{path}: not UTF-8 text ({e.reason})") from None
    rows = list(csv.reader(io.StringIO(text)))
    if not rows or [c.strip() for c in rows[0]] != RESULTS_HEADER:
        raise BopFormatError(f"{path}: header must be {','.join(RESULTS_HEADER)}")
    out = []
    for ln, row in enumerate(rows[1:], start=2):
        if not row or not "".join(row).strip():
            continue
        if len(row) != len(RESULTS_HEADER):
            raise BopFormatError(f"{path}: line {ln} has {len(row)} columns, expected {len(RESULTS_HEADER)}")
        try:
            R = np.array(row[4].split(), dtype=np.float64)
            t = np.array(row[5].split(), dtype=np.float64)
            res = (int(row[0]), int(row[1]), int(row[2]), float(row[3]), float(row[6]))
        except ValueError:
            raise BopFormatError(f"{path}: line {ln} has a non-numeric value") from None
        if R.size != 9 or t.size != 3 or not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            raise BopFormatError(f"{path}: line {ln}: R needs 9 and t 3 finite numbers")
        out.append(BopResult(res[0], res[1], res[2], res[3], Pose(R.reshape(3, 3), t * MM), res[4]))
    return out


__all__ = ["BopResult", "write_results_csv", "read_results_csv", "RESULTS_HEADER"]
