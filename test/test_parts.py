"""Procedural industrial parts: closed, outward-oriented meshes with real symmetries."""
from __future__ import annotations

import numpy as np
import pytest

from perception_config.core.mesh import check_closed_oriented, sample_surface, signed_volume
from perception_config.core.symmetry import symmetries_from_info
from perception_config.datasets.parts import MATERIALS, build_parts, symmetry_transforms, write_models


@pytest.fixture(scope="module")
def parts():
    return build_parts()


def test_part_set(parts):
    names = {p.name for p in parts}
    assert {"bracket", "cover", "flange", "elbow", "hexnut", "bushing"} <= names
    assert len({p.obj_id for p in parts}) == len(parts)
    assert {p.material for p in parts} == {"matte", "shiny"}
    assert all(p.material in MATERIALS for p in parts)
    for p in parts:
        assert all(0.0 <= c <= 1.0 for c in p.color)


def test_sizes_and_triangle_counts(parts):
    for p in parts:
        extent = np.ptp(p.vertices, axis=0)
        assert 20.0 <= extent.max() <= 150.0, (p.name, extent)
        assert 100 <= len(p.faces) <= 5000, (p.name, len(p.faces))
        assert 20.0 <= p.diameter <= 150.0, (p.name, p.diameter)
        # centred on the bounding box
        assert np.allclose(p.vertices.min(0) + p.vertices.max(0), 0.0, atol=1e-6)


def test_closed_consistently_oriented_outward(parts):
    import open3d as o3d

    for p in parts:
        assert check_closed_oriented(p.faces, p.vertices, min_area=1e-4) == [], p.name
        m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(p.vertices), o3d.utility.Vector3iVector(p.faces))
        assert m.is_watertight(), p.name
        assert m.is_orientable(), p.name
        assert not m.is_self_intersecting(), p.name
        assert signed_volume(p.vertices, p.faces) > 0, p.name
        assert m.get_volume() == pytest.approx(signed_volume(p.vertices, p.faces), rel=1e-6)


def test_normals_point_out(parts):
    """Just outside each face (along its normal) is outside the solid, just inside is inside."""
    import open3d as o3d

    for p in parts:
        v, f = p.vertices, p.faces
        n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        c = v[f].mean(axis=1)
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
        eps = 0.05  # mm; parts are at least 2.5 mm thick
        out = scene.compute_occupancy(o3d.core.Tensor((c + eps * n).astype(np.float32))).numpy()
        inn = scene.compute_occupancy(o3d.core.Tensor((c - eps * n).astype(np.float32))).numpy()
        assert out.mean() < 0.01 and inn.mean() > 0.99, (p.name, out.mean(), inn.mean())


def test_known_volumes(parts):
    by = {p.name: p for p in parts}
    hexnut = by["hexnut"]  # hexagon 30 across flats minus a 48-gon bore of r 10, 16 thick
    area = 1.5 * np.sqrt(3) * (30 / np.sqrt(3)) ** 2 - 24 * np.sin(2 * np.pi / 48) * 100
    assert signed_volume(hexnut.vertices, hexnut.faces) == pytest.approx(area * 16, rel=1e-6)


def _nn_error(part, T, pts, tree) -> float:
    q = pts @ T[:3, :3].T + T[:3, 3]
    d, _ = tree.query(q)
    return float(np.percentile(d, 99))


def test_declared_symmetries_are_real(parts):
    from scipy.spatial import cKDTree

    for p in parts:
        pts, _ = sample_surface(p.vertices, p.faces, p.normals, 4000, seed=1)
        dense, _ = sample_surface(p.vertices, p.faces, p.normals, 150000, seed=2)
        tree = cKDTree(dense)
        syms = symmetry_transforms(p, cont_steps=12)
        for T in syms[1:]:
            assert _nn_error(p, T, pts, tree) < 1.0, (p.name, T)
        # a rotation that is no symmetry moves the surface by more than 1 mm
        from perception_config.core.geometry import exp_so3

        cont_axes = [np.asarray(c["axis"], float) for c in p.symmetries_continuous]
        for axis in np.eye(3):
            if any(abs(np.dot(axis, a)) > 0.99 for a in cont_axes):
                continue
            R = exp_so3(axis * 0.35)
            if not any(np.allclose(R, T[:3, :3], atol=1e-6) for T in syms):
                T = np.eye(4)
                T[:3, :3] = R
                assert _nn_error(p, T, pts, tree) > 1.0, (p.name, axis)


def test_symmetry_counts_as_models_reads_them(parts):
    by = {p.name: p for p in parts}
    n = {name: len(symmetries_from_info(by[name].info(), cont_step_deg=30.0)) for name in by}
    assert n["bracket"] == 1
    assert n["cover"] == 2
    assert n["flange"] == 6
    assert n["elbow"] == 2
    assert n["hexnut"] == 12
    assert n["bushing"] == 12  # continuous about z, sampled every 30 deg


def test_write_models_is_a_bop_models_folder(tmp_path, parts):
    from perception_config.core.models import load_model
    from perception_config.core.ply import read_ply_mesh
    from perception_config.datasets.bop_json import load_json
    from perception_config.datasets.bop_models import load_models_info

    d = write_models(tmp_path / "models", parts)
    info = load_models_info(d)
    assert sorted(info) == sorted(p.obj_id for p in parts)
    meta = load_json(d / "parts.json")
    for p in parts:
        v, f, n, c = read_ply_mesh(d / f"obj_{p.obj_id:06d}.ply")
        assert v.shape == p.vertices.shape and f.shape == p.faces.shape
        assert np.abs(v - p.vertices).max() < 1e-4  # float32 mm
        assert n is not None and c is not None
        assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-3)
        e = info[p.obj_id]
        assert e["diameter"] == pytest.approx(p.diameter, rel=1e-6)
        assert e["min_x"] == pytest.approx(p.vertices[:, 0].min(), abs=1e-5)
        assert e["size_z"] == pytest.approx(np.ptp(p.vertices[:, 2]), abs=1e-5)
        assert meta[str(p.obj_id)]["material"] == p.material
        m = load_model(d / f"obj_{p.obj_id:06d}.ply", p.obj_id, e)
        assert m.diameter == pytest.approx(p.diameter / 1000.0, rel=1e-6)
    assert not list(d.glob(".*tmp"))
