"""Image edges and the model contour, for the edge-based refiners (D2CO, chamfer, chamfer-ICP).

- `image_derivatives`: the grey image's Sobel derivatives, once per frame (psi_c uses them too);
  `projected_directions`: image-plane directions of 3D directions at camera-frame points;
  `silhouette_points`: the rendered object's outline with its 2D normals.
- `canny_edges`: the Canny edge map and each edge pixel's direction in [0, pi), once per frame;
  `image_gradients`: gradient magnitude and angle (Sobel), once per frame.
- `directional_chamfer_tensor`: D2CO's directional chamfer distance tensor on a crop
  (Liu et al., CVPR 2010; Imperoli & Pretto, ICVS 2015): edge pixels split into `n_bins`
  orientation bins over [0, pi), a distance transform per bin, then a forward/backward pass
  across bins (cyclic) adding `penalty` px per bin of orientation difference, so a model edge
  point pays for distance and for orientation mismatch. Truncated at `max_distance`.
  `sample_tensor` interpolates it at (x, y, theta) with its spatial gradient; `TensorCache`
  keeps tensors per frame and crop so repeated calls on a frame do not rebuild them.
- `model_contour`: 3D model-frame points with 3D tangent directions on the contour visible from
  a hypothesis: visible sharp mesh edges plus the rendered silhouette back-projected; with
  `min_coherence`, only sharp-edge samples on straight edges (`edge_coherence`: a scanned
  mesh's "sharp" edges, such as LM-O's, are mostly zig-zag noise; the outline carries the signal).
- `crop_problem` / `share_in_image` / `edge_refinement_problem`: the edge refiners' input checks
  (a tiny, blank or over-exposed crop; an object mostly beyond the image border).
- `project_with_directions`: pixel positions and image-plane directions (angle in [0, pi)).
"""
from __future__ import annotations

import math
import weakref

import cv2
import numpy as np

from ..core.geometry import Pose
from ..core.models import ObjectModel
from ..core.render import Box, Rendering
from ..core.scene import Frame
from .visibility import hypothesis_rendering, visible_edges

_GRAD_KEY = "scoring:gradients:gauss1:sobel3"


def image_derivatives(frame: Frame, cache: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Image derivatives (gx, gy) float32 HxW of the grey image in grey levels per pixel (Sobel
    3x3 / 8 after a sigma-1 Gaussian); computed once per frame and cached."""
    if cache is not None and _GRAD_KEY in cache and cache[_GRAD_KEY][0] is frame.rgb:
        return cache[_GRAD_KEY][1]
    gray = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    gray = cv2.GaussianBlur(gray, (5, 5), 1.0)
    gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    if cache is not None:
        cache[_GRAD_KEY] = (frame.rgb, (gx, gy))
    return gx, gy


def projected_directions(points_cam: np.ndarray, dirs_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Image-plane directions (N, 2), not normalised, of 3D directions `dirs_cam` attached to
    camera-frame points: the projection Jacobian at each point applied to its direction."""
    x, y, z = points_cam[:, 0], points_cam[:, 1], points_cam[:, 2]
    dx, dy, dz = dirs_cam[:, 0], dirs_cam[:, 1], dirs_cam[:, 2]
    du = K[0, 0] * (dx * z - x * dz) / z**2 + K[0, 1] * (dy * z - y * dz) / z**2
    dv = K[1, 1] * (dy * z - y * dz) / z**2
    return np.stack([du, dv], axis=1)


def silhouette_points(rendering: Rendering) -> tuple[np.ndarray, np.ndarray]:
    """Pixel positions (N, 2) and 2D normals (N, 2, not normalised) of the rendered object's
    outline: object pixels with a background 4-neighbour, normal = gradient of the slightly
    blurred mask (finer angles than the raw binary mask gives)."""
    if rendering.empty:
        return np.zeros((0, 2)), np.zeros((0, 2))
    obj = (rendering.mask >= 0).astype(np.uint8)
    # The crop has a 1 px background margin except where the image border cuts the object:
    # replicate there, so the image border is not taken for an outline.
    obj = np.pad(obj, 2, mode="edge")
    inner = cv2.erode(obj, np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], np.uint8))
    ys, xs = np.nonzero(obj & (1 - inner))
    soft = cv2.GaussianBlur(obj.astype(np.float32), (5, 5), 1.0)
    gx = cv2.Sobel(soft, cv2.CV_32F, 1, 0, ksize=3)[ys, xs]
    gy = cv2.Sobel(soft, cv2.CV_32F, 0, 1, ksize=3)[ys, xs]
    x0, y0 = rendering.offset
    uv = np.stack([xs - 2 + x0, ys - 2 + y0], axis=1).astype(np.float64)
    return uv, np.stack([gx, gy], axis=1).astype(np.float64)


def canny_edges(frame: Frame, cache: dict | None, low: float = 40.0,
                high: float = 100.0, blur: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(edges uint8 HxW, direction float32 HxW in [0, pi) along the edge), cached per frame;
    Canny runs on the grey image after a Gaussian of sigma `blur` px (a wider one keeps the
    outlines of a blurred photograph and drops fine texture)."""
    key = f"edges:canny:{low}:{high}" + (f":{float(blur)}" if blur != 1.0 else "")
    if cache is not None and key in cache and cache[key][0] is frame.rgb:
        return cache[key][1]
    gray = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY)
    ksize = 5 if blur == 1.0 else 2 * int(math.ceil(3 * blur)) + 1
    edges = cv2.Canny(cv2.GaussianBlur(gray, (ksize, ksize), float(blur)), low, high)
    gx, gy = image_derivatives(frame, cache)
    # The edge runs perpendicular to the gradient.
    direction = np.mod(np.arctan2(gy, gx) + np.pi / 2, np.pi).astype(np.float32)
    if cache is not None:
        cache[key] = (frame.rgb, (edges, direction))
    return edges, direction


def image_gradients(frame: Frame, cache: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(magnitude, angle) float32 HxW of the grey image's gradient (Sobel after a sigma-1
    Gaussian, grey levels per pixel); angle = atan2(gy, gx) in (-pi, pi], across the edge.
    Shares the per-frame derivatives with the scores, so it costs nothing after the first call."""
    key = "edges:gradients"
    if cache is not None and key in cache and cache[key][0] is frame.rgb:
        return cache[key][1]
    gx, gy = image_derivatives(frame, cache)
    value = (cv2.magnitude(gx, gy), np.arctan2(gy, gx).astype(np.float32))
    if cache is not None:
        cache[key] = (frame.rgb, value)
    return value


def directional_chamfer_tensor(
    edges: np.ndarray, direction: np.ndarray, n_bins: int = 60, penalty: float = 0.5, max_distance: float = 30.0,
) -> np.ndarray:
    """The (n_bins, H, W) float32 directional chamfer tensor of an edge map crop (see above).

    Cost is dominated by the n_bins distance transforms (pixel-bound, ~0.25 ms each for
    224x224): bins without edges skip theirs and are filled by the orientation pass. That pass
    runs 1.5 cycles forward and 1.5 backward: a cheapest path across bins goes at most half
    the circle in one direction, and every such path lies inside 1.5 consecutive cycles."""
    h, w = edges.shape
    ys, xs = np.nonzero(edges)
    bins = np.minimum((direction[ys, xs] * (n_bins / np.pi)).astype(np.intp), n_bins - 1)
    dct = np.full((n_bins, h, w), max_distance, np.float32)
    img = np.full((h, w), 255, np.uint8)
    order = np.argsort(bins, kind="stable")
    bounds = np.searchsorted(bins[order], np.arange(n_bins + 1))
    for b in range(n_bins):
        sel = order[bounds[b]:bounds[b + 1]]
        if len(sel) == 0:
            continue
        img[ys[sel], xs[sel]] = 0
        cv2.distanceTransform(img, cv2.DIST_L2, cv2.DIST_MASK_5, dst=dct[b])
        img[ys[sel], xs[sel]] = 255
    np.minimum(dct, max_distance, out=dct)
    if penalty > 0:
        steps = n_bins + (n_bins + 1) // 2
        tmp = np.empty((h, w), np.float32)
        for k in range(1, steps + 1):
            b = k % n_bins
            np.add(dct[b - 1], penalty, out=tmp)
            np.minimum(dct[b], tmp, out=dct[b])
        for k in range(steps - 1, -1, -1):
            b = k % n_bins
            np.add(dct[(b + 1) % n_bins], penalty, out=tmp)
            np.minimum(dct[b], tmp, out=dct[b])
    return dct


def sample_tensor(
    dct: np.ndarray, x: np.ndarray, y: np.ndarray, angle: np.ndarray, outside: float, gradient: bool = False,
):
    """Tensor values at float pixels (x, y) of its crop and orientations `angle` in [0, pi):
    bilinear in the pixel, linear between the two nearest orientation bins (cyclic). With
    `gradient`, also the spatial derivatives (d/dx, d/dy) of that interpolant (0 outside the
    crop and where the value is truncated, so such points do not pull the pose)."""
    n, h, w = dct.shape
    out = np.full(x.shape, float(outside), np.float64)
    gx, gy = np.zeros(x.shape), np.zeros(x.shape)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(angle) & (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    if ok.any() and h > 1 and w > 1:
        xs, ys = x[ok], y[ok]
        x0 = np.minimum(xs.astype(np.intp), w - 2)
        y0 = np.minimum(ys.astype(np.intp), h - 2)
        fx, fy = xs - x0, ys - y0
        tb = angle[ok] * (n / np.pi) - 0.5  # bin centres at (b + 0.5) pi / n
        b0f = np.floor(tb)
        ft = tb - b0f
        b0 = b0f.astype(np.intp) % n
        b1 = (b0 + 1) % n
        flat = dct.reshape(-1)
        i00 = y0 * w + x0

        def corners(b: np.ndarray):
            base = b * (h * w) + i00
            return flat[base], flat[base + 1], flat[base + w], flat[base + w + 1]

        a00, a01, a10, a11 = corners(b0)
        c00, c01, c10, c11 = corners(b1)
        wt0, wt1 = 1.0 - ft, ft
        v00, v01 = wt0 * a00 + wt1 * c00, wt0 * a01 + wt1 * c01
        v10, v11 = wt0 * a10 + wt1 * c10, wt0 * a11 + wt1 * c11
        top, bottom = v00 + fx * (v01 - v00), v10 + fx * (v11 - v10)
        out[ok] = top + fy * (bottom - top)
        if gradient:
            live = out[ok] < outside  # truncated (flat) region: no pull
            gx[ok] = np.where(live, (1 - fy) * (v01 - v00) + fy * (v11 - v10), 0.0)
            gy[ok] = np.where(live, bottom - top, 0.0)
    return (out, gx, gy) if gradient else out


class TensorCache:
    """Directional chamfer tensors of one frame, by crop and parameters, in BlockInput.cache.

    The crop is the box plus `margin` px with its corners snapped outwards to a grid of ALIGN px,
    so the repeated calls of a refinement episode (the hypothesis moves a few pixels) mostly get
    the same crop and build its tensor once. A tensor is reused only for exactly its own crop:
    it is a function of (frame, crop, parameters) alone, never of which boxes were asked for
    before. (Serving a request from any larger cached crop made the values near the crop border,
    and so a refinement, depend on the episodes a process had played before: results then
    depended on which worker played which episode.)"""

    KEY = "edges:dct"
    SIZE = 6  # tensors kept per frame (a 224x224x60 tensor is 12 MB)
    ALIGN = 32  # px: the crop grid

    @staticmethod
    def get(frame: Frame, cache: dict | None, box: Box, margin: int, n_bins: int,
            penalty: float, max_distance: float, low: float, high: float,
            blur: float = 1.0) -> tuple[np.ndarray, Box, int]:
        """(tensor, crop box, edge pixels in the crop); `blur` is canny_edges's."""
        params = (n_bins, float(penalty), float(max_distance), float(low), float(high), float(blur))
        entries = cache.setdefault(TensorCache.KEY, []) if cache is not None else []
        if entries and entries[0][0] is not frame.rgb:  # a new frame in an old cache
            entries.clear()
        crop = crop_box(frame, box, margin, align=TensorCache.ALIGN)
        for _rgb, p, c, dct, n_edges in reversed(entries):
            if p == params and c == crop:
                return dct, crop, n_edges
        edges, direction = canny_edges(frame, cache, low, high, blur)
        cx, cy, cw, ch = crop
        e = edges[cy:cy + ch, cx:cx + cw]
        n_edges = int(np.count_nonzero(e))
        dct = (directional_chamfer_tensor(e, direction[cy:cy + ch, cx:cx + cw], n_bins, penalty, max_distance)
               if n_edges else None)
        if n_edges:
            entries.append((frame.rgb, params, crop, dct, n_edges))
            del entries[:-TensorCache.SIZE]
        return dct, crop, n_edges


def crop_problem(frame: Frame, box: Box, min_size: int = 8, min_contrast: float = 1.0,
                 max_saturated: float = 0.9) -> str:
    """Why the image inside `box` cannot guide an edge refiner, or '' when it can: the object
    projects to fewer than `min_size` px across, the grey crop is over-exposed (more than
    `max_saturated` of its pixels at 250 or above) or blank (standard deviation under
    `min_contrast` grey levels)."""
    x, y, w, h = box
    if min(w, h) < min_size:
        return f"the object projects to only {w}x{h} px (needs {min_size} px across)"
    grey = cv2.cvtColor(np.ascontiguousarray(frame.rgb[y:y + h, x:x + w]), cv2.COLOR_RGB2GRAY)
    saturated = float(np.mean(grey >= 250))
    if saturated > max_saturated:
        return f"the image around the hypothesis is over-exposed ({saturated:.0%} of the pixels saturated)"
    if float(grey.std()) < min_contrast:
        return f"the image around the hypothesis is blank (grey-level spread {grey.std():.1f})"
    return ""


def share_in_image(frame: Frame, model: ObjectModel, pose: Pose) -> float:
    """Share of the model's surface samples that project inside the image in front of the
    camera at `pose` (an object mostly beyond the image border shows too little to fit)."""
    pc = pose.transform(model.points)
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = frame.K[0, 0] * pc[:, 0] / z + frame.K[0, 1] * pc[:, 1] / z + frame.K[0, 2]
        v = frame.K[1, 1] * pc[:, 1] / z + frame.K[1, 2]
        inside = (z > 1e-3) & (u >= 0) & (v >= 0) & (u <= frame.width - 1) & (v <= frame.height - 1)
    return float(np.mean(inside)) if len(pc) else 0.0


def edge_refinement_problem(frame: Frame, model: ObjectModel, pose: Pose, box: Box | None,
                            min_share: float = 0.1) -> str:
    """The common input checks of the edge refiners: why the hypothesis cannot be refined on
    this image ('' when it can): outside the image, under `min_share` of it inside, or a crop
    that is tiny, blank or over-exposed (crop_problem)."""
    if box is None:
        return "the object at the hypothesis is outside the image"
    share = share_in_image(frame, model, pose)
    if share < min_share:
        return f"only {share:.0%} of the object at the hypothesis lies inside the image"
    return crop_problem(frame, box)


def crop_box(frame: Frame, box: Box, margin: int, align: int = 1) -> Box:
    """The box grown by `margin` px, its corners snapped outwards to multiples of `align` (so
    nearby hypotheses share a crop and its cached tensor), clipped to the image."""
    x, y, w, h = box
    x0, y0 = (max(0, x - margin) // align) * align, (max(0, y - margin) // align) * align
    x1 = min(frame.width, -(-(x + w + margin) // align) * align)
    y1 = min(frame.height, -(-(y + h + margin) // align) * align)
    return (x0, y0, x1 - x0, y1 - y0)


_COHERENCE: "weakref.WeakKeyDictionary[ObjectModel, np.ndarray]" = weakref.WeakKeyDictionary()


def edge_coherence(model: ObjectModel, neighbours: int = 4) -> np.ndarray:
    """Per sharp-edge sample of the model, the mean |cos| between its direction and those of its
    `neighbours` nearest edge samples: ~1 on the long straight edges of a CAD model, lower on
    the short zig-zag "sharp" edges of a scanned mesh (LM-O's: 0.69-0.91 on average, where
    procedural models give 0.98-1.0). Computed once per model."""
    value = _COHERENCE.get(model)
    if value is None:
        P, D = model.edge_points, model.edge_dirs
        if len(P) <= 1:
            value = np.zeros(len(P))
        else:
            from scipy.spatial import cKDTree

            k = min(neighbours + 1, len(P))
            _, idx = cKDTree(P).query(P, k=k)
            value = np.abs(np.einsum("nj,nkj->nk", D, D[idx[:, 1:]])).mean(axis=1)
        _COHERENCE[model] = value
    return value


def model_contour(frame: Frame, model: ObjectModel, pose: Pose, cache: dict | None, max_points: int,
                  rng: np.random.Generator, mesh_edges: bool = True,
                  min_coherence: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Model-frame contour points (N, 3) and unit tangent directions (N, 3) visible from `pose`;
    `mesh_edges=False` keeps the silhouette only; sharp-edge samples whose edge_coherence is
    under `min_coherence` (noise of a scanned mesh) are left out."""
    pts, dirs = [], []
    edges = visible_edges(frame, model, pose, cache) if mesh_edges else ()
    if len(edges):
        index = edges.index
        if min_coherence > 0:
            index = index[edge_coherence(model)[index] >= min_coherence]
        pts.append(model.edge_points[index])
        dirs.append(model.edge_dirs[index])
    r = hypothesis_rendering(frame, model, pose, cache)
    uv, n2d = silhouette_points(r)
    if len(uv):
        x0, y0 = r.offset
        iu = np.clip(uv[:, 0].astype(np.intp) - x0, 0, r.depth.shape[1] - 1)
        iv = np.clip(uv[:, 1].astype(np.intp) - y0, 0, r.depth.shape[0] - 1)
        z = r.depth[iv, iu].astype(np.float64)
        ok = np.isfinite(z) & (np.linalg.norm(n2d, axis=1) > 1e-6)
        K = frame.K
        u, v, z = uv[ok, 0], uv[ok, 1], z[ok]
        p_cam = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)
        t2 = np.stack([-n2d[ok, 1], n2d[ok, 0]], axis=1)  # along the outline
        t_cam = np.stack([t2[:, 0] * z / K[0, 0], t2[:, 1] * z / K[1, 1], np.zeros(len(z))], axis=1)
        pts.append((p_cam - pose.t) @ pose.R)  # camera -> model frame
        dirs.append(t_cam @ pose.R)
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, 3))
    P, D = np.concatenate(pts), np.concatenate(dirs)
    norm = np.linalg.norm(D, axis=1)
    keep = norm > 1e-12
    P, D = P[keep], D[keep] / norm[keep, None]
    if len(P) > max_points:
        idx = rng.choice(len(P), max_points, replace=False)
        P, D = P[idx], D[idx]
    return P, D


def project_with_directions(R: np.ndarray, t: np.ndarray, P: np.ndarray, D: np.ndarray, K: np.ndarray,
                            eps: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) of model points under (R, t) and the image angle in [0, pi) of their
    tangents (the projection of P + eps D minus that of P). Points behind the camera get NaN."""
    pc = P @ R.T + t
    qc = pc + eps * (D @ R.T)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2]
        v = K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]
        uq = K[0, 0] * qc[:, 0] / qc[:, 2] + K[0, 2]
        vq = K[1, 1] * qc[:, 1] / qc[:, 2] + K[1, 2]
    behind = pc[:, 2] <= 1e-3
    u[behind] = np.nan
    angle = np.mod(np.arctan2(vq - v, uq - u), math.pi)
    return np.stack([u, v], axis=1), angle


def bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray, outside: float) -> np.ndarray:
    """Bilinear samples of a 2D array at float pixel coordinates; `outside` beyond the array."""
    h, w = img.shape
    ok = np.isfinite(x) & np.isfinite(y) & (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    out = np.full(x.shape, outside, np.float64)
    xs, ys = x[ok], y[ok]
    x0 = np.minimum(xs.astype(np.intp), w - 2) if w > 1 else np.zeros(len(xs), np.intp)
    y0 = np.minimum(ys.astype(np.intp), h - 2) if h > 1 else np.zeros(len(ys), np.intp)
    fx, fy = xs - x0, ys - y0
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    out[ok] = (img[y0, x0] * (1 - fx) * (1 - fy) + img[y0, x1] * fx * (1 - fy)
               + img[y1, x0] * (1 - fx) * fy + img[y1, x1] * fx * fy)
    return out
