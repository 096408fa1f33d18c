"""Symmetries of an object model: the transformations of a BOP models_info entry, or, for a model
whose dataset declares none, the ones derived from its surface geometry (`derive_symmetries`).

Every list of symmetries here is in the model frame, metres, identity first: `Pose(R, t)` maps
a model point x to R @ x + t, and the model's surface onto itself.
"""
from __future__ import annotations

import math
from typing import Any, Mapping, Protocol, Sequence

import numpy as np
from scipy.spatial import cKDTree

from .geometry import MM, Pose, exp_so3, log_so3, rotation_angle


class SurfaceModel(Protocol):
    """What `declared_or_derived_symmetries` reads of a model (core.models.ObjectModel, not
    imported: core/models.py imports this module)."""

    points: np.ndarray  # (P, 3) surface samples, metres
    diameter: float  # metres
    symmetries: Sequence[Pose]  # declared, identity first

DEFAULT_CONT_STEP_DEG = 10.0  # sampling step of continuous symmetries

# Derived symmetries (see derive_symmetries). Tolerance: share of the diameter, measured on the
# YCB-Video, LM-O and procedural meshes (why this value: derive_symmetries).
DEFAULT_SYM_TOLERANCE = 0.025
SYM_PERCENTILE = 95.0  # robust statistic of the surface-to-surface distances a symmetry must meet
MAX_FOLD = 12  # n-fold rotations tested up to this n; passing all of 2..MAX_FOLD means continuous
_MAX_QUERY = 1000  # surface samples transformed to accept a candidate (a deterministic subsample)
_SCREEN_QUERY = 100  # ... to screen one: candidates beyond tolerance + _SCREEN_MARGIN (share of the
_SCREEN_MARGIN = 0.03  # diameter: what a few degrees off the axis cost) are dropped unrefined
_ORDER_SLACK = 0.25  # orders within this x tolerance of the best one's worst turn count as as good
_ROUGH_SLACK = 1.5  # the k/n turns about a refined axis pass on the screening samples below this x tolerance
_NEIGHBOURS = 8  # samples of the local plane fitted around each surface sample
_GATE_FACTOR = 3.0  # principal spreads closer than this x tolerance: a (near) rotation axis
_FLIP_SEARCH_DEG = 5.0  # step of the search for 2-fold axes in a plane of equal spreads
_ICP_ITERS = 6  # refinement of a screened candidate ...
_ICP_QUERY = 500  # ... with this many samples
_MAX_REFINE_DEG = 12.0  # a refinement moving a candidate further than this is not trusted
_SAME_DEG = 5.0  # two group elements closer than this are one
_MAX_GROUP = 120
_SNAP_DEG = 8.0  # axes this close to perpendicular are made perpendicular
_N_MOMENT_DIRS = 600  # directions sampled for the 4th-moment axes of an isotropic spread ...
_MOMENT_QUERY = 500  # ... with this many samples
_MIN_POINTS = 10


def axis_angle_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation by `angle` (rad) about the unit vector `axis`."""
    axis = np.asarray(axis, dtype=np.float64)
    return exp_so3(axis / np.linalg.norm(axis) * angle)


def symmetries_from_info(info: Mapping[str, Any] | None, cont_step_deg: float = DEFAULT_CONT_STEP_DEG) -> list[Pose]:
    """Symmetry transformations (model frame, metres) of a BOP models_info entry (mm).

    As bop_toolkit's get_symmetry_transformations: the discrete ones (identity first) each
    combined with every sample of the continuous ones, which are sampled every cont_step_deg.
    """
    disc = [Pose.identity()]
    cont: list[Pose] = []
    if info:
        for sym in info.get("symmetries_discrete", []) or []:
            T = np.asarray(sym, dtype=np.float64).reshape(4, 4)
            disc.append(Pose(T[:3, :3], T[:3, 3] * MM))
        steps = max(1, int(round(360.0 / cont_step_deg)))
        for sym in info.get("symmetries_continuous", []) or []:
            axis = np.asarray(sym["axis"], dtype=np.float64)
            offset = np.asarray(sym["offset"], dtype=np.float64) * MM
            for i in range(steps):  # i = 0 is the identity, kept so discrete ones survive alone
                R = axis_angle_matrix(axis, 2.0 * np.pi * i / steps)
                cont.append(Pose(R, offset - R @ offset))
    if not cont:
        return disc
    return [c.compose(d) for d in disc for c in cont]


# --------------------------------------------------------------------------- derived symmetries


def _reduced(k: int, n: int) -> tuple[int, int]:
    g = math.gcd(k, n)
    return k // g, n // g


# the turns k/n (reduced) with n <= MAX_FOLD: all n-fold symmetries up to MAX_FOLD are made of them
_FRACTIONS = sorted({_reduced(k, n) for n in range(2, MAX_FOLD + 1) for k in range(1, n)})


def _rotation_about(axis: np.ndarray, angle: float, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of the rotation by `angle` (rad) about the line through `centre` (m) along `axis`."""
    R = axis_angle_matrix(axis, angle)
    return R, centre - R @ centre


def _subsample(n: int, m: int) -> np.ndarray:
    """m indices spread evenly over range(n) (all of them when n <= m): deterministic."""
    if n <= m:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, m).round().astype(np.int64))


def _fibonacci_sphere(n: int) -> np.ndarray:
    """n unit vectors (n, 3) spread evenly over the sphere."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


class _Surface:
    """Surface samples (P, 3) in a KD-tree, with a plane fitted around each (its normal and the
    radius of the patch it was fitted on), to measure how far transformed samples lie from the
    surface without the noise of the sampling itself (two samplings of one surface are a sample
    spacing apart point to point, ~2-3 % of the diameter for 3,000 samples)."""

    def __init__(self, points: np.ndarray) -> None:
        self.points = points
        self.tree = cKDTree(points)
        k = min(_NEIGHBOURS, len(points))
        d, idx = self.tree.query(points, k=k)
        nb = points[idx] - points[idx].mean(axis=1, keepdims=True)
        _, vecs = np.linalg.eigh(np.einsum("pki,pkj->pij", nb, nb))
        self.normals = vecs[:, :, 0]  # the direction of least spread: the local normal
        self.radius = d[:, -1]

    def distances(self, q: np.ndarray) -> np.ndarray:
        """Distance (m) of each point of q (N, 3) to the surface: to the tangent plane of its
        nearest sample, plus what lies beyond that sample's patch sideways; never more than the
        distance to the nearest sample itself."""
        d, j = self.tree.query(q)
        diff = q - self.points[j]
        d_plane = np.abs(np.einsum("ni,ni->n", diff, self.normals[j]))
        lateral = np.sqrt(np.maximum(d * d - d_plane * d_plane, 0.0))
        return np.minimum(d, np.hypot(d_plane, np.maximum(lateral - self.radius[j], 0.0)))

    def error(self, R: np.ndarray, t: np.ndarray, sel: np.ndarray, limit: float = math.inf,
              two_way: bool = True) -> float:
        """SYM_PERCENTILE-th percentile (m) of the distances to the surface of the samples `sel`
        moved by (R, t) and (two_way) of those moved by its inverse: the larger of the two, the
        symmetric distance between the surface and its image. Half turns are their own inverse
        (one way is enough); past `limit` one way, the other is not measured."""
        p = self.points[sel]
        err = float(np.percentile(self.distances(p @ R.T + t), SYM_PERCENTILE))
        if not two_way or err > limit or np.abs(R @ R - np.eye(3)).max() < 1e-9:
            return err
        return max(err, float(np.percentile(self.distances((p - t) @ R), SYM_PERCENTILE)))

    def errors(self, Rs: np.ndarray, ts: np.ndarray, sel: np.ndarray) -> np.ndarray:
        """One-way `error` of each of the transformations (Rs (K, 3, 3), ts (K, 3)) at once: (K,) m."""
        p = self.points[sel]
        q = np.einsum("kij,nj->kni", Rs, p) + ts[:, None, :]
        d = self.distances(q.reshape(-1, 3)).reshape(len(Rs), len(p))
        return np.percentile(d, SYM_PERCENTILE, axis=1)

    def refine(self, R: np.ndarray, t: np.ndarray, sel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(R, t) refined by a few point-to-plane ICP iterations of the samples `sel` against the
        surface (the 10 % farthest pairs left out, a little damping: directions the surface
        leaves free, such as the turn of a cylinder about its axis, stay put); unchanged if it
        moved too far."""
        p = self.points[sel]
        R1, t1 = R, t
        for _ in range(_ICP_ITERS):
            q = p @ R1.T + t1
            d, j = self.tree.query(q)
            keep = d <= np.percentile(d, 90.0)
            q, n = q[keep], self.normals[j[keep]]
            r = np.einsum("ni,ni->n", q - self.points[j[keep]], n)
            J = np.concatenate([np.cross(q, n), n], axis=1)  # d r / d (rotation vector, shift)
            A = J.T @ J
            x = np.linalg.solve(A + 1e-6 * np.trace(A) * np.eye(6), -J.T @ r)
            dR = exp_so3(x[:3])
            R1, t1 = dR @ R1, dR @ t1 + x[3:]
            if np.linalg.norm(x[:3]) < 1e-4:  # converged (a sample spacing turns ~1e-2 rad)
                break
        if math.degrees(rotation_angle(R, R1)) > _MAX_REFINE_DEG:
            return R, t
        return R1, t1


def _moment_axes(q: np.ndarray, max_axes: int = 7) -> list[np.ndarray]:
    """Candidate rotation axes of a shape with isotropic covariance (centred samples q (N, 3)):
    the local extremes over the sphere of the 4th directional moment mean((q . u)^4), found on
    a grid of directions and refined by a local search down to ~0.1 degree. Any rotation axis
    of a shape is a critical point of every function of direction its symmetries leave
    unchanged, and the 4-fold and 3-fold axes of a cube are extremes of this one."""

    def moment(dirs: np.ndarray) -> np.ndarray:
        proj = q @ dirs.T
        proj *= proj
        return np.mean(proj * proj, axis=0)

    dirs = _fibonacci_sphere(_N_MOMENT_DIRS)
    f = moment(dirs)
    _, nb = cKDTree(dirs).query(dirs, k=7)
    is_max = np.all(f[:, None] >= f[nb[:, 1:]], axis=1)
    is_min = np.all(f[:, None] <= f[nb[:, 1:]], axis=1)
    cand = np.flatnonzero(is_max | is_min)
    cand = cand[np.argsort(-np.abs(f[cand] - f.mean()), kind="stable")]
    ring = np.array([[math.cos(a), math.sin(a)] for a in np.radians(np.arange(0.0, 360.0, 45.0))])
    axes: list[np.ndarray] = []
    same = math.cos(math.radians(10.0))
    for i in cand:
        u, sign = dirs[i], (1.0 if is_max[i] else -1.0)
        if any(abs(float(u @ a)) > same for a in axes):
            continue
        step, moved = math.radians(4.0), True
        while step > math.radians(0.2):  # compass search on the sphere
            if moved:
                e1 = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
                e1 /= np.linalg.norm(e1)
                e2 = np.cross(u, e1)
            around = u + step * (ring[:, :1] * e1 + ring[:, 1:] * e2)
            around /= np.linalg.norm(around, axis=1, keepdims=True)
            vals = sign * moment(np.vstack([u, around]))
            best = int(np.argmax(vals))
            moved = best > 0
            if moved:
                u = around[best - 1]
            else:
                step /= 2.0
        if all(abs(float(u @ a)) < same for a in axes):
            axes.append(u)
            if len(axes) >= max_axes:
                break
    return axes


def _axis_and_centre(R: np.ndarray, t: np.ndarray, near: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit axis of the rotation R and the point of its line (R x + t = x) nearest `near`."""
    w = log_so3(R)
    axis = w / max(np.linalg.norm(w), 1e-12)
    M = np.eye(3) - R
    return axis, near + np.linalg.pinv(M, rcond=1e-6) @ (t - M @ near)


def derive_symmetries(
    points: np.ndarray,
    diameter: float,
    tolerance: float = DEFAULT_SYM_TOLERANCE,
    cont_step_deg: float = DEFAULT_CONT_STEP_DEG,
) -> list[Pose]:
    """The rigid transformations (model frame, metres, identity first; the format of
    `symmetries_from_info`) under which the surface maps onto itself within tolerance x diameter.

    points: (P, 3) surface samples in metres, spread uniformly over the area (`ObjectModel.points`);
    diameter: metres; tolerance: share of the diameter the SYM_PERCENTILE-th percentile of the
    symmetric (both ways) distance between the surface and its image may reach.

    Candidates are rotations about axes through the centroid of the samples: about each
    principal axis, the half turn; about a principal axis whose two other spreads are (near)
    equal, the 1/n turns for n = 2..MAX_FOLD (all passing: a continuous symmetry, sampled every
    cont_step_deg) and the half turns about the axes of that plane (searched every
    _FLIP_SEARCH_DEG); with three equal spreads, the 1/n turns about the extremes of the 4th
    directional moment too (a cube's axes). A candidate is screened on a few samples, refined by
    ICP, and its axis kept when the refined transformation passes the distance test. The
    symmetries returned are exact turns about those axes (snapped perpendicular when nearly so)
    through one common centre, closed into a group; each is checked once more. The distance to
    the surface is point to local plane (`_Surface`): the spacing of the samples does not count.
    Deterministic; 10-60 ms for 3,000 samples (a cube, 24 rotations about 7 axes: ~80 ms).

    The default tolerance, 2.5 % of the diameter at the 95th percentile, is the one at which
    every mesh at hand gets what it should, for 6 samplings each: the half turns of the nearly
    symmetric YCB-Video gelatin box (8; its half turns measure 0.6-0.9 %) and foam brick (21;
    1.0-1.2 %, with the quarter turns of its 52.3 x 51.0 mm section), nothing for the mug (14)
    nor the asymmetric LM-O parts (the can's best false half turn: 4.0-5.0 %), the half turns
    LM-O declares for the eggbox (10) and the glue (11) (1.5-1.8 %; 2 % misses one sampling of
    the eggbox), and the declared symmetries of the six procedural parts (datasets/parts.py; at
    3 % the flange's six bolt holes, under 5 % of its surface, stop counting: continuous).
    Features under ~5 % of the surface are invisible to the 95th percentile at any tolerance.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    identity = [Pose.identity()]
    if len(pts) < _MIN_POINTS or not (math.isfinite(diameter) and diameter > 0.0) or not np.all(np.isfinite(pts)):
        return identity
    tol = float(tolerance) * float(diameter)
    surf = _Surface(pts)
    full, screen = _subsample(len(pts), _MAX_QUERY), _subsample(len(pts), _SCREEN_QUERY)
    icp = _subsample(len(pts), _ICP_QUERY)
    c = pts.mean(axis=0)
    lam, vecs = np.linalg.eigh(np.cov((pts - c).T, bias=True))
    sigma = np.sqrt(np.maximum(lam, 0.0))
    gate = _GATE_FACTOR * tol
    screen_limit = tol + _SCREEN_MARGIN * diameter

    def turn_errors(axis: np.ndarray, point: np.ndarray, angles: list[float], sel: np.ndarray) -> np.ndarray:
        """One-way errors (m) of the turns by `angles` about the line through `point` along `axis`."""
        turns = [_rotation_about(axis, angle, point) for angle in angles]
        return surf.errors(np.array([R for R, _ in turns]), np.array([t for _, t in turns]), sel)

    def refined_axis(axis: np.ndarray, angle: float) -> tuple[np.ndarray, np.ndarray]:
        """(axis, point on it) of the turn about `axis` through c refined by ICP."""
        a, p = _axis_and_centre(*surf.refine(*_rotation_about(axis, angle, c), icp), c)
        return (a if float(a @ axis) >= 0.0 else -a), p

    def half_turn(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """The refined axis (and a point on it) of the half turn about `axis`, if a symmetry."""
        if turn_errors(axis, c, [math.pi], screen)[0] > screen_limit:
            return None
        a, p = refined_axis(axis, math.pi)
        return (a, p) if turn_errors(a, p, [math.pi], full)[0] <= tol else None

    def axis_order(axis: np.ndarray) -> tuple[int, tuple[np.ndarray, np.ndarray] | None]:
        """(n, refined axis and a point on it): the largest n <= MAX_FOLD with every k/n turn
        about `axis` a symmetry, n = 0 when every n passes (continuous), 1 when none. The axis
        is refined on the best screened 1/n turn (ICP may slide about the axis, not off it),
        then the turns are tested about it (k/n and (n-k)/n: both ways)."""
        ns = np.arange(2, MAX_FOLD + 1)
        errs = turn_errors(axis, c, list(2.0 * np.pi / ns), screen)
        if not np.any(errs <= screen_limit):
            return 1, None
        a, p = refined_axis(axis, 2.0 * math.pi / int(ns[np.argmin(errs)]))
        # all k/n turns on the screening samples (with slack for their noise), then the turns
        # of the orders passing there on the acceptance samples
        rough = turn_errors(a, p, [2.0 * math.pi * k / n for k, n in _FRACTIONS], screen)
        ok = dict(zip(_FRACTIONS, rough <= _ROUGH_SLACK * tol))
        orders = [int(n) for n in ns if all(ok[_reduced(k, int(n))] for k in range(1, int(n)))]
        if len(orders) == len(ns):  # continuous, if the 1/n turns pass both ways on all samples
            angles = [2.0 * math.pi / n for n in ns]
            if np.all(turn_errors(a, p, angles + [-x for x in angles], full) <= tol):
                return 0, (a, p)
            orders = orders[:-1]
        needed = sorted({_reduced(k, n) for n in orders for k in range(1, n)})
        if not needed:
            return 1, None
        err = dict(zip(needed, turn_errors(a, p, [2.0 * math.pi * k / n for k, n in needed], full)))
        worst = {n: max(err[_reduced(k, n)] for k in range(1, n)) for n in orders}
        passing = [n for n in orders if worst[n] <= tol]
        if not passing:
            return 1, None
        # of a nearly round part, many orders pass: the largest one about as good as the best
        best = min(worst[n] for n in passing)
        return max(n for n in passing if worst[n] <= best + _ORDER_SLACK * tol), (a, p)

    records: list[tuple[np.ndarray, np.ndarray, int]] = []  # (unit axis, point on it, order; 0: continuous)
    isotropic = sigma[2] - sigma[0] <= gate
    axes = [vecs[:, k] for k in range(3)]
    if isotropic:  # the principal axes are arbitrary: the moment's extremes too
        axes += _moment_axes(pts[_subsample(len(pts), _MOMENT_QUERY)] - c)
    for k, axis in enumerate(axes):
        others = [i for i in range(3) if i != k]
        if any(n == 0 for _, _, n in records):
            break  # continuous about an axis: any other turn is a half turn across it (below)
        if k >= 3 and _axis_in_group(axis, [(a, n) for a, _, n in records]):
            continue  # a moment axis the symmetries found so far already turn about (a cube's)
        if isotropic or abs(sigma[others[0]] - sigma[others[1]]) <= gate:
            n, r = axis_order(axis)
            if r is not None:
                records.append((r[0], r[1], n))
            if isotropic or n == 0:
                continue
            # half turns about the axes of the plane of equal spreads: its principal axes and
            # the best of a search (the plane's principal axes are ill-defined)
            u, v = vecs[:, others[0]], vecs[:, others[1]]
            phis = np.radians(np.arange(0.0, 180.0, _FLIP_SEARCH_DEG))
            flips = [_rotation_about(math.cos(p) * u + math.sin(p) * v, math.pi, c) for p in phis]
            errs = surf.errors(np.array([R for R, _ in flips]), np.array([t for _, t in flips]), screen)
            for p in dict.fromkeys([0.0, math.pi / 2.0, float(phis[int(np.argmin(errs))])]):
                r = half_turn(math.cos(p) * u + math.sin(p) * v)
                if r is not None:
                    records.append((r[0], r[1], 2))
        else:  # a principal axis of its own: the half turn only
            r = half_turn(axis)
            if r is not None:
                records.append((r[0], r[1], 2))
    if not records:
        return identity
    records = _snap_axes(records)
    for a, _, n in records[:1]:  # a continuous axis (first after sorting) without a half turn across it
        if n == 0 and not any(m % 2 == 0 and abs(float(a @ b)) < 0.1 for b, _, m in records[1:]):
            r = half_turn(np.cross(a, vecs[:, int(np.argmin(np.abs(vecs.T @ a)))]))
            if r is not None:
                records = _snap_axes(records + [(r[0], r[1], 2)])
    centre = _nearest_point_to_lines([(a, p) for a, p, _ in records], c)
    for a, _, n in records:
        if n == 0:  # continuous: its samples times one half turn across it, if any
            cont = [Pose(*_rotation_about(a, 2.0 * math.pi * i / steps, centre))
                    for steps in [max(1, int(round(360.0 / cont_step_deg)))] for i in range(steps)]
            flips = [Pose(*_rotation_about(b, math.pi, centre)) for b, _, m in records
                     if m != 0 and m % 2 == 0 and abs(float(a @ b)) < 1e-6]
            flips = [f for f in flips[:1] if surf.error(f.R, f.t, full, tol) <= tol]
            return [cr.compose(d) for d in identity + flips for cr in cont]
    gens = [_rotation_about(a, 2.0 * math.pi / n, centre) for a, _, n in records]
    return _close_group(gens, surf, full, tol)


def _axis_in_group(axis: np.ndarray, turns: list[tuple[np.ndarray, int]]) -> bool:
    """Whether a rotation of the group generated by the 1/n turns about the axes (unit axis,
    n; n = 0 continuous, left out) turns about `axis`."""
    gens = [axis_angle_matrix(a, 2.0 * math.pi / n) for a, n in turns if n >= 2]
    if not gens:
        return False
    cos_same = 1.0 + 2.0 * math.cos(math.radians(_SAME_DEG))
    group = [np.eye(3)]
    i = 0
    while i < len(group) <= _MAX_GROUP:
        for G in gens:
            R = G @ group[i]
            if not np.any(np.einsum("eij,ij->e", np.array(group), R) > cos_same):
                group.append(R)
        i += 1
    for R in group[1:]:
        w = log_so3(R)
        if abs(float(w @ axis)) > math.cos(math.radians(_SAME_DEG)) * np.linalg.norm(w):
            return True
    return False


def _snap_axes(records: list[tuple[np.ndarray, np.ndarray, int]]) -> list[tuple[np.ndarray, np.ndarray, int]]:
    """The axis records, continuous and higher orders first, with repeats of one axis merged
    (the higher order kept) and axes within _SNAP_DEG of perpendicular to an earlier one made
    exactly perpendicular (Gram-Schmidt): so the turns about them close into a group."""
    order = sorted(range(len(records)), key=lambda i: (records[i][2] != 0, -records[i][2], i))
    kept: list[tuple[np.ndarray, np.ndarray, int]] = []
    for i in order:
        a, p, n = records[i]
        if any(abs(float(a @ b)) > math.cos(math.radians(_SNAP_DEG)) for b, _, _ in kept):
            continue
        for b, _, _ in kept:
            if abs(float(a @ b)) < math.sin(math.radians(_SNAP_DEG)):
                a = a - float(a @ b) * b
                a = a / np.linalg.norm(a)
        kept.append((a, p, n))
    return kept


def _nearest_point_to_lines(lines: list[tuple[np.ndarray, np.ndarray]], near: np.ndarray) -> np.ndarray:
    """The point (3,) nearest (least squares) to the lines (unit direction, point), the
    components they leave free taken from `near`."""
    A = 1e-6 * np.eye(3)
    b = 1e-6 * near
    for a, p in lines:
        M = np.eye(3) - np.outer(a, a)
        A, b = A + M, b + M @ p
    return np.linalg.solve(A, b)


def _close_group(gens: list[tuple[np.ndarray, np.ndarray]], surf: _Surface, sel: np.ndarray,
                 tol: float) -> list[Pose]:
    """The group generated by the turns `gens` ((R, t) each), identity first, then in the order
    found; elements within _SAME_DEG of one found before are one. Generators are taken in turn:
    one whose products with the group so far do not all pass the distance test is left out
    (so the result stays a group), as is one already in it."""
    elems = [(np.eye(3), np.zeros(3))]
    cos_same = 1.0 + 2.0 * math.cos(math.radians(_SAME_DEG))  # trace(E^T R) = 1 + 2 cos(angle)

    def known(group: list[tuple[np.ndarray, np.ndarray]], R: np.ndarray) -> bool:
        return bool(np.any(np.einsum("eij,ij->e", np.array([E for E, _ in group]), R) > cos_same))

    used: list[tuple[np.ndarray, np.ndarray]] = []
    for R, t in gens:
        if known(elems, R):
            continue
        group, new = list(elems), [(R, t)]
        group.append((R, t))
        i = 0
        while i < len(group) <= _MAX_GROUP:
            Ra, ta = group[i]
            for Rg, tg in used + [(R, t)]:
                Rn = Rg @ Ra
                if not known(group, Rn):
                    group.append((Rn, Rg @ ta + tg))
                    new.append(group[-1])
            i += 1
        # one way each: the group holds the inverse of each element, checked the same way
        if len(group) <= _MAX_GROUP and all(surf.error(Rn, tn, sel, tol, False) <= tol for Rn, tn in new):
            elems, used = group, used + [(R, t)]
    return [Pose(R, t) for R, t in elems]


def declared_or_derived_symmetries(model: SurfaceModel, tolerance: float = DEFAULT_SYM_TOLERANCE,
                                   cont_step_deg: float = DEFAULT_CONT_STEP_DEG) -> list[Pose]:
    """The symmetries a model declares (models_info, `model.symmetries`) when it declares any,
    else those derived from its surface samples (`derive_symmetries`; model frame, metres,
    identity first). `model`: a core.models.ObjectModel (or anything with its points (P, 3) m,
    diameter m and symmetries)."""
    if len(model.symmetries) > 1:
        return list(model.symmetries)
    return derive_symmetries(model.points, model.diameter, tolerance, cont_step_deg)


__all__ = ["axis_angle_matrix", "symmetries_from_info", "derive_symmetries", "declared_or_derived_symmetries",
           "DEFAULT_CONT_STEP_DEG", "DEFAULT_SYM_TOLERANCE"]
