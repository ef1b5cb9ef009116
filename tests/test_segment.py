"""Segmenters: masks folder round trip and errors, a real ONNX model (built here with ``onnx``),
and the offline prior segmenter (names in many languages, properties, geometry)."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from ucad_cl.classify import classify_parts
from ucad_cl.names import name_prior
from ucad_cl.segment import (MasksSegmenter, OnnxSegmenter, PriorSegmenter, material_colors,
                             material_features, material_image, masks_from_labels,
                             write_masks)
from tests.reference import flat_mesh, flat_views
from ucad_cl.artifacts import PART_NAMES, Mesh, PartMasks


# -- PartMasks: two forms of the same masks ----------------------------------------------------
def test_part_masks_bits_and_masks_round_trip():
    rng = np.random.default_rng(3)
    V, P, H, W = 4, 16, 9, 11                            # 16 parts: every bit of the packing
    masks = rng.random((V, P, H, W)) < 0.3
    masks[2, 5] = False
    masks[:, 15] = False                                 # the top bit never set
    conf = np.where(masks.any(axis=(2, 3)), np.float32(0.5), np.float32(0))
    parts = [f"p{i}" for i in range(P)]
    a = PartMasks(parts, masks, conf, "m")               # positional, as before
    assert not a.packed and a.masks is masks
    bits = a.bits
    assert bits.dtype == np.uint16 and bits.shape == (V, H, W)
    want = sum(masks[:, p].astype(np.uint16) << p for p in range(P))
    np.testing.assert_array_equal(bits, want)
    assert a.bits is bits                                # derived once, cached
    b = PartMasks.from_bits(parts, bits, conf, source="b")
    assert b.packed and b.shape == (V, P, H, W) == a.shape and b.source == "b"
    np.testing.assert_array_equal(b.nonempty(), masks.any(axis=(2, 3)))
    assert b.packed                                      # nonempty() does not unpack
    np.testing.assert_array_equal(a.nonempty(), masks.any(axis=(2, 3)))
    got = b.masks
    assert got.dtype == np.bool_ and b.masks is got and not b.packed
    np.testing.assert_array_equal(got, masks)
    # assigning one form drops the other
    a.masks = masks[::-1].copy()
    np.testing.assert_array_equal(a.bits, bits[::-1])
    b.bits = bits[:, ::-1].copy()
    assert b.packed
    np.testing.assert_array_equal(b.masks, masks[:, :, ::-1])
    none = PartMasks.from_bits(parts, np.zeros((0, H, W), np.uint16), np.zeros((0, P)))
    assert none.nonempty().shape == (0, P) and none.masks.shape == (0, P, H, W)
    with pytest.raises(ValueError, match="P <= 16"):
        _ = PartMasks(parts + ["x"], np.zeros((1, 17, 2, 2), bool), np.zeros((1, 17))).bits


def test_masks_from_labels_paints_each_material_with_its_part():
    mat = np.array([[[0, 1, 2], [3, 3, 1]], [[2, 2, 0], [0, 0, 0]]], np.uint16)
    labels = {0: "window", 1: "body", 2: "window", 5: "rim"}     # material 5 not in the views
    pm = masks_from_labels(flat_views(mat), labels, confidence=0.75)
    assert pm.packed and pm.parts == list(PART_NAMES)
    for p, part in enumerate(PART_NAMES):
        ids = [m + 1 for m, lab in labels.items() if lab == part]
        np.testing.assert_array_equal(pm.masks[:, p], np.isin(mat, ids))
    want = np.where(pm.masks.any(axis=(2, 3)), np.float32(0.75), np.float32(0))
    np.testing.assert_array_equal(pm.confidence, want)
    assert pm.confidence.dtype == np.float32


# -- masks folder -------------------------------------------------------------------------------
def test_masks_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    V, P, H, W = 3, len(PART_NAMES), 12, 17
    masks = rng.random((V, P, H, W)) < 0.2
    masks[1, 4] = False                                  # an empty mask: no file, conf 0
    conf = np.where(masks.any(axis=(2, 3)), rng.random((V, P)), 0).astype(np.float32)
    pm = PartMasks(list(PART_NAMES), masks, conf)
    mesh = flat_mesh(1)
    base = write_masks(tmp_path, mesh.sha256, pm)
    assert not (base / "view_001" / f"{PART_NAMES[4]}.png").exists()
    got = MasksSegmenter(tmp_path).segment(mesh, flat_views(np.zeros((V, H, W), np.uint16)))
    assert got.parts == list(PART_NAMES)
    np.testing.assert_array_equal(got.masks, masks)
    np.testing.assert_array_equal(got.confidence, conf)


def test_masks_missing_files_and_confidence(tmp_path):
    import cv2

    mesh = flat_mesh(1)
    d = tmp_path / mesh.sha256 / "view_001"
    d.mkdir(parents=True)
    img = np.zeros((8, 9), np.uint8)
    img[2:5, 3:7] = 200
    img[6, 0] = 127                                      # not > 127: outside the mask
    cv2.imwrite(str(d / "window.png"), img)
    got = MasksSegmenter(tmp_path).segment(mesh, flat_views(np.zeros((2, 8, 9), np.uint16)))
    assert not got.masks[0].any() and not got.confidence[0].any()
    w = PART_NAMES.index("window")
    np.testing.assert_array_equal(got.masks[1, w], img > 127)
    assert got.confidence[1, w] == 1.0                   # no confidence.json: 1 for a present mask
    (tmp_path / mesh.sha256 / "confidence.json").write_text(json.dumps({"1": {"window": 0.25}}))
    got = MasksSegmenter(tmp_path).segment(mesh, flat_views(np.zeros((2, 8, 9), np.uint16)))
    assert got.confidence[1, w] == np.float32(0.25)


def test_masks_errors_name_the_file(tmp_path):
    import cv2

    mesh = flat_mesh(1)
    d = tmp_path / mesh.sha256 / "view_000"
    d.mkdir(parents=True)
    cv2.imwrite(str(d / "wheel.png"), np.zeros((10, 10), np.uint8))
    with pytest.raises(ValueError, match=r"view_000/wheel\.png.*10x10.*8x6"):
        MasksSegmenter(tmp_path).segment(mesh, flat_views(np.zeros((1, 6, 8), np.uint16)))
    cv2.imwrite(str(d / "wheel.png"), np.zeros((6, 8), np.uint16))
    with pytest.raises(ValueError, match=r"wheel\.png.*8-bit"):
        MasksSegmenter(tmp_path).segment(mesh, flat_views(np.zeros((1, 6, 8), np.uint16)))
    (d / "wheel.png").unlink()
    (tmp_path / mesh.sha256 / "confidence.json").write_text("{not json")
    with pytest.raises(ValueError, match="confidence.json"):
        MasksSegmenter(tmp_path).segment(mesh, flat_views(np.zeros((1, 6, 8), np.uint16)))
    with pytest.raises(FileNotFoundError, match="nowhere"):
        MasksSegmenter(tmp_path / "nowhere")


# -- ONNX ---------------------------------------------------------------------------------------
CLASSES = {"0": "background", "1": "window", "2": "light", "3": "plate"}
WEIGHTS = np.array([[-10, -10, -10], [10, 0, 0], [0, 10, 0], [0, 0, 10]], np.float32)
BIAS = np.array([1, 0, 0, 0], np.float32)


def build_onnx(path, argmax: bool):
    """A 1x1 convolution RGB -> 4 logits (background, red, green, blue); optionally ArgMax."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    nodes = [helper.make_node("Conv", ["image", "w", "b"], ["logits"])]
    out = helper.make_tensor_value_info("logits", TensorProto.FLOAT, ["N", 4, "H", "W"])
    if argmax:
        nodes.append(helper.make_node("ArgMax", ["logits"], ["classes"], axis=1, keepdims=0))
        out = helper.make_tensor_value_info("classes", TensorProto.INT64, ["N", "H", "W"])
    graph = helper.make_graph(
        nodes, "tiny_seg",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, ["N", 3, "H", "W"])], [out],
        initializer=[numpy_helper.from_array(WEIGHTS.reshape(4, 3, 1, 1), "w"),
                     numpy_helper.from_array(BIAS, "b")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def blocky_maps(V=3, H=32, W=32, n_ids=9, seed=0):
    rng = np.random.default_rng(seed)
    blocks = rng.integers(0, n_ids, (V, H // 8, W // 8)).astype(np.uint16)
    return np.kron(blocks, np.ones((8, 8), np.uint16))


def numpy_reference(mat_id):
    """Independent reference: the model's maths on the colour-coded maps, in NumPy."""
    x = material_colors(int(mat_id.max()) + 1)[mat_id].astype(np.float64) / 255.0
    z = np.einsum("vhwc,kc->vkhw", x, WEIGHTS.astype(np.float64)) + BIAS[None, :, None, None]
    e = np.exp(z - z.max(axis=1, keepdims=True))
    prob = e / e.sum(axis=1, keepdims=True)
    return prob.argmax(axis=1), prob.max(axis=1)


def test_onnx_logits_model(tmp_path):
    mat = blocky_maps()
    cls, pmax = numpy_reference(mat)
    seg = OnnxSegmenter(build_onnx(tmp_path / "m.onnx", argmax=False),
                        {"classes": CLASSES, "input_size": [32, 32], "batch": 2})
    got = seg.segment(flat_mesh(8), flat_views(mat))
    assert got.masks.shape == (3, len(PART_NAMES), 32, 32)
    for k, part in CLASSES.items():
        if part not in PART_NAMES:
            continue
        p = PART_NAMES.index(part)
        np.testing.assert_array_equal(got.masks[:, p], cls == int(k))
        for v in range(3):
            inside = cls[v] == int(k)
            want = pmax[v][inside].mean() if inside.any() else 0.0
            assert got.confidence[v, p] == pytest.approx(want, rel=1e-5)
    assert got.masks[:, [PART_NAMES.index(p) for p in ("body", "wheel", "rim")]].sum() == 0
    assert not got.masks.any(axis=1)[mat == 0].any()      # background colour -> class 0


def test_onnx_class_map_model_with_resize(tmp_path):
    mat = blocky_maps(H=64, W=64)                         # 8 px blocks survive 2x nearest
    cls, _ = numpy_reference(mat)
    seg = OnnxSegmenter(build_onnx(tmp_path / "c.onnx", argmax=True),
                        {"classes": CLASSES, "input_size": [32, 32]})
    got = seg.segment(flat_mesh(8), flat_views(mat))
    for k, part in CLASSES.items():
        if part in PART_NAMES:
            p = PART_NAMES.index(part)
            np.testing.assert_array_equal(got.masks[:, p], cls == int(k))
            assert set(np.unique(got.confidence[:, p])) <= {0.0, 1.0}
    # and the masks drive classification: the material of each block gets its colour's class
    table = classify_parts(flat_mesh(8), flat_views(mat), got, symmetry=False)
    colors = material_colors(9).astype(int)
    seen = [r for r in table.rows if r.part != "unseen"]
    assert len(seen) == len(np.unique(mat[mat > 0]))
    for r in seen:                                         # red -> window, green -> light, ...
        assert r.part == CLASSES[str(int(np.argmax(colors[r.material + 1])) + 1)]


def test_onnx_bad_config_and_output(tmp_path):
    import onnx
    import onnxruntime as ort
    from onnx import TensorProto, helper

    graph = helper.make_graph(
        [helper.make_node("ReduceMean", ["image"], ["y"], axes=[1], keepdims=0)], "bad",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, ["N", 3, "H", "W"])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["N", "H", "W"])])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.save(model, str(tmp_path / "bad.onnx"))
    seg = OnnxSegmenter(tmp_path / "bad.onnx", {"classes": CLASSES, "input_size": [8, 8]})
    with pytest.raises(ValueError, match=r"bad\.onnx: output must be"):
        seg.segment(flat_mesh(2), flat_views(np.ones((1, 8, 8), np.uint16)))
    with pytest.raises(ValueError, match="input_size"):
        OnnxSegmenter(tmp_path / "x.onnx", {"classes": CLASSES})
    with pytest.raises(FileNotFoundError, match="x.onnx"):
        OnnxSegmenter(tmp_path / "x.onnx", {"classes": CLASSES, "input_size": [8, 8]})
    # a config file that is missing, not JSON, not an object or of the wrong types: one line
    # naming the file (labeller.onnx_config, shared with fit --vgg)
    cfg = tmp_path / "seg.json"
    with pytest.raises(FileNotFoundError, match=r"ONNX config .*seg\.json does not exist"):
        OnnxSegmenter(tmp_path / "bad.onnx", cfg)
    for text, match in (("{not json", r"seg\.json: not JSON \(.*line 1\)"),
                        ("[1, 2]", r"seg\.json: not a JSON object"),
                        ('{"classes": {"a": "body"}, "input_size": [8, 8]}', r"seg\.json: invalid"),
                        ('{"classes": [1], "input_size": [8, 8]}', r"seg\.json: "),
                        ('{"classes": {"1": "body"}, "input_size": [0, 8]}',
                         r"seg\.json: input_size must be"),
                        ('{"classes": {"1": "body"}}', r"seg\.json: an ONNX config needs")):
        cfg.write_text(text, encoding="utf-8")
        with pytest.raises(ValueError, match=match) as exc:
            OnnxSegmenter(tmp_path / "bad.onnx", cfg)
        assert "\n" not in str(exc.value)
    # a model fed an input size its graph refuses: one line naming the file (onnxruntime's
    # own exception, several lines long, is not let through)
    seg = OnnxSegmenter(build_onnx(tmp_path / "m.onnx", argmax=False),
                        {"classes": CLASSES, "input_size": [16, 16]})
    seg.session = ort.InferenceSession(str(_fixed_input(tmp_path / "m.onnx", tmp_path / "f.onnx",
                                                        8)), providers=["CPUExecutionProvider"])
    with pytest.raises(ValueError, match=r"m\.onnx: the segmenter \(input_size \[16, 16\]\) "
                                         r"fails on a \(1, 3, 16, 16\) input") as exc:
        seg.segment(flat_mesh(2), flat_views(np.ones((1, 16, 16), np.uint16)))
    assert "\n" not in str(exc.value)


def _fixed_input(src, dst, side: int):
    """A copy of the ONNX model ``src`` whose input is fixed to (N, 3, side, side)."""
    import onnx

    model = onnx.load(str(src))
    dims = model.graph.input[0].type.tensor_type.shape.dim
    dims[2].dim_value, dims[3].dim_value = side, side
    onnx.save(model, str(dst))
    return dst


# -- priors -------------------------------------------------------------------------------------
@pytest.mark.parametrize("name,part", [
    ("Glass_Gray", "window"), ("Windschutzscheibe", "window"), ("vitre_avant", "window"),
    ("ventana", "window"), ("vetro", "window"), ("フロントガラス", "window"), ("车窗玻璃", "window"),
    ("стекло", "window"), ("Tires", "wheel"), ("Reifen", "wheel"), ("neumático", "wheel"),
    ("タイヤ", "wheel"), ("轮胎", "wheel"), ("шина", "wheel"), ("Felge_VL", "rim"), ("jante", "rim"),
    ("llanta", "rim"), ("cerchio", "rim"), ("轮毂", "rim"), ("Scheinwerfer", "light"),
    ("phare_avant", "light"), ("faro", "light"), ("Taillight_Glass", "light"), ("ライト", "light"),
    ("尾灯", "light"), ("фара", "light"), ("chrome", "chrome"), ("window_trim", "window"),
    ("Kennzeichen", "plate"), ("plaque", "plate"), ("matrícula", "plate"), ("targa", "plate"),
    ("ナンバー", "plate"), ("牌照", "plate"), ("Interior_light", "interior"), ("Sitz", "interior"),
    ("siège", "interior"), ("asiento", "interior"), ("Leather_red", "interior"),
    ("Body_Color", "body"), ("Karosserie", "body"), ("carrosserie", "body"), ("carrocería", "body"),
    ("ボディ", "body"), ("车身", "body"), ("кузов", "body"), ("paint_window_sill_L", "body"),
    ("BodyPaint", "body"), ("Material.001", None), ("Blackboard", None),
    ("Miroir", "chrome"), ("Außenspiegel", "chrome"), ("specchio_dx", "chrome"),
    ("doorknob.001", "chrome"), ("Door_Handle_L", "chrome"), ("ミラー", "chrome"),
    ("зеркало", "chrome"), ("paint_mirror_L", "body")])
def test_name_prior_languages(name, part):
    assert name_prior(name) == part


def _anonymous(mesh: Mesh) -> Mesh:
    return replace(mesh, materials=[replace(m, name=f"Material.{i:03d}")
                                    for i, m in enumerate(mesh.materials)])


@pytest.fixture(scope="module")
def synth_rendered(runtime):
    synth = pytest.importorskip("ucad_cl.synth")
    from ucad_cl.cameras import make_ring
    from ucad_cl.render import render_views

    ring = make_ring(azimuth_step=15.0, elevations=(15.0,), size=128)
    out = []
    for seed in range(4):
        veh = synth.make_vehicle(seed)
        mesh = veh.mesh()
        truth = {i: veh.truth["materials"][m.name] for i, m in enumerate(mesh.materials)}
        out.append((mesh, render_views(mesh, ring), truth))
    return out


def test_prior_masks_follow_material_guesses(synth_rendered):
    mesh, views, _ = synth_rendered[0]
    seg = PriorSegmenter()
    prob = seg.guess(mesh, views)
    np.testing.assert_allclose(prob.sum(axis=1), 1.0)
    pm = seg.segment(mesh, views)
    fg = views.mat_id > 0
    np.testing.assert_array_equal(pm.masks.sum(axis=1), fg.astype(int))  # one part per pixel
    part_of = prob.argmax(axis=1)
    for v in (0, 5):
        for p in range(len(PART_NAMES)):
            pix = fg[v] & (part_of[np.maximum(views.mat_id[v].astype(int) - 1, 0)] == p)
            np.testing.assert_array_equal(pm.masks[v, p], pix)
            if pix.any():
                want = prob[views.mat_id[v][pix].astype(int) - 1, p].mean()
                assert pm.confidence[v, p] == pytest.approx(want, rel=1e-6)
            else:
                assert pm.confidence[v, p] == 0
    assert np.array_equal(seg.segment(mesh, views).masks, pm.masks)       # deterministic


def test_prior_with_meaningless_names_synth(synth_rendered):
    ok = n = 0
    for mesh, views, truth in synth_rendered:
        anon = _anonymous(mesh)
        for r in classify_parts(anon, views, PriorSegmenter().segment(anon, views)).rows:
            if r.part != "unseen":
                n += 1
                ok += r.part == truth[r.material]
    assert ok / n >= 0.80, ok / n


def test_prior_properties_decide_without_names(synth_rendered):
    """Transparent -> window, emissive -> light, dark tyres low at the corners -> wheel."""
    mesh, views, truth = synth_rendered[0]
    prob = PriorSegmenter().guess(_anonymous(mesh), views)
    for m, mat in enumerate(mesh.materials):
        guess = PART_NAMES[int(prob[m].argmax())]
        if mat.alpha_mode == "BLEND" or mat.transmission > 0:
            assert guess == "window" == truth[m], mat.name
        if max(mat.emissive) > 0.1:
            assert guess == "light" == truth[m], mat.name
        if truth[m] == "wheel":
            assert guess == "wheel", mat.name


def test_prior_real_vehicles_meaningless_names(vehicles_dir, runtime):
    """Regression guard for bench/parts.py (which prints the per-model table)."""
    from ucad_cl.cameras import make_ring
    from ucad_cl.ingest import load_mesh
    from ucad_cl.render import render_views

    manifest = {m["file"]: m["materials"]
                for m in json.loads((vehicles_dir / "manifest.json").read_text())["models"]}
    ring = make_ring(azimuth_step=30.0, elevations=(15.0, 45.0), size=96)
    ok = n = 0
    for f in ("o3dv_car.glb", "openmaterial_vehicle/vehicle_example.gltf",
              "openmaterial_truck/truck_example.gltf", "ferrari_348_lowpoly.glb",
              "a_frame_car/car.obj", "cesium_milk_truck.glb"):
        mesh = load_mesh(vehicles_dir / f)
        anon = _anonymous(mesh)
        views = render_views(mesh, ring)
        for r in classify_parts(anon, views, PriorSegmenter().segment(anon, views)).rows:
            if r.part != "unseen":
                n += 1
                ok += r.part == manifest[f][mesh.materials[r.material].name]
    assert ok / n >= 0.70, ok / n


def test_material_image_is_fixed_palette():
    mat = np.array([[[0, 1, 2], [2, 1, 0]]], np.uint16)
    img = material_image(mat)
    assert img.shape == (1, 2, 3, 3) and img.dtype == np.uint8
    assert (img[0, 0, 0] == 0).all() and (img[0, 0, 1] == img[0, 1, 1]).all()
    cols = material_colors(64)
    assert len({tuple(c) for c in cols}) == 64                            # distinct colours


def test_cli_parts_writes_table_and_sheet(vehicles_dir, tmp_path, runtime):
    import csv

    from ucad_cl.cli import main

    out = tmp_path / "out"
    rc = main(["parts", str(vehicles_dir / "o3dv_car.glb"), "--out", str(out),
               "--azimuth-step", "90", "--size", "64"])
    assert rc == 0
    rows = list(csv.DictReader(open(out / "o3dv_car.parts.csv", encoding="utf-8")))
    assert [r["name"] for r in rows][:2] == ["Body Material", "Glass Material"]
    assert rows[0]["part"] == "body" and rows[1]["part"] == "window"
    assert json.loads((out / "o3dv_car.parts.json").read_text())[0]["part"] == "body"
    import cv2
    sheet = cv2.imread(str(out / "o3dv_car.parts.png"))
    assert sheet is not None and sheet.shape[0] >= 64
    assert main(["parts", "x.glb", "--segmenter", "onnx:m.onnx"]) == 2          # no config
    assert main(["parts", str(vehicles_dir / "missing.glb"), "--out", str(out)]) == 1


# -- the packed prior segmenter against the code it replaced -----------------------------------
def reference_prior_segment(prob, mat_id):
    """The unpacked implementation (before packed masks), kept as the reference: per-pixel part
    index, (V, P, H, W) masks, per (view, part) pixel count and summed probability bincounts."""
    M = prob.shape[0]
    part_of = np.argmax(prob, axis=1)
    lut = np.full(M + 1, -1, np.int64)
    lut[1:] = part_of
    pix = lut[mat_id]
    pprob = np.zeros(M + 1)
    pprob[1:] = prob[np.arange(M), part_of]
    pp = pprob[mat_id]
    P = len(PART_NAMES)
    V = pix.shape[0]
    masks = pix[:, None] == np.arange(P)[None, :, None, None]
    key = (np.arange(V)[:, None, None] * (P + 1) + (pix + 1)).ravel()
    cnt = np.bincount(key, minlength=V * (P + 1)).reshape(V, P + 1)[:, 1:]
    sums = np.bincount(key, weights=pp.ravel(), minlength=V * (P + 1)).reshape(V, P + 1)[:, 1:]
    conf = np.where(cnt > 0, sums / np.maximum(cnt, 1), 0.0).astype(np.float32)
    return masks, conf


def reference_material_features(mesh, views=None):
    """``material_features`` before it was made cheaper (two np.unique, two cross products,
    np.add.at), kept as the reference: the new one must give bit-identical arrays."""
    M = len(mesh.materials)
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces, np.int64)
    fm = np.asarray(mesh.face_material, np.int64)
    out = {k: np.zeros(M) for k in ("area", "h", "abs_u", "abs_w", "wheel_zone", "end_zone",
                                     "upper", "centre_w", "plate_zone", "cabin", "roof", "flat",
                                     "visible", "exposure")}
    if f.shape[0] == 0:
        return out
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    c = tri.mean(axis=1)
    lo, hi = v[np.unique(f)].min(axis=0), v[np.unique(f)].max(axis=0)
    mid, half = 0.5 * (lo + hi), np.maximum(0.5 * (hi - lo), 1e-12)
    la, wa = (0, 2) if half[0] >= half[2] else (2, 0)
    h = (c[:, 1] - lo[1]) / (2 * half[1])
    au = np.abs(c[:, la] - mid[la]) / half[la]
    aw = np.abs(c[:, wa] - mid[wa]) / half[wa]
    tot = np.bincount(fm, weights=area, minlength=M)
    tot_safe = np.maximum(tot, 1e-30)

    def share(mask):
        return np.bincount(fm, weights=area * mask, minlength=M) / tot_safe

    out["area"] = tot / max(tot.sum(), 1e-30)
    out["h"] = share(h)
    out["abs_u"] = share(au)
    out["abs_w"] = share(aw)
    out["wheel_zone"] = share((h < 0.42) & (au > 0.35) & (au < 0.9) & (aw > 0.5))
    out["plate_zone"] = share((au > 0.9) & (aw < 0.4) & (h < 0.6))
    out["cabin"] = share((au < 0.5) & (aw < 0.55) & (h > 0.15) & (h < 0.7))
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ny = np.abs(n[:, 1]) / np.maximum(np.linalg.norm(n, axis=1), 1e-30)
    out["roof"] = share((ny > 0.85) & (h > 0.8))
    unit = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    outer = np.zeros((M, 3, 3))
    np.add.at(outer, fm, area[:, None, None] * unit[:, :, None] * unit[:, None, :])
    out["flat"] = np.linalg.eigvalsh(outer / tot_safe[:, None, None])[:, -1]
    out["end_zone"] = share((au > 0.82) & (h > 0.1) & (h < 0.85))
    out["upper"] = share(h > 0.55)
    out["centre_w"] = share(aw < 0.35)
    if views is not None:
        vis = np.bincount(views.mat_id.ravel(), minlength=M + 1)[1:M + 1].astype(np.float64)
        out["visible"] = vis / max(vis.sum(), 1.0)
        out["exposure"] = out["visible"] / np.maximum(out["area"], 1e-9)
    return out


def _with_extras(mesh: Mesh) -> Mesh:
    """``mesh`` plus unreferenced vertices far outside it and a material without faces."""
    from ucad_cl.artifacts import Material

    far = np.array([[9.0, -7.0, 5.0], [-8.0, 6.0, -9.0]])
    return replace(mesh, vertices=np.concatenate([mesh.vertices, far]),
                   materials=[*mesh.materials, Material(name="unused")])


def test_prior_segment_equals_unpacked_reference(synth_rendered):
    for mesh, views, _ in synth_rendered:
        for m in (mesh, _anonymous(mesh)):
            seg = PriorSegmenter()
            pm = seg.segment(m, views)
            assert pm.packed and pm.bits.dtype == np.uint16 and pm.bits.shape == views.mat_id.shape
            masks, conf = reference_prior_segment(seg.guess(m, views), views.mat_id)
            np.testing.assert_array_equal(pm.masks, masks)
            assert pm.confidence.dtype == np.float32
            np.testing.assert_array_equal(pm.confidence.view(np.uint32), conf.view(np.uint32))
    # views where some parts and some materials are absent, one view all background
    mesh, views, _ = synth_rendered[1]
    sub = views.select([0, 1, 2])                        # index list: copies, fixture intact
    sub.mat_id[1] = 0
    sub.mat_id[2][sub.mat_id[2] == sub.mat_id[2].max()] = 0
    mesh = _with_extras(mesh)
    seg = PriorSegmenter()
    pm = seg.segment(mesh, sub)
    masks, conf = reference_prior_segment(seg.guess(mesh, sub), sub.mat_id)
    np.testing.assert_array_equal(pm.masks, masks)
    np.testing.assert_array_equal(pm.confidence.view(np.uint32), conf.view(np.uint32))
    assert not pm.nonempty()[1].any() and not pm.confidence[1].any()


def test_material_features_equal_reference(synth_rendered):
    for mesh, views, _ in synth_rendered[:3]:
        for m in (mesh, _with_extras(mesh)):
            for vs in (None, views):
                want = reference_material_features(m, vs)
                got = material_features(m, vs)
                assert got.keys() == want.keys()
                for k in want:
                    assert got[k].dtype == want[k].dtype
                    np.testing.assert_array_equal(got[k], want[k], err_msg=k)
            views.material_counts()                      # the counts cached on the ViewSet
            got = material_features(m, views)
            for k, w in reference_material_features(m, views).items():
                np.testing.assert_array_equal(got[k], w, err_msg=k)
    empty = flat_mesh(2)
    assert all(not a.any() for a in material_features(empty).values())


def test_material_counts_per_view():
    mat = np.array([[[0, 1, 1], [3, 3, 3]], [[2, 0, 0], [0, 0, 0]]], np.uint16)
    np.testing.assert_array_equal(flat_views(mat).material_counts(5),
                                  [[1, 2, 0, 3, 0], [5, 0, 1, 0, 0]])
    with pytest.raises(ValueError, match="material id 3"):
        flat_views(mat).material_counts(3)
    assert flat_views(np.zeros((2, 0, 4), np.uint16)).material_counts(3).shape == (2, 3)


def test_material_counts_equal_numpy_bincount_on_hard_maps():
    """ViewSet.material_counts (OpenCV histogram per view) against np.bincount: thousands of
    ids, ids at the top of the uint16 range, empty views, odd sizes; cached; padded to n_ids."""
    rng = np.random.default_rng(4)
    for mat in (rng.integers(0, 2001, (5, 33, 47)).astype(np.uint16),
                np.where(rng.random((3, 17, 9)) < 0.5, 65534, 0).astype(np.uint16),
                np.zeros((4, 8, 8), np.uint16),
                rng.integers(0, 3, (2, 1, 1)).astype(np.uint16)):
        views = flat_views(mat)
        n = int(mat.max()) + 1
        ref = np.stack([np.bincount(m.ravel(), minlength=n) for m in mat])
        got = views.material_counts()
        assert got.dtype == np.int64 and np.array_equal(got, ref)
        assert views.material_counts() is not got                  # callers get their own copy
        assert np.array_equal(views.material_counts(n + 3)[:, :n], ref)
        assert not views.material_counts(n + 3)[:, n:].any()


def test_name_prior_regex_matches_the_per_keyword_rule():
    """The one compiled regex gives what the written rule gives keyword by keyword (earliest
    match wins, equal positions -> earlier group; Latin keywords start a word unless marked ~),
    on random compositions of every keyword with separators, case and noise."""
    import random
    import re

    from ucad_cl.names import NAME_KEYWORDS

    def reference(name):
        spaced = re.sub(r"([a-z])([A-Z])", r"\1 \2", name).lower()
        spaced = " " + re.sub(r"[\s_\-.:/\\0-9()\[\]]+", " ", spaced) + " "
        best = None
        for rank, (part, words) in enumerate(NAME_KEYWORDS):
            for kw in words:
                if kw.startswith("~"):
                    pos = spaced.find(kw[1:])
                elif kw.isascii():
                    hit = re.search(r"(?<![a-z])" + re.escape(kw), spaced)
                    pos = hit.start() if hit else -1
                else:
                    pos = spaced.find(kw)
                if pos >= 0 and (best is None or (pos, rank) < best[:2]):
                    best = (pos, rank, part)
        return best[2] if best else None

    kws = [k.lstrip("~") for _, words in NAME_KEYWORDS for k in words]
    rnd = random.Random(11)
    names = []
    for _ in range(3000):
        s = ""
        for _ in range(rnd.randint(1, 3)):
            w = rnd.choice(kws + ["Material", "x", "Obj", "abc"])
            w = w.upper() if rnd.random() < 0.2 else w.capitalize() if rnd.random() < 0.3 else w
            s += rnd.choice(["_", "-", ".", " ", "", "q", "7", "é"]) + w
        names.append(s)
    assert sum(reference(n) is not None for n in names) > 2000
    assert [name_prior(n) for n in names] == [reference(n) for n in names]


def test_painting_with_few_and_many_material_ids_equals_reference():
    """paint_materials against the unpacked reference on both of its lookups: <= 256 ids (an
    8-bit table) and more (np.take view by view), with absent ids, an all-background view and
    ties in the probabilities (-> PART_NAMES order)."""
    from ucad_cl.segment import paint_materials

    rng = np.random.default_rng(11)
    P = len(PART_NAMES)
    for M in (1, 40, 255, 256, 300, 2000):
        prob = rng.random((M, P))
        prob[::7] = 1.0                                    # all tied -> first part
        prob /= prob.sum(axis=1, keepdims=True)
        mat = rng.integers(0, M + 1, (3, 17, 23)).astype(np.uint16)
        mat[1] = 0
        mat[mat == M // 2 + 1] = 0                         # one material never seen
        pm = paint_materials(flat_views(mat), prob, source="test")
        masks, conf = reference_prior_segment(prob, mat)
        np.testing.assert_array_equal(pm.masks, masks, err_msg=f"{M} materials")
        np.testing.assert_array_equal(pm.confidence.view(np.uint32), conf.view(np.uint32))
    with pytest.raises(ValueError, match="material id"):   # an id beyond the materials
        paint_materials(flat_views(np.full((1, 2, 2), 5, np.uint16)), np.ones((3, P)) / P,
                        source="test")
