"""Resting poses of a part on a support plane, and pose hypotheses from them (the `resting_pose`
generator, blocks/resting.py).

A part lying on a table or a bin floor rests on a face of its convex hull, and only on one whose
facet polygon holds the projection of its centre of mass (a stable placement). So a part on a
plane has, per stable face, three degrees of freedom left: where it lies on the plane and how
far it is turned about the plane's normal. `resting_poses` lists the stable faces of a model
once (convex hull facets grouped by normal; the largest first; faces the model's symmetries
make alike kept once). `shortlist_rests` places each rest under an observed region of the
frame at a sweep of turns: the model's camera-facing samples are shifted so that their
centroid on the plane meets the region's, lifted so their top meets the region's top, and
scored cheaply. `refine_rests` aligns the best turns in the plane (`planar_icp`) and scores
them on what the camera sees. The best few go on to render-and-compare verification and ICP.
"""
from __future__ import annotations

import math
import threading
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from ..core.geometry import Pose, rotation_to
from ..core.models import ObjectModel
from .features import DistanceField

MAX_SAMPLES = 150  # model and region points per comparison: enough to tell turns apart, cheap to query
# Translation-only ICP steps that place each turn under its region before it is scored: the region's
# centroid alone is off by a part's occluded share (a mug behind a brick), which hides the right turn.
SHIFT_STEPS = 2
STEP_THIN = 2  # every STEP_THIN-th point of the region and of the samples moves the shift


@dataclass(frozen=True)
class RestingPose:
    """A stable face: R turns the model so that the face's outward normal points down (-z of
    the plane frame, z along the plane's normal towards the camera)."""

    R: np.ndarray  # (3, 3) model frame -> plane frame (before the turn about z)
    lift: float  # metres: height of the model's centroid above the plane in this rest
    height: float  # metres: the part's top above the plane
    area: float  # m^2: the face's area (larger faces are likelier rests)


def _inside_polygon(p: np.ndarray, pts2: np.ndarray) -> bool:
    """Whether 2D point p lies inside the convex hull of pts2 (a degenerate hull: no)."""
    try:
        hull = ConvexHull(pts2)
    except Exception:  # noqa: BLE001  (collinear or too few points: no area to stand on)
        return False
    return bool(np.all(hull.equations[:, :2] @ p + hull.equations[:, 2] <= 1e-9))


def resting_poses(model: ObjectModel, max_poses: int = 6, merge_deg: float = 5.0) -> list[RestingPose]:
    """The model's stable faces on a plane, largest first (see the module docstring). The centre
    of mass is taken as the centroid of the surface samples."""
    hull = ConvexHull(model.hull_points)
    normals, offsets = hull.equations[:, :3], -hull.equations[:, 3]  # outward n . x = offset on the facet
    tri = hull.points[hull.simplices]
    areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    com = model.points.mean(axis=0)
    cos_merge = math.cos(math.radians(merge_deg))
    # Facets of one face of the hull share their plane: group them by their normal rounded to
    # about merge_deg (one sort, also for the ~10^5 facets of a curved model of millions of faces).
    key = np.round(normals * (180.0 / math.pi / merge_deg)).astype(np.int64)
    _, group_of = np.unique(key, axis=0, return_inverse=True)
    group_of = group_of.ravel()
    group_area = np.bincount(group_of, weights=areas)
    order = np.argsort(-group_area, kind="stable")[: 8 * max_poses]  # the largest faces are the likely rests
    groups = [np.flatnonzero(group_of == g) for g in order]
    sym = [s.R for s in model.symmetries] or [np.eye(3)]
    rests: list[RestingPose] = []
    kept_normals: list[np.ndarray] = []
    for g in groups:
        n = np.average(normals[g], axis=0, weights=areas[g] + 1e-12)
        n /= np.linalg.norm(n)
        h0 = float(np.max(offsets[g]))
        R = rotation_to(n, np.array([0.0, 0.0, -1.0]))
        verts = np.unique(hull.simplices[g].ravel())
        footprint = (hull.points[verts] @ R.T)[:, :2]
        if not _inside_polygon((R @ com)[:2], footprint):
            continue  # the centre of mass overhangs: the part tips over
        if any(any((S @ n) @ m > cos_merge for S in sym) for m in kept_normals):
            continue  # a face the symmetries make alike with a kept one
        z = model.hull_points @ n
        rests.append(RestingPose(R=R, lift=h0 - float(com @ n), height=h0 - float(z.min()), area=float(areas[g].sum())))
        kept_normals.append(n)
        if len(rests) >= max_poses:
            break
    return rests


_FIELDS: "weakref.WeakKeyDictionary[ObjectModel, DistanceField]" = weakref.WeakKeyDictionary()
_FIELDS_LOCK = threading.Lock()


def surface_field(model: ObjectModel, cells: int = 32, margin: int = 4) -> DistanceField:
    """A coarse distance field of the model's surface (cell = diameter / `cells`) from its
    surface samples, cached per model: milliseconds even for a model of millions of faces
    (features.distance_field samples the mesh densely, for registration's finer needs)."""
    with _FIELDS_LOCK:
        f = _FIELDS.get(model)
    if f is not None:
        return f
    from scipy.ndimage import distance_transform_edt

    cell = model.diameter / cells
    origin = model.points.min(axis=0) - margin * cell
    shape = np.ceil((model.points.max(axis=0) + margin * cell - origin) / cell).astype(int) + 1
    occ = np.ones(shape, bool)
    ijk = np.floor((model.points - origin) / cell).astype(int)
    occ[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = False
    dist = distance_transform_edt(occ)
    grid = np.maximum(dist * cell - 0.5 * cell, 0.0).astype(np.float32)
    f = DistanceField(origin, cell, grid, np.zeros((*shape, 3), np.float32), model.points.mean(axis=0))
    with _FIELDS_LOCK:
        _FIELDS[model] = f
    return f


def plane_basis(plane: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(B, o): the plane frame's axes as columns of B (x, y in the plane, z its normal towards
    the camera) and its origin o (camera frame): p_camera = o + B @ p_plane. `plane` is
    (n, d) with n . p + d = 0 and n facing the camera."""
    n = plane[:3] / np.linalg.norm(plane[:3])
    x = np.cross([0.0, 1.0, 0.0], n)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross([1.0, 0.0, 0.0], n)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(n, x), n], axis=1), -plane[3] / np.linalg.norm(plane[:3]) * n


def _subsample(p: np.ndarray, k: int = MAX_SAMPLES) -> np.ndarray:
    return p[:: max(1, len(p) // k)]


def _turn(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def planar_icp(model_pts: np.ndarray, observed: np.ndarray, max_dist: float,
               iterations: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Align (P, 3) model points to (N, 3) observed points (both in the plane frame) by a turn
    about z and a shift in the plane only: the resting face stays on the plane, the prior full
    ICP would give up (on a few hundred pixels of a small part it tilts it). Each observed
    point is matched to its nearest model point within `max_dist` (occluded model parts then
    pull nothing). Returns (Rz, shift) with aligned = model_pts @ Rz.T + shift."""
    return planar_icp_many([model_pts], observed, max_dist, iterations)[0]


def planar_icp_many(model_sets: list[np.ndarray], observed: np.ndarray, max_dist: float,
                    iterations: int = 8) -> list[tuple[np.ndarray, np.ndarray]]:
    """`planar_icp` of each of several (P_i, 3) model point sets to the same observed points, in
    one batch: nearest neighbours by brute force over the sets padded to one length (a region's
    ~150 points against ~150 model samples, ~18 sets: a few hundred thousand distances per
    iteration, where a k-d tree per set and iteration took twice as long, in Python overhead).
    A set stops moving once converged or left with fewer than 5 matches, as planar_icp does alone."""
    n_sets = len(model_sets)
    if not n_sets:
        return []
    size = max(len(m) for m in model_sets)
    M0 = np.zeros((n_sets, size, 3))
    real = np.zeros((n_sets, size), bool)
    for b, m in enumerate(model_sets):
        M0[b, : len(m)], real[b, : len(m)] = m, True
    m_sq = np.where(real, (M0 * M0).sum(axis=2), np.inf)  # (sets, P); padding at infinity: never the nearest
    MT = np.ascontiguousarray(M0.transpose(0, 2, 1))
    obs_xy = observed[:, :2]
    Rz = np.repeat(np.eye(3)[None], n_sets, axis=0)
    shift = np.zeros((n_sets, 3))
    active = np.ones(n_sets, bool)
    rows = np.arange(len(observed))
    buf = np.empty((n_sets, len(observed), size))
    for _ in range(iterations):
        b_idx = np.flatnonzero(active)
        if not len(b_idx):
            break
        back = (observed[None] - shift[b_idx, None, :]) @ Rz[b_idx]  # the observed points in each set's frame
        d2 = np.matmul(back, MT[b_idx], out=buf[: len(b_idx)])  # |model|^2 - 2 back . model (+ |back|^2, the
        d2 *= -2.0  # same along a row), in one buffer: each temporary of this size would cost its page faults
        d2 += m_sq[b_idx, None, :]
        idx = np.argmin(d2, axis=2)  # (b, N)
        best = d2[np.arange(len(b_idx))[:, None], rows[None, :], idx] + (back * back).sum(axis=2)
        ok = best <= max_dist * max_dist
        n_ok = ok.sum(axis=1)
        few = n_ok < 5
        active[b_idx[few]] = False
        b_idx, idx, ok, n_ok = b_idx[~few], idx[~few], ok[~few], n_ok[~few]
        if not len(b_idx):
            break
        src = M0[b_idx[:, None], idx, :2] @ Rz[b_idx, :2, :2].transpose(0, 2, 1) + shift[b_idx, None, :2]
        w = ok[..., None].astype(float)
        cs = (src * w).sum(axis=1) / n_ok[:, None]
        cd = (obs_xy[None] * w).sum(axis=1) / n_ok[:, None]
        h = ((src - cs[:, None]) * w).transpose(0, 2, 1) @ (obs_xy[None] - cd[:, None])  # (b, 2, 2)
        phi = np.arctan2(h[:, 0, 1] - h[:, 1, 0], h[:, 0, 0] + h[:, 1, 1])
        c, s_ = np.cos(phi), np.sin(phi)
        step = np.zeros((len(b_idx), 3, 3))
        step[:, 0, 0], step[:, 0, 1], step[:, 1, 0], step[:, 1, 1], step[:, 2, 2] = c, -s_, s_, c, 1.0
        t2 = cd - (step[:, :2, :2] @ cs[..., None])[..., 0]
        Rz[b_idx] = step @ Rz[b_idx]
        shift[b_idx] = (step @ shift[b_idx, :, None])[..., 0]
        shift[b_idx, :2] += t2
        active[b_idx[(np.abs(phi) < 1e-4) & (np.linalg.norm(t2, axis=1) < 1e-5)]] = False
    return [(Rz[b], shift[b]) for b in range(n_sets)]


@dataclass
class RegionShortlist:
    """One region's cheap fit of every rest (shortlist_rests), kept for refine_rests."""

    best: float  # the best cheap cost (diameters): regions are refined in this order
    picks: list[tuple[int, int, np.ndarray]]  # (rest index, turn index, shift) of each rest's best turns
    q: np.ndarray  # (N, 3) the region's points in the plane frame
    tree: cKDTree  # over q
    view: np.ndarray  # camera -> region direction, plane frame
    B: np.ndarray  # plane_basis
    o: np.ndarray
    rotations: np.ndarray  # (T, 3, 3) the turns about z


def _samples(model: ObjectModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centroid, samples about it, their normals), about 2 MAX_SAMPLES of them."""
    com = model.points.mean(axis=0)
    step = max(1, len(model.points) // (2 * MAX_SAMPLES))
    return com, model.points[::step] - com, model.point_normals[::step]


def planar_shift_step(p: np.ndarray, vis: np.ndarray, n_vis: np.ndarray, shifts: np.ndarray, q: np.ndarray,
                      tree_q: cKDTree, prest: np.ndarray, tree_m: cKDTree, Rzs: np.ndarray,
                      max_dist: float) -> np.ndarray:
    """(T, 2) metres: one translation-only ICP step in the plane for each of T turns: the mean
    offset of the matched pairs (nearest within `max_dist`, both ways: camera-facing model
    samples to the region's points, the region's points to all samples). `p` (T, P, 3): the
    samples turned (prest @ Rzs[t].T), `vis` (T, P) which face the camera (`n_vis` per turn),
    `shifts` (T, 3) where each turn is placed, `q` (N, 3) the region (plane frame), `prest`
    (P, 3) the samples in the rest's frame, `Rzs` (T, 3, 3) the turns; trees over q and prest."""
    T = len(shifts)
    placed = (p + shifts[:, None, :])[vis]  # (M, 3)
    dist, idx = tree_q.query(placed, distance_upper_bound=max_dist)
    ok = np.isfinite(dist)
    disp = np.where(ok[:, None], q[np.minimum(idx, len(q) - 1)] - placed, 0.0)[:, :2]
    turn_of = np.repeat(np.arange(T), n_vis)
    total = np.stack([np.bincount(turn_of, weights=disp[:, k], minlength=T) for k in (0, 1)], axis=1)
    count = np.bincount(turn_of, weights=ok, minlength=T)
    back = (q[None] - shifts[:, None, :]) @ Rzs  # (T, N, 3): the region in each turn's rest frame
    dist2, idx2 = tree_m.query(back, distance_upper_bound=max_dist)
    ok2 = np.isfinite(dist2)
    near = prest[np.minimum(idx2, len(prest) - 1)]
    disp2 = np.einsum("tij,tnj->tni", Rzs, back - near)[..., :2] * ok2[..., None]
    total += disp2.sum(axis=1)
    count += ok2.sum(axis=1)
    return total / np.maximum(count, 1.0)[:, None]


def _cheap_cost(p: np.ndarray, vis: np.ndarray, n_vis: np.ndarray, shifts: np.ndarray, q: np.ndarray,
                tree_q: cKDTree, field: DistanceField, R_model: np.ndarray, com: np.ndarray,
                tau: float) -> np.ndarray:
    """(T,) metres: shortlist_rests' cost of each turn placed at its shift, the mean distance
    (truncated at `tau`) of the camera-facing samples to the region plus that of the region's
    points to the model's surface."""
    # model -> observed: the camera-facing samples of every turn in one query
    dm = np.minimum(tree_q.query((p + shifts[:, None, :])[vis], distance_upper_bound=tau)[0], tau)
    model_to_obs = np.add.reduceat(dm, np.concatenate([[0], np.cumsum(n_vis)[:-1]])) / n_vis
    # observed -> model: the region's points in the model frame of every turn, on the distance field
    x_model = (q[None] - shifts[:, None, :]) @ R_model + com
    return model_to_obs + np.minimum(field.lookup(x_model)[0], tau).mean(axis=1)


def shortlist_rests(
    model: ObjectModel, rests: list[RestingPose], plane: np.ndarray, region: np.ndarray, turns: int = 24,
    per_rest: int = 3, truncate: float = 0.1, shift_steps: int = SHIFT_STEPS,
) -> RegionShortlist | None:
    """Every rest at `turns` turns about the plane's normal, shifted under `region` ((N, 3)
    camera-frame points of one observed region: centroid on centroid, or after `shift_steps`
    translation-only ICP steps (planar_shift_step) where that fits better) and scored cheaply: the mean truncated
    (`truncate` diameters) distance of the region's points to the model's surface (its
    distance field) plus that of the model's camera-facing samples to the region's points, in
    diameters; the `per_rest` best turns of each rest. Rests much taller or much lower than the
    region are skipped (a part on its side does not fit a flat region). None: nothing fits."""
    B, o = plane_basis(plane)
    q = _subsample((region - o) @ B)  # plane frame
    if len(q) < 5:
        return None
    top = float(np.percentile(q[:, 2], 98))
    centre = q[:, :2].mean(axis=0)
    view = np.append(centre, top / 2.0) - (-o) @ B  # camera -> region, plane frame
    view /= np.linalg.norm(view)
    tree_q = cKDTree(q)
    q_thin = q[::STEP_THIN]
    tree_thin = cKDTree(q_thin)
    field = surface_field(model)
    d, tau = model.diameter, truncate * model.diameter
    com, pts, nrm = _samples(model)
    Rzs = np.stack([_turn(a) for a in 2.0 * math.pi * np.arange(turns) / turns])  # (T, 3, 3)
    RzT = Rzs.transpose(0, 2, 1)
    picks, best = [], math.inf
    for i, rest in enumerate(rests):
        if top > rest.height + 0.25 * d + 0.01 or top < 0.4 * rest.height:
            continue
        base = max(0.0, top - rest.height)  # the part lies on the plane, or on something under it
        p = (pts @ rest.R.T) @ RzT  # (T, P, 3)
        vis = ((nrm @ rest.R.T) @ RzT) @ view < 0.0  # camera-facing
        vis[vis.sum(axis=1) < 5] = True
        n_vis = vis.sum(axis=1)
        mean_xy = np.einsum("tp,tpi->ti", vis, p[..., :2]) / n_vis[:, None]
        shifts = np.concatenate([centre - mean_xy, np.full((turns, 1), base + rest.lift)], axis=1)  # (T, 3)
        R_model = Rzs @ rest.R
        total = _cheap_cost(p, vis, n_vis, shifts, q, tree_q, field, R_model, com, tau) / d
        if shift_steps:  # the steps' shifts where they fit better (every other point suffices to move them)
            ps, vs, prest = p[:, ::STEP_THIN], vis[:, ::STEP_THIN], (pts @ rest.R.T)[::STEP_THIN]
            tree_m, moved = cKDTree(prest), shifts.copy()
            for _ in range(shift_steps):
                moved[:, :2] += planar_shift_step(ps, vs, vs.sum(axis=1), moved, q_thin, tree_thin, prest, tree_m,
                                                  Rzs, 2.0 * tau)
            total_moved = _cheap_cost(p, vis, n_vis, moved, q, tree_q, field, R_model, com, tau) / d
            better = total_moved < total
            total[better], shifts[better] = total_moved[better], moved[better]
        for k in np.argsort(total, kind="stable")[:per_rest]:
            picks.append((i, int(k), shifts[k]))
            best = min(best, float(total[k]))
    if not picks:
        return None
    return RegionShortlist(best, picks, q, tree_q, view, B, o, Rzs)


def refine_rests(model: ObjectModel, rests: list[RestingPose], sl: RegionShortlist, keep: int = 8,
                 truncate: float = 0.1) -> list[tuple[float, Pose]]:
    """The shortlisted turns aligned in the plane (planar_icp) and scored on what the camera
    sees: the mean truncated (`truncate` diameters) nearest distance between the region's
    points and the model's camera-facing samples, both ways, in diameters. The `keep` best
    (cost, pose), lowest cost first."""
    d, tau = model.diameter, truncate * model.diameter
    com, pts, nrm = _samples(model)
    fronts, starts = [], []
    for i, k, shift in sl.picks:
        R0 = sl.rotations[k] @ rests[i].R
        p = pts @ R0.T
        front = p[(nrm @ R0.T) @ sl.view < 0.0]
        fronts.append(front if len(front) >= 5 else p)
        starts.append((R0, shift))
    aligned = planar_icp_many([f + shift for f, (_, shift) in zip(fronts, starts)], sl.q, 2.0 * tau)
    out: list[tuple[float, Pose]] = []
    for front, (R0, shift), (R2, s2) in zip(fronts, starts, aligned):
        R_plane, shift = R2 @ R0, R2 @ shift + s2
        placed = front @ R2.T + shift
        cost = (np.minimum(cKDTree(placed).query(sl.q, distance_upper_bound=tau)[0], tau).mean()
                + np.minimum(sl.tree.query(placed, distance_upper_bound=tau)[0], tau).mean()) / d
        out.append((float(cost), Pose(sl.B @ R_plane, sl.o + sl.B @ (shift - R_plane @ com))))
    out.sort(key=lambda f: f[0])
    return out[:keep]


def moved_in_plane(pose: Pose, B: np.ndarray, pivot: np.ndarray, angle: float, dx: float = 0.0,
                   dy: float = 0.0) -> Pose:
    """`pose` turned by `angle` (radians) about the plane's normal (B's third column, plane_basis)
    through the camera-frame point `pivot`, then shifted by (dx, dy) metres along the plane."""
    Rw = B @ _turn(angle) @ B.T
    return Pose(Rw @ pose.R, Rw @ (pose.t - pivot) + pivot + B[:, 0] * dx + B[:, 1] * dy)


def settled_on_plane(model: ObjectModel, pose: Pose, plane: np.ndarray, max_gap: float) -> Pose | None:
    """`pose` moved along the plane's normal until the part's lowest surface sample touches the
    plane ((n, d), plane_basis), when it floats above it or sinks into it by less than
    `max_gap` metres; None otherwise (stacked on something, or not this plane's). The region's
    top that places a rest includes its edge pixels' and the sensor's noise: the synthetic hex
    nuts and bushings floated 3-4 mm, 0.1 d, which the pick's MSSD counts in full."""
    n = plane[:3] / np.linalg.norm(plane[:3])
    gap = float(np.min(pose.transform(model.points) @ n)) + plane[3] / np.linalg.norm(plane[:3])
    if not abs(gap) < max_gap:
        return None
    return Pose(pose.R, pose.t - gap * n)


def sweep_in_plane(model: ObjectModel, pose: Pose, score: float, B: np.ndarray, verify: Callable[[Pose], float],
                   deadline: float = math.inf, span_deg: float = 30.0, step_deg: float = 6.0,
                   shift: float = 0.03, tried: list | None = None) -> tuple[float, Pose]:
    """The best-verifying pose near `pose` (verification `score`) among its turns about the
    plane's normal through the part's centre (every `step_deg` within +-`span_deg`, then half a
    step either side of the best), then its shifts by `shift` diameters along the plane's axes
    and diagonals. ICP leaves the turn of a flat or near-symmetric part (a flange's bolt holes,
    a hex nut's flats) where it started, 15-25 deg off; rendering sees the holes and flats (on
    the synthetic parts: the right turn verifies best in 8 of 10 such near misses). Stops at
    `deadline` (perf_counter) with the best so far. `tried`, if given, receives every (score, pose)
    verified on the way: a part whose turn the view cannot settle (a mug with its handle hidden)
    verifies alike over a range of turns, and those are the alternatives worth offering."""
    pivot = pose.transform(model.points.mean(axis=0)[None])[0]
    best = (score, 0.0, 0.0, 0.0)  # (score, turn, dx, dy)
    fine = math.radians(step_deg / 2.0)
    h = shift * model.diameter

    def tries():  # read `best` as it is when each stage starts
        for a in np.radians(np.arange(step_deg, span_deg + 1e-9, step_deg)):
            yield a, 0.0, 0.0
            yield -a, 0.0, 0.0
        a = best[1]
        yield a - fine, 0.0, 0.0
        yield a + fine, 0.0, 0.0
        a = best[1]
        yield from ((a, dx, dy) for dx in (-h, 0.0, h) for dy in (-h, 0.0, h) if dx or dy)

    for a, dx, dy in tries():
        if time.perf_counter() >= deadline:
            break
        moved = moved_in_plane(pose, B, pivot, a, dx, dy)
        s = verify(moved)
        if tried is not None:
            tried.append((s, moved))
        if s > best[0]:
            best = (s, a, dx, dy)
    return best[0], moved_in_plane(pose, B, pivot, best[1], best[2], best[3])


__all__ = ["RestingPose", "RegionShortlist", "resting_poses", "shortlist_rests", "refine_rests", "planar_icp",
           "planar_icp_many", "plane_basis", "surface_field", "moved_in_plane", "settled_on_plane",
           "sweep_in_plane", "planar_shift_step"]
