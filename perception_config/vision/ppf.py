"""Point pair features (Drost et al. 2010, with Vidal et al. 2018's refinements) in numpy: the
depth-based, ground-truth-free candidate source of the `ppf` generator (blocks/generation.py).

A point pair (p1, n1), (p2, n2) is described by F = (|d|, angle(n1, d), angle(n2, d),
angle(n1, n2)), d = p2 - p1, quantised to `dist_step` and `n_angle` bins. The model's table
(`PpfModel`, built once per model and parameter set by `prepare_model`, cached on disk by
`ppf_model`) maps each quantised feature to the model pairs that have it, with each pair's
angle `theta` about the first point's normal. Matching (`vote`): every `ref_step`-th scene
point is paired with its scene neighbours within the model's diameter; each scene pair votes
for (model point, rotation alpha about the normal) of every model pair with the same feature;
the peak per reference point is a pose. `cluster_poses` groups nearby poses and sums their votes.

Not used: Vidal et al. 2018's vote spreading over the neighbouring bins of all four feature
dimensions (16 lookups per pair) with one vote per scene pair and (model point, alpha): in numpy
it took minutes per object (measured; docs/results/generators.md).

The table lives in a compressed .npz named by a hash of the model's geometry, the parameters
and the format version (`PPF_FORMAT`); one that cannot be read or does not match is rebuilt and
rewritten (atomically), never trusted.
"""
from __future__ import annotations

import math
import threading
import time
import weakref
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ..core.models import ObjectModel
from .disk_cache import cache_dir, load_npz, model_digest, store_npz

PPF_FORMAT = 2  # bump when the table's content or layout changes: old cache files are rebuilt
MAX_MODEL_POINTS = 900  # model samples kept after voxel down-sampling (pairs grow as N^2)
MIN_MODEL_POINTS = 20  # fewer samples at the sampling step: the model is too small or degenerate


@dataclass(frozen=True)
class PpfModel:
    """A model's point pair table. Pairs are sorted by feature key; `starts[k]:starts[k+1]` are
    the pairs with key k."""

    points: np.ndarray  # (N, 3) model-frame samples
    normals: np.ndarray  # (N, 3) unit outward normals
    rot: np.ndarray  # (N, 3, 3) rotation taking each point's normal to +x (about the origin)
    pair_i: np.ndarray  # (P,) int32 first point of each pair
    pair_theta: np.ndarray  # (P,) int16 alpha bin of the pair (second point's angle about n1)
    starts: np.ndarray  # (n_keys + 1,) int64
    dist_step: float  # metres
    n_angle: int
    n_dist: int
    diameter: float


def normal_to_x(normals: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations taking each unit normal to +x (Rodrigues; -x turns about +z)."""
    n = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    c = n[:, 0]  # cos of the angle to +x
    axis = np.stack([np.zeros_like(c), n[:, 2], -n[:, 1]], axis=1)  # n x e_x
    s = np.linalg.norm(axis, axis=1)
    R = np.tile(np.eye(3), (len(n), 1, 1))
    turn = s > 1e-9
    k = axis[turn] / s[turn, None]
    Kx = np.zeros((len(k), 3, 3))
    Kx[:, 0, 1], Kx[:, 0, 2], Kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    Kx[:, 1, 0], Kx[:, 2, 0], Kx[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    ang = np.arctan2(s[turn], c[turn])[:, None, None]
    R[turn] = np.eye(3) + np.sin(ang) * Kx + (1.0 - np.cos(ang)) * (Kx @ Kx)
    flip = (~turn) & (c < 0)
    R[flip] = np.diag([-1.0, -1.0, 1.0])
    return R


def pair_features(p1: np.ndarray, n1: np.ndarray, p2: np.ndarray, n2: np.ndarray) -> tuple[np.ndarray, ...]:
    """(|d|, angle(n1, d), angle(n2, d), angle(n1, n2)) of point pairs, angles in [0, pi]."""
    d = p2 - p1
    dist = np.linalg.norm(d, axis=1)
    du = d / np.maximum(dist, 1e-12)[:, None]
    a1 = np.arccos(np.clip(np.einsum("ij,ij->i", n1, du), -1.0, 1.0))
    a2 = np.arccos(np.clip(np.einsum("ij,ij->i", n2, du), -1.0, 1.0))
    a3 = np.arccos(np.clip(np.einsum("ij,ij->i", n1, n2), -1.0, 1.0))
    return dist, a1, a2, a3


def pair_angle(rot1: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """Angle of the second point about the first one's normal, after the normal is turned to +x."""
    q = np.einsum("nij,nj->ni", rot1, p2 - p1)
    return np.arctan2(q[:, 2], q[:, 1])


def quantise(dist: np.ndarray, a1: np.ndarray, a2: np.ndarray, a3: np.ndarray, step: float,
             n_angle: int) -> tuple[np.ndarray, ...]:
    """Continuous bin coordinates (floats): the integer part is the bin."""
    s = n_angle / math.pi
    return dist / step, a1 * s, a2 * s, a3 * s


def feature_key(fd: np.ndarray, f1: np.ndarray, f2: np.ndarray, f3: np.ndarray, n_angle: int) -> np.ndarray:
    return ((fd * n_angle + f1) * n_angle + f2) * n_angle + f3


def angle_bin(theta: np.ndarray, n_bins: int) -> np.ndarray:
    return (np.floor((theta + math.pi) * (n_bins / (2.0 * math.pi))).astype(np.int64)) % n_bins


def downsample(points: np.ndarray, normals: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """Voxel-grid average of points and normals, in each cell separately for the normals on
    either side of the cell's first one: the two faces of a sheet thinner than a voxel (a
    bracket, a cover) stay two samples with opposite normals instead of cancelling."""
    if len(points) == 0:
        return points.reshape(0, 3), normals.reshape(0, 3)
    cell = np.floor(points / voxel).astype(np.int64)
    cell -= cell.min(axis=0)
    dims = cell.max(axis=0) + 1
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    _, first, inv = np.unique(key, return_index=True, return_inverse=True)
    side = np.einsum("ij,ij->i", normals, normals[first][inv]) < 0
    uniq, inv = np.unique(key * 2 + side, return_inverse=True)
    cnt = np.bincount(inv, minlength=len(uniq)).astype(np.float64)
    p = np.stack([np.bincount(inv, points[:, k], len(uniq)) for k in range(3)], axis=1) / cnt[:, None]
    n = np.stack([np.bincount(inv, normals[:, k], len(uniq)) for k in range(3)], axis=1)
    norm = np.linalg.norm(n, axis=1)
    keep = norm > 0.3 * cnt
    return p[keep], n[keep] / norm[keep, None]


def prepare_model(model: ObjectModel, sampling_rel: float, n_angle: int) -> PpfModel:
    """The model's point pair table (seconds for ~900 points; see ppf_model for the cache)."""
    step = sampling_rel * model.diameter
    pts, nrm = downsample(np.asarray(model.points, np.float64), np.asarray(model.point_normals, np.float64), step)
    if len(pts) > MAX_MODEL_POINTS:
        keep = np.linspace(0, len(pts) - 1, MAX_MODEL_POINTS).round().astype(np.int64)
        pts, nrm = pts[keep], nrm[keep]
    if len(pts) < MIN_MODEL_POINTS:
        raise ValueError(f"model {model.obj_id}: only {len(pts)} surface samples at {step * 1000:.1f} mm "
                         "(degenerate or tiny model)")
    n = len(pts)
    rot = normal_to_x(nrm)
    n_dist = int(math.ceil(model.diameter / step)) + 2
    ii, jj = np.nonzero(~np.eye(n, dtype=bool))
    dist, a1, a2, a3 = pair_features(pts[ii], nrm[ii], pts[jj], nrm[jj])
    q = quantise(dist, a1, a2, a3, step, n_angle)
    fd = np.minimum(q[0].astype(np.int64), n_dist - 1)
    fa = [np.minimum(x.astype(np.int64), n_angle - 1) for x in q[1:]]
    key = feature_key(fd, *fa, n_angle)
    theta = angle_bin(pair_angle(rot[ii], pts[ii], pts[jj]), n_angle * 2)
    order = np.argsort(key, kind="stable")
    n_keys = n_dist * n_angle**3
    starts = np.searchsorted(key[order], np.arange(n_keys + 1)).astype(np.int64)
    return PpfModel(pts, nrm, rot, ii[order].astype(np.int32), theta[order].astype(np.int16), starts,
                    step, n_angle, n_dist, float(model.diameter))


def model_hash(model: ObjectModel, sampling_rel: float, n_angle: int) -> str:
    """Hash of what the table is built from: the model's geometry and samples, the parameters,
    the format version."""
    return model_digest(model, f"{model.diameter:.9g}|{sampling_rel:.6g}|{n_angle}|{MAX_MODEL_POINTS}|{PPF_FORMAT}")


_FIELDS = ("points", "normals", "rot", "pair_i", "pair_theta", "starts")
_MEMORY: "weakref.WeakKeyDictionary[ObjectModel, dict[tuple, PpfModel]]" = weakref.WeakKeyDictionary()
_LOCK = threading.Lock()


def _read_cached(path: Path, digest: str, model: ObjectModel, sampling_rel: float, n_angle: int) -> PpfModel | None:
    """The table stored at `path`, or None when it is missing, unreadable or not the one asked for."""
    z = load_npz(path, digest)
    try:
        arrays = {f: z[f] for f in _FIELDS}
        step, n_dist = float(z["dist_step"]), int(z["n_dist"])
    except (TypeError, KeyError, ValueError):
        return None  # missing, corrupt or from another format: rebuilt by the caller
    n = len(arrays["points"])
    ok = (arrays["normals"].shape == (n, 3) and arrays["rot"].shape == (n, 3, 3)
          and len(arrays["starts"]) == n_dist * n_angle**3 + 1 and len(arrays["pair_i"]) == len(arrays["pair_theta"])
          and int(arrays["starts"][-1]) == len(arrays["pair_i"]) and n > 0
          and (len(arrays["pair_i"]) == 0 or int(arrays["pair_i"].max()) < n))
    if not ok:
        return None
    return PpfModel(**arrays, dist_step=step, n_angle=n_angle, n_dist=n_dist, diameter=float(model.diameter))


def ppf_model(model: ObjectModel, sampling_rel: float = 0.04, n_angle: int = 30,
              folder: Path | None = None) -> tuple[PpfModel, str]:
    """The model's table: from memory, else from the disk cache, else built and stored.
    Returns (table, where it came from: 'memory' | 'disk' | 'built')."""
    key = (round(sampling_rel, 6), n_angle)
    with _LOCK:
        hit = _MEMORY.get(model, {}).get(key)
    if hit is not None:
        return hit, "memory"
    digest = model_hash(model, sampling_rel, n_angle)
    path = (folder or cache_dir()) / "ppf" / f"ppf-{digest}.npz"
    table, source = _read_cached(path, digest, model, sampling_rel, n_angle), "disk"
    if table is None:
        table, source = prepare_model(model, sampling_rel, n_angle), "built"
        store_npz(path, digest, {"dist_step": np.array(table.dist_step), "n_dist": np.array(table.n_dist),
                                 **{f: getattr(table, f) for f in _FIELDS}})  # False in a read-only folder
    with _LOCK:
        _MEMORY.setdefault(model, {})[key] = table
    return table, source


@dataclass
class SceneCloud:
    points: np.ndarray  # (S, 3) camera frame
    normals: np.ndarray  # (S, 3) unit, facing the camera
    tree: cKDTree


def scene_cloud(points: np.ndarray, voxel: float, normal_radius: float | None = None) -> SceneCloud:
    """The scene's points down-sampled to `voxel`, with normals fitted to their neighbours within
    3 voxels (open3d) and turned towards the camera. Normals come from the down-sampled cloud,
    not the depth image: sensor dropout leaves few complete pixel windows on small parts."""
    import open3d as o3d

    from .features import point_cloud

    pc = point_cloud(points[np.isfinite(points[:, 2])]).voxel_down_sample(voxel)
    if len(pc.points) >= 3:
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius or 3.0 * voxel, max_nn=30))
        pc.orient_normals_towards_camera_location(np.zeros(3))
    p = np.asarray(pc.points).copy()
    n = np.asarray(pc.normals).copy() if pc.has_normals() else np.zeros_like(p)
    return SceneCloud(p, n, cKDTree(p) if len(p) else cKDTree(np.zeros((1, 3))))


def vote(table: PpfModel, scene: SceneCloud, ref_step: int, max_votes: int = 4_000_000,
         max_cells: int = 2_000_000, deadline: float = math.inf) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hough voting: for every `ref_step`-th scene point the best (model point, alpha) and its
    votes. Returns (R (M, 3, 3), t (M, 3), votes (M,)) of the reference points' poses (model to
    camera), in the order of the reference points. Reference points are processed in chunks of
    about `max_votes` votes, in a fixed shuffled order, so that at `deadline` (perf_counter; no
    new chunk starts) the references that voted are a uniform sample of the scene's, not one
    corner of it: a cluttered frame's vote (1-2 s) leaves the search time to verify."""
    S = len(scene.points)
    if S < 3:
        return np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0)
    refs = np.arange(0, S, ref_step)
    order = np.random.default_rng(len(refs)).permutation(len(refs))  # fixed: the same scene, the same order
    refs = refs[order]
    n_alpha = table.n_angle * 2
    n_model = len(table.points)
    nbrs = scene.tree.query_ball_point(scene.points[refs], r=table.diameter)
    out_R, out_t, out_v, out_i = [], [], [], []
    rot_s = normal_to_x(scene.normals[refs])
    lo = 0
    while lo < len(refs) and (lo == 0 or time.perf_counter() < deadline):
        # Chunk so the expanded votes stay bounded (an estimate: pairs x a typical fan-out of 8).
        hi, pairs = lo, 0
        while hi < len(refs) and (hi == lo or (pairs * 8 < max_votes
                                               and (hi - lo) * n_model * n_alpha < max_cells)):
            pairs += len(nbrs[hi])
            hi += 1
        r_local = np.concatenate([np.full(len(nbrs[k]), k - lo, np.int64) for k in range(lo, hi)])
        s_idx = np.concatenate([np.asarray(nbrs[k], np.int64) for k in range(lo, hi)])
        r_idx = refs[lo:hi][r_local]
        keep = s_idx != r_idx
        r_local, s_idx, r_idx = r_local[keep], s_idx[keep], r_idx[keep]
        P1, N1, P2, N2 = scene.points[r_idx], scene.normals[r_idx], scene.points[s_idx], scene.normals[s_idx]
        q = quantise(*pair_features(P1, N1, P2, N2), table.dist_step, table.n_angle)
        theta_s = angle_bin(pair_angle(rot_s[lo:hi][r_local], P1, P2), n_alpha)
        fd = np.minimum(q[0].astype(np.int64), table.n_dist - 1)
        key = feature_key(fd, *[np.minimum(x.astype(np.int64), table.n_angle - 1) for x in q[1:]], table.n_angle)
        a, b = table.starts[key], table.starts[key + 1]
        cnt = b - a
        total = int(cnt.sum())
        n_chunk = hi - lo
        if total:
            offs = np.repeat(a - np.cumsum(cnt) + cnt, cnt) + np.arange(total)
            mi = table.pair_i[offs].astype(np.int64)
            alpha = (np.repeat(theta_s, cnt) - table.pair_theta[offs]) % n_alpha
            flat = (np.repeat(r_local, cnt) * n_model + mi) * n_alpha + alpha
            acc = np.bincount(flat, minlength=n_chunk * n_model * n_alpha).reshape(n_chunk, n_model * n_alpha)
            best = acc.argmax(axis=1)
            votes = acc[np.arange(n_chunk), best]
            mi_best, a_best = best // n_alpha, best % n_alpha
            alpha_rad = a_best * (2.0 * math.pi / n_alpha)  # a difference of two bins: centred on the bin
            ca, sa = np.cos(alpha_rad), np.sin(alpha_rad)
            Rx = np.zeros((n_chunk, 3, 3))
            Rx[:, 0, 0] = 1.0
            Rx[:, 1, 1], Rx[:, 1, 2], Rx[:, 2, 1], Rx[:, 2, 2] = ca, -sa, sa, ca
            Rs = rot_s[lo:hi]
            R = np.einsum("nji,njk,nkl->nil", Rs, Rx, table.rot[mi_best])  # Rs^T Rx Rm
            t = scene.points[refs[lo:hi]] - np.einsum("nij,nj->ni", R, table.points[mi_best])
            out_R.append(R)
            out_t.append(t)
            out_v.append(votes.astype(np.float64))
            out_i.append(order[lo:hi])
        lo = hi
    if not out_R:
        return np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0)
    back = np.argsort(np.concatenate(out_i))  # the references' own order again
    R, t, v = np.concatenate(out_R)[back], np.concatenate(out_t)[back], np.concatenate(out_v)[back]
    voted = v > 0  # a reference without a vote has no pose
    return R[voted], t[voted], v[voted]


def canonical_poses(R: np.ndarray, t: np.ndarray, symmetries: list) -> tuple[np.ndarray, np.ndarray]:
    """Each pose replaced by the member of its symmetry orbit {(R Rs, t + R ts)} whose rotation is
    nearest the identity. Poses a symmetric part cannot tell apart become one pose, so their
    votes add up in one cluster instead of splitting over up to len(symmetries) clusters (a
    6-fold nut's or a turned bushing's peak is otherwise one of many weak ones)."""
    if len(symmetries) <= 1 or len(R) == 0:
        return R, t
    Rs = np.stack([s.R for s in symmetries])
    ts = np.stack([s.t for s in symmetries])
    k = np.argmax(np.einsum("mij,kji->mk", R, Rs), axis=1)  # trace(R Rs): the largest is nearest I
    return np.einsum("mij,mjk->mik", R, Rs[k]), t + np.einsum("mij,mj->mi", R, ts[k])


def cluster_poses(R: np.ndarray, t: np.ndarray, votes: np.ndarray, centre: np.ndarray, max_dist: float,
                  max_angle: float, keep: int,
                  symmetries: list | None = None) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """Greedy clustering of poses in order of votes: a pose joins the first cluster whose
    leader moves the model's centre by less than `max_dist` and differs by less than
    `max_angle` radians. With the model's `symmetries` the poses are first made canonical
    (canonical_poses). Returns up to `keep` (summed votes, R, t) of the leaders, best first."""
    R, t = canonical_poses(R, t, symmetries or [])
    order = np.argsort(-votes, kind="stable")
    centres = np.einsum("nij,j->ni", R, centre) + t
    leaders: list[int] = []
    score: list[float] = []
    cos_max = 1.0 + 2.0 * (math.cos(max_angle) - 1.0) / 2.0  # trace form: (tr - 1) / 2 >= cos
    for k in order:
        if leaders:
            L = np.asarray(leaders)
            near = np.linalg.norm(centres[L] - centres[k], axis=1) < max_dist
            if near.any():
                Ln = L[near]
                cos = (np.einsum("nij,ij->n", R[Ln], R[k]) - 1.0) / 2.0
                hit = np.flatnonzero(cos > cos_max)
                if len(hit):
                    score[int(np.flatnonzero(near)[hit[0]])] += float(votes[k])
                    continue
        leaders.append(int(k))
        score.append(float(votes[k]))
    best = np.argsort(-np.asarray(score), kind="stable")[:keep]
    return [(score[i], R[leaders[i]], t[leaders[i]]) for i in best]


__all__ = ["PpfModel", "SceneCloud", "ppf_model", "prepare_model", "scene_cloud", "vote", "cluster_poses",
           "canonical_poses", "cache_dir", "downsample", "normal_to_x", "PPF_FORMAT"]
