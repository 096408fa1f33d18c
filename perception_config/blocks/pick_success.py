"""The learned pick-success score: the probability that picking the current hypothesis succeeds.

`pick_success` computes the features of vision/pick_features.py at the hypothesis (the
pipeline's scores at their default parameters, depth residual statistics, outline-to-edge
agreement, visible fraction; the depth ones NaN on an RGB-only frame, which the model was
trained to expect) and returns the calibrated probability of a model fitted with
`perception-config fit-score` (vision/pick_success_model.py). Unlike the other scores it answers the
question an agent asks before a pick in the pick's own terms (symmetry-aware MSSD <= 0.1 x
diameter), so "pick when pick_success is high" is a rule an agent can learn quickly.

The `model` parameter names the model file (or the folder fit-score wrote). A relative path is
looked up in the working directory, then in the package's config folder; the default is the
model shipped there (config/pick_success/, fitted on the synthetic default dataset by the
command in its metrics.json). A missing, corrupt or mismatched model is refused when the block
is built (a pipeline that names it does not load), with the file named; an empty `model` is
refused too, so a pipeline cannot run a score that has no model behind it.

The `versions` parameter follows online learning (online/policy_learner.py): a folder of score
versions (util/versions.PolicyVersions, `<learn_dir>/pick_success/`). While it holds a version,
the version it selects serves instead of `model`, checked before each scoring (a stat of the
index), so a promotion or a rollback reaches every node that scores without a restart; until
the learner writes version 0 (the pipeline's model), `model` serves. A version that cannot be
loaded is skipped: the model that served keeps serving, and the block's info says why.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from ..util.versions import PolicyVersionError, PolicyVersions
from ..vision.pick_success_model import PickSuccessModel, PickSuccessModelError
from .base import MODEL, POSE, RGB, Block, BlockInput, BlockResult, Kind, Param, register
from .features import hypothesis_crop, pick_features

CONFIG_DIR = Path(__file__).resolve().parents[1] / "config"
SHIPPED_MODEL = "pick_success/pick_success.safetensors"  # in CONFIG_DIR: fitted on the synthetic default dataset
_MODELS: dict[tuple[str, int, int], PickSuccessModel] = {}  # (path, mtime_ns, size) -> model, loaded once


def resolve_model_path(name: str) -> Path:
    """The model file `name` names: as given when it exists (absolute, or relative to the working
    directory), else relative to the package's config folder; a folder means its model file."""
    path = Path(name).expanduser()
    if not path.is_absolute() and not path.exists() and (CONFIG_DIR / path).exists():
        path = CONFIG_DIR / path
    return path


def load_model(name: str) -> PickSuccessModel:
    """The model at `name` (resolve_model_path), read once per file version."""
    path = resolve_model_path(name)
    target = path / "pick_success.safetensors" if path.is_dir() else path
    try:
        st = target.stat()
        key = (str(target.resolve()), st.st_mtime_ns, st.st_size)
    except OSError:
        key = None
    if key is not None and key in _MODELS:
        return _MODELS[key]
    model = PickSuccessModel.load(target)  # PickSuccessModelError (a ValueError) naming the file
    if key is not None:
        _MODELS[key] = model
    return model


@register
class PickSuccess(Block):
    """Learned probability that a pick at the hypothesis succeeds (fit with `perception-config fit-score`)."""

    kind = Kind.SCORING
    name = "pick_success"
    default_cost = 0.015  # its own scoring pass: ~15 ms per hypothesis on the synthetic frames, one core
    inputs = (RGB, MODEL, POSE)  # depth is used when the frame has it; RGB-only frames score too
    score_names = ("pick_success",)
    score_ranges = {"pick_success": (0.0, 1.0)}
    params = (
        Param("model", SHIPPED_MODEL, doc="the pick-success model file or folder (perception-config fit-score); "
                                          "relative: the working directory, then the package's config folder"),
        Param("versions", "", doc="a folder of score versions written by online learning (<learn_dir>/pick_success): "
                                  "its selected version serves once there is one; empty: `model` always"),
    )

    def __init__(self, **overrides) -> None:
        super().__init__(**overrides)
        if not self.config["model"]:
            raise ValueError("block 'pick_success' needs a model: set its parameter model to a file written by "
                             f"`perception-config fit-score` (the shipped one: {SHIPPED_MODEL})")
        self.model = load_model(str(self.config["model"]))
        self.version: str | None = None  # the score version serving (None: `model`)
        self._versions: PolicyVersions | None = None
        self._stamp: tuple[int, int] | None = None
        self._problem = ""
        if self.config["versions"]:
            self.follow_versions(self.config["versions"])

    def follow_versions(self, folder: str | Path) -> None:
        """Serve the score versions in `folder` from the next scoring on."""
        self.config["versions"] = str(folder)
        self._versions = PolicyVersions(folder, "pick_success")
        self._stamp = None

    def refresh(self) -> None:
        """Serve the versions folder's selected version when its index changed (module docstring)."""
        if self._versions is None:
            return
        stamp = self._versions.stamp()
        if stamp is None or stamp == self._stamp:
            return
        self._stamp = stamp
        try:
            version = self._versions.current()
            if version is not None and version != self.version:
                self.model = load_model(str(self._versions.path(version)))
                self.version = version
            self._problem = ""
        except (PolicyVersionError, PickSuccessModelError, OSError) as exc:
            self._problem = f"pick_success version not loaded ({exc}); {self.version or 'the model'} keeps serving"

    def run(self, inp: BlockInput) -> BlockResult:
        assert inp.frame is not None and inp.pose is not None
        self.refresh()
        features = pick_features(inp.frame, inp.model, inp.pose, inp.cache)
        crop = hypothesis_crop(inp.frame, inp.model, inp.pose, inp.cache) if self.model.uses_crop else None
        p = self.model.predict_one(features, crop)
        info = {"features": features, "version": self.version}
        if self._problem:
            info["problem"] = self._problem
        return BlockResult(ok=True, scores={"pick_success": p}, info=info)


def follow_score_versions(pipeline: Any, folder: str | Path) -> int:
    """Make every pick_success block of `pipeline`'s scoring set follow the score versions in
    `folder` (module docstring); how many blocks follow."""
    blocks = [b for b in pipeline.scoring if isinstance(b, PickSuccess)]
    for block in blocks:
        block.follow_versions(folder)
    return len(blocks)


__all__ = ["PickSuccess", "load_model", "resolve_model_path", "follow_score_versions"]
