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

Extrusions and sweeps are built with datasets/mesh_builders.py.

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
from typing import Sequence

import numpy as np

from ..core.geometry import MM, Pose
from ..core.mesh import check_closed_oriented, convex_hull_points, max_pairwise_distance
from ..core.ply import write_ply
from ..core.symmetry import axis_angle_matrix, symmetries_from_info
from .mesh_builders import Prism, circle, lathe_ring, rounded_polygon, split_loop_at_x, stadium, sweep

__all__ = ["Part", "build_parts", "write_models", "models_info_entry", "symmetry_transforms", "MATERIALS"]

# Material parameters the renderer and the sensor model use (see sensor.py).
MATERIALS: dict[str, dict[str, float]] = {
    "matte": {"ks": 0.04, "shininess": 8.0, "dropout": 0.0},
    "shiny": {"ks": 0.85, "shininess": 60.0, "dropout": 1.0},
}


@dataclass
class Part:
    """A procedural part: mesh in mm, watertight and outward-oriented (checked when built)."""

    obj_id: int
    name: str
    vertices: np.ndarray  # (N, 3) float64 mm
    faces: np.ndarray  # (M, 3) int32, counter-clockwise seen from outside
    material: str  # "matte" | "shiny"
    color: tuple[float, float, float]  # base albedo, RGB in [0, 1]
    symmetries_discrete: list[list[float]] = field(default_factory=list)  # 4x4 row-major, mm
    symmetries_continuous: list[dict] = field(default_factory=list)  # {"axis": [..], "offset": [..] mm}

    @property
    def normals(self) -> np.ndarray:
        return _vertex_normals(self.vertices, self.faces)

    @property
    def colors_u8(self) -> np.ndarray:
        c = np.clip(np.round(np.asarray(self.color) * 255.0), 0, 255).astype(np.uint8)
        return np.tile(c, (len(self.vertices), 1))

    @property
    def diameter(self) -> float:
        return max_pairwise_distance(convex_hull_points(self.vertices))

    def info(self) -> dict:
        return models_info_entry(self.vertices, self.diameter, self.symmetries_discrete, self.symmetries_continuous)


def _vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals, summed from the unnormalised face cross products (not
    core/mesh.py's vertex_normals, whose unit-normal-times-area sums differ in the last bit:
    the elbow's float32 normals in its PLY file would change)."""
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # area-weighted
    acc = np.zeros_like(v)
    for i in range(3):
        np.add.at(acc, f[:, i], n)
    ln = np.linalg.norm(acc, axis=1, keepdims=True)
    return acc / np.maximum(ln, 1e-12)


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
    outline = rounded_polygon([[x0, -W / 2], [x1, -W / 2], [x1, W / 2], [x0, W / 2]], [7.0, 9.0, 9.0, 7.0], seg=6)
    nb = 8  # bend slabs
    xs = list(xb + L * np.arange(nb + 1) / nb)
    outline = split_loop_at_x(outline, xs)
    P = Prism()
    o = P.loop(outline)
    holes = [P.loop(circle(4.25, 24, (x0 + 18.0, y))) for y in (-10.0, 10.0)]
    holes.append(P.loop(stadium(xb + L + up_len * 0.55, 0.0, 7.0, 3.5, seg=10)))
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
    V, F = sweep(profile, ring, closed=False)
    sym = [_T(axis_angle_matrix([0, 0, 1], np.pi))]
    return V, F, sym, []


def _flange() -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[dict]]:
    """Hub flange: 110 mm disc, 12 mm thick, hub 60 mm x 18 mm, bore 40 mm, six 12 mm bolt holes
    on a 84 mm pitch circle. 6-fold symmetric about z (the hub rules out a flip)."""
    Ro, T, Rh, Hh, ri, rb, Rp, nb = 55.0, 12.0, 30.0, 18.0, 20.0, 6.0, 42.0, 6
    P = Prism()
    lo = P.loop(circle(Ro, 96))
    lh = P.loop(circle(Rh, 60))
    li = P.loop(circle(ri, 48))
    bolts = [P.loop(circle(rb, 20, (Rp * math.cos(2 * np.pi * k / nb), Rp * math.sin(2 * np.pi * k / nb)),
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
    sym = [_T(axis_angle_matrix([0, 0, 1], 2 * np.pi * k / nb)) for k in range(1, nb)]
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
    V, F = sweep(np.array(prof), ring, closed=True)
    axis = np.array([1.0, 1.0, 0.0]) / math.sqrt(2)
    sym = [_T(axis_angle_matrix(axis, np.pi))]  # about the bisector through the bend centre (the origin)
    return V, F, sym, []


def _hexnut() -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[dict]]:
    """Hex nut: 30 mm across flats, 16 mm thick, 20 mm bore. Symmetric by 60 deg steps about z
    and by a half turn about x (flip): 12 symmetries, 11 without the identity."""
    s, m, rbore = 30.0, 16.0, 10.0
    Rc = s / math.sqrt(3)  # corner radius
    P = Prism()
    hexagon = circle(Rc, 6)  # corners at 0, 60, ... deg
    # subdivide the hexagon sides so the cap triangles are not needle-thin
    hexagon = np.concatenate([[hexagon[i] + (hexagon[(i + 1) % 6] - hexagon[i]) * k / 4 for k in range(4)]
                              for i in range(6)])
    o = P.loop(hexagon)
    h = P.loop(circle(rbore, 48))
    P.cap(0.0, o, [h], up=False)
    P.cap(m, o, [h], up=True)
    P.wall(o, 0.0, m, True)
    P.wall(h, 0.0, m, False)
    V, F = P.build()
    V[:, 2] -= m / 2
    rots = [axis_angle_matrix([0, 0, 1], k * np.pi / 3) for k in range(6)]
    flip = axis_angle_matrix([1, 0, 0], np.pi)
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
    V, F = sweep(prof, lathe_ring(64), closed=True)
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
        parts.append(Part(obj_id, name, V, F.astype(np.int32), material, color, disc, cont))
    return parts


def symmetry_transforms(part_or_info, cont_steps: int = 36) -> list[np.ndarray]:
    """4x4 (mm) symmetry transforms, identity first, of a Part or a models_info entry: those of
    core/symmetry.py's symmetries_from_info, continuous ones sampled in `cont_steps` steps."""
    if isinstance(part_or_info, Part):
        info = {"symmetries_discrete": part_or_info.symmetries_discrete,
                "symmetries_continuous": part_or_info.symmetries_continuous}
    else:
        info = part_or_info
    return [Pose(s.R, s.t / MM).matrix() for s in symmetries_from_info(info, 360.0 / cont_steps)]


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
    from .bop_json import save_json
    from .bop_models import write_models_info

    write_models_info(models_dir / "models_info.json", {int(k): v for k, v in info.items()})
    save_json(models_dir / "parts.json", meta)
    return models_dir
