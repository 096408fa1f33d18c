"""The learned pick-success model: a small MLP on the pick features, calibrated, in one file.

Input: the features of vision/pick_features.py, standardised with the training set's median and
spread, NaN (a feature the frame cannot give) set to 0 with a missing indicator per feature
beside it, so RGB-D and RGB-only hypotheses share one model. Output: the probability that a
pick at the hypothesis succeeds: sigmoid(a * logit + b), where (a, b) is Platt scaling of the
network's logit fitted on a calibration split of images the network did not train on.

A model may also look at the hypothesis itself: with a crop branch (`conv`, version 2 files),
the rendered-against-observed crop of vision/verifier_crop.py is embedded by the convolutions
of vision/crop_network.py and the MLP takes that embedding beside the encoded features
(`perception-config fit-score --crops`). Such a model needs the crop wherever it predicts
(`uses_crop`); a version 1 file (no branch) is read as before.

The file is safetensors (the arrays) with the metadata as JSON in its header (format,
version, feature names, layer shapes, calibration, training record, a sha256 over both, as
agents/policy_io.py writes policies): loading runs no code (no pickle), and a file for other
features, damaged or modified, is refused with a PickSuccessModelError naming it and what
differs. Inference is numpy (a few small matrix products); torch only trains (fit_mlp).

The checksum shows only that a file is as it was written; a file edited and re-checksummed passes
it. So every number is range-checked as well (`check_ranges`): the Platt calibration 0 < a <=
MAX_CALIBRATION and |b| <= MAX_CALIBRATION (fit_platt keeps a in [0.001, 10], b in [-50, 50]),
every tensor finite, the weights within +-MAX_ABS_WEIGHT, the feature medians within
+-MAX_ABS_FEATURE and the spreads in [MIN_SPREAD, MAX_ABS_FEATURE] (robust_scaling keeps them >=
0.001). A file outside these is refused with a PickSuccessModelError naming it, the field and
the value.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..util.atomic_file import atomic_write
from ..util.checksum import CHECKSUM_KEY, content_checksum
from ..util.safe_json import JsonLimitError, loads_limited, read_limited
from .crop_network import check_conv, embed, embedding_width
from .pick_features import FEATURE_NAMES
from .verifier_crop import CHANNELS, CROP

FORMAT = "perception_config.pick_success"
VERSION = 2  # 2: an optional crop branch; version 1 files (none) are read too
MAX_CONV = 8
META_KEY = "perception_config"
MODEL_FILE = "pick_success.safetensors"
MAX_MODEL_BYTES = 16 * 1024 * 1024  # a model file larger than this is refused before reading
MAX_JSON_DEPTH = 16
MAX_LAYERS = 8
MAX_CALIBRATION = 1e3  # |a|, |b| of the Platt scaling above this are refused (fit_platt: a <= 10, |b| <= 50)
MAX_ABS_WEIGHT = 1e4  # |weight| or |bias| above this is refused (trained ones are of order 1; inputs are <= 10)
MAX_ABS_FEATURE = 1e6  # |median| and spread of a feature above this are refused (the features are O(1))
MIN_SPREAD = 1e-6  # a spread below this is refused (robust_scaling keeps spreads >= 1e-3)


class PickSuccessModelError(ValueError):
    """A pick-success model file that cannot be used here; the message names the file."""


def encode(X: np.ndarray, median: np.ndarray, spread: np.ndarray) -> np.ndarray:
    """The network input of raw features X (n, F) with NaN: standardised values (NaN -> 0,
    clipped to +-10) and a missing indicator per feature, (n, 2F) float32."""
    X = np.atleast_2d(np.asarray(X, np.float64))
    missing = ~np.isfinite(X)
    z = np.clip((np.where(missing, median, X) - median) / spread, -10.0, 10.0)
    return np.concatenate([z, missing.astype(np.float64)], axis=1).astype(np.float32)


def robust_scaling(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(median, spread) per feature over the finite values: spread = IQR / 1.349 (a standard
    deviation for normal data), at least 1e-3; 0 and 1 for a feature that is never finite."""
    median = np.zeros(X.shape[1])
    spread = np.ones(X.shape[1])
    for j in range(X.shape[1]):
        col = X[:, j][np.isfinite(X[:, j])]
        if len(col):
            q1, q2, q3 = np.percentile(col, [25, 50, 75])
            median[j], spread[j] = q2, max((q3 - q1) / 1.349, float(np.std(col)) * 0.1, 1e-3)
    return median, spread


@dataclass
class PickSuccessModel:
    """An MLP (ReLU hidden layers, one logit out) over `encode`d features, Platt-calibrated."""

    feature_names: tuple[str, ...]
    median: np.ndarray
    spread: np.ndarray
    layers: list[tuple[np.ndarray, np.ndarray]]  # (weight (out, in), bias (out,)) per layer
    calibration: tuple[float, float] = (1.0, 0.0)  # (a, b): p = sigmoid(a * logit + b)
    record: dict[str, Any] = field(default_factory=dict)  # how it was trained and what it measured
    conv: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)  # the crop branch (W (O, C, 3, 3), b)

    @property
    def uses_crop(self) -> bool:
        """Whether the model needs the hypothesis' crop (vision/verifier_crop.py) to predict."""
        return bool(self.conv)

    def logit(self, X: np.ndarray, crops: np.ndarray | None = None) -> np.ndarray:
        """The uncalibrated network logits (n,) of raw features X (n, F) and, for a model with a
        crop branch, the hypotheses' crops (n, C, CROP, CROP)."""
        h = encode(X, self.median, self.spread).astype(np.float64)
        if self.conv:
            if crops is None or len(crops) != len(h):
                raise ValueError("this pick-success model looks at the hypothesis' crop: give one crop per row")
            h = np.concatenate([h, embed(crops, self.conv).astype(np.float64)], axis=1)
        for i, (W, b) in enumerate(self.layers):
            h = h @ W.T + b
            if i < len(self.layers) - 1:
                h = np.maximum(h, 0.0)
        return h[:, 0]

    def predict(self, X: np.ndarray, crops: np.ndarray | None = None) -> np.ndarray:
        """Calibrated probabilities (n,) that a pick at each hypothesis succeeds (`crops`: as logit)."""
        a, b = self.calibration
        return 1.0 / (1.0 + np.exp(-np.clip(a * self.logit(X, crops) + b, -60.0, 60.0)))

    def predict_one(self, features: dict[str, float], crop: np.ndarray | None = None) -> float:
        """The probability for one feature dict (pick_features' output) and its crop (C, CROP, CROP)."""
        X = np.array([[features.get(n, math.nan) for n in self.feature_names]])
        return float(self.predict(X, None if crop is None else crop[None])[0])

    # -- files ---------------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        """Write the model atomically (safetensors + JSON metadata with a checksum)."""
        from safetensors.numpy import save

        tensors = {"median": self.median.astype(np.float64), "spread": self.spread.astype(np.float64)}
        for i, (W, b) in enumerate(self.layers):
            tensors[f"layer{i}.weight"] = np.ascontiguousarray(W, np.float32)
            tensors[f"layer{i}.bias"] = np.ascontiguousarray(b, np.float32)
        for i, (W, b) in enumerate(self.conv):
            tensors[f"conv{i}.weight"] = np.ascontiguousarray(W, np.float32)
            tensors[f"conv{i}.bias"] = np.ascontiguousarray(b, np.float32)
        meta = {"format": FORMAT, "version": 2 if self.conv else 1, "feature_names": list(self.feature_names),
                "n_layers": len(self.layers), "activation": "relu",
                "calibration": {"method": "platt", "a": float(self.calibration[0]), "b": float(self.calibration[1])},
                "record": self.record}
        if self.conv:
            meta["crop"] = {"channels": list(CHANNELS), "size": CROP, "n_conv": len(self.conv)}
        meta[CHECKSUM_KEY] = content_checksum(meta, tensors)
        return atomic_write(path, save(tensors, metadata={META_KEY: json.dumps(meta)}))

    @classmethod
    def load(cls, path: str | Path, expected_features: Sequence[str] | None = FEATURE_NAMES) -> "PickSuccessModel":
        """Read and check a model file (module docstring); `expected_features`: the features this
        code computes (None: accept any)."""
        path = Path(path)
        if path.is_dir():
            path = path / MODEL_FILE
        meta, tensors = _read(path)
        names = meta["feature_names"]
        if expected_features is not None and list(names) != list(expected_features):
            missing = [n for n in expected_features if n not in names]
            extra = [n for n in names if n not in expected_features]
            raise PickSuccessModelError(
                f"pick-success model {path} was fitted on other features than this code computes "
                f"(not in the model: {missing}; not computed here: {extra}): fit it again with "
                f"`perception-config fit-score`")
        F = len(names)
        conv = _crop_branch(meta, tensors, path)
        layers = []
        width = 2 * F + embedding_width(conv)
        for i in range(meta["n_layers"]):
            W, b = tensors.get(f"layer{i}.weight"), tensors.get(f"layer{i}.bias")
            if W is None or b is None or W.ndim != 2 or W.shape[1] != width or b.shape != (W.shape[0],):
                raise PickSuccessModelError(f"pick-success model {path} is corrupt: layer {i} is missing or its "
                                            f"shape does not follow from the previous layer's ({width} inputs)")
            layers.append((W.astype(np.float64), b.astype(np.float64)))
            width = W.shape[0]
        if width != 1:
            raise PickSuccessModelError(f"pick-success model {path} is corrupt: the last layer has {width} outputs, "
                                        f"not 1")
        median, spread = tensors.get("median"), tensors.get("spread")
        if median is None or spread is None or median.shape != (F,) or spread.shape != (F,) or np.any(spread <= 0):
            raise PickSuccessModelError(f"pick-success model {path} is corrupt: its feature scaling does not match "
                                        f"its {F} features")
        cal = meta["calibration"]
        return cls(tuple(names), median.astype(np.float64), spread.astype(np.float64), layers,
                   (float(cal["a"]), float(cal["b"])), dict(meta.get("record", {})), conv)


def _crop_branch(meta: dict[str, Any], tensors: dict[str, np.ndarray],
                 path: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """The crop branch's layers of a model file ([] without one), checked against this code's crop."""
    crop = meta.get("crop")
    if crop is None:
        return []
    if not isinstance(crop, dict) or crop.get("channels") != list(CHANNELS) or crop.get("size") != CROP:
        theirs = (crop.get("channels"), crop.get("size")) if isinstance(crop, dict) else crop
        raise PickSuccessModelError(
            f"pick-success model {path} looks at another crop than this code makes (its channels and size: "
            f"{theirs}; here {list(CHANNELS)}, {CROP}): fit it again with `perception-config fit-score --crops`")
    n = crop.get("n_conv")
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= MAX_CONV:
        raise PickSuccessModelError(f"pick-success model {path} is corrupt: crop.n_conv = {n!r}")
    conv = []
    for i in range(n):
        W, b = tensors.get(f"conv{i}.weight"), tensors.get(f"conv{i}.bias")
        if W is None or b is None:
            raise PickSuccessModelError(f"pick-success model {path} is corrupt: convolution {i} is missing")
        conv.append((W.astype(np.float32), b.astype(np.float32)))
    problem = check_conv(conv, len(CHANNELS), CROP)
    if problem:
        raise PickSuccessModelError(f"pick-success model {path} is corrupt: {problem}")
    return conv


def _read(path: Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """(metadata, tensors) of a model file, every check of the module docstring done."""
    what = f"pick-success model {path}"
    try:
        data = read_limited(path, MAX_MODEL_BYTES, "pick-success model")
    except FileNotFoundError:
        raise PickSuccessModelError(f"{what} does not exist (fit one with `perception-config fit-score`)") from None
    except JsonLimitError as exc:
        raise PickSuccessModelError(f"pick-success model {exc}") from None
    except OSError as exc:
        raise PickSuccessModelError(f"{what} cannot be read: {exc.strerror or exc}") from None
    n = int.from_bytes(data[:8], "little") if len(data) >= 8 else -1
    if n <= 0 or 8 + n > len(data):
        raise PickSuccessModelError(f"{what} is corrupt or not a model: no safetensors header")
    try:
        header = loads_limited(data[8:8 + n], what, MAX_MODEL_BYTES, MAX_JSON_DEPTH)
        raw = header.get("__metadata__", {}).get(META_KEY) if isinstance(header, dict) else None
        meta = loads_limited(raw.encode(), what, MAX_MODEL_BYTES, MAX_JSON_DEPTH) if isinstance(raw, str) else None
    except (JsonLimitError, AttributeError) as exc:
        raise PickSuccessModelError(f"{what} is corrupt: {exc}") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise PickSuccessModelError(f"{path} is not a pick-success model (no {FORMAT!r} metadata)")
    version = meta.get("version")
    if isinstance(version, bool) or not isinstance(version, int) or version > VERSION:
        raise PickSuccessModelError(f"{what} has format version {version!r}; this code reads <= {VERSION}")
    names, n_layers, cal = meta.get("feature_names"), meta.get("n_layers"), meta.get("calibration")
    if not (isinstance(names, list) and names and all(isinstance(x, str) for x in names)
            and isinstance(n_layers, int) and not isinstance(n_layers, bool) and 1 <= n_layers <= MAX_LAYERS
            and isinstance(cal, dict) and all(isinstance(cal.get(k), (int, float)) and not isinstance(cal.get(k), bool)
                                              and math.isfinite(cal[k]) for k in ("a", "b"))
            and isinstance(meta.get("record", {}), dict)):
        raise PickSuccessModelError(f"{what} is corrupt: malformed metadata (feature_names, n_layers, calibration)")
    try:
        from safetensors.numpy import load

        tensors = dict(load(data))
    except Exception as exc:  # safetensors raises its own error types; all mean "corrupt"
        raise PickSuccessModelError(f"{what} is corrupt: {type(exc).__name__}: {exc}") from None
    if CHECKSUM_KEY not in meta or content_checksum(meta, tensors) != meta[CHECKSUM_KEY]:
        raise PickSuccessModelError(f"{what} is corrupt: its content does not match its {CHECKSUM_KEY} checksum "
                                    f"(modified or damaged after it was written)")
    check_ranges(meta, tensors, what)
    return meta, tensors


def check_ranges(meta: dict[str, Any], tensors: dict[str, np.ndarray], what: str) -> None:
    """Every number of a model within the bounds of the module docstring; PickSuccessModelError
    naming `what` (the model and its file), the field and the value otherwise."""
    a, b = meta["calibration"]["a"], meta["calibration"]["b"]
    if not 0 < a <= MAX_CALIBRATION:
        raise PickSuccessModelError(f"{what} is corrupt: calibration.a = {a!r} is outside (0, {MAX_CALIBRATION:g}] "
                                    f"(fit-score fits a in [0.001, 10]; a <= 0 would reverse or flatten the score)")
    if not abs(b) <= MAX_CALIBRATION:
        raise PickSuccessModelError(f"{what} is corrupt: calibration.b = {b!r} is outside [-{MAX_CALIBRATION:g}, "
                                    f"{MAX_CALIBRATION:g}] (fit-score fits b in [-50, 50])")
    for name, t in tensors.items():
        if t.dtype.kind != "f" or not np.isfinite(t).all():
            raise PickSuccessModelError(f"{what} is corrupt: tensor {name!r} is not finite floating point")
        if name == "spread":
            lo, hi = MIN_SPREAD, MAX_ABS_FEATURE
        elif name == "median":
            lo, hi = -MAX_ABS_FEATURE, MAX_ABS_FEATURE
        else:
            lo, hi = -MAX_ABS_WEIGHT, MAX_ABS_WEIGHT
        bad = np.flatnonzero((t < lo) | (t > hi))
        if bad.size:
            value = float(t.reshape(-1)[bad[0]])
            raise PickSuccessModelError(f"{what} is corrupt: tensor {name!r} holds {value:g} (element {int(bad[0])}), "
                                        f"outside [{lo:g}, {hi:g}]")


# -- training (torch) --------------------------------------------------------------------
def fit_mlp(Z: np.ndarray, y: np.ndarray, hidden: Sequence[int] = (32, 16), epochs: int = 300, lr: float = 0.01,
            weight_decay: float = 1e-3, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Train the MLP on encoded inputs Z (n, 2F) and labels y (n,): full-batch Adam on the
    binary cross-entropy, classes weighted to equal total weight (the rarer class is not
    ignored; calibration restores the base rate). Seeded, single-threaded: reproducible."""
    import torch

    torch.manual_seed(seed)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        dims = [Z.shape[1], *[int(h) for h in hidden], 1]
        mods: list[Any] = []
        for i in range(len(dims) - 1):
            mods.append(torch.nn.Linear(dims[i], dims[i + 1]))
            if i < len(dims) - 2:
                mods.append(torch.nn.ReLU())
        net = torch.nn.Sequential(*mods).double()
        X = torch.from_numpy(np.asarray(Z, np.float64))
        t = torch.from_numpy(np.asarray(y, np.float64))
        pos = float(t.mean())
        w = torch.where(t > 0.5, 0.5 / max(pos, 1e-6), 0.5 / max(1 - pos, 1e-6))
        opt = torch.optim.Adam(net.parameters(), lr=lr, weight_decay=weight_decay)
        for _ in range(int(epochs)):
            opt.zero_grad()
            loss = torch.nn.functional.binary_cross_entropy_with_logits(net(X)[:, 0], t, weight=w)
            loss.backward()
            opt.step()
        linears = [m for m in net if isinstance(m, torch.nn.Linear)]
        return [(m.weight.detach().numpy().copy(), m.bias.detach().numpy().copy()) for m in linears]
    finally:
        torch.set_num_threads(threads)


def fit_platt(logits: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """(a, b) minimising the log loss of sigmoid(a * logit + b) on a calibration set, a in
    [1e-3, 10] (bounded L-BFGS: on a separable set the unbounded optimum runs off to infinity),
    with a small ridge on a - 1 and b so a tiny or one-class set stays near the identity."""
    from scipy.optimize import minimize

    s, t = np.asarray(logits, float), np.asarray(y, float)
    ridge = 1e-3

    def loss(v: np.ndarray) -> tuple[float, np.ndarray]:
        z = v[0] * s + v[1]
        # log(1 + e^z) - t z, stable; its derivative sigmoid(z) - t
        nll = np.logaddexp(0.0, z) - t * z
        p = 0.5 * (1.0 + np.tanh(0.5 * z))
        g = p - t
        n = max(1, len(s))
        return (float(nll.sum() / n + ridge * ((v[0] - 1.0) ** 2 + v[1] ** 2)),
                np.array([np.sum(g * s) / n + 2 * ridge * (v[0] - 1.0), np.sum(g) / n + 2 * ridge * v[1]]))

    res = minimize(loss, np.array([1.0, 0.0]), jac=True, method="L-BFGS-B", bounds=[(1e-3, 10.0), (-50.0, 50.0)])
    return float(res.x[0]), float(res.x[1])


__all__ = ["PickSuccessModel", "PickSuccessModelError", "check_ranges", "encode", "robust_scaling", "fit_mlp",
           "fit_platt", "MODEL_FILE", "FORMAT", "VERSION"]
