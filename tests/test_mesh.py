from pathlib import Path

import numpy as np
import pytest
from bubble_rt.mesh import PRESET_NODES, Mesh, MeshError, MeshGeometry, lumped_areas


@pytest.mark.parametrize("name", sorted(PRESET_NODES))
def test_preset_has_paper_node_count_and_good_quality(name):
    m = Mesh.preset(name)
    assert m.n_nodes == PRESET_NODES[name]
    assert m.min_angle_deg() > 20.0
    e = m.edge_lengths()
    assert e.std() / e.mean() < 0.3  # roughly uniform spacing
    g = MeshGeometry()
    assert np.allclose(m.vertices[m.boundary, 2], 0.0)
    assert abs(m.vertices[:, 2].max() - g.dome_height) < 0.002
    assert m.vertices[:, 0].max() <= g.semi_axis_x + 1e-9


def test_preset_is_deterministic():
    a = Mesh.generate(227)
    Mesh.generate.__func__  # noqa: B018 - classmethod exists
    from bubble_rt.mesh import _generate

    _generate.cache_clear()
    b = Mesh.generate(227)
    assert np.array_equal(a.vertices, b.vertices)
    assert np.array_equal(a.triangles, b.triangles)


def test_normals_point_outward_away_from_camera():
    m = Mesh.preset("coarse")
    p = m.vertices[m.triangles]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert (n[:, 2] > 0).all()


def test_save_and_load_round_trip(tmp_path):
    m = Mesh.preset("coarse")
    for ext in ("vtk", "obj", "ply"):
        path = tmp_path / f"m.{ext}"
        m.save(path)
        r = Mesh.load(path)
        assert np.allclose(r.vertices, m.vertices)
        assert np.array_equal(r.triangles, m.triangles)
        assert np.array_equal(r.boundary, m.boundary)


def test_load_flips_inward_orientation():
    m = Mesh.preset("coarse")
    r = Mesh.validated(m.vertices, m.triangles[:, ::-1])
    assert np.array_equal(r.triangles, m.triangles)


def test_load_missing_file_is_clear(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        Mesh.load(tmp_path / "nope.vtk")


def test_load_garbage_file_is_clear(tmp_path):
    p = tmp_path / "bad.vtk"
    p.write_bytes(b"\x00garbage\xff" * 10)
    with pytest.raises(MeshError, match="cannot read"):
        Mesh.load(p)


def _square():
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 0.2]], float)
    t = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    return v, t


def test_validated_accepts_small_pyramid():
    v, t = _square()
    m = Mesh.validated(v, t)
    assert list(m.boundary) == [0, 1, 2, 3]


def test_sliver_triangle_is_named():
    v, t = _square()
    v[4] = [0.5, 0.001, 0.0]
    with pytest.raises(MeshError, match="triangle 0 .* sliver"):
        Mesh.validated(v, t)


def test_degenerate_triangle_is_named():
    v, t = _square()
    t[2] = [2, 2, 4]
    with pytest.raises(MeshError, match="triangle 2 is degenerate"):
        Mesh.validated(v, t)


def test_unreferenced_vertex_is_named():
    v, t = _square()
    v = np.vstack([v, [5, 5, 5]])
    with pytest.raises(MeshError, match="vertex 5 is not referenced"):
        Mesh.validated(v, t)


def test_non_manifold_edge_is_named():
    v, t = _square()
    v = np.vstack([v, [0.5, -0.5, 0.3], [0.5, -0.5, -0.3]])
    t = np.vstack([t, [[1, 0, 5], [0, 1, 6]]])
    with pytest.raises(MeshError, match=r"edge \(0, 1\) is non-manifold"):
        Mesh.validated(v, t)


def test_inconsistent_orientation_is_named():
    v, t = _square()
    t[1] = t[1][::-1]
    with pytest.raises(MeshError, match="inconsistent orientation"):
        Mesh.validated(v, t)


def test_closed_surface_has_no_boundary():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    t = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    with pytest.raises(MeshError, match="no boundary"):
        Mesh.validated(v, t)


def test_index_out_of_range_is_named():
    v, t = _square()
    t[3, 0] = 17
    with pytest.raises(MeshError, match="triangle 3 indexes a vertex outside"):
        Mesh.validated(v, t)


def test_nan_vertex_is_named():
    v, t = _square()
    v[2, 1] = np.nan
    with pytest.raises(MeshError, match="vertex 2 has a non-finite"):
        Mesh.validated(v, t)


def test_unknown_preset():
    with pytest.raises(ValueError, match="unknown mesh preset"):
        Mesh.preset("huge")


SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "punyo-demo-0"


@pytest.mark.skipif(not SHARED.exists(), reason="../shared/data is not beside this clone")
def test_load_public_reference_mesh():
    m = Mesh.load(SHARED / "reference-mesh-390.vtk")
    assert m.n_nodes == 390
    assert len(m.boundary) > 0
    # Rim in the plane z = 0.054 m, dome above it, normals away from the camera (+z).
    assert np.allclose(m.vertices[m.boundary, 2], 0.054, atol=1e-6)
    p = m.vertices[m.triangles]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert n.sum(axis=0)[2] > 0


def test_msh_round_trip(tmp_path):
    m = Mesh.preset("coarse")
    m.save(tmp_path / "m.msh")
    assert np.allclose(Mesh.load(tmp_path / "m.msh").vertices, m.vertices)


def test_lumped_areas_sum_to_surface_area():
    mesh = Mesh.preset("coarse")
    v, t = mesh.vertices, mesh.triangles
    total = 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)
    np.testing.assert_allclose(lumped_areas(v, t).sum(), total.sum())


def test_generated_mesh_is_cached_on_disk_and_equal_to_a_fresh_one(tmp_path, monkeypatch):
    from bubble_rt import mesh as mesh_mod

    monkeypatch.setenv("BUBBLE_RT_CACHE", str(tmp_path))
    mesh_mod._generate.cache_clear()
    try:
        first = Mesh.generate(60)  # generated, then stored
        (entry,) = tmp_path.glob("mesh-*.npz")
        mesh_mod._generate.cache_clear()
        cached = Mesh.generate(60)  # read back from the file
        assert cached is not first
        assert np.array_equal(cached.vertices, first.vertices)
        assert np.array_equal(cached.triangles, first.triangles)
        assert np.array_equal(cached.boundary, first.boundary)
        # Another geometry is another entry.
        Mesh.generate(60, MeshGeometry(dome_height=0.02))
        assert len(list(tmp_path.glob("mesh-*.npz"))) == 2
    finally:
        mesh_mod._generate.cache_clear()


def test_damaged_mesh_cache_entry_is_generated_again(tmp_path, monkeypatch):
    from bubble_rt import mesh as mesh_mod

    monkeypatch.setenv("BUBBLE_RT_CACHE", str(tmp_path))
    mesh_mod._generate.cache_clear()
    try:
        first = Mesh.generate(60)
        (entry,) = tmp_path.glob("mesh-*.npz")
        entry.write_bytes(b"not an npz file")
        mesh_mod._generate.cache_clear()
        again = Mesh.generate(60)
        assert again is not first and np.array_equal(again.vertices, first.vertices)
        assert np.load(entry)["vertices"].shape == (60, 3)  # rewritten
    finally:
        mesh_mod._generate.cache_clear()
