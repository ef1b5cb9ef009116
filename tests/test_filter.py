"""Tests of ucad_cl.filter: hand-made meshes/maps with exact counts, real models, a ray-cast reference."""
from __future__ import annotations

import numpy as np
import pytest

from ucad_cl.filter import filter_mesh, filter_views
from ucad_cl.ingest import load_mesh
from ucad_cl.artifacts import CameraRing, Material, Mesh, ViewSet

from .conftest import VEHICLES


def _mesh(n_faces=4, materials=("a", "b"), face_material=None, vertices=None) -> Mesh:
    v = np.random.default_rng(0).uniform(-0.5, 0.5, (n_faces + 2, 3)) if vertices is None else vertices
    f = np.array([(i, i + 1, i + 2) for i in range(n_faces)], np.uint32).reshape(-1, 3)
    fm = (np.arange(n_faces) % len(materials)) if face_material is None else face_material
    return Mesh(path="hand.glb", sha256="0" * 64, vertices=v, faces=f,
                face_material=np.asarray(fm, np.uint16), materials=[Material(n) for n in materials])


def _views(counts: dict[int, int], n_views=2, size=16) -> ViewSet:
    """mat_id maps holding exactly counts[id] pixels of each id (split over views), rest background."""
    flat = np.zeros(n_views * size * size, np.uint16)
    pos = 0
    for mid, n in counts.items():
        flat[pos:pos + n] = mid
        pos += n
    assert pos <= flat.size
    flat = np.random.default_rng(1).permutation(flat)
    mat = flat.reshape(n_views, size, size)
    ring = CameraRing(K=np.eye(3), w2c=np.tile(np.eye(4), (n_views, 1, 1)), width=size, height=size,
                      azimuth=np.zeros(n_views), elevation=np.zeros(n_views), distance=2.0, near=0.1)
    tri = np.where(mat == 0, np.uint32(0xFFFFFFFF), np.uint32(0))
    depth = np.where(mat == 0, np.inf, 1.0).astype(np.float32)
    return ViewSet(cameras=ring, tri_id=tri, mat_id=mat, depth=depth)


# --------------------------------------------------------------------------- filter_mesh

def test_filter_mesh_reasons_in_order():
    assert filter_mesh(_mesh()).accepted
    v = filter_mesh(_mesh(n_faces=0))
    assert (v.accepted, v.reason) == (False, "empty")
    bad = _mesh()
    bad.vertices[3, 1] = np.nan
    v = filter_mesh(bad)
    assert v.reason == "non_finite" and "1 of 6" in v.detail
    v = filter_mesh(_mesh(n_faces=5), max_triangles=4)
    assert v.reason == "too_many_triangles" and "5" in v.detail and "4" in v.detail
    assert filter_mesh(_mesh(n_faces=4), max_triangles=4).accepted          # limit is inclusive
    # two materials in the table but only one used by faces -> too few
    v = filter_mesh(_mesh(face_material=[1, 1, 1, 1]))
    assert v.reason == "too_few_materials" and "1 distinct" in v.detail
    assert filter_mesh(_mesh(face_material=[1, 1, 1, 1]), min_materials=1).accepted
    v = filter_mesh(_mesh(materials=("a", "b", "c"), face_material=[0, 2, 0, 2]), min_materials=3)
    assert v.reason == "too_few_materials" and "2 distinct" in v.detail
    # order: too_many_triangles is reported before too_few_materials
    assert filter_mesh(_mesh(face_material=[0] * 4), max_triangles=2).reason == "too_many_triangles"


def test_filter_mesh_bad_input():
    with pytest.raises(ValueError, match="face_material refers to material 5"):
        filter_mesh(_mesh(face_material=[0, 5, 0, 1]))
    with pytest.raises(ValueError, match="face_material must have shape"):
        filter_mesh(_mesh(face_material=[0, 1]))
    m = _mesh()
    m.faces = m.faces[:, :2]
    with pytest.raises(ValueError, match=r"faces must have shape \(F, 3\)"):
        filter_mesh(m)
    with pytest.raises(ValueError, match="min_materials"):
        filter_mesh(_mesh(), min_materials=0)


def test_filter_mesh_real_models():
    if not (VEHICLES / "manifest.json").exists():
        pytest.skip("shared vehicle models not found")
    v = filter_mesh(load_mesh(VEHICLES / "kenney_truck_green/vehicle-truck-green.glb"))
    assert (v.accepted, v.reason) == (False, "too_few_materials")
    for rel in ("o3dv_car.glb", "cesium_milk_truck.glb", "a_frame_car/car.obj",
                "toy_car/ToyCar.gltf", "godot_truck_town_vehicles.glb"):
        assert filter_mesh(load_mesh(VEHICLES / rel)).accepted, rel
    v = filter_mesh(load_mesh(VEHICLES / "o3dv_car.glb"), max_triangles=1000)
    assert v.reason == "too_many_triangles"


# --------------------------------------------------------------------------- filter_views

def test_dominant_fraction_threshold_is_inclusive():
    mesh = _mesh()
    v = filter_views(mesh, _views({1: 97, 2: 3}))                 # exactly 0.97
    assert (v.accepted, v.reason) == (False, "dominant_material")
    assert "'a'" in v.detail and "0.9700" in v.detail and "100" in v.detail
    v = filter_views(mesh, _views({1: 96, 2: 4}), min_pixels=4)   # 0.96 < 0.97
    assert v.accepted, v.detail
    v = filter_views(mesh, _views({1: 3, 2: 97}))                 # the second material dominates
    assert v.reason == "dominant_material" and "'b'" in v.detail


def test_dominant_tie_names_lowest_material():
    v = filter_views(_mesh(), _views({1: 50, 2: 50}), dominant_fraction=0.5)
    assert v.reason == "dominant_material" and "material 0 ('a')" in v.detail


def test_too_few_visible_parts_min_pixels():
    mesh = _mesh(materials=("a", "b", "c"))
    v = filter_views(mesh, _views({1: 300, 2: 100, 3: 19}), min_visible_materials=3)
    assert v.reason == "too_few_visible_parts" and "2 material(s)" in v.detail
    assert filter_views(mesh, _views({1: 300, 2: 100, 3: 20}), min_visible_materials=3).accepted
    v = filter_views(mesh, _views({1: 300, 3: 10}), dominant_fraction=1.0)
    assert v.reason == "too_few_visible_parts"                    # only 'a' has >= 20 pixels
    v = filter_views(mesh, _views({}))
    assert v.reason == "too_few_visible_parts" and "no material is visible" in v.detail
    # a single visible material is reported as dominant (checked first)
    assert filter_views(mesh, _views({2: 50})).reason == "dominant_material"


def test_filter_views_bad_input():
    mesh = _mesh()
    views = _views({1: 10, 2: 10})
    with pytest.raises(ValueError, match="material id 3 but the mesh has 2"):
        filter_views(mesh, _views({1: 10, 3: 1}))
    bad = _views({1: 10})
    bad.mat_id = bad.mat_id.astype(np.int32)
    with pytest.raises(ValueError, match="uint16"):
        filter_views(mesh, bad)
    bad.mat_id = np.zeros((4, 4), np.uint16)
    with pytest.raises(ValueError, match=r"shape \(V, H, W\)"):
        filter_views(mesh, bad)
    with pytest.raises(ValueError, match="dominant_fraction"):
        filter_views(mesh, views, dominant_fraction=0.0)
    with pytest.raises(ValueError, match="min_pixels"):
        filter_views(mesh, views, min_pixels=0)


def test_filter_views_deterministic():
    mesh, views = _mesh(), _views({1: 60, 2: 40})
    assert filter_views(mesh, views) == filter_views(mesh, views)


# --------------------------------------------------------------------------- real renders

@pytest.mark.parametrize("rel,reason", [("kenney_truck_green/vehicle-truck-green.glb", "dominant_material"),
                                        ("o3dv_car.glb", ""),
                                        ("cesium_milk_truck.glb", "")])
def test_filter_views_on_renders_agrees_with_raycast(runtime, rel, reason):
    """filter_views on the rasterizer's maps and on Embree ray-cast maps give the same verdict."""
    pytest.importorskip("embreex")
    from ucad_cl.cameras import make_ring
    from ucad_cl.render import render_views

    from .reference import raycast_views
    if not (VEHICLES / rel).exists():
        pytest.skip(f"{rel} not found")
    mesh = load_mesh(VEHICLES / rel)
    ring = make_ring(azimuth_step=60.0, elevations=(15.0,), size=64)
    rendered = filter_views(mesh, render_views(mesh, ring))
    _, mat, depth = raycast_views(mesh, ring)
    cast = filter_views(mesh, ViewSet(ring, np.zeros(mat.shape, np.uint32), mat, depth))
    assert rendered.reason == cast.reason == reason, (rendered, cast)
    assert rendered.accepted == (reason == "")


def test_synth_single_material_rejected(tmp_path):
    synth = pytest.importorskip("ucad_cl.synth")
    bad = synth.make_vehicle(3, "sedan", messy=("single_material",))
    v = filter_mesh(load_mesh(bad.write(tmp_path)))
    assert (v.accepted, v.reason) == (False, "too_few_materials") == (False, bad.truth["expected_reject"])
    good = synth.make_vehicle(3, "sedan")
    assert good.truth["expected_reject"] is None
    assert filter_mesh(load_mesh(good.write(tmp_path))).accepted
