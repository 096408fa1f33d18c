"""Appearance agreement of a hypothesis with an RGB image, without depth (the psi_rgb score).

Two cues, both smooth over the few pixels by which real annotations and good hypotheses are
off (the LM-O ground truth is itself 2-6 px off the image in places, so a score that peaks
within 1-2 px ranks noise):

- `region_separation`: how well the hypothesis's outline separates the image colours, as in
  region-based tracking (PWP3D, RBOT). Colour histograms (`bits` per channel) of a band
  `band` px wide inside the rendered outline (foreground) and of the same band outside it
  (background) give each band pixel a foreground posterior P = h_f / (h_f + h_b); the score
  is the mean of P inside and of 1 - P outside, 0.5 when the two bands look alike and 1 when
  they share no colour. Only the image's colours are used, so it needs no model colour and
  does not depend on the lighting the model was scanned under; occluders inside the band
  lower it alike for every hypothesis of the instance.
- `edge_agreement`: the rendered outline against the image's Canny edges, orientation-aware
  and truncated: each outline pixel's distance to the nearest edge pixel (distance transform
  with labels on the hypothesis's crop) counts as `tau` when that edge's direction differs from the
  outline's by more than `max_angle`; the score is 1 - mean(min(distance, tau)) / tau.

The search (`disc_shifts`, `shifted_region`, `shifted_separation`, `shifted_edges`): the same
cues with the hypothesis's outline moved over the image by every shift up to a radius, the
region term both with the hypothesis's band histograms kept (one cv2.matchTemplate correlation
of the posterior map with the +1/n_inner, -1/n_outer band template) and with the histograms
re-estimated at the moved outline (one bincount over all shifts); psi_rgb takes the best fit.

Measured on lmo-rgb (20 real frames, 142 instances, 5680 poses at lambda 0.05-0.5; AUC of
in-tolerance over out-of-tolerance poses of the same instance): at the pose, region 0.831,
edges 0.797, region + 0.5 edges 0.838; best fit within 8 px with kept histograms 0.861, with
re-estimated ones 0.849 (within 4 px 0.868, 16 px 0.797: the re-estimated optimum wanders on
weak colour contrast), the two averaged 0.876. The shift of the optimum ranks worse than the
fit (its length within 16 px: 0.52 kept, 0.79 re-estimated, 0.59 on object 10), and subtracting
it or the gain of moving from the fit lowers the AUC (0.80-0.85).
Tried and dropped: histograms from the model's vertex colours (0.751), per-sector histograms
(0.818), the score relative to the outline shifted by 4-8 px (0.756-0.804), image-gradient
profiles along the outline normals (0.733), adding psi_c (0.833), histograms of the whole
object against a wider ring (0.824-0.836); psi_c 0.718.
"""
from __future__ import annotations

import cv2
import numpy as np

from ..core.render import Rendering
from ..core.scene import Frame


def colour_codes(rgb: np.ndarray, bits: int) -> np.ndarray:
    """(H, W) int32 colour bin of every pixel of an (H, W, 3) uint8 image: the top `bits` bits
    of R, G and B."""
    q = (rgb >> (8 - bits)).astype(np.int32)
    return (q[..., 0] << (2 * bits)) | (q[..., 1] << bits) | q[..., 2]


def padded_mask(frame: Frame, rendering: Rendering, pad: int) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """The rendered object mask (uint8 0/1) in its box grown by `pad` px (clipped to the image),
    and that box as (x0, y0, x1, y1)."""
    x, y, w, h = rendering.box
    x0, y0 = max(0, x - pad), max(0, y - pad)
    x1, y1 = min(frame.width, x + w + pad), min(frame.height, y + h + pad)
    m = np.zeros((y1 - y0, x1 - x0), np.uint8)
    m[y - y0:y - y0 + h, x - x0:x - x0 + w] = rendering.mask >= 0
    return m, (x0, y0, x1, y1)


def outline_bands(mask: np.ndarray, band: float) -> tuple[np.ndarray, np.ndarray]:
    """Boolean (inner, outer) bands of a 0/1 mask: pixels within `band` px of the outline."""
    din = cv2.distanceTransform(mask, cv2.DIST_L2, 3)
    dout = cv2.distanceTransform(1 - mask, cv2.DIST_L2, 3)
    return (mask > 0) & (din <= band), (mask == 0) & (dout <= band)


def region_separation(codes: np.ndarray, inner: np.ndarray, outer: np.ndarray, bits: int) -> float:
    """Mean foreground posterior inside plus mean background posterior outside, halved, from
    the colour histograms of the two bands (see the module docstring); in [0.5, 1] up to the
    histograms' smoothing. `codes` and the bands are arrays of one crop."""
    qi, qo = codes[inner], codes[outer]
    pf = band_posterior(codes, inner, outer, bits)
    return 0.5 * (float(pf[qi].mean()) + float(1.0 - pf[qo].mean()))


def outline_separation(frame: Frame, rendering: Rendering, band: int, bits: int = 4) -> float:
    """The region cue at a rendered hypothesis: 2 x region_separation - 1 of its outline's inner
    and outer `band` px bands (histograms of their own colours, `bits` per channel), 0 when the
    two sides look alike (or a band is empty), 1 when they share no colour."""
    if rendering.empty:
        return 0.0
    mask, (x0, y0, x1, y1) = padded_mask(frame, rendering, band + 1)
    inner, outer = outline_bands(mask, band)
    if not inner.any() or not outer.any():
        return 0.0
    codes = colour_codes(frame.rgb[y0:y1, x0:x1], bits)
    return max(0.0, 2.0 * region_separation(codes, inner, outer, bits) - 1.0)


def band_posterior(codes: np.ndarray, inner: np.ndarray, outer: np.ndarray, bits: int) -> np.ndarray:
    """Foreground posterior h_f / (h_f + h_b) of every colour bin (2^(3 bits) float64), from
    the normalised colour histograms of the inner and outer bands (+1e-4 each)."""
    n_bins = 1 << (3 * bits)
    hf = np.bincount(codes[inner], minlength=n_bins).astype(np.float64)
    hb = np.bincount(codes[outer], minlength=n_bins).astype(np.float64)
    hf = hf / max(hf.sum(), 1.0) + 1e-4
    hb = hb / max(hb.sum(), 1.0) + 1e-4
    return hf / (hf + hb)


def nearest_edges(edges: np.ndarray, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distance float32 HxW to the nearest edge pixel, direction float32 HxW in [0, pi) of that
    edge pixel) for an edge map (non-zero = edge) and its directions, e.g. a crop of
    edges.canny_edges; all-inf distance when there is no edge. Run on a crop around the
    hypothesis grown by the truncation distance, it is exact for truncated distances and costs
    ~0.5 ms (the whole 640x480 frame: ~7 ms)."""
    ys, xs = np.nonzero(edges)
    if len(ys) == 0:
        return np.full(edges.shape, np.inf, np.float32), np.zeros(edges.shape, np.float32)
    src = np.where(edges > 0, 0, 255).astype(np.uint8)
    dist, labels = cv2.distanceTransformWithLabels(src, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
    # DIST_LABEL_PIXEL numbers the zero pixels 1..N in row-major order, as np.nonzero lists them
    angle = np.zeros(len(ys) + 1, np.float32)
    angle[1:] = direction[ys, xs]
    return dist, angle[labels]


def edge_agreement(distance: np.ndarray, edge_angle: np.ndarray, uv: np.ndarray, normals: np.ndarray,
                   tau: float, max_angle: float) -> tuple[float, int]:
    """1 - mean truncated oriented distance / tau of outline pixels `uv` (N, 2; integer-valued,
    in the coordinates of `distance`) with unit 2D normals (N, 2), and how many lie inside
    `distance` (only those count)."""
    h, w = distance.shape
    u, v = uv[:, 0].astype(np.intp), uv[:, 1].astype(np.intp)
    inside = (u >= 0) & (v >= 0) & (u < w) & (v < h)
    if not inside.any():
        return 0.0, 0
    u, v, n = u[inside], v[inside], normals[inside]
    d = np.minimum(distance[v, u], tau)
    along = np.mod(np.arctan2(n[:, 1], n[:, 0]) + np.pi / 2, np.pi)  # outline direction
    diff = np.abs(edge_angle[v, u] - along)
    diff = np.minimum(diff, np.pi - diff)
    d = np.where(diff <= max_angle, d, tau)
    return float(1.0 - d.mean() / tau), int(len(u))


def disc_shifts(radius: int) -> np.ndarray:
    """(S, 2) integer image shifts (dx, dy) with |shift| <= radius, (0, 0) first."""
    r = int(radius)
    a = np.arange(-r, r + 1)
    dx, dy = (g.ravel() for g in np.meshgrid(a, a))
    keep = dx * dx + dy * dy <= r * r
    order = np.argsort(dx[keep] ** 2 + dy[keep] ** 2, kind="stable")
    return np.stack([dx[keep], dy[keep]], axis=1)[order]


def shifted_region(posterior: np.ndarray, inner: np.ndarray, outer: np.ndarray, radius: int) -> np.ndarray:
    """(2r+1, 2r+1) region term (mean foreground posterior over the inner band minus over the
    outer band) with both bands shifted by every (dx, dy) in [-r, r]^2 (entry [dy + r, dx + r]),
    the posterior map kept fixed. `posterior` (float32) covers the bands' array grown by
    `radius` on every side; one correlation (cv2.matchTemplate) gives all shifts."""
    ni, no = max(int(inner.sum()), 1), max(int(outer.sum()), 1)
    template = inner.astype(np.float32) / ni - outer.astype(np.float32) / no
    return cv2.matchTemplate(posterior, template, cv2.TM_CCORR)


def shifted_separation(codes: np.ndarray, inner: np.ndarray, outer: np.ndarray, shifts: np.ndarray, radius: int,
                       bits: int) -> np.ndarray:
    """(S,) region term (as `shifted_region`) with both bands moved by each of `shifts` and the
    histograms re-estimated there: 2 x region_separation - 1 of every shifted outline. `codes`
    covers the bands' array grown by `radius` on every side, -1 where there is no image (not
    counted); one bincount over all shifts."""
    n_bins = 1 << (3 * bits)
    w, n = codes.shape[1], len(shifts)
    off = (shifts[:, 1] * w + shifts[:, 0]).astype(np.intp)[:, None]
    rows = np.arange(n, dtype=np.intp)[:, None] * (n_bins + 1)
    flat = codes.ravel()

    def histograms(band: np.ndarray) -> np.ndarray:
        ys, xs = np.nonzero(band)
        q = flat[((ys + radius) * w + xs + radius)[None, :] + off]
        h = np.bincount((rows + np.where(q < 0, n_bins, q)).ravel(), minlength=n * (n_bins + 1))
        h = h.reshape(n, n_bins + 1)[:, :n_bins].astype(np.float64)
        return h / np.maximum(h.sum(axis=1, keepdims=True), 1.0)

    hf, hb = histograms(inner), histograms(outer)
    pf = (hf + 1e-4) / (hf + hb + 2e-4)
    return (hf * pf).sum(axis=1) - (hb * pf).sum(axis=1)


def shifted_edges(distance: np.ndarray, edge_angle: np.ndarray, uv: np.ndarray, normals: np.ndarray,
                  shifts: np.ndarray, tau: float, max_angle: float) -> np.ndarray:
    """edge_agreement of the outline (uv, normals; uv in the maps' coordinates) moved by each of
    `shifts` (S, 2); the maps must cover every shifted pixel (grow them by the largest shift,
    distance `tau` where there is no image)."""
    w = distance.shape[1]
    at = uv[:, 1].astype(np.intp) * w + uv[:, 0].astype(np.intp)
    flat = at[None, :] + (shifts[:, 1] * w + shifts[:, 0]).astype(np.intp)[:, None]
    along = np.mod(np.arctan2(normals[:, 1], normals[:, 0]) + np.pi / 2, np.pi)
    diff = np.abs(edge_angle.ravel()[flat] - along[None, :])
    diff = np.minimum(diff, np.pi - diff)
    d = np.where(diff <= max_angle, np.minimum(distance.ravel()[flat], tau), tau)
    return 1.0 - d.mean(axis=1) / tau


__all__ = ["colour_codes", "padded_mask", "outline_bands", "region_separation", "outline_separation", "nearest_edges",
           "edge_agreement", "band_posterior", "disc_shifts", "shifted_region", "shifted_separation", "shifted_edges"]
