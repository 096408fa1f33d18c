"""Region-based 6-DoF pose refinement on a colour image (RBOT / SRT3D style), without depth.

Region-based tracking (Prisacariu & Reid 2012, PWP3D; Tjaden et al. 2017/2018, RBOT; Stoiber et
al. 2020/2022, SRT3D) fits the object's silhouette to the image's foreground/background colour
statistics instead of to edges:

- `ColourModel`: foreground/background colour histograms of the start hypothesis's inner and
  outer outline bands (vision.appearance's bands and histograms) turned into a per-pixel
  foreground posterior map P_f = h_f / (h_f + h_b) over a crop around the hypothesis (0.5,
  "no information", beyond the image). With `sectors` the histograms are local (Tjaden et al.
  2017's local colour histograms, here per angular sector about the silhouette's centre): a
  cluttered background or an occluder on one side no longer sets the posterior on the others.
- `outline_samples`: points of the rendered silhouette (vision.edges.silhouette_points), spread
  evenly along it, back-projected onto the model with the rendered depth, with the inward 2D
  normal; the silhouette is re-rendered at every iteration (its contour generator moves over
  the surface as the object rotates).
- `line_displacements`: SRT3D's 1D correspondence lines: along each normal, samples of P_f at
  -L..L px; the likelihood of the foreground/background transition lying between samples j and
  j+1 is prod(1 - P_f) outside it times prod(P_f) inside it (tempered: neighbouring pixels are
  not independent); its mean is the displacement the outline point should make, its standard
  deviation the uncertainty (a flat, uninformative line gets a large one).
- The pose step: robust Gauss-Newton / Levenberg-Marquardt (vision.pose_solver) on the
  normal-projected residuals n . (pi(R P + t) - uv) - d, divided by their uncertainty, with the
  analytic projection Jacobian and weak priors (depth along the viewing ray, rotation) anchored
  at the call's start; line half-lengths shrink coarse-to-fine.
- `region_cost`: 1 - colour separation of the pose's own bands: the mean posterior inside minus
  outside, averaged over the start's posterior map (kept) and histograms re-estimated at the
  pose (as psi_rgb's region term does); the block returns its start unless this drops.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..core.geometry import Pose
from ..core.render import Rendering
from ..core.scene import Frame
from .appearance import band_posterior, colour_codes, outline_bands, padded_mask, region_separation
from .edges import bilinear, silhouette_points


@dataclass
class ColourModel:
    """The start hypothesis's colour statistics: the foreground posterior per colour bin (always
    the whole bands': `region_cost` judges by it), the posterior map over a crop that the lines
    sample (float32, origin `origin` in the image; per sector when the histograms are local),
    the band width (px) and the histogram bits."""

    posterior: np.ndarray
    pmap: np.ndarray
    origin: tuple[int, int]
    band: int
    bits: int
    codes: np.ndarray  # colour bins of the map's crop

    @property
    def box(self) -> tuple[int, int, int, int]:
        """The posterior map's crop (x0, y0, x1, y1) in the image."""
        return self.origin[0], self.origin[1], self.origin[0] + self.pmap.shape[1], self.origin[1] + self.pmap.shape[0]

    def blended(self, other: "ColourModel", weight: float) -> "ColourModel":
        """This model with its posterior (and map) moved towards `other`'s by `weight` (`other`
        built on the same map crop): the histograms re-estimated at a later pose, as RBOT updates
        them from frame to frame."""
        posterior = ((1.0 - weight) * self.posterior + weight * other.posterior).astype(np.float32)
        pmap = ((1.0 - weight) * self.pmap + weight * other.pmap).astype(np.float32)
        return ColourModel(posterior, pmap, self.origin, self.band, self.bits, self.codes)


def band_width(rendering: Rendering, fraction: float, largest: int) -> int:
    """Band width (px) as psi_rgb's: `fraction` x sqrt(object pixels), 2 to `largest` px."""
    n_obj = 0 if rendering.empty else int(np.count_nonzero(rendering.mask >= 0))
    return int(np.clip(round(fraction * math.sqrt(n_obj)), 2, largest)) if fraction > 0 else int(largest)


def sector_posterior_map(codes: np.ndarray, inner: np.ndarray, outer: np.ndarray, origin: tuple[int, int],
                         crop: np.ndarray, crop_origin: tuple[int, int], centre: np.ndarray, bits: int,
                         sectors: int, prior_px: float) -> np.ndarray:
    """Foreground posterior map (float32) of `crop` (colour codes, origin `crop_origin`) from
    local histograms: the bands (of `codes`, origin `origin`) split into `sectors` angular
    sectors about `centre` (image px), each sector's inner and outer histograms pulled towards
    the whole bands' by `prior_px` pixels; a pixel's posterior interpolates between its two
    nearest sectors' (no seam)."""
    n_bins = 1 << (3 * bits)

    def sector_coordinate(shape: tuple[int, ...], at: tuple[int, int]) -> np.ndarray:
        yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
        angle = np.arctan2(yy + at[1] - centre[1], xx + at[0] - centre[0])
        return (angle + np.pi) / (2.0 * np.pi) * sectors - 0.5  # sector k's centre at k

    sector = np.floor(sector_coordinate(codes.shape, origin) + 0.5).astype(np.intp) % sectors

    def histograms(band: np.ndarray) -> np.ndarray:
        h = np.bincount(sector[band] * n_bins + codes[band], minlength=sectors * n_bins)
        h = h.reshape(sectors, n_bins).astype(np.float64)
        whole = h.sum(axis=0) / max(float(h.sum()), 1.0)
        return (h + prior_px * whole) / (h.sum(axis=1, keepdims=True) + prior_px) + 1e-4

    hf, hb = histograms(inner), histograms(outer)
    posterior = (hf / (hf + hb)).astype(np.float32)
    f = sector_coordinate(crop.shape, crop_origin)
    k0 = np.floor(f).astype(np.intp)
    w = (f - k0).astype(np.float32)
    k0 %= sectors
    return (1.0 - w) * posterior[k0, crop] + w * posterior[(k0 + 1) % sectors, crop]


def colour_model(frame: Frame, rendering: Rendering, band: int, bits: int, margin: int,
                 gap: float = 0.0, sectors: int = 0, sector_prior_px: float = 50.0,
                 box: tuple[int, int, int, int] | None = None) -> ColourModel | None:
    """The colour model of the hypothesis rendered as `rendering`; the histograms come from the
    bands `gap` to `gap` + `band` px inside and outside the outline (a gap leaves out the pixels
    that a few px of misalignment puts on the wrong side), per angular sector when `sectors` > 1
    (`sector_posterior_map`); the posterior map covers `box` (x0, y0, x1, y1), by default the
    rendering's box grown by `margin` px (clipped to the image). None when a band is empty."""
    mask, (x0, y0, x1, y1) = padded_mask(frame, rendering, int(math.ceil(gap)) + band + 1)
    inner, outer = outline_bands(mask, gap + band)
    if gap > 0:
        near_in, near_out = outline_bands(mask, gap)
        inner, outer = inner & ~near_in, outer & ~near_out
    if not inner.any() or not outer.any():
        return None
    codes = colour_codes(frame.rgb[y0:y1, x0:x1], bits)
    posterior = band_posterior(codes, inner, outer, bits).astype(np.float32)
    if box is None:
        x, y, w, h = rendering.box
        box = (max(0, x - margin), max(0, y - margin),
               min(frame.width, x + w + margin), min(frame.height, y + h + margin))
    X0, Y0, X1, Y1 = box
    crop = colour_codes(frame.rgb[Y0:Y1, X0:X1], bits)
    if sectors > 1:
        ys, xs = np.nonzero(mask)
        centre = np.array([xs.mean() + x0, ys.mean() + y0])
        pmap = sector_posterior_map(codes, inner, outer, (x0, y0), crop, (X0, Y0), centre, bits, sectors,
                                    sector_prior_px)
    else:
        pmap = posterior[crop]
    return ColourModel(posterior, pmap, (X0, Y0), band, bits, crop)


def region_cost(frame: Frame, rendering: Rendering, cm: ColourModel) -> float:
    """1 - colour separation of the outline at `rendering` (see the module docstring): the mean
    foreground posterior over the inner band minus over the outer band, with the start's
    posterior map and with histograms re-estimated at this outline, averaged; in [0, 1] up to
    the histograms' smoothing, lower is better. 1 when the rendering is empty."""
    if rendering.empty:
        return 1.0
    mask, (x0, y0, x1, y1) = padded_mask(frame, rendering, cm.band + 1)
    inner, outer = outline_bands(mask, cm.band)
    if not inner.any() or not outer.any():
        return 1.0
    codes = colour_codes(frame.rgb[y0:y1, x0:x1], cm.bits)
    kept = float(cm.posterior[codes[inner]].mean() - cm.posterior[codes[outer]].mean())
    moved = 2.0 * region_separation(codes, inner, outer, cm.bits) - 1.0
    return 1.0 - 0.5 * (kept + moved)


def outline_samples(frame: Frame, rendering: Rendering, pose: Pose,
                    n_points: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Up to `n_points` silhouette pixels spread evenly along the rendered outline (those inside
    the image): model-frame points (N, 3), pixels (N, 2) and unit inward normals (N, 2)."""
    uv, n2d = silhouette_points(rendering)
    norm = np.linalg.norm(n2d, axis=1)
    ok = (norm > 1e-6) & np.all((uv >= 0) & (uv < (frame.width, frame.height)), axis=1)
    uv, n2d = uv[ok], n2d[ok] / norm[ok, None]
    if len(uv) > n_points:
        idx = np.linspace(0, len(uv) - 1, n_points).round().astype(np.intp)
        uv, n2d = uv[idx], n2d[idx]
    x0, y0 = rendering.offset
    iu = np.clip(uv[:, 0].astype(np.intp) - x0, 0, rendering.depth.shape[1] - 1)
    iv = np.clip(uv[:, 1].astype(np.intp) - y0, 0, rendering.depth.shape[0] - 1)
    z = rendering.depth[iv, iu].astype(np.float64)
    ok = np.isfinite(z)
    uv, n2d, z = uv[ok], n2d[ok], z[ok]
    K = frame.K
    p_cam = np.stack([(uv[:, 0] - K[0, 2] - K[0, 1] * (uv[:, 1] - K[1, 2]) / K[1, 1]) * z / K[0, 0],
                      (uv[:, 1] - K[1, 2]) * z / K[1, 1], z], axis=1)
    return (p_cam - pose.t) @ pose.R, uv, n2d


def line_displacements(cm: ColourModel, uv: np.ndarray, normals: np.ndarray, half_length: int,
                       temperature: float = 0.5, clip: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """(mean, standard deviation) px of the foreground/background transition along each 1D
    correspondence line (pixel `uv`, unit inward normal; samples at -L..L px; positive = inward):
    the transition between samples j and j+1 has log-likelihood temperature x (sum of
    log(1 - P_f) outside it + sum of log P_f inside it), P_f clipped to [clip, 1 - clip]."""
    s = np.arange(-half_length, half_length + 1, dtype=np.float64)
    x = uv[:, 0:1] + s[None, :] * normals[:, 0:1] - cm.origin[0]
    y = uv[:, 1:2] + s[None, :] * normals[:, 1:2] - cm.origin[1]
    p = bilinear(cm.pmap, x.ravel(), y.ravel(), 0.5).reshape(x.shape)
    p = np.clip(p, clip, 1.0 - clip)
    out = np.cumsum(np.log1p(-p), axis=1)[:, :-1]  # samples 0..j outside
    inside = np.cumsum(np.log(p)[:, ::-1], axis=1)[:, ::-1][:, 1:]  # samples j+1.. inside
    ll = temperature * (out + inside)
    ll -= ll.max(axis=1, keepdims=True)
    w = np.exp(ll)
    w /= w.sum(axis=1, keepdims=True)
    d = s[:-1] + 0.5
    mean = w @ d
    var = w @ (d * d) - mean * mean
    return mean, np.sqrt(np.maximum(var, 0.0))


__all__ = ["ColourModel", "band_width", "sector_posterior_map", "colour_model", "region_cost", "outline_samples",
           "line_displacements"]
