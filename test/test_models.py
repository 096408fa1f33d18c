"""ObjectModel preparation: PLY reading, diameter, samples, symmetries, edge points, caching."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from frames import box_mesh
from perception_config.core.geometry import MM, Pose, exp_so3
from perception_config.core.mesh import sharp_edges
from perception_config.core.models import load_model, make_model
from perception_config.core.ply import PlyError, read_ply_mesh, write_ply
from perception_config.core.symmetry import symmetries_from_info

LMO_IDS = [1, 5, 6, 8, 9, 10, 11, 12]


# --------------------------------------------------------------------------- PLY


@pytest.mark.parametrize("binary", [True, False])
def test_ply_round_trip(tmp_path: Path, binary: bool) -> None:
    v, f = box_mesh((100.0, 60.0, 40.0))
    normals = v / np.linalg.norm(v, axis=1, keepdims=True)
    colors = np.arange(24, dtype=np.uint8).reshape(8, 3)
    p = tmp_path / "box.ply"
    write_ply(p, v, f, normals=normals, colors=colors, binary=binary)
    v2, f2, n2, c2 = read_ply_mesh(p)
    np.testing.assert_allclose(v2, v, atol=1e-5)
    np.testing.assert_array_equal(f2, f)
    np.testing.assert_allclose(n2, normals, atol=1e-6)
    np.testing.assert_array_equal(c2, colors)


def test_ply_polygons_are_triangulated(tmp_path: Path) -> None:
    p = tmp_path / "quad.ply"
    p.write_text(
        "ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n1 1 0\n0 1 0\n0 0 1\n4 0 1 2 3\n3 0 1 4\n"
    )
    v, f, n, c = read_ply_mesh(p)

    def same_winding(tri: list[int]) -> tuple[int, ...]:  # rotated to start at its smallest index
        i = tri.index(min(tri))
        return tuple(tri[i:] + tri[:i])

    # the quad becomes two triangles covering it with its winding (trimesh orders them its own way)
    assert sorted(same_winding(t) for t in f.tolist()) == [(0, 1, 2), (0, 1, 4), (0, 2, 3)]
    assert n is None and c is None


@pytest.mark.parametrize("binary", [True, False])
def test_truncated_ply_names_the_file(tmp_path: Path, binary: bool) -> None:
    v, f = box_mesh((1.0, 1.0, 1.0))
    p = tmp_path / "obj_000001.ply"
    write_ply(p, v, f, binary=binary)
    data = p.read_bytes()
    p.write_bytes(data[: len(data) - 30])
    with pytest.raises(PlyError, match="obj_000001.ply.*truncated"):
        read_ply_mesh(p)
    with pytest.raises(PlyError, match="obj_000001.ply"):
        load_model(p, 1)


def test_garbage_ply_names_the_file(tmp_path: Path) -> None:
    p = tmp_path / "obj_000002.ply"
    p.write_bytes(b"\x00\x01 not a ply at all")
    with pytest.raises(PlyError, match="obj_000002.ply.*not a PLY"):
        load_model(p, 2)
    with pytest.raises(FileNotFoundError, match="obj_000003.ply"):
        load_model(tmp_path / "obj_000003.ply", 3)


@pytest.mark.parametrize("fmt, vtype, body, message", [
    ("binary_middle_endian", "float", "", "unknown PLY format 'binary_middle_endian'"),
    ("ascii", "float128", "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n", "bad PLY header.*float128"),
    ("ascii", "float", "0 0 0\n1 x 0\n0 1 0\n3 0 1 2\n", "malformed PLY"),
    ("ascii", "float", "0 0 0\n", "truncated: element 'vertex' has 1 of 3 records"),
])
def test_malformed_ply_names_the_file_and_the_problem(tmp_path: Path, fmt: str, vtype: str, body: str,
                                                       message: str) -> None:
    p = tmp_path / "obj_000004.ply"
    p.write_text(f"ply\nformat {fmt} 1.0\nelement vertex 3\nproperty {vtype} x\nproperty float y\n"
                 "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n" + body)
    with pytest.raises(PlyError, match=f"obj_000004.ply: {message}"):
        read_ply_mesh(p)


def test_ply_bad_face_index(tmp_path: Path) -> None:
    p = tmp_path / "bad.ply"
    p.write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n"
    )
    with pytest.raises(PlyError, match="bad.ply.*out of range"):
        read_ply_mesh(p)


# --------------------------------------------------------------------------- derived data on a box


def test_box_model_geometry(make_box) -> None:
    size = np.array([0.1, 0.06, 0.04])
    m = make_box(tuple(size))
    assert m.diameter == pytest.approx(float(np.linalg.norm(size)))
    np.testing.assert_allclose(m.bbox_min, -size / 2)
    np.testing.assert_allclose(m.bbox_size, size)
    # surface samples lie on the box surface with the face normal
    on_face = np.isclose(np.abs(m.points), size / 2, atol=1e-12)
    assert np.all(on_face.any(axis=1))
    assert len(m.points) == 2000
    np.testing.assert_allclose(np.linalg.norm(m.point_normals, axis=1), 1.0, atol=1e-9)
    # edge points: on the 12 box edges (two coordinates at the limit) with axis-aligned directions
    assert len(sharp_edges(m.vertices, m.faces)) == 12
    assert len(m.edge_points) > 100
    at_limit = np.isclose(np.abs(m.edge_points), size / 2, atol=1e-12).sum(axis=1)
    assert np.all(at_limit >= 2)
    assert np.all(np.isclose(np.abs(m.edge_dirs).max(axis=1), 1.0))
    assert m.symmetries[0].matrix().tolist() == np.eye(4).tolist() and not m.is_symmetric
    assert not m.vertices.flags.writeable


def test_samples_are_deterministic(make_box) -> None:
    v, f = box_mesh((0.1, 0.06, 0.04))
    a, b = make_model(7, v, f), make_model(7, v, f)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.edge_points, b.edge_points)


def test_continuous_symmetries_of_a_prism() -> None:
    # A 36-gon prism around z is symmetric under rotations of 10 degrees about z.
    n = 36
    ang = np.arange(n) * 2 * np.pi / n
    ring = np.stack([np.cos(ang), np.sin(ang), np.zeros(n)], 1) * 0.05
    offset_mm = np.array([10.0, -5.0, 0.0])
    v = np.concatenate([ring + [0, 0, -0.02], ring + [0, 0, 0.02]]) + offset_mm * MM
    faces = []
    for i in range(n):
        j = (i + 1) % n
        faces += [[i, j, n + j], [i, n + j, n + i]]
    # plus a discrete flip about the x axis through the offset point: t = offset - R offset
    R = np.diag([1.0, -1.0, -1.0])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, offset_mm - R @ offset_mm
    info = {"diameter": 110.0, "symmetries_continuous": [{"axis": [0, 0, 1], "offset": offset_mm.tolist()}],
            "symmetries_discrete": [T.reshape(-1).tolist()]}
    syms = symmetries_from_info(info, cont_step_deg=10.0)
    assert len(syms) == 2 * 36
    np.testing.assert_allclose(syms[0].matrix(), np.eye(4), atol=1e-12)
    tree = cKDTree(v)
    for s in syms:
        d, _ = tree.query(s.transform(v))
        assert d.max() < 1e-9


# --------------------------------------------------------------------------- caching


def test_load_model_is_cached_by_mtime(tmp_path: Path) -> None:
    v, f = box_mesh((100.0, 60.0, 40.0))
    p = tmp_path / "obj_000001.ply"
    write_ply(p, v, f)
    a, b = load_model(p, 1), load_model(p, 1)
    assert a is b
    assert a.diameter == pytest.approx(np.linalg.norm([0.1, 0.06, 0.04]))  # mm -> m
    write_ply(p, v * 2, f)
    st = p.stat()
    os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns + 10_000_000))
    c = load_model(p, 1)
    assert c is not a and c.diameter == pytest.approx(2 * a.diameter)


# --------------------------------------------------------------------------- real LM-O models


@pytest.fixture(scope="module")
def lmo_info(lmo_root: Path) -> dict[str, dict]:
    return json.loads((lmo_root / "models" / "models_info.json").read_text())


def test_lmo_diameters_match_models_info(lmo_root: Path, lmo_info: dict) -> None:
    for obj_id in LMO_IDS:
        m = load_model(lmo_root / "models" / f"obj_{obj_id:06d}.ply", obj_id)  # no info: computed
        expected = lmo_info[str(obj_id)]["diameter"] * MM
        assert m.diameter == pytest.approx(expected, rel=5e-3), obj_id
        assert m.colors is not None and m.colors.shape == (len(m.vertices), 3)
        assert 0.01 < np.ptp(m.vertices, axis=0).max() < 0.3  # metres, not mm


@pytest.mark.parametrize("obj_id", [10, 11])
def test_lmo_discrete_symmetries_are_real(lmo_root: Path, lmo_info: dict, obj_id: int) -> None:
    m = load_model(lmo_root / "models" / f"obj_{obj_id:06d}.ply", obj_id, lmo_info[str(obj_id)])
    assert len(m.symmetries) == 2 and m.is_symmetric
    tree = cKDTree(m.vertices)
    d_sym, _ = tree.query(m.symmetries[1].transform(m.points))
    # a rotation that is not a symmetry moves the points far off the surface
    wrong = Pose(exp_so3([0.0, 0.0, np.pi / 2]), np.zeros(3))
    d_wrong, _ = tree.query(wrong.transform(m.points))
    print(f"obj {obj_id}: symmetry NN distance mean {d_sym.mean() * 1e3:.2f} mm, "
          f"95% {np.percentile(d_sym, 95) * 1e3:.2f} mm; non-symmetry mean {d_wrong.mean() * 1e3:.1f} mm")
    assert d_sym.mean() < 3e-3 and np.percentile(d_sym, 95) < 6e-3
    assert d_wrong.mean() > 3 * d_sym.mean()
