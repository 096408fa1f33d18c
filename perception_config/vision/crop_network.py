"""The convolutional branch of the pick-success model: an embedding of the rendered-against-
observed crop (vision/verifier_crop.py), run in numpy, trained with torch.

Layers (CONV_WIDTHS): four 3x3 convolutions, padding 1, each followed by a ReLU, the first three
by a 2x2 max pooling: (8, 64, 64) -> (16, 32, 32) -> (32, 16, 16) -> (48, 8, 8) -> (64, 8, 8);
the embedding is the mean and the max of the last map per channel, (128,). The pick-success
model's MLP head takes it beside the encoded features (vision/pick_success_model.py).

Inference is numpy (im2col and one matrix product per layer, ~3 ms a crop on one core), so a
node that scores does not import torch; `embed` equals torch's forward to float32 rounding
(test/test_crop_verifier.py checks it). `fit_hybrid` trains the branch and the head together.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

CONV_WIDTHS = (16, 32, 48, 64)  # output channels of the four convolutions
POOLED = 3  # the first this many convolutions are followed by a 2x2 max pooling
EMBED_CHUNK = 64  # crops embedded at once: bounds the im2col buffers to ~100 MB


def conv3x3(x: np.ndarray, W: np.ndarray, b: np.ndarray) -> np.ndarray:
    """3x3 convolution with zero padding 1 of maps x (n, C, H, W) by W (O, C, 3, 3) plus b (O,):
    (n, O, H, W) float32 (a cross-correlation, as torch's Conv2d)."""
    n, C, H, Wd = x.shape
    xp = np.pad(x, ((0, 0), (0, 0), (1, 1), (1, 1)))
    cols = sliding_window_view(xp, (3, 3), axis=(2, 3))  # (n, C, H, W, 3, 3)
    cols = cols.transpose(0, 2, 3, 1, 4, 5).reshape(n * H * Wd, C * 9)
    out = cols @ W.reshape(W.shape[0], -1).T + b
    return out.reshape(n, H, Wd, W.shape[0]).transpose(0, 3, 1, 2)


def max_pool2(x: np.ndarray) -> np.ndarray:
    """2x2 max pooling, stride 2, of (n, C, H, W) with even H, W."""
    n, C, H, W = x.shape
    return x.reshape(n, C, H // 2, 2, W // 2, 2).max(axis=(3, 5))


def embed(crops: np.ndarray, conv: Sequence[tuple[np.ndarray, np.ndarray]], chunk: int = EMBED_CHUNK) -> np.ndarray:
    """The embedding (n, 2 x last width) of crops (n, C, H, W) by the layers `conv`
    [(W (O, C, 3, 3), b (O,))] (module docstring), `chunk` crops at a time (im2col of a 64 x 64
    crop is ~1 MB)."""
    if len(crops) > chunk:
        return np.concatenate([embed(crops[s:s + chunk], conv, chunk) for s in range(0, len(crops), chunk)])
    h = np.asarray(crops, np.float32)
    for i, (W, b) in enumerate(conv):
        h = np.maximum(conv3x3(h, W.astype(np.float32), b.astype(np.float32)), 0.0)
        if i < POOLED:
            h = max_pool2(h)
    return np.concatenate([h.mean(axis=(2, 3)), h.max(axis=(2, 3))], axis=1)


def embedding_width(conv: Sequence[tuple[np.ndarray, np.ndarray]]) -> int:
    return 2 * int(conv[-1][0].shape[0]) if conv else 0


def check_conv(conv: Sequence[tuple[np.ndarray, np.ndarray]], channels: int, crop: int) -> str:
    """'' when the layers chain from `channels` input maps of side `crop`, else what is wrong."""
    width = channels
    if crop % (2 ** POOLED):
        return f"crop side {crop} is not divisible by {2 ** POOLED}"
    for i, (W, b) in enumerate(conv):
        if W.ndim != 4 or W.shape[1] != width or W.shape[2:] != (3, 3) or b.shape != (W.shape[0],):
            return f"convolution {i} has shape {W.shape} / {b.shape}, expected (out, {width}, 3, 3) / (out,)"
        width = W.shape[0]
    return ""


def _torch_net(n_features: int, channels: int, hidden: Sequence[int]) -> Any:
    import torch

    class Hybrid(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            layers: list[Any] = []
            width = channels
            for i, out in enumerate(CONV_WIDTHS):
                layers += [torch.nn.Conv2d(width, out, 3, padding=1), torch.nn.ReLU()]
                if i < POOLED:
                    layers.append(torch.nn.MaxPool2d(2))
                width = out
            self.conv = torch.nn.Sequential(*layers)
            dims = [n_features + 2 * width, *[int(h) for h in hidden], 1]
            head: list[Any] = []
            for i in range(len(dims) - 1):
                head.append(torch.nn.Linear(dims[i], dims[i + 1]))
                if i < len(dims) - 2:
                    head.append(torch.nn.ReLU())
            self.head = torch.nn.Sequential(*head)

        def forward(self, crops: Any, z: Any) -> Any:
            h = self.conv(crops)
            return self.head(torch.cat([z, h.mean(dim=(2, 3)), h.amax(dim=(2, 3))], 1))[:, 0]

    return Hybrid()


def fit_hybrid(Z: np.ndarray, crops: np.ndarray, y: np.ndarray, hidden: Sequence[int] = (64,), epochs: int = 12,
               lr: float = 2e-3, batch: int = 128, seed: int = 0, threads: int = 2, progress: bool = True,
               on_epoch: Any = None) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[tuple[np.ndarray, np.ndarray]]]:
    """(conv layers, head layers) trained on encoded features Z (n, 2F), crops (n, C, H, W) and
    labels y (n,): AdamW with a one-cycle learning rate, mini-batches, the classes weighted to
    equal total weight, each batch flipped and turned by a multiple of 90 degrees (a crop turned
    is still a rendering against its observation). Seeded; `threads` torch threads.
    `on_epoch(epoch, mean_loss)` after each epoch."""
    import torch
    from tqdm import tqdm

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    before = torch.get_num_threads()
    torch.set_num_threads(max(1, int(threads)))
    try:
        net = _torch_net(Z.shape[1], crops.shape[1], hidden)
        opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-4)
        n = len(y)
        per_epoch = max(1, -(-n // batch))
        sched = torch.optim.lr_scheduler.OneCycleLR(opt, lr, total_steps=epochs * per_epoch)
        pos = float(np.mean(y))
        yt = torch.from_numpy(np.asarray(y, np.float32))
        weight = torch.where(yt > 0.5, 0.5 / max(pos, 1e-6), 0.5 / max(1 - pos, 1e-6))
        for epoch in tqdm(range(int(epochs)), desc="fit verifier", unit="epoch", disable=not progress):
            order = rng.permutation(n)
            total = 0.0
            for s in range(per_epoch):
                idx = order[s * batch:(s + 1) * batch]
                x = torch.from_numpy(np.asarray(crops[idx], np.float32))
                if rng.random() < 0.5:
                    x = torch.flip(x, (3,))
                x = torch.rot90(x, int(rng.integers(4)), (2, 3))
                loss = torch.nn.functional.binary_cross_entropy_with_logits(
                    net(x, torch.from_numpy(np.asarray(Z[idx], np.float32))), yt[idx], weight=weight[idx])
                opt.zero_grad()
                loss.backward()
                opt.step()
                sched.step()
                total += float(loss.detach()) * len(idx)
            if on_epoch is not None:
                on_epoch(epoch, total / n)
        convs = [m for m in net.conv if isinstance(m, torch.nn.Conv2d)]
        linears = [m for m in net.head if isinstance(m, torch.nn.Linear)]

        def arrays(m: Any) -> tuple[np.ndarray, np.ndarray]:
            return m.weight.detach().numpy().astype(np.float64), m.bias.detach().numpy().astype(np.float64)

        return [arrays(m) for m in convs], [arrays(m) for m in linears]
    finally:
        torch.set_num_threads(before)


__all__ = ["CONV_WIDTHS", "conv3x3", "max_pool2", "embed", "embedding_width", "check_conv", "fit_hybrid"]
