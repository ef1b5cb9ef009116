"""Procedural vehicle library: ground truth checked against trimesh re-loads, NumPy geometry,
SciPy nearest neighbours and embree ray casts (all independent of the generator's own code)."""
from __future__ import annotations

import hashlib
import io
import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from ucad_cl import synth
from ucad_cl.synth import KINDS, MESSY_TRAITS, make_vehicle, majority_part, write_library
from ucad_cl.artifacts import PART_NAMES, Material, Mesh


@pytest.fixture(scope="module")
def cars():
    return {k: make_vehicle(101 + i, k) for i, k in enumerate(KINDS)}


def _load(data: bytes) -> trimesh.Scene:
    return trimesh.load(io.BytesIO(data), file_type="glb", force="scene")


def _glb_json(data: bytes) -> dict:
    n = int.from_bytes(data[12:16], "little")
    return json.loads(data[20:20 + n])


def _faces_per_material(scene: trimesh.Scene) -> dict[str, int]:
    out: dict[str, int] = {}
    for node in scene.graph.nodes_geometry:
        _, g = scene.graph[node]
        geom = scene.geometry[g]
        name = geom.visual.material.name
        out[name] = out.get(name, 0) + len(geom.faces)
    return out


def _file_points(scene: trimesh.Scene) -> dict[str, np.ndarray]:
    """node -> (F, 3, 3) triangle corners in file coordinates (scene graph flattened)."""
    out = {}
    for node in scene.graph.nodes_geometry:
        M, g = scene.graph[node]
        geom = scene.geometry[g]
        v = np.asarray(geom.vertices, np.float64) @ M[:3, :3].T + M[:3, 3]
        out[node] = v[geom.faces]
    return out


def _node_tris(m: Mesh, node: str) -> np.ndarray:
    return m.vertices[m.faces[m.face_node == m.node_names.index(node)]]


# ---------------------------------------------------------------------------------------------

def test_every_kind_builds_with_parts_and_realistic_materials(cars):
    for kind, v in cars.items():
        t = v.truth
        assert v.kind == kind == t["kind"]
        assert 10_000 <= t["n_triangles"] <= 60_000, (kind, t["n_triangles"])
        assert set(t["materials"].values()) == set(PART_NAMES), kind  # every part, nothing else
        m = v.mesh()
        assert m.n_faces == t["n_triangles"]
        n_tyres = sum(1 for n in t["materials"] if n.startswith("tyre_"))
        assert n_tyres == (6 if kind == "truck" else 4)
        assert sum(1 for n in t["materials"] if n.startswith("rim_")) == n_tyres
        for mat in m.materials:
            part = t["materials"][mat.name]
            if part == "window":
                assert mat.base_color[3] < 1 and mat.alpha_mode == "BLEND"
                assert mat.transmission > 0
            elif part == "light":
                assert max(mat.emissive) > 0.5
            elif mat.name == "grille":               # trim policy: grilles count as chrome
                assert part == "chrome" and mat.metallic == 0.0
            elif part in ("chrome", "rim"):
                assert mat.metallic == 1.0 and mat.roughness <= 0.2
            elif part == "wheel":
                assert max(mat.base_color[:3]) < 0.1 and mat.roughness >= 0.8
            else:
                assert mat.alpha_mode == "OPAQUE" and max(mat.emissive) == 0.0
    bus = cars["bus"].truth["materials"]
    assert sum(1 for n in bus if n.startswith("glass_side_")) >= 12
    paint = {m.base_color for m in cars["sedan"].mesh().materials if m.name.startswith("paint_")}
    assert len(paint) == 1                       # one paint colour, many panel materials


def test_mesh_is_canonical_and_clean(cars):
    for kind, v in cars.items():
        m = v.mesh()
        assert m.vertices.dtype == np.float64 and m.faces.dtype == np.uint32
        assert m.face_material.dtype == np.uint16 and m.face_node.dtype == np.int32
        assert all(isinstance(x, Material) for x in m.materials)
        assert len({x.name for x in m.materials}) == len(m.materials)
        lo, hi = m.vertices.min(0), m.vertices.max(0)
        np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-12)
        assert abs(np.linalg.norm(hi - lo) - 1.0) < 1e-9
        ext = hi - lo                            # length along X, up +Y, width along Z
        assert ext[0] > ext[2] and ext[0] > ext[1], kind
        assert int(m.faces.max()) < len(m.vertices)
        tri = m.vertices[m.faces]
        area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        assert area.min() > 0, f"{kind}: zero-area triangles"
        assert len(np.unique(np.sort(m.faces, axis=1), axis=0)) == m.n_faces, "duplicate faces"
        # wheels stand on the ground: the lowest tyre point is the lowest point of the car
        tyres = [i for i, n in enumerate(m.node_names) if n.startswith("tyre_")]
        ymin = m.vertices[m.faces[np.isin(m.face_node, tyres)]][..., 1].min()
        assert ymin == pytest.approx(lo[1], abs=1e-9)
        assert m.file_to_norm.shape == (4, 4)
        assert m.sha256 == v.mesh().sha256 and len(m.sha256) == 64


def test_same_seed_gives_identical_bytes_and_other_seed_differs():
    a = make_vehicle(7, "sedan").glb_bytes()
    assert a == make_vehicle(7, "sedan").glb_bytes()
    assert a != make_vehicle(8, "sedan").glb_bytes()
    # another process with another str-hash seed (trimesh dedupes by hash) gives the same file
    code = ("import hashlib,sys; from ucad_cl.synth import make_vehicle;"
            "sys.stdout.write(hashlib.sha256(make_vehicle(7,'sedan').glb_bytes()).hexdigest())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "PYTHONHASHSEED": "12345"}).stdout
    assert out == hashlib.sha256(a).hexdigest()


def test_random_kind_is_drawn_from_seed():
    kinds = {make_vehicle(s).kind for s in range(40)}
    assert kinds == set(KINDS)
    assert make_vehicle(5).kind == make_vehicle(5).kind


def test_glb_round_trip_keeps_one_material_per_part(cars):
    for kind, v in cars.items():
        data = v.glb_bytes()
        scene = _load(data)
        m = v.mesh()
        before = {x.name: int(np.sum(m.face_material == i)) for i, x in enumerate(m.materials)}
        after = _faces_per_material(scene)
        assert after == before, kind
        assert set(scene.graph.nodes_geometry) == set(m.node_names)
        # material properties in the file (read from the glTF JSON, not trimesh)
        tree = _glb_json(data)
        mats = {x["name"]: x for x in tree["materials"]}
        assert set(mats) == set(before)
        for x in m.materials:
            f = mats[x.name]
            pbr = f["pbrMetallicRoughness"]
            np.testing.assert_allclose(pbr["baseColorFactor"], x.base_color, atol=1e-12)
            assert pbr["metallicFactor"] == x.metallic
            assert pbr["roughnessFactor"] == x.roughness
            assert f.get("alphaMode", "OPAQUE") == x.alpha_mode
            np.testing.assert_allclose(f.get("emissiveFactor", [0, 0, 0]), x.emissive)
            trans = f.get("extensions", {}).get("KHR_materials_transmission", {})
            assert trans.get("transmissionFactor", 0.0) == x.transmission
        assert "KHR_materials_transmission" in tree["extensionsUsed"]


def test_left_right_pairs_are_mirror_images(cars):
    for kind, v in cars.items():
        m = v.mesh()
        pairs = v.truth["symmetric_pairs"]
        assert len(pairs) >= 15, kind
        for left, right in pairs:
            assert left[-1] == "L" and right[-1] == "R" and left[:-1] == right[:-1]
            a = _node_tris(m, left).reshape(-1, 3) * [1.0, 1.0, -1.0]
            b = _node_tris(m, right).reshape(-1, 3)
            assert a.shape == b.shape
            d1, _ = cKDTree(b).query(a)
            d2, _ = cKDTree(a).query(b)
            assert max(d1.max(), d2.max()) < 1e-12, (kind, left)
            assert np.mean(-a[:, 2]) < 0 < np.mean(b[:, 2])        # left is at -Z
        # the check can fail: a front and a rear wheel are not mirror images
        a = _node_tris(m, "tyre_FL").reshape(-1, 3) * [1.0, 1.0, -1.0]
        assert cKDTree(_node_tris(m, "tyre_RR").reshape(-1, 3)).query(a)[0].max() > 0.05


def test_interior_is_visible_through_side_windows(cars):
    """Embree ray casts from the left at window height, glass removed: rays reach seats."""
    for kind in ("sedan", "van", "bus"):
        m = cars[kind].mesh()
        names = m.node_names
        glass = np.isin(m.face_node, [i for i, n in enumerate(names) if n.startswith("glass")])
        tm = trimesh.Trimesh(m.vertices, m.faces[~glass], process=False)
        fnode = m.face_node[~glass]
        win = _node_tris(m, next(n for n in names if n.startswith("glass_side")
                                 and n.endswith("_L"))).reshape(-1, 3)
        lo, hi = win.min(0), win.max(0)
        xs, ys = np.meshgrid(np.linspace(lo[0], hi[0], 15)[1:-1],
                             np.linspace(lo[1], hi[1], 9)[1:-1])
        orig = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, -2.0)], 1)
        dirs = np.tile([0.0, 0.0, 1.0], (len(orig), 1))
        tri, _ = tm.ray.intersects_id(orig, dirs, multiple_hits=False)
        hit = {names[fnode[t]] for t in tri}
        assert any(h.startswith("interior_seat") for h in hit), (kind, hit)
        # and with the glass kept, the first hit at the window centre is the window itself
        full = trimesh.Trimesh(m.vertices, m.faces, process=False)
        c = np.array([[(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, -2.0]])
        t0, _ = full.ray.intersects_id(c, np.array([[0.0, 0.0, 1.0]]), multiple_hits=False)
        assert names[m.face_node[t0[0]]].startswith("glass_side"), kind


@pytest.mark.parametrize("traits", [["z_up"], ["rotated"], ["units_mm"], ["units_km"],
                                    ["offset"], ["units_cm", "offset"],
                                    ["rotated", "units_mm", "offset"]])
def test_pose_traits_map_back_with_file_to_canonical(traits):
    v = make_vehicle(21, "suv", messy=traits)
    clean = make_vehicle(21, "suv")
    assert v.truth["messy"] == traits
    assert v.truth["expected_reject"] is None
    scene = _load(v.glb_bytes())
    T = np.array(v.truth["file_to_canonical"])
    m = v.mesh()
    np.testing.assert_array_equal(m.vertices, clean.mesh().vertices)   # mesh() is the clean car
    pts = _file_points(scene)
    allp = np.concatenate([p.reshape(-1, 3) for p in pts.values()])
    lo, hi = allp.min(0), allp.max(0)
    diag_m = np.linalg.norm(np.ptp(np.concatenate([q.vertices for q in clean.nodes]), axis=0))
    scale = {"units_mm": 1000.0, "units_cm": 100.0, "units_km": 1e-3}
    s = np.prod([scale.get(t, 1.0) for t in traits])
    if "rotated" not in traits:                  # axis-aligned: the bbox diagonal shows units
        assert np.linalg.norm(hi - lo) == pytest.approx(diag_m * s, rel=1e-6)
    if "z_up" in traits:                          # the height is now along Z
        ext = hi - lo
        assert ext[2] < ext[1] and ext[2] < ext[0]
    if "offset" in traits:
        assert np.abs((lo + hi) / 2).max() > 1e3
    for node, tri in pts.items():
        got = tri.reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
        ref = _node_tris(m, node).reshape(-1, 3)
        assert np.abs(got - ref).max() < 1e-6, node          # mesh diagonal is 1: relative
    # the same check fails with a wrong transform (the identity)
    node, tri = next(iter(pts.items()))
    assert np.abs(tri.reshape(-1, 3) - _node_tris(m, node).reshape(-1, 3)).max() > 1e-3


def test_merged_materials_truth_is_the_majority_part():
    v = make_vehicle(5, "sedan", messy=["merged_materials"])
    scene = _load(v.glb_bytes())
    per_mat = _faces_per_material(scene)
    nodes = v.truth["nodes"]
    assert len(per_mat) < len(nodes)             # some nodes share a material
    counts: dict[str, dict[str, int]] = {}       # recount from the file, by node part
    for node in scene.graph.nodes_geometry:
        _, g = scene.graph[node]
        geom = scene.geometry[g]
        c = counts.setdefault(geom.visual.material.name, {})
        c[nodes[node]] = c.get(nodes[node], 0) + len(geom.faces)
    assert counts == v.truth["material_part_faces"]
    assert set(counts) - set(nodes)              # materials named after a group, not a node
    for mat, c in counts.items():
        best = sorted(c.items(), key=lambda kv: (-kv[1], PART_NAMES.index(kv[0])))[0][0]
        assert v.truth["materials"][mat] == best
    flat = [x for pair in v.truth["symmetric_pairs"] for x in pair]
    assert all(flat.count(x) == 1 and x in per_mat for x in flat)


def test_majority_tie_goes_to_earlier_part():
    assert majority_part({"rim": 10, "wheel": 10}) == "wheel"
    assert majority_part({"chrome": 3, "plate": 3, "body": 2}) == "chrome"
    assert majority_part({"rim": 11, "wheel": 10}) == "rim"
    with pytest.raises(ValueError, match="tyre"):
        majority_part({"tyre": 3})


def test_reject_and_structure_traits():
    single = make_vehicle(3, "van", messy=["single_material"])
    assert single.truth["expected_reject"] == "too_few_materials"
    assert len(_faces_per_material(_load(single.glb_bytes()))) == 1

    nowheels = make_vehicle(3, "van", messy=["missing_wheels"])
    names = set(nowheels.truth["materials"])
    assert not any(n.startswith(("tyre_", "rim_")) for n in names)
    assert not any(p[0].startswith(("tyre", "rim")) for p in nowheels.truth["symmetric_pairs"])
    assert nowheels.truth["expected_reject"] is None
    assert _faces_per_material(_load(nowheels.glb_bytes())).keys() == names

    many = make_vehicle(3, "van", messy=["many_materials"])
    loaded = _faces_per_material(_load(many.glb_bytes()))
    assert len(loaded) >= 1000 and len(loaded) == len(many.truth["materials"])
    assert sum(loaded.values()) == many.truth["n_triangles"]

    nan = make_vehicle(3, "van", messy=["nan_vertex"])
    assert nan.truth["expected_reject"] == "non_finite"
    pts = np.concatenate([p.reshape(-1, 3) for p in _file_points(_load(nan.glb_bytes())).values()])
    assert np.isnan(pts).any()

    empty = make_vehicle(3, "van", messy=["empty_file"])
    assert empty.glb_bytes() == b"" and empty.truth["expected_reject"] == "empty"
    cut = make_vehicle(3, "van", messy=["truncated"])
    assert cut.truth["expected_reject"] == "unreadable"
    full = make_vehicle(3, "van").glb_bytes()
    data = cut.glb_bytes()
    assert 0 < len(data) < len(full) and full.startswith(data)
    with pytest.raises(Exception):  # noqa: B017  any reader error: the file is cut mid-buffer
        _load(data)


def test_target_triangles_and_detail():
    base = make_vehicle(9, "sedan").truth["n_triangles"]
    assert make_vehicle(9, "sedan", detail=2).truth["n_triangles"] > 3 * base
    for target in (10_000, 100_000):
        n = make_vehicle(9, "hatchback", target_triangles=target).truth["n_triangles"]
        assert abs(n - target) <= 0.1 * target, (target, n)
    t = time.perf_counter()
    v = make_vehicle(9, "truck", target_triangles=500_000)
    data = v.glb_bytes()
    dt = time.perf_counter() - t
    assert abs(v.truth["n_triangles"] - 500_000) <= 50_000
    assert dt < 10.0, dt
    assert sum(_faces_per_material(_load(data)).values()) == v.truth["n_triangles"]


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="'boat'"):
        make_vehicle(1, "boat")
    with pytest.raises(ValueError, match="seed"):
        make_vehicle(-1)
    with pytest.raises(ValueError, match="wobbly"):
        make_vehicle(1, messy=["wobbly"])
    with pytest.raises(ValueError, match="detail"):
        make_vehicle(1, detail=0)
    with pytest.raises(ValueError, match="target_triangles"):
        make_vehicle(1, target_triangles=10)
    with pytest.raises(ValueError, match="messy_fraction"):
        write_library("/nonexistent/never", 1, 0, messy_fraction=1.5)
    with pytest.raises(ValueError, match="'tank'"):
        write_library("/nonexistent/never", 1, 0, kinds=["tank"])


def test_write_library_is_deterministic_and_covers_traits(tmp_path):
    a = write_library(tmp_path / "a", 28, 4, messy_fraction=0.5, progress=False)
    b = write_library(tmp_path / "b", 28, 4, messy_fraction=0.5, progress=False)
    assert [p.name for p in a] == [p.name for p in b]
    for pa, pb in zip(a, b):
        assert pa.read_bytes() == pb.read_bytes()
        assert pa.with_suffix(".json").read_bytes() == pb.with_suffix(".json").read_bytes()
    truths = [json.loads(p.with_suffix(".json").read_text()) for p in a]
    assert sum(1 for t in truths if t["messy"]) == 14
    seen = {x for t in truths for x in t["messy"]}
    assert seen == set(MESSY_TRAITS) - {"huge"}
    for p, t in zip(a, truths):
        assert p.stem == t["name"] and t["kind"] in KINDS
        assert set(t["materials"].values()) <= set(PART_NAMES)
        assert t["expected_reject"] == next((synth.REJECT_OF[x] for x in t["messy"]
                                             if x in synth.REJECT_OF), None)
        if t["expected_reject"] is None:         # every readable file re-loads with its truth
            assert set(_faces_per_material(_load(p.read_bytes()))) == set(t["materials"])


def test_cli_writes_library(tmp_path):
    from ucad_cl.cli import main
    rc = main(["synth", str(tmp_path / "lib"), "--count", "3", "--seed", "2", "--kinds", "bus",
               "pickup", "--messy-fraction", "0", "--no-progress"])
    assert rc == 0
    glbs = sorted((tmp_path / "lib").glob("*.glb"))
    assert len(glbs) == 3 and len(list((tmp_path / "lib").glob("*.json"))) == 3
    kinds = {json.loads(g.with_suffix(".json").read_text())["kind"] for g in glbs}
    assert kinds <= {"bus", "pickup"}
    with pytest.raises(SystemExit):
        main(["synth", str(tmp_path / "x"), "--kinds", "boat"])


def test_realism_traits_change_materials_as_documented():
    from ucad_cl.names import name_prior
    from ucad_cl.synth import REALISM_TRAITS, apply_realism  # noqa: F401

    base = make_vehicle(21, "sedan")
    n_base = len(base.truth["materials"])

    def v(*traits):
        out = make_vehicle(21, "sedan", realism=traits)
        assert out.truth["realism"] == [t for t in REALISM_TRAITS if t in traits]
        return out.truth

    t = v("one_paint")
    assert "paint" in t["materials"] and t["materials"]["paint"] == "body"
    assert not any(n.startswith("paint_") for n in t["materials"])
    t = v("one_paint", "paint_rims")                 # one paint on panels and rims
    assert t["material_part_faces"]["paint"].keys() == {"body", "rim"}
    assert not any(n.startswith("rim_") for n in t["materials"])
    t = v("shared_black")
    assert t["material_part_faces"]["black"].keys() >= {"wheel", "chrome"}
    assert t["materials"]["black"] == majority_part(t["material_part_faces"]["black"])
    t = v("dark_trim")
    assert t["materials"]["trim_dark"] == "chrome"
    t = v("textured_body")
    assert t["materials"]["body_tex"] == "body" and "glass_windshield" in t["materials"]
    t = v("no_rims")
    assert "rim" not in t["materials"].values()
    t = v("chassis_only")
    assert not {"wheel", "rim", "interior"} & set(t["materials"].values())
    t = v("brake_discs")
    assert t["materials"]["brake_disc"] == "other" and t["materials"]["brake_calliper"] == "other"
    t = v("lens_lamps")
    assert t["materials"]["lamp_lens"] == "light"
    t = v("rich_interior")
    assert t["materials"]["steering_wheel"] == "interior"
    assert t["materials"]["leather_seats"] == t["materials"]["door_panel"] == "interior"
    assert not any(n.startswith("interior_seat") for n in t["materials"])   # one leather
    assert len(t["materials"]) == n_base - 3 + 3        # 3 seat materials -> 1, + 2 new
    t = v("meaningless_names")
    assert all(n.startswith("Material.") for n in t["materials"])
    assert all(name_prior(n) is None for n in t["materials"])
    assert all(n.startswith("Object_") for n in t["nodes"])
    t = v("misleading_names")
    lies = [n for n, p in t["materials"].items() if name_prior(n) not in (None, p)]
    assert 0 < len(lies) < len(t["materials"]) / 2
    m = make_vehicle(21, "sedan", realism=["mtl_like", "opaque_glass", "plain_lights"]).mesh()
    assert all(x.metallic == 0 and x.roughness == 1 and max(x.emissive) == 0
               and x.transmission == 0 for x in m.materials)
    assert all(x.alpha_mode == "OPAQUE" for x in m.materials)


def test_realism_traits_are_deterministic_and_checked():
    a = make_vehicle(5, "van", realism=["brake_discs", "lens_lamps", "shared_black"])
    b = make_vehicle(5, "van", realism=["shared_black", "lens_lamps", "brake_discs"])
    assert a.glb_bytes() == b.glb_bytes()               # applied in REALISM_TRAITS order
    with pytest.raises(ValueError, match="unknown realism trait"):
        make_vehicle(5, "van", realism=["chrome_everything"])


def test_shape_traits_cartoon_and_wedge():
    """cartoon: the body shorter (x 0.72-0.88) and taller (y 1.1-1.3), every tyre bigger
    (1.15-1.45) and still on the ground; wedge: heights scaled from 1 - k at the nose to
    1 + k at the tail (k 0.08-0.2), wheels untouched. Part bounding boxes against the plain
    build; other traits' bytes do not move, and the result is deterministic."""
    from ucad_cl.synth import SHAPE_TRAITS
    from ucad_cl.synth.builder import build_parts
    from ucad_cl.synth.realism import apply_realism

    def boxes(traits):
        parts = build_parts("sedan", np.random.default_rng([4, 1]), 1.0)
        parts = apply_realism(parts, traits, np.random.default_rng([4, 3]))
        return {q.node: (q.vertices.min(0), q.vertices.max(0)) for q in parts}

    plain, toon, wedge = boxes(()), boxes(("cartoon",)), boxes(("wedge",))
    assert SHAPE_TRAITS == ("cartoon", "wedge")
    body = [n for n in plain if not n.startswith(("tyre_", "rim_"))]
    ext = lambda b, k: (max(b[n][1][k] for n in body) - min(b[n][0][k] for n in body))  # noqa
    assert 0.72 <= ext(toon, 0) / ext(plain, 0) <= 0.88
    assert 1.1 <= max(toon[n][1][1] for n in body) / max(plain[n][1][1] for n in body) <= 1.3
    k = [(toon[n][1][1] - toon[n][0][1]) / (plain[n][1][1] - plain[n][0][1])
         for n in plain if n.startswith("tyre_")]
    assert 1.15 <= min(k) and max(k) <= 1.45 and np.ptp(k) < 1e-9      # one factor
    assert all(abs(toon[n][0][1] - plain[n][0][1]) < 1e-9 for n in plain if n.startswith("tyre_"))
    for n in plain:
        if n.startswith(("tyre_", "rim_")):
            assert np.array_equal(wedge[n][0], plain[n][0])
    roof = [n for n in body if plain[n][1][1] > 1.2]              # the tallest parts
    front = max(roof, key=lambda n: plain[n][1][0])
    rear = min(roof, key=lambda n: plain[n][0][0])
    assert wedge[front][1][1] < plain[front][1][1] and wedge[rear][1][1] > plain[rear][1][1]
    a = make_vehicle(6, "suv", realism=["cartoon", "wedge", "axles"])
    assert a.glb_bytes() == make_vehicle(6, "suv", realism=["axles", "wedge", "cartoon"]).glb_bytes()
    assert a.truth["realism"] == ["cartoon", "wedge", "axles"]


def test_lamp_variety_and_ground_base_traits():
    """lamp_variety: an amber indicator beside every lamp, a see-through red lens over a grey
    reflector at the back, all part light; ground_base: one base of part other under the
    tyres, larger than the vehicle. Same seed -> same bytes."""
    from ucad_cl.labeller import see_through

    v = make_vehicle(8, "sedan", realism=["lamp_variety", "ground_base"])
    t = v.truth["materials"]
    lamps = {n for n, p in t.items() if p == "light"}
    assert "indicator" in lamps and lamps & {"taillight_glass", "headlight_glass"}
    assert "reflector" in lamps
    m = v.mesh()
    mats = {x.name: i for i, x in enumerate(m.materials)}
    clear = see_through(m)
    for lens in lamps & {"taillight_glass", "headlight_glass"}:
        assert clear[mats[lens]]
    assert t["indicator"] == "light" and m.materials[mats["indicator"]].base_color[0] > 0.9
    base = [n for n in t if n in ("ground", "base", "fabric")]
    assert len(base) == 1 and t[base[0]] == "other"
    fm = np.asarray(m.face_material)
    vb = m.vertices[np.asarray(m.faces)[fm == mats[base[0]]].ravel()]
    vc = m.vertices[np.asarray(m.faces)[fm != mats[base[0]]].ravel()]
    assert vb[:, 1].max() <= vc[:, 1].min() + 1e-6            # under the vehicle
    assert np.ptp(vb[:, 0]) > 1.1 * np.ptp(vc[:, 0])          # larger than it
    for seed in range(6):                                      # planes and cloths: one sheet up
        w = make_vehicle(seed, "sedan", realism=["ground_base"])
        mw = w.mesh()
        name = next(n for n in w.truth["materials"] if n in ("ground", "base", "fabric"))
        k = [x.name for x in mw.materials].index(name)
        Fb = np.asarray(mw.faces)[np.asarray(mw.face_material) == k]
        up = np.cross(mw.vertices[Fb[:, 1]] - mw.vertices[Fb[:, 0]],
                      mw.vertices[Fb[:, 2]] - mw.vertices[Fb[:, 0]])[:, 1] > 0
        assert up.all() if name != "base" else 0.2 < up.mean() < 0.8
    again = make_vehicle(8, "sedan", realism=["ground_base", "lamp_variety"])
    assert again.glb_bytes() == v.glb_bytes()


def test_axles_light_bar_and_plate_looks_traits():
    """axles: one rod of part other per axle between the two tyres' inner faces, seen from
    below (under the floor); light_bar: part light on the roof, across the car; plate_looks:
    the plates share one material. Adding them changes no other trait's draws."""
    v = make_vehicle(8, "truck", realism=["axles", "light_bar", "plate_looks"])
    t, m = v.truth["materials"], v.mesh()
    mats = {x.name: i for i, x in enumerate(m.materials)}
    fm, F, V = np.asarray(m.face_material), np.asarray(m.faces), m.vertices

    def verts(name):
        return V[F[fm == mats[name]].ravel()]

    rod = next(n for n in t if n in ("axle", "chassis_frame"))
    assert t[rod] == "other"
    tyre_z = [verts(n)[:, 2] for n in t if n.startswith("tyre_")]
    inner = min(z.min() for z in tyre_z if z.mean() > 0)        # right tyres: inner face
    va = verts(rod)
    assert va[:, 2].max() == pytest.approx(inner, abs=1e-6)              # tyre to tyre
    assert va[:, 1].max() <= verts("underbody")[:, 1].min() + 1e-6       # under the floor
    bars = [n for n in t if n.startswith("light_bar_") and n != "light_bar_base"]
    assert bars and all(t[n] == "light" for n in bars)
    vb = np.concatenate([verts(n) for n in bars])
    assert vb[:, 1].min() >= verts("paint_roof")[:, 1].max() - 1e-6      # on the roof
    assert np.ptp(vb[:, 2]) > 0.5 * np.ptp(verts("paint_roof")[:, 2])   # across it
    assert t["plate"] == "plate" and not any(n.startswith("plate_") for n in t)
    base = {x.name: x for x in make_vehicle(8, "truck", realism=["lamp_variety"]).mesh().materials}
    more = make_vehicle(8, "truck", realism=["lamp_variety", "axles", "plate_looks"])
    kept = {x.name: x for x in more.mesh().materials if x.name in base}
    assert kept == {n: x for n, x in base.items() if not n.startswith("plate_")}
    assert more.glb_bytes() == make_vehicle(8, "truck", realism=["plate_looks", "axles",
                                                                "lamp_variety"]).glb_bytes()
    bare = make_vehicle(8, "truck", realism=["no_glass"]).truth["materials"]
    assert "window" not in bare.values() and "interior" in bare.values()


def test_trait_streams_leave_the_shared_stream_alone():
    from ucad_cl.synth.realism import _trait_rng

    a, b = np.random.default_rng([8, 3]), np.random.default_rng([8, 3])
    ra, rb = _trait_rng(b, "axles"), _trait_rng(b, "plate_looks")
    assert a.random() == b.random()                       # b's own draws did not move
    assert ra.random() != rb.random()                     # one stream per trait
    assert _trait_rng(np.random.default_rng([8, 3]), "axles").random() == \
        _trait_rng(np.random.default_rng([8, 3]), "axles").random()


def test_opaque_glass_colours_vary_and_pairs_match():
    """opaque_glass: every window opaque without transmission; the colour is the first
    recipe's light blue or a blue/blue-grey/grey (blue >= green >= red), one for all windows or
    one per window material with a left/right pair alike; drawn from its own stream."""
    colours, several = set(), False
    for seed in range(12):
        v = make_vehicle(seed, "sedan", realism=["opaque_glass"])
        windows = {m.name: m for m in v.mesh().materials if v.truth["materials"][m.name] == "window"}
        assert windows
        for m in windows.values():
            assert m.alpha_mode == "OPAQUE" and m.transmission == 0.0 and m.base_color[3] == 1.0
            r, g, b = m.base_color[:3]
            assert b + 1e-9 >= g >= r - 1e-9
            colours.add(tuple(m.base_color))
        for name, m in windows.items():
            if name.endswith("_L"):
                assert windows[name[:-2] + "_R"].base_color == m.base_color
        several |= len({m.base_color for m in windows.values()}) > 1
    assert any(np.allclose(c, (0.55, 0.7, 0.85, 1.0), atol=1 / 255) for c in colours)
    assert len(colours) >= 6 and several
    # only the windows change: every other material is as without the trait
    a = {m.name: m for m in make_vehicle(3, "sedan").mesh().materials}
    b = {m.name: m for m in make_vehicle(3, "sedan", realism=["opaque_glass"]).mesh().materials}
    assert a.keys() == b.keys()
    changed = {n for n in a if a[n] != b[n]}
    assert changed and all(n.startswith("glass") for n in changed)


def test_inner_shell_and_mirror_glass_traits():
    """inner_shell: inside-out copies of the cabin's body panels, part interior, inside the
    body's box, facing its centre, from near the floor to near the roof; mirror_glass:
    part chrome, on the back face of each mirror housing. Neither changes another material,
    and a vehicle without an interior gets no liner."""
    own, lengths = 0, []
    for seed in range(10):
        v = make_vehicle(seed, "sedan", realism=["inner_shell", "mirror_glass"])
        t, m = v.truth["materials"], v.mesh()
        assert any(n.startswith("interior_liner_") and p == "interior"
                   for n, p in v.truth["nodes"].items())
        F, V, fm = np.asarray(m.faces), m.vertices, np.asarray(m.face_material)
        mats = {x.name: i for i, x in enumerate(m.materials)}

        def faces(*names, F=F, fm=fm, mats=mats):
            return F[np.isin(fm, [mats[n] for n in names])]

        body = V[faces(*[n for n, p in t.items() if p == "body"]).ravel()]
        lo, hi = body.min(axis=0), body.max(axis=0)
        assert t["mirror_glass"] == "chrome"
        mirror = V[faces("mirror_glass").ravel()]
        for side, sign in (("L", -1), ("R", 1)):
            glass = mirror[np.sign(mirror[:, 2]) == sign]
            housing = V[faces(f"paint_mirror_{side}").ravel()]
            assert len(glass)
            assert glass[:, 0].max() < housing[:, 0].min()             # behind the housing
            assert (glass[:, 1:] > housing[:, 1:].min(axis=0)).all()
            assert (glass[:, 1:] < housing[:, 1:].max(axis=0)).all()
        if "interior_liner" not in t:
            continue
        own += 1
        assert t["interior_liner"] == "interior"
        Fl = faces("interior_liner")
        lined = V[Fl.ravel()]
        assert (lined > lo).all() and (lined < hi).all()               # inside the body
        n = np.cross(V[Fl[:, 1]] - V[Fl[:, 0]], V[Fl[:, 2]] - V[Fl[:, 0]])
        out = np.einsum("ij,ij->i", n, V[Fl].mean(axis=1) - (lo + hi) / 2)
        assert (out < 0).mean() > 0.8                                  # inside out
        lengths.append(np.ptp(lined[:, 0]) / np.ptp(body[:, 0]))
        assert np.ptp(lined[:, 1]) > 0.85 * np.ptp(body[:, 1])        # sides up to the roof
    assert own >= 2 and max(lengths) < 0.8                            # the cabin, not the nose
    bare = make_vehicle(3, "sedan", realism=["chassis_only", "inner_shell"]).truth["nodes"]
    assert not any(n.startswith("interior_liner_") for n in bare)
    a = {x.name: x for x in make_vehicle(3, "sedan").mesh().materials}
    b = {x.name: x for x in make_vehicle(3, "sedan", realism=["mirror_glass"]).mesh().materials}
    assert b.keys() - a.keys() == {"mirror_glass"} and all(a[n] == b[n] for n in a)


def test_plastic_trim_and_cargo_paint_traits():
    """plastic_trim: one neutral grey plastic (linear grey <= 0.3) on the grille, the bumpers
    (taller than built, their bottom kept), mirrors, side trim and a sill cladding on both sides
    that stays clear of every wheel arch; a truck's chassis sides take it too; part chrome
    (underbody other), the material's truth its majority part. cargo_paint: a truck's cargo box
    or a pickup's bed in one paint of its own, part body, sometimes under a canvas cover; a
    sedan's bytes do not move. Parts against the plain build of the same seed."""
    from ucad_cl.synth.builder import build_parts
    from ucad_cl.synth.realism import apply_realism

    def parts(kind, seed, traits):
        built = build_parts(kind, np.random.default_rng([seed, 1]), 1.0)
        return {q.node: q for q in apply_realism(built, traits, np.random.default_rng([seed, 3]))}

    bb = lambda q: (q.vertices.min(0), q.vertices.max(0))  # noqa: E731
    for kind, seed in (("sedan", 1), ("truck", 2), ("van", 3), ("pickup", 4)):
        plain, trim = parts(kind, seed, ()), parts(kind, seed, ("plastic_trim",))
        mat = trim["grille"].material
        rgb = np.asarray(mat.base_color[:3])
        assert mat.name == "plastic" and rgb.max() <= 0.3 * 1.05 and np.ptp(rgb) < 0.02
        for n in ("grille", "bumper_front", "bumper_rear", "paint_mirror_R", "chrome_trim_L"):
            assert trim[n].material is mat and trim[n].part == "chrome"
        for n in ("bumper_front", "bumper_rear"):
            (lo0, hi0), (lo1, hi1) = bb(plain[n]), bb(trim[n])
            assert abs(lo1[1] - lo0[1]) < 1e-9 and hi1[1] >= hi0[1]
            lamp = min(bb(plain[h])[0][1] for h in ("headlight_R", "headlight_L"))
            assert hi1[1] <= max(lamp - 0.02, hi0[1]) + 1e-9
        clad = [q for n, q in trim.items() if n.startswith("cladding_")]
        assert clad and {q.node[-1] for q in clad} == {"L", "R"}
        wheels = [bb(q) for n, q in plain.items() if n.startswith("tyre_")]
        for q in clad:
            lo, hi = bb(q)
            assert q.material is mat and q.part == "chrome"
            assert all(hi[0] < w[0][0] or lo[0] > w[1][0] for w in wheels)   # between arches
        sides = [q for n, q in trim.items() if n.startswith("paint_side_")]
        assert (kind == "truck") == bool(sides and all(q.material is mat for q in sides))
        assert trim["underbody"].part == "other"
        kept = [n for n in plain if not n.startswith(("grille", "bumper_", "paint_mirror_",
                                                      "chrome_trim_", "paint_side_", "underbody"))]
        assert all(trim[n] is plain[n] or np.array_equal(trim[n].vertices, plain[n].vertices)
                   for n in kept)
    t = make_vehicle(2, "truck", realism=["plastic_trim"]).truth
    assert t["materials"]["plastic"] == majority_part(t["material_part_faces"]["plastic"])
    covers = 0
    for seed in range(6):
        for kind, load in (("truck", ("cargo_box",)),
                           ("pickup", ("paint_bed_side_R", "paint_bed_floor", "paint_tailgate"))):
            plain, cargo = parts(kind, seed, ()), parts(kind, seed, ("cargo_paint",))
            mat = cargo[load[0]].material
            assert mat.name == "paint_cargo" and all(cargo[n].material is mat for n in load)
            assert all(cargo[n].part == "body" for n in load)
            assert all(q.material is not mat for n, q in cargo.items()
                       if not n.startswith(("cargo_box", "paint_bed_", "paint_tailgate")))
            if "cargo_cover" in cargo:
                covers += 1
                assert cargo["cargo_cover"].part == "body"
                (lo0, hi0), (lo1, hi1), (lo2, hi2) = (bb(plain["cargo_box"]),
                                                      bb(cargo["cargo_box"]),
                                                      bb(cargo["cargo_cover"]))
                assert np.allclose(lo1, lo0) and abs(hi1[1] - lo2[1]) <= 0.03 + 1e-9   # bulge
                assert hi2[1] >= hi0[1] - 1e-9 and lo0[1] < lo2[1] < hi0[1]
    assert 0 < covers < 6
    assert (make_vehicle(7, "sedan", realism=["cargo_paint"]).glb_bytes()
            == make_vehicle(7, "sedan").glb_bytes())
