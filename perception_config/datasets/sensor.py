"""Sensor models for the synthetic dataset: an RGB-D depth-noise model and RGB shading.

Depth (`simulate_depth`), applied to a clean z-depth image in metres, in this order:

1. Projector shadow. An active stereo / structured-light sensor has its projector a baseline
   `b` beside the camera; surface points the projector cannot see get no depth. For a
   horizontal baseline this is exact per image row: a pixel at column u and depth z lands at
   projector column u' = u - fx b / z, and it is shadowed when some pixel on its projector side
   lands at a smaller u' (the ordering constraint is violated, the nearer point wins). The
   shadow is a band of about fx b (1/z_near - 1/z_far) pixels beside each depth step.
2. Edge effects. At depth discontinuities (a 4-neighbour step above `edge_step` m) a pixel is
   missing with probability `edge_missing`, otherwise with probability `edge_flying` it is a
   flying pixel: a random mixture of the near and the far depth.
3. Dropout at grazing angles: with theta the angle between the surface normal and the
   direction to the camera, a pixel is missing with probability
   sigmoid((theta - grazing_deg) / grazing_width_deg) (about 50 % at 78 deg, ~100 % at 85).
4. Dropout on shiny surfaces (per-pixel weight `shiny` in [0, 1], 1 = polished metal):
   (a) near the mirror direction of the projector the return saturates: missing with
   probability specular_missing * exp(-alpha^2 / (2 specular_deg^2)), alpha the angle between
   the normal and the half vector of projector and camera directions; (b) away from it the
   diffuse return of a shiny surface is weak, so the grazing threshold is lowered to
   `shiny_grazing_deg`; (c) anywhere, `shiny_missing` (weak diffuse return). All scaled by
   the weight. The dropout decisions of 3 and 4 use a spatially correlated random field
   (Gaussian, `blob_sigma_px`), so holes come in blobs as on real sensors; the share of
   missing pixels is still the probability.
5. Axial Gaussian noise, z-dependent (Nguyen, Izadi, Lovell 2012, Kinect v1):
   sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 m  (1.2 mm at 0.4 m, 1.7 mm at 0.9 m).
6. Quantisation to `quantum` metres (1 mm) and the working range [z_min, z_max].

Missing depth is NaN. Every random draw comes from the caller's np.random.Generator, so a
seeded generator reproduces the image exactly.

RGB (`shade`, `finish_rgb`): Lambert diffuse plus Blinn-Phong specular from one point light
(with cast shadows computed by the caller), an ambient term, then a slight optical blur,
Gaussian sensor noise, gamma encoding and rounding to uint8. `make_texture` makes seeded
procedural textures (concrete, wood, plastic) for the bin and table.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "DepthNoise", "sigma_z", "simulate_depth", "shade", "finish_rgb", "make_texture", "pixel_rays",
]


@dataclass(frozen=True)
class DepthNoise:
    """Parameters of the depth-sensor model (metres, degrees, probabilities)."""

    sigma_a: float = 0.0012  # m, noise floor (Nguyen et al. 2012)
    sigma_b: float = 0.0019  # 1/m, quadratic growth
    z_ref: float = 0.4  # m
    baseline: float = 0.05  # m, projector to the right of the camera (+x); 0 = no shadows
    edge_step: float = 0.01  # m, depth step that counts as a discontinuity
    edge_missing: float = 0.5
    edge_flying: float = 0.3
    grazing_deg: float = 78.0
    grazing_width_deg: float = 2.5
    specular_deg: float = 6.0
    specular_missing: float = 0.6
    shiny_missing: float = 0.1  # weak diffuse return of polished metal: missing anywhere
    shiny_grazing_deg: float = 62.0
    blob_sigma_px: float = 1.5  # spatial correlation of the dropout (holes come in blobs)
    quantum: float = 0.001  # m
    z_min: float = 0.15  # m
    z_max: float = 4.0  # m


def sigma_z(z: np.ndarray | float, p: DepthNoise = DepthNoise()) -> np.ndarray:
    """Standard deviation (m) of the axial depth noise at depth z (m)."""
    z = np.asarray(z, dtype=np.float64)
    return p.sigma_a + p.sigma_b * (z - p.z_ref) ** 2


_RAY_CACHE: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}


def pixel_rays(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W, 3) camera-frame ray directions K^-1 [u, v, 1] (z = 1), pixel centres at integers."""
    Kinv = np.linalg.inv(np.asarray(K, dtype=np.float64))
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    return np.stack([u, v, np.ones_like(u)], axis=-1) @ Kinv.T


def _rays_and_view(K: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Cached float32 rays (z = 1) and unit directions towards the camera, per camera."""
    key = (np.asarray(K, dtype=np.float64).tobytes(), int(width), int(height))
    hit = _RAY_CACHE.get(key)
    if hit is None:
        rays = pixel_rays(K, width, height).astype(np.float32)
        view = -rays / np.linalg.norm(rays, axis=-1, keepdims=True)
        if len(_RAY_CACHE) > 8:
            _RAY_CACHE.clear()
        hit = _RAY_CACHE[key] = (rays, view.astype(np.float32))
    return hit


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _correlated_uniform(rng: np.random.Generator, shape: tuple[int, int], sigma: float) -> np.ndarray:
    """Uniform(0, 1) values with Gaussian spatial correlation (sigma px): thresholding them
    at p gives missing-pixel blobs covering a share p, instead of salt-and-pepper."""
    import cv2
    from scipy.special import ndtr

    g = rng.standard_normal(shape, dtype=np.float32)
    if sigma <= 0:
        return ndtr(g).astype(np.float32)
    g = cv2.GaussianBlur(g, (0, 0), sigma)
    g /= np.float32(np.sqrt(1.0 / (4.0 * np.pi * sigma * sigma)))  # unit variance again
    return ndtr(g).astype(np.float32)


def _projector_shadow(depth: np.ndarray, fx: float, baseline: float) -> np.ndarray:
    """Pixels the projector (at +baseline along x) cannot see, from the ordering constraint."""
    H, W = depth.shape
    valid = np.isfinite(depth) & (depth > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        up = np.arange(W, dtype=np.float32)[None, :] - np.float32(fx * baseline) / depth  # projector column
    up = np.where(valid, up, np.float32(np.inf))
    # Projector to the right: a pixel is hidden by any pixel to its right with a smaller u'.
    suffix_min = np.minimum.accumulate(up[:, ::-1], axis=1)[:, ::-1]
    right_min = np.empty_like(up)
    right_min[:, :-1] = suffix_min[:, 1:]
    right_min[:, -1] = np.inf
    return valid & (right_min < up - 0.5)


def simulate_depth(
    depth: np.ndarray,
    normals: np.ndarray,
    K: np.ndarray,
    rng: np.random.Generator,
    shiny: np.ndarray | None = None,
    params: DepthNoise = DepthNoise(),
) -> np.ndarray:
    """Noisy float32 depth (m, NaN = missing) from a clean z-depth (m, NaN/0 = nothing), the
    camera-frame normals (H, W, 3) facing the camera, the intrinsics and a shiny weight map."""
    import cv2

    p = params
    d = np.asarray(depth, dtype=np.float32)
    H, W = d.shape
    valid = np.isfinite(d) & (d > 0)
    d = np.where(valid, d, np.float32(0.0))
    rays, view = _rays_and_view(K, W, H)
    n = np.asarray(normals, dtype=np.float32)
    cos_t = np.minimum(np.abs(_dot(n, view)), 1.0)
    theta = np.degrees(np.arccos(cos_t))

    # 1. projector shadow
    missing = ~valid
    if p.baseline > 0:
        missing |= _projector_shadow(np.where(valid, d, np.nan), float(K[0, 0]), p.baseline)

    # 2. discontinuities: largest step to a 4-neighbour (min/max filters ignore missing pixels)
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    dmax = cv2.dilate(d, cross, borderType=cv2.BORDER_REPLICATE)
    dmin = cv2.erode(np.where(valid, d, np.float32(1e4)), cross, borderType=cv2.BORDER_REPLICATE)
    up_step = np.where(valid, dmax - d, 0.0)
    down_step = np.where(valid & (dmin < 1e4), d - dmin, 0.0)
    use_far = up_step >= down_step
    near = np.where(use_far, d, dmin)
    far = np.where(use_far, dmax, d)
    edge = valid & (np.maximum(up_step, down_step) > p.edge_step)
    u_edge = rng.random((H, W), dtype=np.float32)
    mix = rng.random((H, W), dtype=np.float32)
    missing |= edge & (u_edge < p.edge_missing)
    flying = edge & (u_edge >= p.edge_missing) & (u_edge < p.edge_missing + p.edge_flying)
    d = np.where(flying, near + mix * (far - near), d)

    # 3. grazing angles and 4. shiny surfaces
    p_drop = _sigmoid((theta - p.grazing_deg) / p.grazing_width_deg)
    if shiny is not None:
        s = np.clip(np.asarray(shiny, dtype=np.float32), 0.0, 1.0)
        sel = valid & (s > 0)
        if sel.any():
            ns, vs = n[sel], view[sel]
            pts = rays[sel] * d[sel][:, None]
            proj_dir = np.array([p.baseline, 0.0, 0.0], np.float32) - pts
            proj_dir /= np.maximum(np.linalg.norm(proj_dir, axis=-1, keepdims=True), 1e-12)
            half = proj_dir + vs
            half /= np.maximum(np.linalg.norm(half, axis=-1, keepdims=True), 1e-12)
            alpha = np.degrees(np.arccos(np.clip(np.abs(_dot(ns, half)), 0.0, 1.0)))
            p_spec = p.specular_missing * np.exp(-0.5 * (alpha / p.specular_deg) ** 2)
            p_graze_shiny = _sigmoid((theta[sel] - p.shiny_grazing_deg) / (2.0 * p.grazing_width_deg))
            p_shiny = 1.0 - (1.0 - p.shiny_missing) * (1.0 - p_spec) * (1.0 - p_graze_shiny)
            p_drop[sel] = 1.0 - (1.0 - p_drop[sel]) * (1.0 - s[sel] * p_shiny)
    missing |= _correlated_uniform(rng, (H, W), p.blob_sigma_px) < p_drop

    # 5. axial noise, 6. quantisation and range
    sig = sigma_z(np.where(valid, d, np.float32(p.z_ref)), p).astype(np.float32)
    d = d + rng.standard_normal((H, W), dtype=np.float32) * sig
    if p.quantum > 0:
        d = np.round(d / np.float32(p.quantum)) * np.float32(p.quantum)
    missing |= (d < p.z_min) | (d > p.z_max)
    return np.where(missing, np.float32(np.nan), d).astype(np.float32)


def shade(
    albedo: np.ndarray,
    normals: np.ndarray,
    points: np.ndarray,
    light_pos: np.ndarray,
    ks: np.ndarray,
    shininess: np.ndarray,
    lit: np.ndarray | None = None,
    light_power: float = 1.0,
    ambient: float = 0.25,
    ref_dist: float | None = None,
    eye: np.ndarray | None = None,
) -> np.ndarray:
    """Linear RGB (H, W, 3) of surfaces: ambient + Lambert + Blinn-Phong from a point light.

    All vectors in one frame: the camera frame by default, or any frame (e.g. the world) with
    `eye` the camera position in it. albedo (H, W, 3) in [0, 1]; normals (H, W, 3) facing
    the camera; points (H, W, 3) (m); light_pos (3,); ks, shininess (H, W) specular
    weight and exponent; lit (H, W) bool, False where the light is blocked (cast shadow).
    Light intensity falls off with the squared distance, normalised to `light_power` at
    `ref_dist` metres from the light (default: the light's distance from the camera).
    """
    points = np.asarray(points, dtype=np.float32)
    normals = np.asarray(normals, dtype=np.float32)
    L = np.asarray(light_pos, dtype=np.float32) - points
    dist2 = np.maximum(_dot(L, L), 1e-6)
    L /= np.sqrt(dist2)[..., None]
    V = (np.zeros(3, np.float32) if eye is None else np.asarray(eye, np.float32)) - points
    V /= np.maximum(np.sqrt(_dot(V, V)), 1e-9)[..., None]
    Hh = L + V
    Hh /= np.maximum(np.sqrt(_dot(Hh, Hh)), 1e-9)[..., None]
    ndl = np.clip(_dot(normals, L), 0.0, None)
    ndh = np.clip(_dot(normals, Hh), 0.0, None)
    if ref_dist is None:
        rel = np.asarray(light_pos, np.float64) - (0.0 if eye is None else np.asarray(eye, np.float64))
        ref2 = float(np.dot(rel, rel))
    else:
        ref2 = float(ref_dist) ** 2
    falloff = ref2 / dist2 * light_power
    direct = falloff * ndl
    spec = (falloff * ks * np.where(ndl > 0, np.exp(shininess * np.log(np.maximum(ndh, 1e-12))), 0.0)
            * (shininess + 8.0) / 32.0)
    if lit is not None:
        direct = direct * lit
        spec = spec * lit
    return (albedo * (ambient + direct)[..., None] + spec[..., None]).astype(np.float32)


def finish_rgb(linear: np.ndarray, rng: np.random.Generator, noise: float = 0.012, blur_sigma: float = 0.6,
               exposure: float = 1.0) -> np.ndarray:
    """Camera pipeline: optical blur, sensor noise (on linear values), gamma 2.2, uint8."""
    import cv2

    img = np.asarray(linear, dtype=np.float32) * exposure
    if blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
    img = img + rng.standard_normal(img.shape).astype(np.float32) * noise
    img = np.clip(img, 0.0, 1.0) ** (1.0 / 2.2)
    return np.round(img * 255.0).astype(np.uint8)


def _octave_noise(rng: np.random.Generator, size: int, octaves: int = 5, persistence: float = 0.55) -> np.ndarray:
    """Tileable-enough fractal noise in [0, 1] (sum of upsampled random grids)."""
    import cv2

    out = np.zeros((size, size), np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        cells = 4 * 2 ** o
        grid = rng.random((cells, cells)).astype(np.float32)
        grid = np.pad(grid, 1, mode="wrap")
        up = cv2.resize(grid, (size + 2 * size // cells, size + 2 * size // cells), interpolation=cv2.INTER_CUBIC)
        off = size // cells
        out += amp * up[off:off + size, off:off + size]
        total += amp
        amp *= persistence
    out /= total
    lo, hi = out.min(), out.max()
    return (out - lo) / max(hi - lo, 1e-6)


def make_texture(rng: np.random.Generator, kind: str, base: tuple[float, float, float], size: int = 512) -> np.ndarray:
    """A procedural albedo texture (size, size, 3) float32 in [0, 1] around a base colour.

    kind: "concrete" (mottled with speckles), "wood" (grain along x), "plastic" (faint mottling).
    """
    base_c = np.asarray(base, dtype=np.float32)[None, None, :]
    n = _octave_noise(rng, size)
    if kind == "wood":  # boards along x: fine grain rings, slowly wandering, stretched along x
        import cv2

        stretched = cv2.resize(_octave_noise(rng, size // 8)[:, :], (size, size), interpolation=cv2.INTER_CUBIC)
        stretched = cv2.resize(stretched[:, : size // 8], (size, size), interpolation=cv2.INTER_CUBIC)
        y = np.linspace(0, 1, size, dtype=np.float32)[:, None]
        grain = 0.5 + 0.5 * np.sin(2 * np.pi * (y * 60.0 + 3.0 * stretched))
        v = 0.82 + 0.18 * grain[..., None] + 0.12 * (n[..., None] - 0.5)
    elif kind == "concrete":
        speck = ((rng.random((size, size)) < 0.02).astype(np.float32)
                 * rng.uniform(-0.25, 0.25, (size, size)).astype(np.float32))
        v = 0.75 + 0.45 * n[..., None] + speck[..., None]
    else:  # plastic
        v = 0.9 + 0.15 * n[..., None]
    return np.clip(base_c * v, 0.0, 1.0).astype(np.float32)
