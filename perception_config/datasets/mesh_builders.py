"""Building blocks of the procedural parts' meshes (datasets/parts.py), in millimetres:

- 2D loops (circles, filleted polygons, slots), stored counter-clockwise;
- layered extrusions (`Prism`): planar caps bounded by shared loops, triangulated by a conforming
  Delaunay triangulation (scipy) refined jointly until every loop segment is a triangle edge,
  and vertical walls along the loops, so caps and walls meet edge to edge (watertight by
  construction);
- sweeps (`sweep`) of a 2D profile through a family of rings (`lathe_ring`: circles about z).
"""
from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np

from ..core.mesh import signed_volume


def ccw(loop: np.ndarray) -> np.ndarray:
    loop = np.asarray(loop, dtype=np.float64)
    x, y = loop[:, 0], loop[:, 1]
    area = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
    return loop if area > 0 else loop[::-1].copy()


def circle(r: float, n: int, center=(0.0, 0.0), phase: float = 0.0) -> np.ndarray:
    a = phase + 2.0 * np.pi * np.arange(n) / n
    return np.stack([center[0] + r * np.cos(a), center[1] + r * np.sin(a)], axis=1)


def rounded_polygon(corners: Sequence[Sequence[float]], radii: Sequence[float], seg: int = 6) -> np.ndarray:
    """A convex-cornered CCW polygon with each corner filleted by its radius (0 = sharp)."""
    P = ccw(np.asarray(corners, dtype=np.float64))
    out = []
    n = len(P)
    for i in range(n):
        r = radii[i]
        p, a, b = P[i], P[i - 1], P[(i + 1) % n]
        if r <= 0:
            out.append(p)
            continue
        u = (a - p) / np.linalg.norm(a - p)
        w = (b - p) / np.linalg.norm(b - p)
        half = math.acos(np.clip(np.dot(u, w), -1, 1)) / 2.0
        d = r / math.tan(half)
        bis = (u + w) / np.linalg.norm(u + w)
        c = p + bis * (r / math.sin(half))
        t0, t1 = p + u * d, p + w * d
        a0 = math.atan2(*(t0 - c)[::-1])
        a1 = math.atan2(*(t1 - c)[::-1])
        da = (a1 - a0 + np.pi) % (2 * np.pi) - np.pi
        for k in range(seg + 1):
            ang = a0 + da * k / seg
            out.append(c + r * np.array([math.cos(ang), math.sin(ang)]))
    return ccw(np.array(out))


def stadium(cx: float, cy: float, half_len: float, r: float, seg: int = 10) -> np.ndarray:
    """A slot: two half circles of radius r joined by straight sides along x."""
    a1 = np.linspace(-np.pi / 2, np.pi / 2, seg + 1)
    a2 = np.linspace(np.pi / 2, 3 * np.pi / 2, seg + 1)
    right = np.stack([cx + half_len + r * np.cos(a1), cy + r * np.sin(a1)], axis=1)
    left = np.stack([cx - half_len + r * np.cos(a2), cy + r * np.sin(a2)], axis=1)
    return ccw(np.concatenate([right, left]))


def _inside(pts: np.ndarray, loop: np.ndarray) -> np.ndarray:
    """Even-odd point-in-polygon test of (P, 2) points against a loop."""
    x, y = pts[:, 0:1], pts[:, 1:2]
    x0, y0 = loop[:, 0][None], loop[:, 1][None]
    x1, y1 = np.roll(loop[:, 0], -1)[None], np.roll(loop[:, 1], -1)[None]
    cond = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xint = x0 + (y - y0) * (x1 - x0) / np.where(y1 != y0, y1 - y0, 1.0)
    return (np.sum(cond & (x < xint), axis=1) % 2) == 1


def split_loop_at_x(loop: np.ndarray, xs: Sequence[float]) -> np.ndarray:
    """Insert a vertex wherever a loop segment crosses one of the vertical lines x = xs."""
    out = []
    n = len(loop)
    for i in range(n):
        p, q = loop[i], loop[(i + 1) % n]
        out.append(p)
        cuts = [(x - p[0]) / (q[0] - p[0]) for x in xs if q[0] != p[0] and min(p[0], q[0]) < x < max(p[0], q[0])]
        for t in sorted(cuts):
            out.append(p + t * (q - p))
    return np.array(out)


def _triangulate_regions(
    loops: list[np.ndarray], regions: list[tuple[int, list[int]]], steiner: dict[int, np.ndarray] | None = None,
    max_iter: int = 30,
) -> tuple[list[np.ndarray], list[tuple[np.ndarray, np.ndarray]]]:
    """Conforming Delaunay triangulation of planar regions bounded by shared loops.

    regions: (outer loop index, [hole loop indices]). Loops are refined (midpoints inserted) until
    every loop segment is an edge of every region that uses it. Returns the refined loops and per
    region (points (P, 2), triangles (T, 3) counter-clockwise), points listed loop by loop first.
    """
    from scipy.spatial import Delaunay

    loops = [np.asarray(lp, dtype=np.float64) for lp in loops]
    steiner = steiner or {}
    for _ in range(max_iter):
        missing: dict[int, set[int]] = {}
        results = []
        for r, (oi, holes) in enumerate(regions):
            ids = [oi] + list(holes)
            pts = [loops[i] for i in ids]
            offs = np.cumsum([0] + [len(p) for p in pts])
            boundary = np.concatenate(pts)
            extra = np.zeros((0, 2))
            if r in steiner and len(steiner[r]):
                s = np.asarray(steiner[r], dtype=np.float64)
                ok = _inside(s, loops[oi])
                for h in holes:
                    ok &= ~_inside(s, loops[h])
                extra = s[ok]
            lo, hi = boundary.min(0), boundary.max(0)
            span = (hi - lo).max()
            frame = np.array([[lo[0] - span, lo[1] - span], [hi[0] + span, lo[1] - span],
                              [hi[0] + span, hi[1] + span], [lo[0] - span, hi[1] + span]])
            allp = np.concatenate([boundary, extra, frame])
            tri = Delaunay(allp)
            if len(tri.coplanar):
                raise RuntimeError("triangulation dropped coincident points")
            simp = tri.simplices
            nreal = len(boundary) + len(extra)
            simp = simp[np.all(simp < nreal, axis=1)]
            edges = set()
            for a, b in ((0, 1), (1, 2), (2, 0)):
                e = np.sort(simp[:, [a, b]], axis=1)
                edges.update(map(tuple, e.tolist()))
            for k, li in enumerate(ids):
                n = len(loops[li])
                for j in range(n):
                    e = tuple(sorted((int(offs[k] + j), int(offs[k] + (j + 1) % n))))
                    if e not in edges:
                        missing.setdefault(li, set()).add(j)
            cen = allp[simp].mean(axis=1)
            keep = _inside(cen, loops[oi])
            for h in holes:
                keep &= ~_inside(cen, loops[h])
            simp = simp[keep]
            p = allp[simp]
            cross = ((p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1])
                     - (p[:, 1, 1] - p[:, 0, 1]) * (p[:, 2, 0] - p[:, 0, 0]))
            simp = np.where((cross < 0)[:, None], simp[:, [0, 2, 1]], simp)
            results.append((allp[:nreal], simp))
        if not missing:
            return loops, results
        for li, segs in missing.items():
            lp, out = loops[li], []
            for j in range(len(lp)):
                out.append(lp[j])
                if j in segs:
                    out.append(0.5 * (lp[j] + lp[(j + 1) % len(lp)]))
            loops[li] = np.array(out)
    raise RuntimeError("conforming triangulation did not converge")


class Prism:
    """Layered extrusion: planar caps at given heights bounded by shared 2D loops, and
    vertical walls between two heights along a loop. Loops are stored counter-clockwise."""

    def __init__(self) -> None:
        self.loops: list[np.ndarray] = []
        self.caps: list[tuple[float, int, list[int], bool]] = []
        self.walls: list[tuple[int, float, float, bool]] = []
        self.steiner: dict[int, np.ndarray] = {}

    def loop(self, pts: np.ndarray) -> int:
        self.loops.append(ccw(pts))
        return len(self.loops) - 1

    def cap(self, z: float, outer: int, holes: Sequence[int] = (), up: bool = True, steiner=None) -> None:
        if steiner is not None:
            self.steiner[len(self.caps)] = np.asarray(steiner)
        self.caps.append((z, outer, list(holes), up))

    def wall(self, loop: int, z0: float, z1: float, outward: bool = True) -> None:
        """outward=True: the material is inside the loop (an outer wall); False: a hole's wall."""
        self.walls.append((loop, z0, z1, outward))

    def build(self) -> tuple[np.ndarray, np.ndarray]:
        loops, tris = _triangulate_regions(self.loops, [(o, h) for _, o, h, _ in self.caps], self.steiner)
        V: list[np.ndarray] = []
        F: list[np.ndarray] = []
        nv = 0
        for (z, _, _, up), (p2, t) in zip(self.caps, tris):
            V.append(np.column_stack([p2, np.full(len(p2), z)]))
            F.append((t if up else t[:, [0, 2, 1]]) + nv)
            nv += len(p2)
        for li, z0, z1, outward in self.walls:
            lp = loops[li]
            n = len(lp)
            V.append(np.column_stack([lp, np.full(n, z0)]))
            V.append(np.column_stack([lp, np.full(n, z1)]))
            i = np.arange(n)
            j = (i + 1) % n
            b0, b1, t0, t1 = nv + i, nv + j, nv + n + i, nv + n + j
            f = np.concatenate([np.stack([b0, b1, t1], 1), np.stack([b0, t1, t0], 1)])
            F.append(f if outward else f[:, [0, 2, 1]])
            nv += 2 * n
        return _weld(np.concatenate(V), np.concatenate(F))


def _weld(V: np.ndarray, F: np.ndarray, decimals: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices with identical coordinates (the builders produce them bit-identically)."""
    key = np.round(V, decimals)
    uniq, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # keep first-seen order: deterministic and readable
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return V[first[order]], rank[inv.reshape(-1)][F].astype(np.int32)


def sweep(
    profile: np.ndarray, ring: Callable[[float, float], np.ndarray], closed: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Sweep a 2D profile through a family of rings: ring(u, v) gives the (N, 3) loop of profile
    point (u, v); consecutive profile points are joined by quad strips. An open profile is closed
    at both ends by a fan to the centre of the end ring (the end rings must be convex)."""
    rings = [np.asarray(ring(float(u), float(v)), dtype=np.float64) for u, v in profile]
    N = len(rings[0])
    V = np.concatenate(rings)
    k = np.arange(N)
    k1 = (k + 1) % N
    F = []
    npts = len(rings)
    for i in range(npts if closed else npts - 1):
        a, b = i * N, ((i + 1) % npts) * N
        F.append(np.stack([a + k, a + k1, b + k1], 1))
        F.append(np.stack([a + k, b + k1, b + k], 1))
    if not closed:
        c0 = len(V)
        c1 = c0 + 1
        V = np.concatenate([V, rings[0].mean(0, keepdims=True), rings[-1].mean(0, keepdims=True)])
        last = (npts - 1) * N
        F.append(np.stack([np.full(N, c0), k1, k], 1))
        F.append(np.stack([np.full(N, c1), last + k, last + k1], 1))
    F = np.concatenate(F).astype(np.int32)
    if signed_volume(V, F) < 0:
        F = F[:, [0, 2, 1]]
    return V, F


def lathe_ring(n: int, phase: float = 0.0) -> Callable[[float, float], np.ndarray]:
    a = phase + 2 * np.pi * np.arange(n) / n
    c, s = np.cos(a), np.sin(a)
    return lambda r, z: np.stack([r * c, r * s, np.full(n, z)], 1)


__all__ = ["ccw", "circle", "rounded_polygon", "stadium", "split_loop_at_x", "Prism", "sweep", "lathe_ring"]
