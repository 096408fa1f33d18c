"""Stable resting orientations of a rigid body on a floor, with their probabilities: how the
synthetic generator (synthetic.py) drops its objects into a bin or onto a table.

A different computation from vision/resting_poses.py's, which hypothesises poses of an observed
part: that one takes the centroid of the surface samples as the centre of mass, groups hull
facets by their normal to within degrees and keeps the largest faces the symmetries do not make
alike; this one takes the solid's centre of mass, groups exactly coplanar facets, drops rests
that tip over within a few degrees and weights each rest by its solid angle (the quasi-static
drop heuristic).
"""
from __future__ import annotations

import math

import numpy as np

from ..core.geometry import rotation_to

DOWN = np.array([0.0, 0.0, -1.0])


def _down_rotation(n: np.ndarray) -> np.ndarray:
    """The smallest rotation turning direction `n` to point down (-z)."""
    return rotation_to(n / np.linalg.norm(n), DOWN)


def _center_of_mass(vertices: np.ndarray, faces: np.ndarray, hull_pts: np.ndarray) -> np.ndarray:
    """Solid centroid of a closed mesh; the hull's centroid when the mesh is not a solid."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    vol6 = np.einsum("ij,ij->i", a, np.cross(b, c))
    V = vol6.sum()
    ext = np.ptp(vertices, axis=0).max()
    if V > 1e-3 * ext ** 3:
        return ((a + b + c) * vol6[:, None]).sum(0) / (4.0 * V)
    from scipy.spatial import ConvexHull

    h = ConvexHull(hull_pts)
    o = hull_pts.mean(0)
    tri = hull_pts[h.simplices]
    v6 = np.einsum("ij,ij->i", tri[:, 0] - o, np.cross(tri[:, 1] - o, tri[:, 2] - o))
    cen = (tri[:, 0] + tri[:, 1] + tri[:, 2] + o) / 4.0  # centroids of the tetrahedra (o, a, b, c)
    return (cen * np.abs(v6)[:, None]).sum(0) / np.abs(v6).sum()


def stable_poses(
    vertices: np.ndarray, faces: np.ndarray, min_prob: float = 1e-3, min_tip_deg: float = 8.0,
) -> tuple[list[np.ndarray], np.ndarray]:
    """Stable resting orientations of a rigid body on a floor (z up): rotations R (model to
    world, before yaw) that put a convex-hull face down with the centre of mass above it, and
    their probabilities (solid angle of the face seen from the centre of mass, renormalised
    over the stable faces; faces below `min_prob` dropped).

    Marginal rests are dropped: the body must tip by at least `min_tip_deg` before its centre
    of mass passes over the edge of its support (the hull points within 2 % of its size of the
    floor, so a tessellated disc does not stand on its rim like a coin)."""
    from scipy.spatial import ConvexHull

    V = np.asarray(vertices, dtype=np.float64)
    hull = ConvexHull(V)
    com = _center_of_mass(V, np.asarray(faces), V[hull.vertices])
    tri = V[hull.simplices]
    a, b, c = tri[:, 0] - com, tri[:, 1] - com, tri[:, 2] - com
    la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
    num = np.abs(np.einsum("ij,ij->i", a, np.cross(b, c)))
    den = (la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", a, c) * lb
           + np.einsum("ij,ij->i", b, c) * la)
    omega = 2.0 * np.arctan2(num, den)  # solid angle of each hull triangle (Van Oosterom)
    eq = hull.equations
    scale = float(np.ptp(V, axis=0).max())
    # Coplanar hull triangles (one facet) share their plane: group by the rounded plane.
    key = np.round(np.column_stack([eq[:, :3] * 1e6, eq[:, 3:] / scale * 1e6])).astype(np.int64)
    first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)[1:]
    inv = inv.reshape(-1)
    # Is the projection of the centre of mass onto the triangle's plane inside the triangle?
    n = eq[:, :3]
    q = com - (np.einsum("ij,j->i", n, com) + eq[:, 3])[:, None] * n  # projection
    e0, e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 1], tri[:, 0] - tri[:, 2]
    s0 = np.einsum("ij,ij->i", np.cross(e0, q - tri[:, 0]), n)
    s1 = np.einsum("ij,ij->i", np.cross(e1, q - tri[:, 1]), n)
    s2 = np.einsum("ij,ij->i", np.cross(e2, q - tri[:, 2]), n)
    tol = -1e-9 * scale * scale
    inside = ((s0 >= tol) & (s1 >= tol) & (s2 >= tol)) | ((s0 <= -tol) & (s1 <= -tol) & (s2 <= -tol))
    ng = len(first)
    g_omega = np.bincount(inv, weights=omega, minlength=ng)
    g_stable = np.bincount(inv, weights=inside.astype(float), minlength=ng) > 0
    idx = np.flatnonzero(g_stable)
    tip = np.array([_tip_angle(V[hull.vertices], eq[first[g]], com, 0.02 * scale) for g in idx])
    if idx.size and (tip >= math.radians(min_tip_deg)).any():
        idx = idx[tip >= math.radians(min_tip_deg)]
    elif idx.size:
        idx = idx[[int(np.argmax(tip))]]
    if idx.size == 0:  # numerically unstable body: rest on the facet with the largest solid angle
        idx = np.array([int(np.argmax(g_omega))])
    probs = g_omega[idx] / g_omega[idx].sum()
    keep = probs >= min_prob
    if not keep.any():
        keep = probs == probs.max()
    idx, probs = idx[keep], probs[keep] / probs[keep].sum()
    rots = [_down_rotation(n[first[g]]) for g in idx]
    return rots, probs


def _tip_angle(hull_pts: np.ndarray, plane: np.ndarray, com: np.ndarray, eps: float) -> float:
    """Angle (rad) a body resting on `plane` (outward normal, offset) must tip before its
    centre of mass leaves the support polygon (hull points within eps of the plane)."""
    from scipy.spatial import ConvexHull, QhullError

    n, d = plane[:3], plane[3]
    heights = hull_pts @ n + d  # <= 0 inside
    sup = hull_pts[heights > -eps]
    R0 = _down_rotation(n)
    p2 = (sup @ R0.T)[:, :2]
    c2 = (com @ R0.T)[:2]
    h = float(-(com @ n + d))
    try:
        ch = ConvexHull(p2)
    except (QhullError, ValueError):
        return 0.0
    margin = float(-(ch.equations[:, :2] @ c2 + ch.equations[:, 2]).max())  # > 0 inside
    return math.atan2(margin, max(h, 1e-12))


__all__ = ["stable_poses"]
