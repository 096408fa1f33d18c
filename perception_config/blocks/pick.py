"""Pick blocks: the last action of an episode, the one that ends it when it succeeds.

`simulated_pick` judges a hypothesis against the ground truth, BOP-style (the paper's
systematic evaluation); `external_pick` hands the hypothesis to a robot cell and reports
what the cell says. Neither charges the robot's attempt time for a failed pick: the
environment does that (it is a property of the cell, not of the block's computation).

`ok` means "a pick was attempted and has an outcome" (`picked` True or False); `ok=False`
means the pick could not be attempted (no ground truth, a degenerate hypothesis, no robot
cell, an executor error or timeout), with the reason.
"""
from __future__ import annotations

import math
import threading
from typing import Any, Callable, ClassVar, Protocol

import numpy as np

from ..core.geometry import Pose
from ..core.metrics import derived_eval_symmetries, eval_symmetries, pose_mssd, pose_mssd_derived
from ..core.models import ObjectModel
from ..core.scene import Frame
from .base import GROUND_TRUTH, MODEL, POSE, Block, BlockInput, BlockResult, Kind, Param, register

GT_ROTATION_TOL = 1e-2  # as datasets/bop_json.py checks annotated rotations


@register
class SimulatedPick(Block):
    """Succeeds when the hypothesis is close enough to the ground truth to grasp the object.

    criterion "mssd" (default, BOP 2019): symmetry-aware maximum surface distance <=
    mssd_threshold x diameter; a hypothesis that differs from the ground truth by a symmetry of
    the object picks (`symmetries`: declared, or derived from the shape of a model declaring
    none). criterion "re_te" (BOP's 5 deg / 5 cm): rotation error <= max_re_deg and
    translation error <= max_te, taken at the best symmetry when `symmetry_aware` (default),
    plain otherwise. Scores: pick_mssd (m), pick_re (rad), pick_te (m) whatever the criterion.
    """

    kind = Kind.PICK
    name = "simulated_pick"
    default_cost = 0.5
    inputs = (POSE, MODEL, GROUND_TRUTH)
    params = (
        Param("criterion", "mssd", choices=("mssd", "re_te"),
              doc="success test: BOP MSSD or rotation/translation error"),
        Param("mssd_threshold", 0.1, 0.01, 1.0, doc="max MSSD as a share of the object diameter"),
        Param("max_re_deg", 5.0, 0.1, 180.0, doc="re_te: max rotation error, degrees"),
        Param("max_te", 0.05, 0.001, 1.0, doc="re_te: max translation error, metres"),
        Param("symmetry_aware", True, doc="re_te: errors at the best symmetry of the object"),
        Param("symmetries", "declared", choices=("declared", "derived"),
              doc="the symmetries a pick tolerates: those the model declares (BOP), or, for a model declaring "
                  "none, those its shape has (a gripper picks a nearly symmetric box flipped; real meshes "
                  "rarely declare them)"),
    )

    def run(self, inp: BlockInput) -> BlockResult:
        est, gt, model = inp.pose, inp.ground_truth, inp.model
        assert est is not None and gt is not None  # checked by Block._check_inputs
        # Annotated rotations are stored rounded (LM-O's are up to 2e-3 off orthonormal): accept
        # them with the BOP reader's tolerance; the errors below do not assume orthonormality.
        if not gt.is_valid(tol=GT_ROTATION_TOL):
            return BlockResult.fail("the ground-truth pose is degenerate (NaN, not a rotation, or behind the camera)")
        if not (math.isfinite(model.diameter) and model.diameter > 0):
            return BlockResult.fail(f"model {model.obj_id} has no valid diameter ({model.diameter})")
        derived = self.config["symmetries"] == "derived"
        err_mssd = pose_mssd_derived(est, gt, model) if derived else pose_mssd(est, gt, model)
        syms = ((derived_eval_symmetries(model) if derived else eval_symmetries(model))
                if self.config["symmetry_aware"] else [Pose.identity()])
        err_re, err_te = _best_re_te(est, gt, syms, math.radians(self.config["max_re_deg"]), self.config["max_te"])
        scores = {"pick_mssd": err_mssd, "pick_re": err_re, "pick_te": err_te}
        if not all(math.isfinite(v) for v in scores.values()):
            return BlockResult.fail(f"pose errors are not finite: {scores}")
        if self.config["criterion"] == "mssd":
            picked = err_mssd <= self.config["mssd_threshold"] * model.diameter
        else:
            picked = err_re <= math.radians(self.config["max_re_deg"]) and err_te <= self.config["max_te"]
        return BlockResult(ok=True, picked=bool(picked), scores=scores,
                           info={"criterion": self.config["criterion"], "diameter": model.diameter})


def _best_re_te(est: Pose, gt: Pose, syms: list[Pose], max_re: float, max_te: float) -> tuple[float, float]:
    """(re rad, te m) between est and gt∘S for the symmetry S that fits best: the smallest
    max(re / max_re, te / max_te), so the pair passes the re/te test iff some symmetry does."""
    R_s = np.stack([gt.R @ s.R for s in syms])
    t_s = np.stack([gt.R @ s.t + gt.t for s in syms])
    cos = (np.einsum("ij,sij->s", est.R, R_s) - 1.0) / 2.0  # trace(est.R^T R_s)
    res = np.arccos(np.clip(cos, -1.0, 1.0))
    tes = np.linalg.norm(t_s - est.t, axis=1)
    k = int(np.argmin(np.maximum(res / max_re, tes / max_te)))
    return float(res[k]), float(tes[k])


class PickExecutor(Protocol):
    """What a robot cell provides: try to pick `model` at `pose` (model-to-camera, metres) seen
    in `frame`; return True when the object was picked, False when the attempt failed. Raise
    (e.g. TimeoutError, ConnectionError) when no attempt could be made."""

    def __call__(self, pose: Pose, model: ObjectModel, frame: Frame) -> bool: ...


@register
class ExternalPick(Block):
    """Asks a robot cell to pick at the hypothesis; the outcome is the cell's answer.

    The cell is a `PickExecutor` callable: given at construction (`ExternalPick(executor=fn)`),
    attached later (`block.set_executor(fn)`), or attached process-wide for blocks created from
    a pipeline configuration (`ExternalPick.set_default_executor(fn)`, e.g. by the ROS pick node
    forwarding to the cell's service). The call runs in a daemon thread bounded by `timeout`
    seconds: a cell that does not answer in time gives ok=False, and its thread is left to
    finish on its own (a blocking call cannot be cancelled from Python; the executor should
    honour its own timeout too).
    """

    kind = Kind.PICK
    name = "external_pick"
    default_cost = 0.5
    inputs = (POSE, MODEL)
    params = (Param("timeout", 30.0, 0.01, 600.0, doc="seconds to wait for the robot cell's answer"),)

    default_executor: ClassVar[PickExecutor | None] = None
    _default_lock: ClassVar[threading.Lock] = threading.Lock()

    def __init__(self, executor: PickExecutor | None = None, **overrides: Any) -> None:
        super().__init__(**overrides)
        self.executor = executor

    @classmethod
    def set_default_executor(cls, executor: PickExecutor | None) -> None:
        """Attach (or detach with None) the robot cell every ExternalPick without its own uses."""
        with cls._default_lock:
            cls.default_executor = executor

    def set_executor(self, executor: PickExecutor | None) -> None:
        """Attach (or detach with None) this block's robot cell; it wins over the default."""
        self.executor = executor

    def run(self, inp: BlockInput) -> BlockResult:
        executor = self.executor or type(self).default_executor
        if executor is None:
            return BlockResult.fail("no robot cell connected (attach a pick executor)")
        pose, model, frame = inp.pose, inp.model, inp.frame
        box: dict[str, Any] = {}

        def call() -> None:
            try:
                box["value"] = executor(pose, model, frame)
            except BaseException as exc:  # reported to the caller, never raised in the thread
                box["error"] = exc

        timeout = float(self.config["timeout"])
        worker = threading.Thread(target=call, name="external_pick", daemon=True)
        worker.start()
        worker.join(timeout)
        if worker.is_alive():
            return BlockResult.fail(f"the robot cell did not answer within {timeout:g} s")
        if "error" in box:
            exc = box["error"]
            return BlockResult.fail(f"the robot cell could not pick: {type(exc).__name__}: {exc}")
        value = box.get("value")
        if not isinstance(value, (bool, np.bool_)):
            return BlockResult.fail(f"the robot cell answered {value!r}, expected True or False")
        return BlockResult(ok=True, picked=bool(value), info={"executor": _describe(executor)})


def _describe(fn: Callable[..., Any]) -> str:
    return getattr(fn, "__qualname__", None) or type(fn).__name__


__all__ = ["SimulatedPick", "ExternalPick", "PickExecutor"]
