"""Procedural industrial parts: the objects of the embedded synthetic dataset.

Every part is built here from its dimensions, without booleans and without downloaded data,
as a closed, consistently oriented triangle mesh in **millimetres** (BOP model units) with
outward normals:

- planar parts with holes (flange, hex nut, bracket) are *layered extrusions*: 2D loops shared
  between caps and side walls; the caps are triangulated by a conforming Delaunay triangulation
  (scipy) of the loops, refined jointly until every loop segment is a triangle edge, so caps and
  walls meet edge to edge (watertight by construction, checked on every build);
- turned and swept parts (bushing, cover, elbow) are *sweeps* of a 2D profile along a family of
  rings (circles around an axis or a spine, or offsets of a rounded rectangle).

Each part declares its BOP symmetries in the frame of the final (bounding-box-centred) model:
`symmetries_discrete` as row-major 4x4 matrices with translation in mm (identity excluded, as
BOP does) and `symmetries_continuous` as {axis, offset (mm, a point on the axis)}; plus a
material ("matte" or "shiny") and a base colour used by the synthetic renderer.

Parts (obj_id: name, extent in mm, symmetry, material; ~150-1700 vertices each):
  1 bracket   bent L plate, 2 holes + slot         64 x  40 x 46   none                   matte
  2 cover     rounded-rectangle lid with rim       110 x  80 x 22   180 deg about z        matte
  3 flange    hub flange, bore, 6 bolt holes       110 x 110 x 30   6-fold about z         shiny
  4 elbow     90 deg socket-weld elbow              80 x  80 x 40   180 deg about bisector shiny
  5 hexnut    M20-like, 30 across flats             35 x  30 x 16   6-fold about z x flip  shiny
  6 bushing   flanged (top-hat) bushing             40 x  40 x 25   continuous about z     matte
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..core.ply import write_ply

__all__ = [
    "Part", "build_parts", "part_names", "write_models", "models_info_entry",
    "check_closed_oriented", "signed_volume", "symmetry_transforms", "MATERIALS",
]

# Material parameters the renderer and the sensor model use (see sensor.py).
MATERIALS: dict[str, dict[str, float]] = {
    "matte": {"ks": 0.04, "shininess": 8.0, "dropout": 0.0},
    "shiny": {"ks": 0.85, "shininess": 60.0, "dropout": 1.0},
}


@dataclass
class Part:
    """A procedural part: mesh in mm (watertight and outward-oriented when `watertight`)."""

    obj_id: int
    name: str
    vertices: np.ndarray  # (N, 3) float64 mm
    faces: np.ndarray  # (M, 3) int32, counter-clockwise seen from outside
    material: str  # "matte" | "shiny"
    color: tuple[float, float, float]  # base albedo, RGB in [0, 1]
    symmetries_discrete: list[list[float]] = field(default_factory=list)  # 4x4 row-major, mm
    symmetries_continuous: list[dict] = field(default_factory=list)  # {"axis": [..], "offset": [..] mm}
    watertight: bool = True

    @property
    def normals(self) -> np.ndarray:
        return _vertex_normals(self.vertices, self.faces)

    @property
    def colors_u8(self) -> np.ndarray:
        c = np.clip(np.round(np.asarray(self.color) * 255.0), 0, 255).astype(np.uint8)
        return np.tile(c, (len(self.vertices), 1))

    @property
    def diameter(self) -> float:
        from scipy.spatial import ConvexHull
        from scipy.spatial.distance import pdist

        hull = self.vertices[ConvexHull(self.vertices).vertices]
        return float(pdist(hull).max())

    def info(self) -> dict:
        return models_info_entry(self.vertices, self.diameter, self.symmetries_discrete, self.symmetries_continuous)


# --------------------------------------------------------------------------- mesh checks


def _vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # area-weighted
    acc = np.zeros_like(v)
    for i in range(3):
        np.add.at(acc, f[:, i], n)
    ln = np.linalg.norm(acc, axis=1, keepdims=True)
    return acc / np.maximum(ln, 1e-12)


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume enclosed by a closed mesh: positive when the faces are oriented outward."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def check_closed_oriented(faces: np.ndarray, vertices: np.ndarray | None = None, min_area: float = 1e-6) -> list[str]:
    """Problems of a mesh that should be closed and consistently oriented (empty list: fine).

    Every directed edge must occur exactly once and its reverse exactly once (closed, manifold,
    consistently oriented); with vertices: no triangle below `min_area` (mm^2) and a positive
    signed volume (outward normals).
    """
    problems: list[str] = []
    f = np.asarray(faces, dtype=np.int64)
    if np.any((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])):
        problems.append("triangles with a repeated vertex")
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    n = int(f.max()) + 1
    key = e[:, 0] * n + e[:, 1]
    uniq, counts = np.unique(key, return_counts=True)
    if np.any(counts > 1):
        problems.append(f"{int((counts > 1).sum())} directed edges used twice (flipped or non-manifold)")
    rev = e[:, 1] * n + e[:, 0]
    if not np.all(np.isin(rev, uniq)):
        problems.append(f"{int((~np.isin(rev, uniq)).sum())} edges without a reverse partner (open boundary)")
    if vertices is not None:
        v = np.asarray(vertices, dtype=np.float64)
        area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
        if np.any(area < min_area):
            problems.append(f"{int((area < min_area).sum())} degenerate triangles (area < {min_area} mm^2)")
        if signed_volume(v, f) <= 0:
            problems.append("non-positive signed volume (normals point inward)")
    return problems


# --------------------------------------------------------------------------- 2D helpers


def _ccw(loop: np.ndarray) -> np.ndarray:
    loop = np.asarray(loop, dtype=np.float64)
    x, y = loop[:, 0], loop[:, 1]
    area = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
    return loop if area > 0 else loop[::-1].copy()


def _circle(r: float, n: int, center=(0.0, 0.0), phase: float = 0.0) -> np.ndarray:
    a = phase + 2.0 * np.pi * np.arange(n) / n
    return np.stack([center[0] + r * np.cos(a), center[1] + r * np.sin(a)], axis=1)


def _rounded_polygon(corners: Sequence[Sequence[float]], radii: Sequence[float], seg: int = 6) -> np.ndarray:
    """A convex-cornered CCW polygon with each corner filleted by its radius (0 = sharp)."""
    P = _ccw(np.asarray(corners, dtype=np.float64))
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
    return _ccw(np.array(out))


def _stadium(cx: float, cy: float, half_len: float, r: float, seg: int = 10) -> np.ndarray:
    """A slot: two half circles of radius r joined by straight sides along x."""
    a1 = np.linspace(-np.pi / 2, np.pi / 2, seg + 1)
    a2 = np.linspace(np.pi / 2, 3 * np.pi / 2, seg + 1)
    right = np.stack([cx + half_len + r * np.cos(a1), cy + r * np.sin(a1)], axis=1)
    left = np.stack([cx - half_len + r * np.cos(a2), cy + r * np.sin(a2)], axis=1)
    return _ccw(np.concatenate([right, left]))


def _inside(pts: np.ndarray, loop: np.ndarray) -> np.ndarray:
    """Even-odd point-in-polygon test of (P, 2) points against a loop."""
    x, y = pts[:, 0:1], pts[:, 1:2]
    x0, y0 = loop[:, 0][None], loop[:, 1][None]
    x1, y1 = np.roll(loop[:, 0], -1)[None], np.roll(loop[:, 1], -1)[None]
    cond = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xint = x0 + (y - y0) * (x1 - x0) / np.where(y1 != y0, y1 - y0, 1.0)
    return (np.sum(cond & (x < xint), axis=1) % 2) == 1


def _split_loop_at_x(loop: np.ndarray, xs: Sequence[float]) -> np.ndarray:
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


# --------------------------------------------------------------------------- builders


class _Prism:
    """Layered extrusion: planar caps at given heights bounded by shared 2D loops, and
    vertical walls between two heights along a loop. Loops are stored counter-clockwise."""

    def __init__(self) -> None:
        self.loops: list[np.ndarray] = []
        self.caps: list[tuple[float, int, list[int], bool]] = []
        self.walls: list[tuple[int, float, float, bool]] = []
        self.steiner: dict[int, np.ndarray] = {}

    def loop(self, pts: np.ndarray) -> int:
        self.loops.append(_ccw(pts))
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


def _sweep(
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


def _lathe_ring(n: int, phase: float = 0.0) -> Callable[[float, float], np.ndarray]:
    a = phase + 2 * np.pi * np.arange(n) / n
    c, s = np.cos(a), np.sin(a)
    return lambda r, z: np.stack([r * c, r * s, np.full(n, z)], 1)


def _rot(axis: Sequence[float], angle: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def _T(R: np.ndarray, t: Sequence[float] = (0, 0, 0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


# --------------------------------------------------------------------------- the parts


def _bracket() -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[dict]]:
    """Bent L bracket: a 3 mm plate, flat pattern with two round holes in the base leg and a slot
    in the upright leg, bent up by 90 deg with inner radius 3 mm. Legs of different lengths: no
    rotational symmetry (only a mirror plane, which is not a pose symmetry)."""
    T, Ri, W = 3.0, 3.0, 40.0
    xb = 0.0  # bend starts here; base leg is x < 0
    Rn = Ri + T / 2  # neutral radius
    L = 0.5 * np.pi * Rn  # developed length of the bend zone
    base_len, up_len = 58.0, 40.0  # flat lengths of the legs (outside the bend zone)
    x0, x1 = xb - base_len, xb + L + up_len
    outline = _rounded_polygon([[x0, -W / 2], [x1, -W / 2], [x1, W / 2], [x0, W / 2]], [7.0, 9.0, 9.0, 7.0], seg=6)
    nb = 8  # bend slabs
    xs = list(xb + L * np.arange(nb + 1) / nb)
    outline = _split_loop_at_x(outline, xs)
    P = _Prism()
    o = P.loop(outline)
    holes = [P.loop(_circle(4.25, 24, (x0 + 18.0, y))) for y in (-10.0, 10.0)]
    holes.append(P.loop(_stadium(xb + L + up_len * 0.55, 0.0, 7.0, 3.5, seg=10)))
    # Steiner points on the bend lines, so no cap triangle spans the bend.
    ys = np.linspace(-W / 2, W / 2, 17)[1:-1]
    st = np.array([[x, y] for x in xs for y in ys])
    P.cap(T, o, holes, up=True, steiner=st)
    P.cap(0.0, o, holes, up=False, steiner=st)
    P.wall(o, 0.0, T, True)
    for h in holes:
        P.wall(h, 0.0, T, False)
    V, F = P.build()
    # Bend about the axis parallel to y at (x = xb, z = T + Ri): x beyond the zone goes up.
    x, y, z = V[:, 0].copy(), V[:, 1].copy(), V[:, 2].copy()
    rho = Ri + (T - z)
    th = np.clip((x - xb) / Rn, 0.0, np.pi / 2)
    extra = np.maximum(x - (xb + L), 0.0)
    zone = x > xb
    cx, cz = xb, T + Ri
    nx = cx + rho * np.sin(th)
    nz = cz - rho * np.cos(th) + extra
    V = np.column_stack([np.where(zone, nx, x), y, np.where(zone, nz, z)])
    return V, F, [], []


def _cover() -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[dict]]:
    """Shallow rounded-rectangle lid (open at the bottom) with a 2.5 mm wall and an outward rim,
    swept along offsets of a rounded rectangle. Symmetric by 180 deg about z."""
    a, b, rc = 38.0, 23.0, 12.0  # half lengths of the straight sides, corner radius (outer wall)
    seg_c, seg_s = 8, 6
    base, nrm = [], []
    corners = [(a, b, 0.0), (-a, b, 0.5 * np.pi), (-a, -b, np.pi), (a, -b, 1.5 * np.pi)]
    for ci, (cx, cy, a0) in enumerate(corners):
        for k in range(seg_c):
            ang = a0 + 0.5 * np.pi * k / seg_c
            base.append((cx + rc * math.cos(ang), cy + rc * math.sin(ang)))
            nrm.append((math.cos(ang), math.sin(ang)))
        # straight side from the end of this corner to the start of the next
        ang = a0 + 0.5 * np.pi
        nx, ny = math.cos(ang), math.sin(ang)
        p = np.array([cx + rc * nx, cy + rc * ny])
        nxt = corners[(ci + 1) % 4]
        q = np.array([nxt[0] + rc * nx, nxt[1] + rc * ny])
        for k in range(seg_s):
            base.append(tuple(p + (q - p) * k / seg_s))
            nrm.append((nx, ny))
    base, nrm = np.array(base), np.array(nrm)

    def ring(d: float, z: float) -> np.ndarray:
        xy = base + d * nrm
        return np.column_stack([xy, np.full(len(xy), z)])

    H, t, c = 22.0, 2.5, 1.5  # height, wall, top chamfer
    rim_w, rim_h = 5.0, 3.0
    profile = np.array([
        [-c, H], [0.0, H - c], [0.0, rim_h], [rim_w, rim_h], [rim_w, 0.0], [-t, 0.0], [-t, H - t],
    ])
    V, F = _sweep(profile, ring, closed=False)
    sym = [_T(_rot([0, 0, 1], np.pi))]
    return V, F, sym, []


def _flange() -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[dict]]:
    """Hub flange: 110 mm disc, 12 mm thick, hub 60 mm x 18 mm, bore 40 mm, six 12 mm bolt holes
    on a 84 mm pitch circle. 6-fold symmetric about z (the hub rules out a flip)."""
    Ro, T, Rh, Hh, ri, rb, Rp, nb = 55.0, 12.0, 30.0, 18.0, 20.0, 6.0, 42.0, 6
    P = _Prism()
    lo = P.loop(_circle(Ro, 96))
    lh = P.loop(_circle(Rh, 60))
    li = P.loop(_circle(ri, 48))
    bolts = [P.loop(_circle(rb, 20, (Rp * math.cos(2 * np.pi * k / nb), Rp * math.sin(2 * np.pi * k / nb)),
                            phase=2 * np.pi * k / nb)) for k in range(nb)]
    P.cap(0.0, lo, [li] + bolts, up=False)
    P.cap(T, lo, [lh] + bolts, up=True)
    P.cap(T + Hh, lh, [li], up=True)
    P.wall(lo, 0.0, T, True)
    P.wall(lh, T, T + Hh, True)
    P.wall(li, 0.0, T + Hh, False)
    for bl in bolts:
        P.wall(bl, 0.0, T, False)
    V, F = P.build()
    sym = [_T(_rot([0, 0, 1], 2 * np.pi * k / nb)) for k in range(1, nb)]
    return V, F, sym, []


def _elbow() -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[dict]]:
    """90 deg socket-weld elbow: body OD 33 / ID 23 on a 36 mm bend radius, with a 40 mm socket
    (bore 28, for a 28 mm pipe) on both ends. Symmetric by 180 deg about the bisector of the bend."""
    Rb, leg = 36.0, 24.0
    arc = 0.5 * np.pi * Rb
    S = 2 * leg + arc
    r_out, r_in, s_out, s_in, s_len = 16.5, 11.5, 20.0, 14.0, 18.0
    n_phi, n_arc = 36, 18

    def spine(s: float) -> tuple[np.ndarray, np.ndarray]:
        if s <= leg:  # first leg along +y, at x = Rb, ending at (Rb, 0)
            return np.array([Rb, s - leg, 0.0]), np.array([1.0, 0.0, 0.0])
        if s <= leg + arc:
            th = (s - leg) / Rb
            return np.array([Rb * math.cos(th), Rb * math.sin(th), 0.0]), np.array([math.cos(th), math.sin(th), 0.0])
        return np.array([-(s - leg - arc), Rb, 0.0]), np.array([0.0, 1.0, 0.0])

    phi = 2 * np.pi * np.arange(n_phi) / n_phi
    cphi, sphi = np.cos(phi)[:, None], np.sin(phi)[:, None]
    zhat = np.array([0.0, 0.0, 1.0])

    def ring(s: float, r: float) -> np.ndarray:
        p, n = spine(s)
        return p + r * (cphi * n + sphi * zhat)

    corners = [
        (0.0, s_in), (0.0, s_out), (s_len, s_out), (s_len, r_out), (S - s_len, r_out), (S - s_len, s_out),
        (S, s_out), (S, s_in), (S - s_len, s_in), (S - s_len, r_in), (s_len, r_in), (s_len, s_in),
    ]
    arc_s = leg + arc * np.arange(1, n_arc) / n_arc
    prof = []
    for i, (s0, r0) in enumerate(corners):
        s1, r1 = corners[(i + 1) % len(corners)]
        prof.append((s0, r0))
        if s1 != s0:  # subdivide along the spine where it bends
            inner = [s for s in arc_s if min(s0, s1) < s < max(s0, s1)]
            for s in sorted(inner, reverse=s1 < s0):
                prof.append((s, r0 + (r1 - r0) * (s - s0) / (s1 - s0)))
    V, F = _sweep(np.array(prof), ring, closed=True)
    axis = np.array([1.0, 1.0, 0.0]) / math.sqrt(2)
    sym = [_T(_rot(axis, np.pi))]  # about the bisector through the bend centre (the origin)
    return V, F, sym, []


def _hexnut() -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[dict]]:
    """Hex nut: 30 mm across flats, 16 mm thick, 20 mm bore. Symmetric by 60 deg steps about z
    and by a half turn about x (flip): 12 symmetries, 11 without the identity."""
    s, m, rbore = 30.0, 16.0, 10.0
    Rc = s / math.sqrt(3)  # corner radius
    P = _Prism()
    hexagon = _circle(Rc, 6)  # corners at 0, 60, ... deg
    # subdivide the hexagon sides so the cap triangles are not needle-thin
    hexagon = np.concatenate([[hexagon[i] + (hexagon[(i + 1) % 6] - hexagon[i]) * k / 4 for k in range(4)]
                              for i in range(6)])
    o = P.loop(hexagon)
    h = P.loop(_circle(rbore, 48))
    P.cap(0.0, o, [h], up=False)
    P.cap(m, o, [h], up=True)
    P.wall(o, 0.0, m, True)
    P.wall(h, 0.0, m, False)
    V, F = P.build()
    V[:, 2] -= m / 2
    rots = [_rot([0, 0, 1], k * np.pi / 3) for k in range(6)]
    flip = _rot([1, 0, 0], np.pi)
    sym = [_T(R) for R in rots[1:]] + [_T(R @ flip) for R in rots]
    return V, F, sym, []


def _bushing() -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[dict]]:
    """Flanged (top-hat) bushing, turned: bore 16, body 24 x 25, flange 40 x 4, 0.8 mm chamfers.
    Continuously symmetric about z (the flange rules out a flip)."""
    c = 0.8
    rb, rbody, rfl, L, tf = 8.0, 12.0, 20.0, 25.0, 4.0
    prof = np.array([
        [rb + c, 0.0], [rbody - c, 0.0], [rbody, c], [rbody, L - tf], [rfl - c, L - tf], [rfl, L - tf + c],
        [rfl, L - c], [rfl - c, L], [rb + c, L], [rb, L - c], [rb, c],
    ])
    V, F = _sweep(prof, _lathe_ring(64), closed=True)
    return V, F, [], [{"axis": [0.0, 0.0, 1.0], "offset": [0.0, 0.0, 0.0]}]


_SPECS = [
    # obj_id, name, builder, material, colour (RGB 0..1)
    (1, "bracket", _bracket, "matte", (0.16, 0.29, 0.56)),  # blue powder coat
    (2, "cover", _cover, "matte", (0.62, 0.63, 0.60)),  # grey plastic, textureless
    (3, "flange", _flange, "shiny", (0.50, 0.51, 0.54)),  # machined steel
    (4, "elbow", _elbow, "shiny", (0.80, 0.58, 0.25)),  # brass
    (5, "hexnut", _hexnut, "shiny", (0.46, 0.47, 0.50)),  # zinc-plated steel
    (6, "bushing", _bushing, "matte", (0.80, 0.78, 0.70)),  # white nylon
]


def part_names() -> dict[int, str]:
    return {i: n for i, n, *_ in _SPECS}


def build_parts() -> list[Part]:
    """Build all procedural parts, each centred on its bounding box, checked closed and outward."""
    parts = []
    for obj_id, name, fn, material, color in _SPECS:
        V, F, sym_d, sym_c = fn()
        c0 = 0.5 * (V.min(0) + V.max(0))
        V = V - c0
        # Conjugate the symmetries by the centring shift: x' = x - c0.
        disc = []
        for S in sym_d:
            R, t = S[:3, :3], S[:3, 3]
            S2 = _T(R, R @ c0 + t - c0)
            S2[np.abs(S2) < 1e-12] = 0.0
            disc.append([float(round(x, 9)) for x in S2.reshape(-1)])
        cont = [{"axis": [float(a) for a in s["axis"]],
                 "offset": [float(round(x, 9)) for x in (np.asarray(s["offset"], float) - c0)]} for s in sym_c]
        problems = check_closed_oriented(F, V)
        if problems:
            raise RuntimeError(f"procedural part {name}: {'; '.join(problems)}")
        parts.append(Part(obj_id, name, V, F.astype(np.int32), material, color, disc, cont, True))
    return parts


def symmetry_transforms(part_or_info, cont_steps: int = 36) -> list[np.ndarray]:
    """4x4 (mm) symmetry transforms incl. identity of a Part or a models_info entry."""
    if isinstance(part_or_info, Part):
        info = {"symmetries_discrete": part_or_info.symmetries_discrete,
                "symmetries_continuous": part_or_info.symmetries_continuous}
    else:
        info = part_or_info
    disc = [np.eye(4)] + [np.asarray(s, float).reshape(4, 4) for s in info.get("symmetries_discrete", [])]
    out = list(disc)
    for s in info.get("symmetries_continuous", []):
        axis, off = np.asarray(s["axis"], float), np.asarray(s["offset"], float)
        for k in range(1, cont_steps):
            R = _rot(axis, 2 * np.pi * k / cont_steps)
            C = _T(R, off - R @ off)
            out += [C @ D for D in disc]
    return out


# --------------------------------------------------------------------------- BOP output


def models_info_entry(vertices: np.ndarray, diameter: float, sym_d=(), sym_c=()) -> dict:
    """A BOP models_info.json entry (mm)."""
    lo, hi = vertices.min(0), vertices.max(0)
    e = {"diameter": round(float(diameter), 6)}
    for k, ax in enumerate("xyz"):
        e[f"min_{ax}"] = round(float(lo[k]), 6)
    for k, ax in enumerate("xyz"):
        e[f"size_{ax}"] = round(float(hi[k] - lo[k]), 6)
    if sym_d:
        e["symmetries_discrete"] = [list(s) for s in sym_d]
    if sym_c:
        e["symmetries_continuous"] = [dict(s) for s in sym_c]
    return e


def write_models(models_dir: str | os.PathLike, parts: Sequence[Part] | None = None) -> Path:
    """Write the parts as a BOP models folder: obj_XXXXXX.ply (mm, normals, colours),
    models_info.json, and parts.json (name, material, colour: what the synthetic renderer uses)."""
    models_dir = Path(models_dir)
    parts = build_parts() if parts is None else list(parts)
    info, meta = {}, {}
    for p in parts:
        write_ply(models_dir / f"obj_{p.obj_id:06d}.ply", p.vertices, p.faces, p.normals, p.colors_u8)
        info[p.obj_id] = p.info()
        meta[str(p.obj_id)] = {"name": p.name, "material": p.material, "color": [round(c, 4) for c in p.color]}
    from .bop import save_json, write_models_info

    write_models_info(models_dir / "models_info.json", {int(k): v for k, v in info.items()})
    save_json(models_dir / "parts.json", meta)
    return models_dir
