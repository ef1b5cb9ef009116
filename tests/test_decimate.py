"""Tests of ucad_cl.decimate: budget, material boundaries, rendered material maps, determinism."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from ucad_cl.decimate import decimate
from ucad_cl.artifacts import Material, Mesh

VEHICLES = Path(__file__).resolve().parents[2] / "shared/data/vehicles"


# ----------------------------------------------------------------------------- hand-made meshes

def grid(n: int, x0: float = 0.0, x1: float = 1.0, bump: float = 0.05):
    """(n+1)^2 vertices on a bumpy height field over [x0, x1] x [0, 1], 2 n^2 triangles."""
    xs, ys = np.linspace(x0, x1, n + 1), np.linspace(0.0, 1.0, n + 1)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    Z = bump * np.sin(3.0 * X) * np.cos(2.0 * Y) + 0.3 * X * Y
    V = np.stack([X, Y, Z], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (i * (n + 1) + j).ravel()
    b, c, d = a + (n + 1), a + 1, a + n + 2
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([c, b, d], 1)])
    return V, F


def make_mesh(V, F, fm, n_materials=None, name="hand") -> Mesh:
    n_materials = int(np.max(fm)) + 1 if n_materials is None else n_materials
    return Mesh(path=name, sha256="ab" * 32, vertices=np.asarray(V, np.float64),
                faces=np.asarray(F, np.uint32), face_material=np.asarray(fm, np.uint16),
                materials=[Material(f"m{i}") for i in range(n_materials)],
                file_to_norm=np.diag([2.0, 2.0, 2.0, 1.0]),
                face_node=np.arange(len(F), dtype=np.int32) % 7, node_names=[f"n{i}" for i in range(7)])


def two_materials(welded: bool, n: int = 40) -> Mesh:
    """A bumpy square: left half material 0, right half material 1 (shared or duplicated seam)."""
    if welded:
        V, F = grid(n)
        centre_x = V[F].mean(axis=1)[:, 0]
        return make_mesh(V, F, (centre_x > 0.5).astype(int))
    VA, FA = grid(n // 2, 0.0, 0.5, bump=0.0)
    VB, FB = grid(n // 2, 0.5, 1.0, bump=0.0)
    for Vx in (VA, VB):       # same height field on both halves, so the seams coincide exactly
        Vx[:, 2] = 0.05 * np.sin(3.0 * Vx[:, 0]) * np.cos(2.0 * Vx[:, 1]) + 0.3 * Vx[:, 0] * Vx[:, 1]
    V = np.concatenate([VA, VB])
    F = np.concatenate([FA, FB + len(VA)])
    return make_mesh(V, F, np.r_[np.zeros(len(FA), int), np.ones(len(FB), int)])


def material_boundary_edges(mesh: Mesh) -> set:
    """Edges (as sorted coordinate pairs) used by faces of two different materials.

    Independent of the module: vertices are identified by coordinates through Python tuples.
    """
    owners: dict = {}
    V = mesh.vertices
    for f, m in zip(mesh.faces.tolist(), mesh.face_material.tolist()):
        for a, b in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0])):
            key = tuple(sorted((tuple(V[a]), tuple(V[b]))))
            owners.setdefault(key, set()).add(m)
    return {e for e, ms in owners.items() if len(ms) > 1}


def boundary_vertex_coords(mesh: Mesh) -> set:
    return {p for e in material_boundary_edges(mesh) for p in e}


# ----------------------------------------------------------------------------- boundaries

@pytest.mark.parametrize("welded", [True, False])
def test_two_material_boundary_kept_exactly(welded):
    mesh = two_materials(welded)
    budget = mesh.n_faces // 4
    out = decimate(mesh, budget)
    assert budget - 1 <= out.n_faces <= budget
    before, after = material_boundary_edges(mesh), material_boundary_edges(out)
    assert len(before) == (40 if welded else 20)  # the seam x = 0.5: one edge per grid row
    # every seam edge survives with exact coordinates and no new seam edge appears
    assert after == before
    # the interior really was decimated
    assert out.n_faces < mesh.n_faces / 3


def test_without_preserve_boundaries_seam_may_move_but_budget_holds():
    mesh = two_materials(welded=True)
    out = decimate(mesh, 200, preserve_boundaries=False)
    assert out.n_faces <= 200
    assert set(np.unique(out.face_material)) == {0, 1}
    # plain QEM simplifies the seam too: fewer seam vertices than the 41 of the input
    assert len(boundary_vertex_coords(out)) < len(boundary_vertex_coords(mesh))


def test_faces_stay_inside_their_material_region():
    """Collapses happen inside one material: every output vertex of a material-m face lies in
    material m's half of the square (x <= 0.5 for m = 0, x >= 0.5 for m = 1)."""
    mesh = two_materials(welded=True)
    out = decimate(mesh, 800)
    assert "boundaries may have moved" not in " ".join(out.report.notes)
    x = out.vertices[out.faces][:, :, 0]
    m = out.face_material
    assert np.all(x[m == 0] <= 0.5 + 1e-12) and np.all(x[m == 1] >= 0.5 - 1e-12)


def test_band_over_half_the_budget_falls_back_to_unlocked_pass_with_note():
    mesh = two_materials(welded=True)            # the locked seam band has 4 x 40 = 160 faces
    out = decimate(mesh, 300)
    assert out.n_faces <= 300
    assert "boundaries may have moved" in out.report.notes[-1]
    assert set(np.unique(out.face_material)) == {0, 1}


# ----------------------------------------------------------------------------- budget, materials

def many_materials_mesh() -> Mesh:
    """A 60x60 bumpy grid (material 0) plus 20 separate closed tetrahedra, one material each."""
    V, F = grid(60)
    Vs, Fs, fm = [V], [F], [np.zeros(len(F), int)]
    n = len(V)
    tet = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float) * 0.02
    tf = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    for k in range(20):
        Vs.append(tet + [0.05 * k, 1.2, 0.0])
        Fs.append(tf + n)
        fm.append(np.full(4, k + 1))
        n += 4
    return make_mesh(np.concatenate(Vs), np.concatenate(Fs), np.concatenate(fm))


@pytest.mark.parametrize("budget", [3000, 500, 150])
def test_budget_and_every_material_survives(budget):
    mesh = many_materials_mesh()
    out = decimate(mesh, budget)
    assert out.n_faces <= budget
    assert out.n_faces >= 0.8 * budget
    assert set(np.unique(out.face_material)) == set(range(21))
    assert not np.any(out.faces == out.faces[:, [1, 2, 0]])   # no face with a repeated vertex


def test_lowest_index_face_is_kept_when_a_material_has_no_boundary():
    """Tie rule: a material with no locked face keeps its lowest-index face, bit-identical."""
    mesh = many_materials_mesh()
    out = decimate(mesh, 150)
    assert out.n_faces <= 150
    for k in range(1, 21):
        first = np.flatnonzero(mesh.face_material == k)[0]
        want = mesh.vertices[mesh.faces[first].astype(np.int64)]
        got = out.vertices[out.faces[out.face_material == k].astype(np.int64)]
        assert any(np.array_equal(g, want) for g in got)


def test_carried_fields_and_report():
    mesh = two_materials(welded=False)
    out = decimate(mesh, 400)
    assert out is not mesh and out.sha256 == mesh.sha256 and out.path == mesh.path
    np.testing.assert_array_equal(out.file_to_norm, mesh.file_to_norm)
    assert [m.name for m in out.materials] == [m.name for m in mesh.materials]
    assert out.node_names == mesh.node_names
    assert out.report.notes[-1] == f"decimated {mesh.n_faces}->{out.n_faces}"
    assert mesh.report.notes == []                       # input untouched
    assert out.faces.dtype == np.uint32 and out.face_material.dtype == np.uint16
    assert out.vertices.dtype == np.float64 and out.face_node.dtype == np.int32
    assert out.faces.max() == len(out.vertices) - 1      # no unreferenced trailing vertices
    assert len(np.unique(out.faces)) == len(out.vertices)
    # face_node is carried with its face: material 0 faces come from the first half whose
    # face_node pattern is i % 7, so every value stays in range and both materials keep nodes
    assert set(np.unique(out.face_node)) <= set(range(7))


def test_budget_at_or_above_face_count_returns_mesh_unchanged():
    mesh = two_materials(welded=True, n=10)
    assert decimate(mesh, mesh.n_faces) is mesh
    assert decimate(mesh, mesh.n_faces + 5) is mesh


def test_deterministic_bit_identical():
    mesh = many_materials_mesh()
    a, b = decimate(mesh, 700), decimate(mesh, 700)
    for name in ("vertices", "faces", "face_material", "face_node"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name


# ----------------------------------------------------------------------------- errors

def test_errors_name_the_problem():
    mesh = many_materials_mesh()                         # 21 materials in use
    with pytest.raises(ValueError, match="below the number of materials in use \\(21\\)"):
        decimate(mesh, 20)
    with pytest.raises(TypeError, match="budget must be an int"):
        decimate(mesh, 100.0)
    bad = dataclasses.replace(mesh, vertices=mesh.vertices.copy())
    bad.vertices[3, 1] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        decimate(bad, 100)
    bad = dataclasses.replace(mesh, faces=mesh.faces.copy())
    bad.faces[0, 0] = len(mesh.vertices)
    with pytest.raises(ValueError, match="face index out of range"):
        decimate(bad, 100)
    with pytest.raises(ValueError, match="one entry per face"):
        decimate(dataclasses.replace(mesh, face_material=mesh.face_material[:-1]), 100)
    with pytest.raises(ValueError, match="no faces"):
        decimate(dataclasses.replace(mesh, faces=np.zeros((0, 3), np.uint32),
                                     face_material=np.zeros(0, np.uint16), face_node=None), 100)


# ----------------------------------------------------------------------------- rendered maps

def agreement(full: Mesh, reduced: Mesh, ring) -> tuple[float, float]:
    """(material-map agreement, silhouette disagreement) on the union of foreground pixels."""
    from ucad_cl.render import render_views
    a = render_views(full, ring).mat_id
    b = render_views(reduced, ring).mat_id
    union = (a > 0) | (b > 0)
    return float(np.mean(a[union] == b[union])), float(np.mean((a > 0)[union] != (b > 0)[union]))


@pytest.fixture(scope="module")
def ring():
    from ucad_cl.cameras import make_ring
    return make_ring(azimuth_step=30.0, elevations=(15.0,), size=160)


def test_synth_vehicle_material_maps_at_4x(ring):
    from ucad_cl.synth import make_vehicle
    mesh = make_vehicle(5, target_triangles=40_000).mesh()
    budget = mesh.n_faces // 4
    out = decimate(mesh, budget)
    assert out.n_faces <= budget
    assert set(np.unique(out.face_material)) == set(np.unique(mesh.face_material))
    agree, silhouette = agreement(mesh, out, ring)
    assert agree >= 0.98, agree
    assert silhouette <= 0.01, silhouette
    # every material-boundary position of the welded input survives exactly
    assert boundary_vertex_coords(out) >= boundary_vertex_coords(mesh)


def test_real_vehicle_material_maps_at_4x(ring):
    path = VEHICLES / "openmaterial_truck/truck_example.gltf"
    if not path.exists():
        pytest.skip(f"shared vehicle models not found at {VEHICLES}")
    from ucad_cl.ingest import load_mesh
    mesh = load_mesh(path)
    out = decimate(mesh, mesh.n_faces // 4)
    assert out.n_faces <= mesh.n_faces // 4
    assert set(np.unique(out.face_material)) == set(np.unique(mesh.face_material))
    agree, _ = agreement(mesh, out, ring)
    assert agree >= 0.98, agree


# ----------------------------------------------------------------------------- render proxy

def _proxy_reference(mesh: Mesh, cells: int):
    """render_proxy's rule written plainly (a dict of cells, one vertex at a time): (the kept
    faces as input-vertex triples of representatives, the kept face mask)."""
    V = np.asarray(mesh.vertices, np.float64)
    lo = V.min(axis=0)
    side = np.linalg.norm(V.max(axis=0) - lo) / cells
    first: dict = {}
    rep = np.empty(len(V), np.int64)
    for i, v in enumerate(V):
        cell = tuple(int(c) for c in np.minimum(np.floor((v - lo) / side), cells))
        rep[i] = first.setdefault(cell, i)
    G = rep[np.asarray(mesh.faces, np.int64)]
    keep = np.array([len(set(g)) == 3 for g in G.tolist()])
    return G[keep], keep


def test_render_proxy_is_the_clustering_rule_and_moves_vertices_within_a_cell(ring):
    """Against a plain re-implementation: the same faces (as positions), in the same order,
    with their materials and nodes; every proxy vertex is an input vertex; no corner moves
    more than sqrt(3) / cells of the diagonal; silhouettes at 160 px all but unchanged."""
    from ucad_cl.decimate import render_proxy
    from ucad_cl.synth import make_vehicle

    mesh = make_vehicle(7, target_triangles=20_000).mesh()
    mesh.face_node = np.arange(mesh.n_faces, dtype=np.int32) % 5
    cells = 128
    out = render_proxy(mesh, cells)
    want, keep = _proxy_reference(mesh, cells)
    assert 0 < out.n_faces == len(want) < mesh.n_faces
    assert np.array_equal(out.vertices[out.faces], mesh.vertices[want])
    assert np.array_equal(out.face_material, mesh.face_material[keep])
    assert np.array_equal(out.face_node, mesh.face_node[keep])
    assert np.unique(out.faces).size == len(out.vertices)           # compact
    diag = np.linalg.norm(np.ptp(mesh.vertices, axis=0))
    moved = np.linalg.norm(out.vertices[out.faces] - mesh.vertices[mesh.faces[keep]], axis=-1)
    assert moved.max() <= np.sqrt(3.0) * diag / cells
    assert out.materials is mesh.materials and out.sha256 == mesh.sha256
    agree, silhouette = agreement(mesh, out, ring)
    assert silhouette <= 0.002 and agree >= 0.95, (silhouette, agree)
    again = render_proxy(mesh, cells)                                # deterministic
    assert np.array_equal(again.vertices, out.vertices) and np.array_equal(again.faces, out.faces)


def test_render_proxy_returns_the_mesh_when_nothing_or_everything_would_go():
    from ucad_cl.decimate import render_proxy

    V, F = grid(6)
    mesh = make_mesh(V, F, np.zeros(len(F), int))
    assert render_proxy(mesh, 10_000) is mesh            # one vertex per cell: nothing dropped
    assert not _proxy_reference(mesh, 1)[1].any() and render_proxy(mesh, 1) is mesh   # all
    flat = make_mesh(np.zeros((3, 3)), [[0, 1, 2]], [0])
    assert render_proxy(flat, 64) is flat                # a zero-size box
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="cells"):
            render_proxy(mesh, bad)
