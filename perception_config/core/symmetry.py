"""Symmetries of an object model: the transformations of a BOP models_info entry."""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from .geometry import MM, Pose, exp_so3

DEFAULT_CONT_STEP_DEG = 10.0  # sampling step of continuous symmetries


def axis_angle_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation by `angle` (rad) about the unit vector `axis`."""
    axis = np.asarray(axis, dtype=np.float64)
    return exp_so3(axis / np.linalg.norm(axis) * angle)


def symmetries_from_info(info: Mapping[str, Any] | None, cont_step_deg: float = DEFAULT_CONT_STEP_DEG) -> list[Pose]:
    """Symmetry transformations (model frame, metres) of a BOP models_info entry (mm).

    As bop_toolkit's get_symmetry_transformations: the discrete ones (identity first) each
    combined with every sample of the continuous ones, which are sampled every cont_step_deg.
    """
    disc = [Pose.identity()]
    cont: list[Pose] = []
    if info:
        for sym in info.get("symmetries_discrete", []) or []:
            T = np.asarray(sym, dtype=np.float64).reshape(4, 4)
            disc.append(Pose(T[:3, :3], T[:3, 3] * MM))
        steps = max(1, int(round(360.0 / cont_step_deg)))
        for sym in info.get("symmetries_continuous", []) or []:
            axis = np.asarray(sym["axis"], dtype=np.float64)
            offset = np.asarray(sym["offset"], dtype=np.float64) * MM
            for i in range(steps):  # i = 0 is the identity, kept so discrete ones survive alone
                R = axis_angle_matrix(axis, 2.0 * np.pi * i / steps)
                cont.append(Pose(R, offset - R @ offset))
    if not cont:
        return disc
    return [c.compose(d) for d in disc for c in cont]


__all__ = ["axis_angle_matrix", "symmetries_from_info", "DEFAULT_CONT_STEP_DEG"]
