"""Tests of ucad_cl.ingest against the shared vehicle manifest, hand-made files, pymeshlab and trimesh."""
from __future__ import annotations

import hashlib
import json
import os
import re
import signal
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ucad_cl import ingest
from ucad_cl.ingest import IngestError, load_mesh_isolated
from ucad_cl.artifacts import IngestReport

from .conftest import VEHICLES

MANIFEST = VEHICLES / "manifest.json"
MODELS = json.loads(MANIFEST.read_text())["models"] if MANIFEST.exists() else []


def load_mesh(path, **kw):
    """Ingest in the file frame (orientation "file"): the tests here check ingest's own
    normalisation contract; tests/test_orient.py checks the orientation stage on top of it."""
    kw.setdefault("orientation", "file")
    return ingest.load_mesh(path, **kw)


def _vehicle(rel: str):
    if not (VEHICLES / rel).exists():
        pytest.skip(f"shared vehicle model {rel} not found")
    return VEHICLES / rel


def _write_obj(path, vertices, faces, extra: str = ""):
    lines = ["v " + " ".join(repr(float(c)) for c in row) for row in np.asarray(vertices, np.float64)]
    lines += ["f " + " ".join(str(i + 1) for i in f) for f in faces]
    path.write_text(extra + "\n".join(lines) + "\n", encoding="utf-8")
    return path


def _write_off(path, vertices, faces):
    rows = [f"OFF\n{len(vertices)} {len(faces)} 0"]
    rows += [" ".join(repr(float(c)) for c in row) for row in np.asarray(vertices, np.float64)]
    rows += [f"3 {a} {b} {c}" for a, b, c in faces]
    path.write_text("\n".join(rows) + "\n")
    return path


def _canonical_frame_holds(mesh, atol=1e-12):
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=atol)
    assert abs(np.linalg.norm(hi - lo) - 1.0) < atol


# --------------------------------------------------------------------------- real models

@pytest.mark.parametrize("model", MODELS, ids=[m["file"] for m in MODELS])
def test_real_model_matches_manifest(model):
    path = _vehicle(model["file"])
    mesh = load_mesh(path, clean=False)
    # drawn triangle count, material count, names (kept as written, incl. spaces / Japanese)
    assert mesh.n_faces == model["triangles"]
    assert len(mesh.materials) == model["material_count"]
    names = [m.name for m in mesh.materials]
    assert sorted(names) == sorted(model["materials"])
    per_material = {n: int(np.sum(mesh.face_material == i)) for i, n in enumerate(names)}
    assert per_material == model["triangles_per_material"]
    # dtypes and alignment
    assert mesh.vertices.dtype == np.float64 and mesh.faces.dtype == np.uint32
    assert mesh.face_material.dtype == np.uint16 and mesh.face_node.dtype == np.int32
    assert mesh.face_node.shape == (mesh.n_faces,) and mesh.face_node.min() >= 0
    assert mesh.face_node.max() < len(mesh.node_names)
    _canonical_frame_holds(mesh)
    # file_to_norm maps the manifest's file-frame bounds onto the canonical bounding box
    inv = np.linalg.inv(mesh.file_to_norm)
    corners = np.c_[np.stack([mesh.vertices.min(0), mesh.vertices.max(0)]), np.ones(2)] @ inv.T
    np.testing.assert_allclose(corners[0, :3], model["bounds_min"], atol=1e-4)
    np.testing.assert_allclose(corners[1, :3], model["bounds_max"], atol=1e-4)
    assert mesh.sha256 == load_mesh(path, clean=False).sha256


def test_cleaning_on_real_models_matches_pymeshlab():
    pymeshlab = pytest.importorskip("pymeshlab")
    for rel in ("o3dv_car.glb", "godot_truck_town_vehicles.glb",
                "kenney_truck_green/vehicle-truck-green.glb"):
        raw = load_mesh(_vehicle(rel), clean=False)
        ms = pymeshlab.MeshSet()
        ms.add_mesh(pymeshlab.Mesh(vertex_matrix=raw.vertices, face_matrix=raw.faces.astype(np.int32)))
        f0 = ms.current_mesh().face_number()
        ms.meshing_remove_null_faces()
        f1 = ms.current_mesh().face_number()
        ms.meshing_remove_duplicate_faces()
        f2 = ms.current_mesh().face_number()
        v0 = ms.current_mesh().vertex_number()
        ms.meshing_remove_unreferenced_vertices()
        v1 = ms.current_mesh().vertex_number()
        rep = load_mesh(_vehicle(rel)).report
        assert (rep.zero_area_faces, rep.duplicate_faces, rep.unreferenced_vertices) == (
            f0 - f1, f1 - f2, v0 - v1), rel
        assert rep.faces_in == f0 and rep.faces_out == f2
        assert rep.zero_area_faces > 0          # the check has something to find on these models


def test_draco_pair_same_geometry():
    a = load_mesh(_vehicle("ferrari_458.glb"))
    b = load_mesh(_vehicle("ferrari_458_nodraco.glb"))
    assert "draco decoded" in a.report.notes and "draco decoded" not in b.report.notes
    assert a.n_faces == b.n_faces
    np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_array_equal(a.face_material, b.face_material)
    np.testing.assert_allclose(a.vertices, b.vertices, atol=1e-9)
    assert np.abs(a.vertices).max() > 0.1                   # never placeholder zeros
    assert [m.name for m in a.materials] == [m.name for m in b.materials]
    assert a.sha256 != b.sha256


def test_draco_without_decoder_is_rejected(monkeypatch):
    path = _vehicle("ferrari_458.glb")
    monkeypatch.setitem(sys.modules, "DracoPy", None)       # import DracoPy -> ImportError
    with pytest.raises(IngestError) as e:
        load_mesh(path)
    assert e.value.reason == "unsupported_compression" and "ferrari_458.glb" in str(e.value)


def test_draco_placeholder_zeros_are_caught(monkeypatch):
    """If the up-front check were bypassed, trimesh's placeholder zeros must still be refused."""
    path = _vehicle("ferrari_458.glb")
    monkeypatch.setitem(sys.modules, "DracoPy", None)
    monkeypatch.setattr(ingest, "_check_compression", lambda *a: True)
    with pytest.raises(IngestError) as e:
        load_mesh(path)
    assert e.value.reason == "unsupported_compression" and "placeholder zeros" in str(e.value)


def test_instanced_wheels_drawn_at_each_node():
    mesh = load_mesh(_vehicle("cesium_milk_truck.glb"), clean=False)
    assert mesh.n_faces == 3624
    wheels = [m.name for m in mesh.materials].index("wheels")
    nodes = np.unique(mesh.face_node[mesh.face_material == wheels])
    assert len(nodes) == 2                                  # one wheel mesh, two nodes
    a, b = (mesh.vertices[np.unique(mesh.faces[mesh.face_node == n])] for n in nodes)
    assert a.shape == b.shape
    offset = b.mean(axis=0) - a.mean(axis=0)
    assert np.linalg.norm(offset) > 0.1                     # drawn at two different places
    np.testing.assert_allclose(b - offset, a, atol=1e-9)    # same geometry, translated


def test_obj_japanese_names_and_mtl_colours():
    path = _vehicle("a_frame_car/car.obj")
    mesh = load_mesh(path)
    names = {m.name: m for m in mesh.materials}
    assert {"マテリアル", "マテリアル.001"} <= set(names)
    # independent reference: parse Kd straight from the MTL text
    kd, current = {}, None
    for line in (path.parent / "car.mtl").read_text(encoding="utf-8").splitlines():
        parts = line.split()
        if parts and parts[0] == "newmtl":
            current = " ".join(parts[1:])
        elif parts and parts[0] == "Kd":
            kd[current] = tuple(float(x) for x in parts[1:4])
    for name, rgb in kd.items():
        np.testing.assert_allclose(names[name].base_color[:3], rgb)
        assert names[name].base_color[3] == 1.0 and names[name].alpha_mode == "OPAQUE"


def test_material_properties_from_gltf_json():
    toy = _vehicle("toy_car/ToyCar.gltf")
    raw = json.loads(toy.read_text())
    glass_raw = next(m for m in raw["materials"] if m["name"] == "Glass")
    expected = glass_raw["extensions"]["KHR_materials_transmission"]["transmissionFactor"]
    mats = {m.name: m for m in load_mesh(toy).materials}
    assert expected > 0 and mats["Glass"].transmission == pytest.approx(expected)
    assert mats["ToyCar"].has_texture and mats["ToyCar"].transmission == 0.0
    ov = {m.name: m for m in load_mesh(_vehicle("openmaterial_vehicle/vehicle_example.gltf")).materials}
    assert ov["Glass"].alpha_mode == "BLEND" and ov["Glass"].base_color[3] == pytest.approx(0.4)
    assert load_mesh(_vehicle("kenney_truck_green/vehicle-truck-green.glb")).materials[0].has_texture
    assert not any(m.has_texture for m in load_mesh(_vehicle("o3dv_car.glb")).materials)


def _identity(fmt: str, *blobs: bytes) -> str:
    """Independent reference of the content key: tag, format, then length-prefixed blobs."""
    h = hashlib.sha256(b"ucad-mesh/1\0" + fmt.encode() + b"\0")
    for b in blobs:
        h.update(len(b).to_bytes(8, "little") + b)
    return h.hexdigest()


def test_sha256_of_file_and_gltf_buffers(tmp_path):
    glb = _vehicle("o3dv_car.glb")
    assert load_mesh(glb).sha256 == _identity("glb", glb.read_bytes())
    gltf = _vehicle("openmaterial_vehicle/vehicle_example.gltf")
    key = _identity("gltf", gltf.read_bytes(), gltf.with_suffix(".bin").read_bytes())
    assert load_mesh(gltf).sha256 == key == ingest.mesh_identity(gltf)
    obj = _vehicle("a_frame_car/car.obj")
    key = _identity("obj", obj.read_bytes(), (obj.parent / "car.mtl").read_bytes())
    assert load_mesh(obj).sha256 == key == ingest.mesh_identity(obj)
    # identity = content + format: the same bytes under another suffix are another mesh, the
    # same bytes under another name with the same suffix the same mesh
    (tmp_path / "copy.glb").write_bytes(glb.read_bytes())
    (tmp_path / "copy.stl").write_bytes(glb.read_bytes())
    assert ingest.mesh_identity(tmp_path / "copy.glb") == load_mesh(glb).sha256
    assert ingest.mesh_identity(tmp_path / "copy.stl") == _identity("stl", glb.read_bytes())
    assert ingest.mesh_identity(tmp_path / "copy.stl") != load_mesh(glb).sha256


def test_deterministic_bit_identical():
    path = _vehicle("openmaterial_truck/truck_example.gltf")
    a, b = load_mesh(path), load_mesh(path)
    for field in ("vertices", "faces", "face_material", "face_node", "file_to_norm"):
        assert getattr(a, field).tobytes() == getattr(b, field).tobytes(), field
    assert a.materials == b.materials and a.node_names == b.node_names and a.report == b.report


# --------------------------------------------------------------------------- hand-made files

def test_cleaning_counts_hand_made(tmp_path):
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [2, 1, 1], [0, 0, 1],
                  [5, 5, 5], [6, 5, 5], [5, 6, 5]], dtype=np.float64)    # 7..9 unreferenced
    good = [(0, 1, 2), (0, 2, 3), (1, 4, 5), (3, 6, 5)]
    faces = [good[0], (2, 0, 1), good[1], (0, 1, 4), good[2], (0, 3, 2), good[3]]
    # (2,0,1) duplicates face 0 (rotated), (0,3,2) duplicates (0,2,3) reversed, (0,1,4) is collinear
    mesh = load_mesh(_write_off(tmp_path / "dirty.off", v, faces))
    r = mesh.report
    assert (r.faces_in, r.faces_out, r.duplicate_faces, r.zero_area_faces,
            r.unreferenced_vertices) == (7, 4, 2, 1, 3)
    assert mesh.vertices.shape == (7, 3)
    # kept faces are the good ones, in order, on the kept (order-preserved) vertices
    inv = np.linalg.inv(mesh.file_to_norm)
    back = np.c_[mesh.vertices, np.ones(7)] @ inv.T
    np.testing.assert_allclose(back[:, :3], v[:7], atol=1e-12)
    np.testing.assert_array_equal(mesh.faces, good)
    # independent reference: pymeshlab on the same arrays
    pymeshlab = pytest.importorskip("pymeshlab")
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=np.array(faces, np.int32)))
    ms.meshing_remove_null_faces()
    ms.meshing_remove_duplicate_faces()
    ms.meshing_remove_unreferenced_vertices()
    assert ms.current_mesh().face_number() == 4 and ms.current_mesh().vertex_number() == 7
    # clean=False keeps everything
    raw = load_mesh(tmp_path / "dirty.off", clean=False)
    assert raw.n_faces == 7 and raw.vertices.shape == (10, 3) and raw.report.duplicate_faces == 0


def test_duplicates_with_different_materials_are_kept():
    """Coplanar duplicates of two materials are a renderer hard case: ingest must not hide them."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0]], dtype=np.float64)
    f = np.array([[0, 1, 2], [2, 1, 0], [0, 2, 1], [0, 1, 3]])
    mat = np.array([0, 1, 0, 0])
    rep = IngestReport()
    _, faces, fm, fn = ingest._clean(v, f, mat, np.arange(4), rep)
    # face 1 (material 1) stays; face 2 repeats face 0 with the same material; face 3 is zero-area
    np.testing.assert_array_equal(faces, [[0, 1, 2], [2, 1, 0]])
    np.testing.assert_array_equal(fm, [0, 1])
    np.testing.assert_array_equal(fn, [0, 1])               # lowest index of a duplicate kept
    assert (rep.duplicate_faces, rep.zero_area_faces, rep.unreferenced_vertices) == (1, 1, 1)


def test_ngons_are_triangulated(tmp_path):
    v = [[0, 0, 0], [2, 0, 0], [3, 1, 0], [1.5, 2.5, 0], [0, 1, 0],      # convex pentagon
         [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]]                      # unit quad
    path = _write_obj(tmp_path / "ngon.obj", v, [(0, 1, 2, 3, 4), (5, 6, 7, 8)])
    mesh = load_mesh(path)
    assert mesh.n_faces == 3 + 2
    p = np.asarray(v)[:5, :2]
    shoelace = 0.5 * abs(np.dot(p[:, 0], np.roll(p[:, 1], -1)) - np.dot(p[:, 1], np.roll(p[:, 0], -1)))
    scale = np.linalg.inv(mesh.file_to_norm)[0, 0]
    tri = mesh.vertices[mesh.faces.astype(np.int64)] * scale
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    assert area.sum() == pytest.approx(shoelace + 1.0, rel=1e-12)


def _gltf_with_wireframe(path, glb: bool):
    """One mesh: tetra A ('paint'), a LINES and a POINTS primitive ('wire', a wireframe helper
    on A's vertices), tetra B ('glass', 3 units along x), a LINE_STRIP ('wire'); as .gltf with a
    data: URI buffer or as .glb. Returns the two tetras' file-frame vertices and faces."""
    import base64
    import struct
    va = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    vb = va + np.float32([3, 0, 0])
    ia = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.uint32)
    il = np.array([0, 1, 1, 2, 2, 3], np.uint32)
    blobs = [va.tobytes(), ia.tobytes(), il.tobytes(), vb.tobytes()]
    offsets = np.cumsum([0] + [len(b) for b in blobs]).tolist()
    buf = b"".join(blobs)

    def acc(view, n, ctype, typ, **kw):
        return dict(bufferView=view, componentType=ctype, count=n, type=typ, **kw)
    buffer = {"byteLength": len(buf)}
    if not glb:
        buffer["uri"] = "data:application/octet-stream;base64," + base64.b64encode(buf).decode()
    doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
           "nodes": [{"mesh": 0, "name": "car"}], "buffers": [buffer],
           "bufferViews": [{"buffer": 0, "byteOffset": offsets[i], "byteLength": len(b)}
                           for i, b in enumerate(blobs)],
           "accessors": [acc(0, 4, 5126, "VEC3", min=[0, 0, 0], max=[1, 1, 1]),
                         acc(1, 12, 5125, "SCALAR"), acc(2, 6, 5125, "SCALAR"),
                         acc(3, 4, 5126, "VEC3", min=[3, 0, 0], max=[4, 1, 1])],
           "materials": [{"name": "paint"}, {"name": "wire"}, {"name": "glass"}],
           "meshes": [{"primitives": [
               {"attributes": {"POSITION": 0}, "indices": 1, "material": 0},
               {"attributes": {"POSITION": 0}, "indices": 2, "material": 1, "mode": 1},
               {"attributes": {"POSITION": 0}, "material": 1, "mode": 0},
               {"attributes": {"POSITION": 3}, "indices": 1, "material": 2},
               {"attributes": {"POSITION": 3}, "material": 1, "mode": 3}]}]}
    text = json.dumps(doc).encode()
    if glb:
        text += b" " * (-len(text) % 4)
        body = struct.pack("<II", len(text), 0x4E4F534A) + text
        body += struct.pack("<II", len(buf), 0x004E4942) + buf
        path.write_bytes(struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body)
    else:
        path.write_text(text.decode())
    return np.concatenate([va, vb]).astype(np.float64), np.concatenate([ia, ia + 4])


@pytest.mark.parametrize("suffix", [".gltf", ".glb"])
def test_lines_and_points_primitives_are_skipped_with_a_note(tmp_path, suffix):
    path = tmp_path / f"wire{suffix}"
    vertices, faces = _gltf_with_wireframe(path, glb=suffix == ".glb")
    mesh = load_mesh(path)
    # the two tetras' triangles, in file order, with their own materials; 'wire' draws nothing
    assert [m.name for m in mesh.materials] == ["paint", "glass"]
    np.testing.assert_array_equal(mesh.face_material, [0] * 4 + [1] * 4)
    file_xyz = np.c_[mesh.vertices, np.ones(len(mesh.vertices))] @ np.linalg.inv(
        mesh.file_to_norm).T
    np.testing.assert_allclose(file_xyz[mesh.faces.astype(np.int64), :3], vertices[faces],
                               atol=1e-12)
    assert mesh.report.notes == ["skipped non-triangle primitives (1 points, 1 lines, "
                                 "1 line strip): not drawn, not labelled"]
    # the same through the worker-side loader the build uses
    assert load_mesh_isolated(path, orientation="file").report.notes == mesh.report.notes


def _box(lo, hi):
    """(8, 3) corners and (12, 3) outward triangles of an axis-aligned box."""
    import trimesh

    box = trimesh.creation.box(bounds=[lo, hi])
    return np.asarray(box.vertices, np.float64), np.asarray(box.faces)


def _car_obj(path, plate=None, lid=False, wheels=True, plate_y=0.0, sag=0.0):
    """An OBJ car (a body box on four wheel boxes, materials body and wheel, y up) with, as a
    third material: a quad at y = ``plate_y`` spanning ``plate`` = (x0, z0, x1, z1) (its second triangle
    wound the other way; with ``sag``, four triangles meeting at a centre ``sag`` lower), or
    with ``lid`` a flat panel exactly on the body's top."""
    parts = [("body", *_box((0.0, 0.3, 0.0), (4.0, 1.5, 1.8)))]
    for x in (0.5, 3.0) if wheels else ():
        for z in (-0.1, 1.6):
            parts.append(("wheel", *_box((x, 0.0, z), (x + 0.6, 0.6, z + 0.3))))
    if plate is not None:
        x0, z0, x1, z1 = plate
        quad = np.array([[x0, plate_y, z0], [x1, plate_y, z0], [x1, plate_y, z1],
                         [x0, plate_y, z1]], np.float64)
        tris = np.array([(0, 2, 1), (0, 2, 3)])
        if sag:
            quad = np.vstack([quad, quad.mean(axis=0) - (0.0, sag, 0.0)])
            tris = np.array([(0, 4, 1), (1, 4, 2), (2, 4, 3), (3, 4, 0)])
        parts.append(("shadow", quad, tris))
    if lid:
        top = np.array([[0, 1.5, 0], [4, 1.5, 0], [4, 1.5, 1.8], [0, 1.5, 1.8]], np.float64)
        parts.append(("roof", top, np.array([(0, 2, 1), (0, 3, 2)])))
    rows, base = [f"mtllib {path.stem}.mtl"], 1
    for name, v, f in parts:
        rows += [f"v {a!r} {b!r} {c!r}" for a, b, c in v.tolist()] + [f"usemtl {name}"]
        rows += [f"f {a + base} {b + base} {c + base}" for a, b, c in f.tolist()]
        base += len(v)
    path.write_text("\n".join(rows) + "\n", encoding="utf-8")
    names = dict.fromkeys(name for name, _, _ in parts)
    path.with_suffix(".mtl").write_text("".join(f"newmtl {n}\nKd 0.5 0.5 0.5\n" for n in names))
    return path


def test_a_ground_plate_spanning_the_model_is_left_out_with_a_note(tmp_path):
    """A baked-shadow quad under the whole car (larger than its outline, mixed winding) is left
    out with a note, and the canonical frame is the car's alone; a plate inside the outline, one
    through the car's middle, a sagging sheet under it, a roof panel exactly the body's top
    (with wheels and without: a box's lid) and a one-material model keep every face."""
    car = load_mesh(_car_obj(tmp_path / "plain.obj"))
    shadow = load_mesh(_car_obj(tmp_path / "shadow.obj", plate=(-0.4, -0.6, 4.5, 2.3)))
    assert sorted(m.name for m in shadow.materials) == ["body", "wheel"]
    assert shadow.report.notes == ["material 'shadow' left out: a flat plate spanning the whole "
                                   "model (2 faces; a baked shadow or ground sheet, not part of "
                                   "the vehicle)"]
    assert shadow.n_faces == car.n_faces == shadow.report.faces_in - 2
    np.testing.assert_array_equal(shadow.vertices, car.vertices)     # the car's frame alone
    np.testing.assert_array_equal(shadow.file_to_norm, car.file_to_norm)
    for name, kw in [("inside", dict(plate=(0.2, 0.1, 3.8, 1.7))),
                     ("roof", dict(lid=True)), ("lid", dict(lid=True, wheels=False)),
                     ("through", dict(plate=(-0.4, -0.6, 4.5, 2.3), plate_y=0.9)),
                     ("sagging", dict(plate=(-0.4, -0.6, 4.5, 2.3), sag=0.05))]:
        kept = load_mesh(_car_obj(tmp_path / f"{name}.obj", **kw))
        assert kept.n_faces == kept.report.faces_in, name
        assert not any("left out" in n for n in kept.report.notes), name
    one = tmp_path / "one.obj"
    one.write_text(_car_obj(tmp_path / "tmp.obj", plate=(-0.4, -0.6, 4.5, 2.3)).read_text()
                   .replace("usemtl wheel", "usemtl body").replace("usemtl shadow", "usemtl body")
                   .replace("mtllib tmp.mtl", ""))
    assert load_mesh(one).n_faces == 4 * 12 + 12 + 2


def test_ground_plates_test_at_most_the_largest_materials():
    """A file of many large one-triangle materials (hostile: each is flat) has only the
    ``PLATE_CANDIDATES`` largest tested, chosen by box diagonal (ties: the lower material)."""
    from ucad_cl import ground

    n = 3 * ground.PLATE_CANDIDATES
    size = 1.0 + np.arange(n) % 7                     # repeated sizes: ties
    v = np.zeros((3 * n, 3))
    v[1::3, 0], v[2::3, 1] = size, size
    faces, mats = np.arange(3 * n).reshape(n, 3), np.arange(n)
    got = ground._large_materials(v, faces, mats, 0.0)
    want = sorted(sorted(range(n), key=lambda m: (-size[m], m))[:ground.PLATE_CANDIDATES])
    assert got == want
    assert ground.ground_plates(v, faces, mats) == []


def test_real_baked_shadow_quad_is_left_out():
    """The Toyama sedan's 'Shadow' (a 2-triangle baked-shadow quad under the car, documented
    in the manifest as a helper) is left out; the vehicle's ten materials stay."""
    mesh = ingest.load_mesh(_vehicle("toyama_xr_sedan/sedan.glb"))
    assert "Shadow" not in [m.name for m in mesh.materials] and len(mesh.materials) == 10
    assert mesh.report.faces_in - mesh.report.faces_out == 2
    assert any("'Shadow' left out" in n for n in mesh.report.notes)


def test_obj_alpha_from_d_and_tr(tmp_path):
    (tmp_path / "m.mtl").write_text("newmtl glassy\nKd 0.1 0.2 0.3\nd 0.25\n"
                                    "newmtl tinted\nKd 1 1 1\nTr 0.6\n")
    v = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [0, 1, 1]]
    text = ("mtllib m.mtl\n" + "".join(f"v {x} {y} {z}\n" for x, y, z in v)
            + "usemtl glassy\nf 1 2 3\nusemtl tinted\nf 4 5 6\n")
    (tmp_path / "a.obj").write_text(text)
    mats = {m.name: m for m in load_mesh(tmp_path / "a.obj").materials}
    assert mats["glassy"].base_color == pytest.approx((0.1, 0.2, 0.3, 0.25))
    assert mats["glassy"].alpha_mode == "BLEND"
    assert mats["tinted"].base_color[3] == pytest.approx(0.4)
    # the .mtl is part of the content hash
    h1 = load_mesh(tmp_path / "a.obj").sha256
    (tmp_path / "m.mtl").write_text((tmp_path / "m.mtl").read_text().replace("0.25", "0.5"))
    assert load_mesh(tmp_path / "a.obj").sha256 != h1


def _tetra():
    import trimesh
    return trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]],
                           [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], process=False)


def _signed_volumes(mesh):
    out = []
    for n in range(len(mesh.node_names)):
        t = mesh.vertices[mesh.faces[mesh.face_node == n].astype(np.int64)]
        out.append(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0)
    return np.array(out)


def test_shared_and_same_named_materials_and_mirrored_node(tmp_path):
    import trimesh
    from trimesh.visual import TextureVisuals
    from trimesh.visual.material import PBRMaterial
    red = PBRMaterial(name="paint", baseColorFactor=[255, 0, 0, 255])
    blue = PBRMaterial(name="paint", baseColorFactor=[0, 0, 255, 255])
    scene = trimesh.Scene()
    for i, (mat, sx) in enumerate([(red, 1.0), (blue, 1.0), (red, -1.0)]):
        g = _tetra()
        g.visual = TextureVisuals(material=mat)
        t = np.diag([sx, 1.0, 1.0, 1.0])
        t[0, 3] = 3.0 * i
        scene.add_geometry(g, node_name=f"n{i}", geom_name=f"g{i}", transform=t)
    scene.export(tmp_path / "s.glb")
    mesh = load_mesh(tmp_path / "s.glb")
    assert [m.name for m in mesh.materials] == ["paint", "paint"]       # same name, two materials
    assert mesh.materials[0].base_color[:3] == pytest.approx((1, 0, 0))
    assert mesh.materials[1].base_color[:3] == pytest.approx((0, 0, 1))
    np.testing.assert_array_equal(np.bincount(mesh.face_material), [8, 4])  # red shared by 2 nodes
    assert sorted(mesh.node_names) == ["n0", "n1", "n2"]      # draw order: trimesh traversal
    vols = _signed_volumes(mesh)
    assert np.all(vols > 0)                      # mirrored instance keeps outward-facing winding
    np.testing.assert_allclose(vols, vols[0])


@pytest.mark.parametrize("offset,scale", [(1e5, 1.0), (0.0, 1e-6), (0.0, 1e6), (-3e5, 1e3)])
def test_far_and_scaled_normalise_in_float64(tmp_path, offset, scale):
    rng = np.random.default_rng(7)
    base = rng.uniform(-1, 1, size=(39, 3))
    faces = [(i, i + 1, i + 2) for i in range(0, 39, 3)]
    ref = load_mesh(_write_obj(tmp_path / "ref.obj", base, faces))
    moved = load_mesh(_write_obj(tmp_path / "moved.obj", base * scale + offset, faces))
    _canonical_frame_holds(moved, atol=1e-10)     # file coordinates themselves round at 1e5
    np.testing.assert_allclose(moved.vertices, ref.vertices, atol=1e-9)
    raw = np.c_[base * scale + offset, np.ones(len(base))]
    np.testing.assert_allclose(raw @ moved.file_to_norm.T[:, :3], moved.vertices, atol=1e-12)


def test_far_node_translation_keeps_float64_precision(tmp_path):
    """A 1e5 node translation (float64 in the glTF JSON) on float32 geometry loses nothing."""
    import trimesh
    g = trimesh.creation.icosphere(subdivisions=1)
    near, far = trimesh.Scene(), trimesh.Scene()
    near.add_geometry(g.copy(), node_name="n", geom_name="g")
    t = np.eye(4)
    t[:3, 3] = [1e5, -2e5, 3e5]
    far.add_geometry(g.copy(), node_name="n", geom_name="g", transform=t)
    near.export(tmp_path / "near.glb")
    far.export(tmp_path / "far.glb")
    a, b = load_mesh(tmp_path / "near.glb"), load_mesh(tmp_path / "far.glb")
    np.testing.assert_allclose(b.vertices, a.vertices, atol=1e-9)
    np.testing.assert_allclose(np.linalg.inv(b.file_to_norm)[:3, 3],
                               t[:3, 3] + np.linalg.inv(a.file_to_norm)[:3, 3], rtol=1e-12)


# --------------------------------------------------------------------------- errors

def _expect(path, reason):
    with pytest.raises(IngestError) as e:
        load_mesh(path)
    assert e.value.reason == reason, str(e.value)
    assert os.path.basename(str(path)) in str(e.value)
    assert isinstance(e.value, ValueError)
    return str(e.value)


def test_errors_name_file_and_reason(tmp_path):
    _write_obj(tmp_path / "nan.obj", [[0, 0, 0], [1, 0, 0], [np.nan, 1, 0]], [(0, 1, 2)])
    assert "NaN" in _expect(tmp_path / "nan.obj", "non_finite")
    _write_obj(tmp_path / "inf.obj", [[0, 0, 0], [1, 0, np.inf], [0, 1, 0]], [(0, 1, 2)])
    _expect(tmp_path / "inf.obj", "non_finite")
    (tmp_path / "zero.obj").write_bytes(b"")
    _expect(tmp_path / "zero.obj", "empty")
    (tmp_path / "points.obj").write_text("v 0 0 0\nv 1 0 0\n")
    _expect(tmp_path / "points.obj", "empty")
    _write_obj(tmp_path / "flat.obj", [[0, 0, 0], [1, 1, 1], [2, 2, 2]], [(0, 1, 2)])
    _expect(tmp_path / "flat.obj", "empty")                # only a zero-area face
    assert "not found" in _expect(tmp_path / "missing.glb", "unreadable")
    (tmp_path / "car.fbx").write_bytes(b"Kaydara FBX Binary  \x00")
    assert ".fbx" in _expect(tmp_path / "car.fbx", "unsupported_format")
    (tmp_path / "junk.glb").write_bytes(b"this is not a glb file at all")
    _expect(tmp_path / "junk.glb", "unreadable")
    (tmp_path / "junk.ply").write_bytes(b"\x00\x01garbage" * 10)
    _expect(tmp_path / "junk.ply", "unreadable")


def test_truncated_glb(tmp_path):
    data = _vehicle("o3dv_car.glb").read_bytes()
    (tmp_path / "cut.glb").write_bytes(data[: len(data) // 2])
    assert "truncated" in _expect(tmp_path / "cut.glb", "unreadable")
    (tmp_path / "head.glb").write_bytes(data[:10])
    _expect(tmp_path / "head.glb", "unreadable")


def test_gltf_missing_buffer(tmp_path):
    src = _vehicle("openmaterial_vehicle/vehicle_example.gltf")
    (tmp_path / "v.gltf").write_bytes(src.read_bytes())        # .bin not copied
    assert "vehicle_example.bin" in _expect(tmp_path / "v.gltf", "missing_reference")


def test_too_many_materials_for_uint16_ids(monkeypatch):
    monkeypatch.setattr(ingest, "MAX_MATERIALS", 8)
    assert "9 materials" in _expect(_vehicle("o3dv_car.glb"), "unsupported_format")


@pytest.mark.parametrize("suffix", ["ply", "stl", "off", "glb"])
def test_single_material_formats(tmp_path, suffix):
    import trimesh
    box = trimesh.creation.box(extents=(4.0, 2.0, 1.0))
    box.apply_translation((10.0, 0.0, -3.0))
    box.export(tmp_path / f"box.{suffix}")
    mesh = load_mesh(tmp_path / f"box.{suffix}")
    assert mesh.n_faces == 12 and len(mesh.materials) == 1
    _canonical_frame_holds(mesh)
    # canonical box: extents (4, 2, 1) / sqrt(21), Y stays up (no axis swap)
    np.testing.assert_allclose(mesh.vertices.max(0) - mesh.vertices.min(0),
                               np.array([4.0, 2.0, 1.0]) / np.sqrt(21.0), atol=1e-7)


def test_ingest_error_rejects_unknown_reason():
    with pytest.raises(ValueError, match="unknown ingest reason"):
        IngestError("x.glb", "bogus", "msg")


# --------------------------------------------------------------------------- isolation

def _segfault_loader(path, clean=True):
    os.kill(os.getpid(), signal.SIGSEGV)


def _sleepy_loader(path, clean=True):
    time.sleep(60)


def _raising_loader(path, clean=True):
    raise RuntimeError("native library said no")


def test_isolated_matches_in_process():
    """Same bits in a fresh interpreter (another str hash seed): no set/hash order leaks in."""
    path = _vehicle("openmaterial_truck/truck_example.gltf")
    a, b = load_mesh_isolated(path, timeout=60), ingest.load_mesh(path)
    for field in ("vertices", "faces", "face_material", "face_node", "file_to_norm"):
        assert getattr(a, field).tobytes() == getattr(b, field).tobytes(), field
    assert a.materials == b.materials and a.node_names == b.node_names


def _in_modules(name):
    return name in sys.modules


def _exits_slowly(seconds):
    import atexit
    atexit.register(time.sleep, seconds)       # runs only if the interpreter shuts down
    return "answered"


def _pid():
    return os.getpid()


def test_isolated_child_warms_answers_calls_and_leaves_at_once():
    """system.IsolatedChild: the modules ``warm`` names are imported before the first call (a
    module that does not import is skipped; without ``warm`` the same call says not imported);
    one child answers call after call until a call crashes it (then ``alive`` is False and a
    call says it died) or it is closed; a closed child leaves at once (no interpreter shutdown
    waited for: an atexit handler does not run) unless its last call asked for a clean exit
    (its exit checked); close() kills a child never called."""
    import psutil

    from ucad_cl.system import IsolatedCallFailed, IsolatedChild, call_isolated

    with IsolatedChild(warm=("no_such_module_ucad", "xml.dom.pulldom")) as child:
        assert child.call(_in_modules, "xml.dom.pulldom", timeout=60) is True
        first = child.call(_pid, timeout=60)
        assert child.call(_pid, timeout=60) == first != os.getpid() and child.alive
        with pytest.raises(ValueError, match="bad input"):
            child.call(_raises_value_error, "input", timeout=60)
        assert child.call(_pid, timeout=60) == first              # an exception is an answer
        with pytest.raises(IsolatedCallFailed, match="SIGSEGV"):
            child.call(_segfault_loader, "x", timeout=60)
        assert not child.alive
        with pytest.raises(IsolatedCallFailed, match="died"):
            child.call(_pid, timeout=60)
    with pytest.raises(RuntimeError, match="closed"):
        child.call(_pid, timeout=60)
    assert call_isolated(_in_modules, "xml.dom.pulldom", timeout=60) is False
    t0 = time.monotonic()
    assert call_isolated(_exits_slowly, 30, timeout=60) == "answered"
    with IsolatedChild() as child:
        assert child.call(_exits_slowly, 30, timeout=60) == "answered"
    assert time.monotonic() - t0 < 20
    t0 = time.monotonic()
    assert call_isolated(_exits_slowly, 2, timeout=60, clean_exit=True) == "answered"
    assert time.monotonic() - t0 >= 2
    with IsolatedChild(warm=("xml.dom.pulldom",), hide=("xml.dom",)) as child:
        assert child.call(_in_modules, "xml.dom.pulldom", timeout=60) is False  # hidden
        assert child.call(_in_modules, "xml.dom", timeout=60) is False
        assert child.call(_imports, "xml.dom.pulldom", timeout=60) is True      # and back
    before = {p.pid for p in psutil.Process().children()}
    child = IsolatedChild(warm=("trimesh",))
    (new,) = [p for p in psutil.Process().children() if p.pid not in before]
    child.close()
    assert not new.is_running() and not child.alive


def _imports(name):
    import importlib
    return importlib.import_module(name).__name__ == name


def test_mesh_readers_child_reads_every_real_model_as_this_process_without_scipy(tmp_path):
    """The mesh reader's child (``system.reader_child``, ``ingest.MeshLoader``'s) imports
    trimesh with SciPy hidden (``system.READER_HIDDEN``: half of trimesh's import, for functions
    a read never calls): every shared real model (GLB with and without Draco, glTF with external
    buffers, OBJ+MTL), a LINES/POINTS glTF and PLY, OFF and STL files read there give this
    process's mesh field for field (the same arrays to the byte, materials, nodes, report) or
    the same error, and SciPy is still not imported in the child after all the reads; this
    process's own import of it works."""
    import dataclasses

    import trimesh

    from ucad_cl.system import reader_child

    if not MODELS or not (VEHICLES / MODELS[0]["file"]).exists():
        pytest.skip("shared vehicle models not found")
    _gltf_with_wireframe(tmp_path / "wire.glb", glb=True)
    paths = [VEHICLES / m["file"] for m in MODELS] + [tmp_path / "wire.glb"]
    for ext in ("ply", "off", "stl"):                 # the other formats ingest reads
        trimesh.creation.box().export(tmp_path / f"box.{ext}")
        paths.append(tmp_path / f"box.{ext}")
    with reader_child() as reader:
        with ingest.MeshLoader(child=reader) as loader:
            for path in paths:
                got = []
                for read in (loader.load, lambda p: ingest.load_mesh(p, orientation=None)):
                    try:
                        got.append(read(path))
                    except IngestError as e:
                        got.append(f"{e.reason}: {e}")
                child, here = got
                if isinstance(here, str) or isinstance(child, str):
                    assert child == here, path
                    continue
                for f in dataclasses.fields(here):
                    a, b = getattr(child, f.name), getattr(here, f.name)
                    if isinstance(b, np.ndarray):
                        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), (path, f.name)
                    else:
                        assert a == b, (path, f.name)
            assert reader.call(_in_modules, "scipy", timeout=60) is False
            assert reader.call(_in_modules, "trimesh", timeout=60) is True
    import scipy.spatial  # noqa: F401 - hidden in the child only
    assert sys.modules.get("scipy") is not None


def _sleep_then_pid(seconds):
    time.sleep(seconds)
    return os.getpid()


def test_isolated_child_submitted_call_runs_ahead():
    """IsolatedChild.submit: the call runs in the child while this process goes on (a 1 s call
    submitted, 1 s spent here, its answer then collected at once by the call with the same
    arguments); any other call before that is refused; a crash during it is the collecting
    call's; closing with a submitted call nobody collected kills the child (no wait for it)."""
    from ucad_cl.system import IsolatedCallFailed, IsolatedChild

    with IsolatedChild() as child:
        child.call(_pid, timeout=60)                 # the interpreter is up
        child.submit(_sleep_then_pid, 1.0)
        with pytest.raises(RuntimeError, match="submitted"):
            child.submit(_pid)
        with pytest.raises(RuntimeError, match="submitted"):
            child.call(_pid, timeout=60)
        time.sleep(1.2)
        t0 = time.monotonic()
        assert child.call(_sleep_then_pid, 1.0, timeout=60) == child.call(_pid, timeout=60)
        assert time.monotonic() - t0 < 0.5
        child.submit(_segfault_loader, "x")
        with pytest.raises(IsolatedCallFailed, match="SIGSEGV"):
            child.call(_segfault_loader, "x", timeout=60)
    child = IsolatedChild()
    child.submit(_sleep_then_pid, 30.0)
    t0 = time.monotonic()
    child.close()
    assert time.monotonic() - t0 < 5.0 and not child.alive


def test_mesh_loader_prefetch_reads_ahead_and_gives_the_same_mesh(tmp_path):
    """ingest.MeshLoader.prefetch: the read runs in the child ahead of ``load`` (which then
    returns at once), the mesh is the one ``load_mesh`` gives here; a read ahead of another
    file than the one loaded is dropped (a new child reads the right one), and a second
    prefetch before any load too; in this process (not isolated) prefetch does nothing."""
    path = _vehicle("openmaterial_truck/truck_example.gltf")
    other = _vehicle("cesium_milk_truck.glb")
    here = ingest.load_mesh(path, orientation=None)
    with ingest.MeshLoader(isolated=True) as loader:
        loader.prefetch(path)
        time.sleep(3.0)                               # imports and the read happen meanwhile
        t0 = time.monotonic()
        got = loader.load(path)
        assert time.monotonic() - t0 < 0.5
        assert got.vertices.tobytes() == here.vertices.tobytes()
        assert got.faces.tobytes() == here.faces.tobytes() and got.materials == here.materials
        loader.prefetch(other)
        assert loader.load(path).faces.tobytes() == here.faces.tobytes()
        loader.prefetch(other)
        loader.prefetch(path)
        assert loader.load(path).face_material.tobytes() == here.face_material.tobytes()
    with ingest.MeshLoader(isolated=False) as loader:
        loader.prefetch(path)
        assert loader.load(path).faces.tobytes() == here.faces.tobytes()


def test_isolated_errors(tmp_path):
    with pytest.raises(IngestError) as e:
        load_mesh_isolated(tmp_path / "nope.glb", timeout=60)
    assert e.value.reason == "unreadable" and "nope.glb" in str(e.value)
    with pytest.raises(IngestError) as e:
        load_mesh_isolated(tmp_path / "seg.glb", timeout=60, loader=_segfault_loader)
    assert e.value.reason == "loader_crashed" and "SIGSEGV" in str(e.value)
    assert "seg.glb" in str(e.value)
    t0 = time.monotonic()
    with pytest.raises(IngestError) as e:
        load_mesh_isolated(tmp_path / "slow.glb", timeout=1.0, loader=_sleepy_loader)
    assert e.value.reason == "timeout" and "slow.glb" in str(e.value)
    assert time.monotonic() - t0 < 20
    with pytest.raises(IngestError, match="native library said no"):
        load_mesh_isolated(tmp_path / "r.glb", timeout=60, loader=_raising_loader)


# --------------------------------------------------------------------------- synthetic library

def _by_node(mesh):
    """node name -> (material name, triangle corner coordinates) of the node's faces."""
    out = {}
    for i, name in enumerate(mesh.node_names):
        sel = mesh.face_node == i
        mats = {mesh.materials[k].name for k in np.unique(mesh.face_material[sel])}
        out[name] = (mats, mesh.vertices[mesh.faces[sel].astype(np.int64)])
    return out


@pytest.mark.parametrize("messy", [(), ("offset",), ("units_mm",), ("merged_materials",)])
def test_synth_vehicle_matches_generator_truth(tmp_path, messy):
    synth = pytest.importorskip("ucad_cl.synth")
    vehicle = synth.make_vehicle(11, "pickup", messy=messy)
    mesh = load_mesh(vehicle.write(tmp_path), clean=False)
    truth = vehicle.mesh()                      # the generator's canonical mesh
    assert {m.name for m in mesh.materials} == set(vehicle.truth["materials"])
    assert mesh.n_faces == truth.n_faces
    got, ref = _by_node(mesh), _by_node(truth)
    assert got.keys() == ref.keys()
    for node, (mats, corners) in ref.items():
        assert got[node][0] == mats, node
        np.testing.assert_allclose(got[node][1], corners, atol=1e-6, err_msg=node)
    np.testing.assert_allclose(mesh.file_to_norm, vehicle.truth["file_to_canonical"],
                               rtol=1e-6, atol=1e-8)
    glass = [m for m in mesh.materials if vehicle.truth["materials"][m.name] == "window"]
    assert glass and all(m.transmission > 0 for m in glass)     # from the raw glTF JSON


@pytest.mark.parametrize("trait", ["nan_vertex", "empty_file", "truncated"])
def test_synth_broken_files_rejected_with_expected_reason(tmp_path, trait):
    synth = pytest.importorskip("ucad_cl.synth")
    vehicle = synth.make_vehicle(5, "sedan", messy=(trait,))
    path = vehicle.write(tmp_path)
    with pytest.raises(IngestError) as e:
        load_mesh(path)
    assert e.value.reason == vehicle.truth["expected_reject"] and path.name in str(e.value)


def test_node_names_are_the_same_on_every_load(vehicles_dir):
    """trimesh gives repeated node names a random hex suffix, new on every load: node names are
    kept without it (artifacts.node_stem), so two processes load identical meshes."""
    import subprocess
    import sys
    code = ("import sys, json; from ucad_cl.ingest import load_mesh; "
            "m = load_mesh(sys.argv[1], orientation=None); print(json.dumps(m.node_names))")
    path = vehicles_dir / "kenney_ambulance" / "ambulance.glb"
    runs = [subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True,
                           text=True, check=True, cwd=Path(__file__).resolve().parents[1]).stdout
            for _ in range(2)]
    names = json.loads(runs[0])
    assert runs[0] == runs[1] and len(names) > len(set(names))     # repeated names, same stems
    assert not any(re.search(r"_[0-9a-f]{6}$", n) for n in names)


def _returns(x, *, times=1):
    return [x] * times


def _raises_value_error(text):
    raise ValueError(f"bad {text}")


class _Unpicklable(Exception):
    def __init__(self, a, b):                 # pickles as Unpicklable(msg): one argument short
        super().__init__(f"{a} and {b}")


def _raises_unpicklable():
    raise _Unpicklable("one", "two")


def test_call_isolated_returns_raises_and_survives_crashes():
    """system.call_isolated: the value back; the child's exception raised again here with its
    type; one that does not pickle as RuntimeError text; a crash or a hang as
    IsolatedCallFailed naming the signal or the timeout."""
    from ucad_cl.system import IsolatedCallFailed, call_isolated

    assert call_isolated(_returns, (1, "a"), times=2, timeout=60) == [(1, "a"), (1, "a")]
    with pytest.raises(ValueError, match="bad input"):
        call_isolated(_raises_value_error, "input", timeout=60)
    with pytest.raises(RuntimeError, match="_Unpicklable: one and two"):
        call_isolated(_raises_unpicklable, timeout=60)
    with pytest.raises(IsolatedCallFailed, match="SIGSEGV") as e:
        call_isolated(_segfault_loader, "x", timeout=60)
    assert e.value.kind == "crashed"
    with pytest.raises(IsolatedCallFailed, match="within 1 s") as e:
        call_isolated(_sleepy_loader, "x", timeout=1.0)
    assert e.value.kind == "timeout"
    with pytest.raises(ValueError, match="timeout must be > 0"):
        call_isolated(_returns, 1, timeout=0)
