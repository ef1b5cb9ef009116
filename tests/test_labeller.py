"""The learned labeller: features on hand-made cases, the layer behind glass, the shipped ONNX
model (loads and predicts with onnxruntime alone, in a fresh environment), the training script
end to end, shared-material splits, and the labeller as the default segmenter."""
from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ucad_cl.artifacts import PART_NAMES, Material, Mesh
from ucad_cl.cameras import make_ring
from ucad_cl.labeller import FEATURE_NAMES, MODEL_PATH, material_table, see_through

ROOT = Path(__file__).resolve().parents[1]
COL = {n: i for i, n in enumerate(FEATURE_NAMES)}


# ---------------------------------------------------------------------------------------------
# hand-made meshes (file frame: metres, +Y up, length along X), canonicalised like ingest
# ---------------------------------------------------------------------------------------------
def box(lo, hi):
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    v = np.array([[x, y, z] for x in (x0, x1) for y in (y0, y1) for z in (z0, z1)], float)
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return v, f


def torus(centre, R, r, n=32, m=12):
    """Ring around an axis parallel to Z (a tyre seen from the side is a circle)."""
    a = 2 * np.pi * np.arange(n) / n
    b = 2 * np.pi * np.arange(m) / m
    A, B = np.meshgrid(a, b, indexing="ij")
    v = np.stack([(R + r * np.cos(B)) * np.cos(A), (R + r * np.cos(B)) * np.sin(A),
                  r * np.sin(B)], -1).reshape(-1, 3) + centre
    i, j = np.meshgrid(np.arange(n), np.arange(m), indexing="ij")
    q = lambda i, j: (i % n) * m + (j % m)  # noqa: E731
    f = np.concatenate([np.stack([q(i, j), q(i + 1, j), q(i + 1, j + 1)], -1).reshape(-1, 3),
                        np.stack([q(i, j), q(i + 1, j + 1), q(i, j + 1)], -1).reshape(-1, 3)])
    return v, f


def disc(centre, R, thick, n=32):
    """Flat cylinder (a rim seen from the side is a disc), axis parallel to Z."""
    a = 2 * np.pi * np.arange(n) / n
    ring = np.stack([R * np.cos(a), R * np.sin(a), np.zeros(n)], 1)
    v = np.concatenate([ring, ring + [0, 0, thick], [[0, 0, 0], [0, 0, thick]]]) + centre
    k = np.arange(n)
    f = np.concatenate([np.stack([k, (k + 1) % n, n + (k + 1) % n], 1),
                        np.stack([k, n + (k + 1) % n, n + k], 1),
                        np.stack([np.full(n, 2 * n), (k + 1) % n, k], 1),
                        np.stack([np.full(n, 2 * n + 1), n + k, n + (k + 1) % n], 1)])
    return v, f


def make_mesh(parts, materials):
    """parts: [(vertices, faces, material index, node name)] -> canonical Mesh."""
    vs, fs, fm, fn, off = [], [], [], [], 0
    for k, (v, f, m, _) in enumerate(parts):
        vs.append(v)
        fs.append(f + off)
        fm.append(np.full(len(f), m))
        fn.append(np.full(len(f), k))
        off += len(v)
    v = np.concatenate(vs)
    lo, hi = v.min(0), v.max(0)
    d = np.linalg.norm(hi - lo)
    return Mesh(path="hand-made", sha256="cd" * 32, vertices=(v - (lo + hi) / 2) / d,
                faces=np.concatenate(fs).astype(np.uint32),
                face_material=np.concatenate(fm).astype(np.uint16), materials=materials,
                face_node=np.concatenate(fn).astype(np.int32),
                node_names=[p[3] for p in parts])


def car():
    """Body box, 4 tyres (tori), 4 rims (discs), a glass box enclosing a seat, and a box
    enclosed by the opaque body shell (never visible)."""
    mats = [Material("paint", (0.6, 0.1, 0.1, 1.0), metallic=0.5, roughness=0.3),
            Material("tyre", (0.02, 0.02, 0.02, 1.0)),
            Material("rim", (0.8, 0.8, 0.8, 1.0), metallic=1.0, roughness=0.2),
            Material("glass", (0.1, 0.1, 0.1, 0.3), "BLEND", transmission=0.9),
            Material("seat", (0.3, 0.2, 0.1, 1.0)),
            Material("hidden", (0.5, 0.5, 0.5, 1.0))]
    parts = [(*box([-2, 0.3, -0.8], [2, 1.0, 0.8]), 0, "body")]
    for x in (-1.3, 1.3):
        for z, s in ((0.85, 1), (-0.85, -1)):
            parts.append((*torus([x, 0.38, z], 0.28, 0.1), 1, f"tyre_{x}_{z}"))
            parts.append((*disc([x, 0.38, z + s * 0.02 - (0.04 if s < 0 else 0)], 0.2, 0.04),
                          2, f"rim_{x}_{z}"))
    parts.append((*box([-0.8, 1.0, -0.7], [0.8, 1.5, 0.7]), 3, "cabin_glass"))
    parts.append((*box([-0.3, 1.05, -0.3], [0.3, 1.3, 0.3]), 4, "seat"))
    parts.append((*box([-1.5, 0.5, -0.2], [-1.0, 0.8, 0.2]), 5, "inner_block"))
    return make_mesh(parts, mats)


@pytest.fixture(scope="module")
def car_views(runtime):
    from ucad_cl.render import render_views

    mesh = car()
    return mesh, render_views(mesh, make_ring(azimuth_step=30, elevations=(15.0, 40.0), size=96))


# ---------------------------------------------------------------------------------------------
# features
# ---------------------------------------------------------------------------------------------
def reference_components(mesh):
    """Union-find over faces, face by face: two faces of one material are joined when they
    share a vertex position on the ``WELD`` grid. Ids numbered by (material, first face)."""
    from ucad_cl.labeller import WELD

    fm = np.asarray(mesh.face_material, np.int64)
    key = [tuple(k) for k in np.round(np.asarray(mesh.vertices) / WELD).astype(np.int64)]
    parent = list(range(len(fm)))

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    seen = {}
    for i, face in enumerate(np.asarray(mesh.faces)):
        for c in face:
            j = seen.setdefault((int(fm[i]), key[c]), i)
            a, b = root(i), root(j)
            parent[max(a, b)] = min(a, b)
    roots = [root(i) for i in range(len(fm))]
    first = sorted({r: None for r in roots}, key=lambda r: (fm[r], r))   # root = lowest face
    ids = {r: k for k, r in enumerate(first)}
    return np.array([ids[r] for r in roots]), np.array([fm[r] for r in first])


def test_components_equal_union_find_reference(car_views):
    """Connected components (faces joined through welded vertices, per material) against a
    union-find: vertices duplicated at one position (split seams), shared by two materials,
    1e-7 apart (welded), a face touching another at one corner, a shuffled face order."""
    mesh, views = car_views
    rng = np.random.default_rng(3)
    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.faces).astype(np.int64)
    fm = np.asarray(mesh.face_material)
    # split every face of the body onto its own vertex copies (a seam everywhere), 1e-7 off
    body = np.flatnonzero(fm == 0)
    copies = v[f[body]].reshape(-1, 3) + 1e-7 * (rng.random((3 * body.size, 3)) < 0.5)
    f2 = f.copy()
    f2[body] = v.shape[0] + np.arange(3 * body.size).reshape(-1, 3)
    v2 = np.concatenate([v, copies])
    # a glass triangle sharing one corner with a tyre face, and a lone tyre triangle far away
    f2 = np.concatenate([f2, [[f[fm == 1][0][0], 0, 1]], [[len(v2), len(v2) + 1, len(v2) + 2]]])
    v2 = np.concatenate([v2, [[0.4, 0.4, 0.4], [0.41, 0.4, 0.4], [0.4, 0.41, 0.4]]])
    fm2 = np.concatenate([fm, [3, 1]]).astype(np.uint16)
    perm = rng.permutation(len(f2))
    m2 = replace(mesh, vertices=v2, faces=f2[perm].astype(np.uint32), face_material=fm2[perm],
                 face_node=None)
    for m in (mesh, m2):
        t = material_table(m, views)
        comp, comp_mat = reference_components(m)
        np.testing.assert_array_equal(t.face_comp, comp)
        np.testing.assert_array_equal(t.comp_material, comp_mat)


def test_a_ring_is_a_ring_and_a_disc_a_disc(car_views):
    mesh, views = car_views
    t = material_table(mesh, views)
    X = t.X
    assert len(t.wheels) == 4                                    # tyre + rim merged per axle
    tyre, rim, body = X[1], X[2], X[0]
    assert tyre[COL["comp_wheel"]] == pytest.approx(1.0)
    assert rim[COL["comp_wheel"]] == pytest.approx(1.0)
    assert body[COL["comp_wheel"]] == 0.0
    assert 10 ** tyre[COL["log_comps"]] == pytest.approx(4.0)    # four separate tyres
    # a torus of radii 0.28 +- 0.1 around the axle: r / R (R = 0.38) between 0.47 and 1,
    # concentrated near 0.74, with a hole (no area near the axle); a disc reaches the axle
    assert 0.65 < tyre[COL["ring_r"]] < 0.85 and tyre[COL["ring_spread"]] < 0.2
    assert rim[COL["ring_r"]] < tyre[COL["ring_r"]]
    assert tyre[COL["rho_hub"]] < 0.3 and rim[COL["rho_hub"]] > 0.9     # rho: / tyre radius
    assert tyre[COL["rho_tyre"]] + tyre[COL["rho_rim"]] + tyre[COL["rho_hub"]] > 0.99  # inside
    assert body[COL["rho_mean"]] > 1.0


def test_behind_glass_layer_finds_the_seat_and_not_the_enclosed_block(car_views):
    mesh, views = car_views
    assert see_through(mesh).tolist() == [False, False, False, True, False, False]
    t = material_table(mesh, views)
    assert t.pixels[4] == 0 and t.behind_pixels[4] > 20          # seat: only through glass
    assert t.X[4, COL["through_glass"]] == pytest.approx(1.0)
    assert t.pixels[5] == 0 and t.behind_pixels[5] == 0          # inside the opaque body
    assert t.X[0, COL["through_glass"]] < 0.5                    # paint: seen directly


def test_mirror_pairs_names_and_hidden_names(car_views):
    mesh, views = car_views
    X = material_table(mesh, views).X
    name_cols = [COL[f"name_{p}"] for p in PART_NAMES]
    # names: 'paint' -> body, 'tyre' -> wheel, 'rim' -> rim, 'glass' -> window, 'seat' ->
    # interior, 'hidden' -> nothing
    want = {0: "body", 1: "wheel", 2: "rim", 3: "window", 4: "interior"}
    for m, p in want.items():
        assert X[m, name_cols].sum() == 1 and X[m, COL[f"name_{p}"]] == 1
    assert X[5, name_cols].sum() == 0
    meaningless = replace(mesh, materials=[replace(m, name=f"Material.{i:03d}")
                                           for i, m in enumerate(mesh.materials)],
                          node_names=[f"Object_{i}" for i in range(len(mesh.node_names))])
    Xm = material_table(meaningless, views).X
    assert not Xm[:, name_cols].any()
    assert not Xm[:, [COL[f"node_{p}"] for p in PART_NAMES]].any()
    np.testing.assert_array_equal(np.delete(Xm, name_cols + [COL[f"node_{p}"]
                                                             for p in PART_NAMES], axis=1),
                                  np.delete(X, name_cols + [COL[f"node_{p}"]
                                                            for p in PART_NAMES], axis=1))
    # off-centre mirror images: tyres are one material on both sides (centred), so no pair
    assert X[1, COL["mirror"]] == 0.0


def test_features_do_not_depend_on_front_back_or_left_right(car_views, runtime):
    """Geometric features use |u| and |w|: the car turned by 180 degrees about +Y gives the
    same rows (visibility features come from the same ring, which is symmetric too)."""
    from ucad_cl.render import render_views

    mesh, views = car_views
    turned = replace(mesh, vertices=mesh.vertices * [-1.0, 1.0, -1.0])
    ring = make_ring(azimuth_step=30, elevations=(15.0, 40.0), size=96)
    a = material_table(mesh, views).X
    b = material_table(turned, render_views(turned, ring)).X
    geo = [COL[k] for k in ("h_mean", "u_mean", "w_mean", "comp_wheel", "ring_r", "rho_tyre",
                            "flat", "log_area", "z_wheel", "log_comps")]
    np.testing.assert_allclose(a[:, geo], b[:, geo], atol=1e-6)
    np.testing.assert_allclose(a[:, COL["pix_share"]], b[:, COL["pix_share"]], atol=0.02)


# ---------------------------------------------------------------------------------------------
# the shipped model
# ---------------------------------------------------------------------------------------------
def test_shipped_model_record_and_size():
    rec = json.loads(MODEL_PATH.with_suffix(".json").read_text())
    assert MODEL_PATH.stat().st_size < 5 * 2**20
    assert tuple(rec["features"]) == FEATURE_NAMES and rec["classes"] == list(PART_NAMES)
    assert rec["recipe"]["seed"] == 2026 and rec["recipe"]["vehicles"] >= 100
    assert rec["metrics"]["heldout_generated_material_accuracy"] >= 0.97
    assert len(rec["check"]["X"]) >= 5
    # trained on every real model of ../shared (the manifest's, less the Draco duplicate of
    # ferrari_458_nodraco.glb that labeller_train.load_real_models skips)
    manifest = ROOT.parent / "shared" / "data" / "vehicles" / "manifest.json"
    if manifest.exists():
        models = json.loads(manifest.read_text())["models"]
        assert rec["recipe"]["real_models"] == len(models) - 1 and not rec["recipe"]["leave_out"]


def test_model_loads_and_predicts_in_a_fresh_environment(tmp_path):
    """The wheel holds the model; a fresh venv with only numpy and onnxruntime (no scikit-learn,
    no onnx, no OpenCL) loads it and reproduces scikit-learn's probabilities stored at training."""
    wheel_dir = tmp_path / "wheel"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps",
                    "--no-build-isolation", "-w", str(wheel_dir), str(ROOT)], check=True,
                   capture_output=True, timeout=300)
    whl = next(wheel_dir.glob("ucad_cl-*.whl"))
    with zipfile.ZipFile(whl) as z:
        names = z.namelist()
        assert "ucad_cl/models/labeller.onnx" in names and "ucad_cl/models/labeller.json" in names
        venv = tmp_path / "venv"
        subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True,
                       timeout=120)
        site = next((venv / "lib").glob("python*/site-packages"))
        z.extractall(site)                                       # installing a pure wheel
    deps = tmp_path / "deps"
    deps.mkdir()
    import numpy
    import onnxruntime
    for mod in (numpy, onnxruntime):
        src = Path(mod.__file__).parent
        (deps / src.name).symlink_to(src)
        libs = src.parent / f"{src.name}.libs"
        if libs.exists():
            (deps / libs.name).symlink_to(libs)
    (site / "deps.pth").write_text(str(deps) + "\n")
    code = ("import json, numpy as np, importlib.util as u\n"
            "assert u.find_spec('sklearn') is None and u.find_spec('onnx') is None\n"
            "assert u.find_spec('pyopencl') is None\n"
            "from ucad_cl.labeller import LabellerModel, MODEL_PATH\n"
            "assert 'site-packages' in str(MODEL_PATH), MODEL_PATH\n"
            "rec = json.loads(MODEL_PATH.with_suffix('.json').read_text())\n"
            "p = LabellerModel(MODEL_PATH).predict(np.array(rec['check']['X'], np.float32))\n"
            "ref = np.array(rec['check']['prob'])\n"
            "assert np.abs(p - ref).max() < 1e-4, np.abs(p - ref).max()\n"
            "assert (p.argmax(1) == ref.argmax(1)).all()\n"
            "print('ok', p.shape)\n")
    out = subprocess.run([str(venv / "bin" / "python"), "-I", "-c", code], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("ok")


def test_stale_or_missing_model_is_a_clear_error(tmp_path):
    from ucad_cl.labeller import LabellerModel

    with pytest.raises(FileNotFoundError, match="does not exist"):
        LabellerModel(tmp_path / "nope.onnx")
    bad = tmp_path / "m.onnx"
    bad.write_bytes(MODEL_PATH.read_bytes())
    rec = json.loads(MODEL_PATH.with_suffix(".json").read_text())
    rec["features"] = rec["features"][:-1]
    bad.with_suffix(".json").write_text(json.dumps(rec))
    with pytest.raises(ValueError, match="retrain"):
        LabellerModel(bad)


# ---------------------------------------------------------------------------------------------
# training script
# ---------------------------------------------------------------------------------------------
def test_training_script_end_to_end_is_deterministic(tmp_path, runtime):
    pytest.importorskip("sklearn")
    pytest.importorskip("onnx")
    sys.path.insert(0, str(ROOT / "scripts"))
    from train_labeller import main

    outs = []
    for k in range(2):
        out = tmp_path / f"run{k}" / "labeller.onnx"
        assert main(["--vehicles", "2", "--test-vehicles", "1", "--max-iter", "3",
                     "--no-real", "--seed", "5", "--out", str(out)]) == 0
        outs.append(out)
    assert outs[0].read_bytes() == outs[1].read_bytes()
    rec = json.loads(outs[0].with_suffix(".json").read_text())
    assert rec["recipe"]["seed"] == 5 and rec["recipe"]["vehicles"] == 2
    assert rec["recipe"]["member_seeds"] == [5, 6, 7]
    assert 0 <= rec["metrics"]["heldout_generated_material_accuracy"] <= 1
    import onnx

    from ucad_cl.labeller import LabellerModel

    ops = [n.op_type for n in onnx.load(str(outs[0])).graph.node]
    assert ops.count("TreeEnsembleClassifier") == 3 and "Mean" in ops
    p = LabellerModel(outs[0]).predict(np.array(rec["check"]["X"], np.float32))
    np.testing.assert_allclose(p, np.array(rec["check"]["prob"]), atol=1e-4)
    # one member: its own graph, and probabilities other than the three members' average
    one = tmp_path / "one" / "labeller.onnx"
    assert main(["--vehicles", "2", "--test-vehicles", "1", "--max-iter", "3", "--no-real",
                 "--seed", "5", "--members", "1", "--out", str(one)]) == 0
    ops = [n.op_type for n in onnx.load(str(one)).graph.node]
    assert ops.count("TreeEnsembleClassifier") == 1 and "Mean" not in ops
    p1 = LabellerModel(one).predict(np.array(rec["check"]["X"], np.float32))
    assert np.abs(p1 - p).max() > 1e-3


# ---------------------------------------------------------------------------------------------
# segmenter + classification
# ---------------------------------------------------------------------------------------------
def test_labeller_segmenter_behind_glass_unseen_and_prob(car_views):
    from ucad_cl.classify import classify_parts
    from ucad_cl.segment import LabellerSegmenter, make_segmenter

    mesh, views = car_views
    seg = make_segmenter("labeller")
    assert isinstance(seg, LabellerSegmenter)
    masks = seg.segment(mesh, views)
    assert masks.source.startswith("labeller") and masks.labels is not None
    table = classify_parts(mesh, views, masks)
    rows = {r.name: r for r in table.rows}
    assert rows["seat"].decision == "behind-glass" and rows["seat"].pixels > 0
    assert rows["seat"].part in PART_NAMES
    # no pixel in the views nor behind glass: the labeller's part from geometry, own flag
    hidden = rows["hidden"]
    assert (hidden.decision, hidden.pixels, hidden.view) == ("never-visible", 0, -1)
    assert hidden.part == PART_NAMES[int(masks.labels.part[hidden.material])]
    for r in table.rows:
        if r.part != "unseen":
            assert 0.0 < r.prob <= 1.0
            assert r.prob == pytest.approx(float(masks.labels.prob[r.material,
                                                                   PART_NAMES.index(r.part)]))
    # the mask confidence of a part is the probability of the materials painted with it
    lab = masks.labels
    part = PART_NAMES[int(lab.part[0])]
    v = int(np.argmax(views.material_counts()[:, 1]))
    only = [m for m in range(len(mesh.materials)) if lab.part[m] == lab.part[0]
            and views.material_counts(len(mesh.materials) + 1)[v, m + 1] > 0]
    if only == [0]:
        assert masks.confidence[v, PART_NAMES.index(part)] == pytest.approx(
            lab.probability(0), rel=1e-5)


def test_shared_paint_on_rims_is_split_by_component(runtime):
    from ucad_cl.classify import classify_parts
    from ucad_cl.render import render_views
    from ucad_cl.segment import LabellerSegmenter
    from ucad_cl.synth import make_vehicle

    veh = make_vehicle(11, "sedan", realism=["one_paint", "paint_rims"])
    mesh = veh.mesh()
    views = render_views(mesh, make_ring(azimuth_step=30, elevations=(15.0,), size=96))
    masks = LabellerSegmenter().segment(mesh, views)
    table = classify_parts(mesh, views, masks)
    row = next(r for r in table.rows if r.name == "paint")
    assert row.split is not None
    parts = [g["part"] for g in row.split]
    assert "rim" in parts and "body" in parts
    rim = next(g for g in row.split if g["part"] == "rim")
    assert rim["components"] == 4 and 0.0 < rim["area_share"] < 0.5
    assert all(len(b) == 6 for b in rim["boxes"])
    tyre = next(r for r in table.rows if r.name.startswith("tyre"))
    assert tyre.split is None


def test_default_segmenter_everywhere():
    from ucad_cl.build import BuildOptions
    from ucad_cl.segment import segmenter_from_spec as make_segmenter
    from ucad_cl.segment import LabellerSegmenter

    assert BuildOptions().segmenter == "labeller"
    assert isinstance(make_segmenter("labeller"), LabellerSegmenter)
    assert isinstance(make_segmenter(f"labeller:{MODEL_PATH}"), LabellerSegmenter)
    with pytest.raises(FileNotFoundError):
        make_segmenter("labeller:/no/such/model.onnx")


def test_show_prints_the_probability():
    from ucad_cl.artifacts import MaterialPart
    from ucad_cl.commands.common import format_rows
    from ucad_catalog.reader import PartRow

    rows = [MaterialPart(0, "paint", "body", 1.0, 0.9, 3, "best-view", 500, 0.873,
                         [{"part": "body", "area_share": 0.8}, {"part": "rim",
                                                                "area_share": 0.2}]),
            MaterialPart(1, "m1", "unseen", 0.0, 0.0, -1, "unseen", 0)]
    text = format_rows(rows)
    assert " 0.87 " in text and "body:0.80 rim:0.20" in text
    assert text.splitlines()[2].split()[2] == "-"
    stored = [PartRow("paint", "body", 1.0, 0.9, 3, "best-view", 500, 0,
                      {"prob": 0.5, "split": None})]
    assert " 0.50 " in format_rows(stored)


def test_same_labels_in_all_24_axis_aligned_poses(tmp_path, runtime):
    """Acceptance: the same model in any of the 24 axis-aligned poses gets the same labels for
    >= 99 % of its materials (the orientation stage at load gives every pose one canonical
    frame)."""
    import itertools

    from ucad_cl.classify import classify_parts
    from ucad_cl.ingest import load_mesh
    from ucad_cl.render import render_views
    from ucad_cl.segment import LabellerSegmenter
    from ucad_cl.synth import make_vehicle

    veh = make_vehicle(31, "hatchback", realism=["one_paint", "lens_lamps"])
    ring = make_ring(azimuth_step=30, elevations=(15.0,), size=96)
    seg = LabellerSegmenter()
    labels = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1, -1), repeat=3):
            R = np.zeros((3, 3))
            R[np.arange(3), perm] = signs
            if np.linalg.det(R) < 0:
                continue
            T = np.eye(4)
            T[:3, :3] = R
            scene = veh.scene.copy()
            scene.apply_transform(T)
            path = tmp_path / f"pose_{len(labels)}.glb"
            path.write_bytes(scene.export(file_type="glb"))
            mesh = load_mesh(path)
            views = render_views(mesh, ring)
            table = classify_parts(mesh, views, seg.segment(mesh, views))
            labels.append({r.name: r.part for r in table.rows})
    assert len(labels) == 24
    same = [sum(lab[k] == labels[0][k] for k in labels[0]) / len(labels[0]) for lab in labels]
    assert min(same) >= 0.99, same


# ---------------------------------------------------------------------------------------------
# relative features (each material against the others of its vehicle) and the realism traits
# that real libraries showed and the generator lacked
# ---------------------------------------------------------------------------------------------
def test_relative_features_on_the_hand_made_car(car_views):
    from ucad_cl.labeller import CUE_NAMES, RELATIVE_NAMES

    mesh, views = car_views
    X = material_table(mesh, views).X
    # appended after the base columns, then the cue columns last
    assert FEATURE_NAMES[-len(CUE_NAMES):] == CUE_NAMES
    assert FEATURE_NAMES[-len(RELATIVE_NAMES + CUE_NAMES):-len(CUE_NAMES)] == RELATIVE_NAMES
    c = lambda name: X[:, COL[name]]  # noqa: E731
    paint, tyre, rim, glass, seat, hidden = range(6)
    # the paint has the most pixels and the largest area: 0 against itself
    assert c("rel_pix")[paint] == 0 and c("rel_area")[paint] == 0
    assert (c("rel_pix")[[tyre, rim, glass]] < 0).all()
    assert c("h_rel_paint")[paint] == 0 and c("u_rel_paint")[paint] == 0
    assert -0.25 < c("h_rel_paint")[tyre] < -0.12            # tyre centres 0.2, body 0.39 high
    # the tyre (L about 1.5) is the darkest: nobody darker; the rim (L about 92) the lightest
    assert c("dark_frac")[tyre] == 0 and c("dark_frac")[rim] == 1
    # the paint (red) is the most colourful
    assert c("chroma_frac")[paint] == 0
    # the main glass is the only see-through material: 1 against itself, 0 for opaque ones
    assert c("glass_rel_pix")[glass] == 1 and (np.delete(c("glass_rel_pix"), glass) == 0).all()
    assert c("d_glass")[glass] == 0 and c("h_rel_glass")[glass] == 0
    assert c("h_rel_glass")[tyre] < -0.4                     # the glass band is far above tyres
    assert (c("rel_emission") == 0).all()                    # nothing glows
    # hidden (grey L 76) and rim (L 92, same hue) are not the same colour; no two materials are
    assert (c("same_colour") == 0).all()


def test_relative_features_follow_a_permutation_of_the_materials(car_views):
    mesh, views = car_views
    X = material_table(mesh, views).X
    perm = np.array([3, 5, 0, 1, 4, 2])                     # new index k holds old perm[k]
    inv = np.argsort(perm)
    pm = replace(mesh, materials=[mesh.materials[k] for k in perm],
                 face_material=inv[np.asarray(mesh.face_material)].astype(np.uint16))
    from ucad_cl.render import render_views

    Y = material_table(pm, render_views(pm, views.cameras)).X
    rel = [COL[n] for n in ("rel_area", "rel_pix", "dark_frac", "chroma_frac", "same_colour",
                            "h_rel_paint", "u_rel_paint", "h_rel_glass", "d_glass",
                            "glass_rel_pix")]
    np.testing.assert_allclose(Y[:, rel], X[perm][:, rel], atol=1e-5)


def test_two_tone_and_dark_glass_traits():
    from ucad_cl.labeller import _lab
    from ucad_cl.synth import make_vehicle

    plain = make_vehicle(5, "sedan").mesh()
    for seed in (5, 6, 7):
        v = make_vehicle(seed, "sedan", realism=["two_tone"])
        mats = {m.name: m for m in v.mesh().materials}
        assert v.truth["materials"]["paint_second"] == "body"
        second = np.asarray(mats["paint_second"].base_color[:3])
        first = np.asarray(next(m for n, m in mats.items()
                                if n.startswith("paint_") and n != "paint_second").base_color[:3])
        assert np.abs(second - first).max() > 0.35
    d = make_vehicle(5, "sedan", realism=["dark_glass"])
    glass = [m for m in d.mesh().materials if d.truth["materials"][m.name] == "window"]
    # every window keeps its own material, now opaque, dark and not see-through
    assert len(glass) == sum(plain_m.name.startswith("glass") for plain_m in plain.materials)
    assert len({m.base_color for m in glass}) == 1
    for m in glass:
        assert m.alpha_mode == "OPAQUE" and m.transmission == 0 and m.base_color[3] == 1
        assert _lab(np.asarray(m.base_color[:3]))[0] < 45
    assert not see_through(d.mesh())[[i for i, m in enumerate(d.mesh().materials)
                                      if m in glass]].any()


def test_one_glass_and_glass_looks_traits():
    from ucad_cl.synth import make_vehicle

    plain = make_vehicle(9, "van")
    v = make_vehicle(9, "van", realism=["one_glass"])
    windows = [m for m in v.mesh().materials if v.truth["materials"][m.name] == "window"]
    assert [m.name for m in windows] == ["glass"]                # the whole glasshouse
    n_plain = sum(plain.truth["materials"][m.name] == "window" for m in plain.mesh().materials)
    assert n_plain > 1
    looks = set()
    for seed in range(12):
        g = make_vehicle(seed, "sedan", realism=["glass_looks"])
        mesh = g.mesh()
        win = [i for i, m in enumerate(mesh.materials) if g.truth["materials"][m.name] == "window"]
        for i in win:
            m = mesh.materials[i]
            assert m.transmission == 0                          # alpha only, never transmission
            # see-through exactly when alpha < 0.9 (the documented see-through rule)
            assert see_through(mesh)[i] == (m.base_color[3] < 0.9)
        looks.add((mesh.materials[win[0]].base_color[3] < 1, mesh.materials[win[0]].alpha_mode))
    assert len(looks) >= 2                                      # see-through and opaque both drawn


def test_grey_trim_trait():
    from ucad_cl.synth import make_vehicle

    greys = set()
    for seed in (3, 4, 5):
        v = make_vehicle(seed, "sedan", realism=["grey_trim"])
        mats = {m.name: m for m in v.mesh().materials}
        assert v.truth["materials"]["trim_grey"] == "chrome"        # the trim policy
        assert not any(n.startswith(("bumper_", "grille", "chrome_trim_")) for n in mats)
        r, g, b, a = mats["trim_grey"].base_color
        assert a == 1 and abs(r - g) < 1e-6 and 0.04 < g < 0.71
        greys.add(round(g, 3))
    assert len(greys) == 3                                         # the grey is drawn per vehicle


def test_wheel_assembly_and_never_visible_rules():
    """Tyre against rim by radial position; the part of a material no view sees, from
    geometry: rim in a wheel, other under the floor, else interior."""
    from ucad_cl.labeller import never_visible_part, wheel_assembly

    X = np.zeros((5, len(FEATURE_NAMES)), np.float32)
    X[:3, COL["rho_tyre"]] = 0.9                       # 0, 1, 2 in a wheel; 3, 4 not
    X[:, COL["rho_mean"]] = [1.0, 0.7, 0.9, 0.2, 0.5]
    X[:, COL["h_mean"]] = [0.1, 0.1, 0.1, 0.15, 0.5]
    X[4, COL["z_under"]] = 0.0
    W, R = PART_NAMES.index("wheel"), PART_NAMES.index("rim")
    prob = np.full((5, len(PART_NAMES)), 0.01, np.float32)
    prob[:, W] = 0.9
    prob[:, R] = 0.03
    out = wheel_assembly(prob, X)
    # 0 is the outermost: stays; 1 lies 0.3 inside it: rim (probabilities swapped); 2 only
    # 0.1 inside: stays; 3 and 4 are outside any wheel: untouched
    assert list(out.argmax(axis=1)) == [W, R, W, W, W]
    assert out[1, R] == pytest.approx(0.9) and out[1, W] == pytest.approx(0.03)
    np.testing.assert_array_equal(np.delete(out, 1, axis=0), np.delete(prob, 1, axis=0))
    # one wheel material alone is never changed
    np.testing.assert_array_equal(wheel_assembly(prob[[1, 3]], X[[1, 3]]), prob[[1, 3]])
    assert [PART_NAMES[p] for p in never_visible_part(X)] == ["rim", "rim", "rim", "other",
                                                              "interior"]


# ---------------------------------------------------------------------------------------------
# the issue-24 cues (``CUE_GROUPS``): views from above and below, component shape, zones
# ---------------------------------------------------------------------------------------------
def _projected_area(corners: np.ndarray, ring, view: int) -> float:
    """Image area (pixels) of a planar convex quadrilateral (4, 3) seen by ``ring``'s ``view``
    (pinhole projection, shoelace formula): the NumPy reference of the rasteriser's count."""
    P = ring.K @ ring.w2c[view, :3]
    x = np.c_[corners, np.ones(4)] @ P.T
    p = x[:, :2] / x[:, 2:]
    c = p.mean(axis=0)
    p = p[np.argsort(np.arctan2(p[:, 1] - c[1], p[:, 0] - c[0]))]
    return 0.5 * abs(np.dot(p[:, 0], np.roll(p[:, 1], -1)) - np.dot(p[:, 1], np.roll(p[:, 0], -1)))


def test_top_and_bottom_views_against_projected_areas(runtime):
    """``top_bottom_counts``: a body slab with a smaller plate under it. From above only the
    body shows; from below the plate covers its own projection and the body the rest of its
    bottom face (the side faces show as slivers at 1 degree off vertical): pixel shares within
    0.02 of the shoelace areas of the projected faces."""
    from ucad_cl.labeller import BEHIND_SIZE, TB_ELEVATION, top_bottom_counts

    mats = [Material("paint", (0.6, 0.1, 0.1, 1.0)), Material("under", (0.1, 0.1, 0.1, 1.0))]
    mesh = make_mesh([(*box([-2, 0.3, -0.8], [2, 1.2, 0.8]), 0, "body"),
                      (*box([-1.0, 0.1, -0.5], [1.0, 0.2, 0.5]), 1, "pan")], mats)
    counts = top_bottom_counts(mesh, runtime)
    assert counts.shape == (2, 2)
    assert counts[0, 1] == 0 and counts[0, 0] > 0                 # the plate is hidden above
    ring = make_ring(azimuths=(0.0,), elevations=(TB_ELEVATION, -TB_ELEVATION),
                     size=BEHIND_SIZE)
    v = np.asarray(mesh.vertices)

    def bottom_face(lo_idx):          # the 4 corners of a box's bottom face (y = min)
        b = v[lo_idx:lo_idx + 8]
        return b[b[:, 1] <= b[:, 1].min() + 1e-12]

    body, pan = bottom_face(0), bottom_face(8)
    a_body, a_pan = _projected_area(body, ring, 1), _projected_area(pan, ring, 1)
    assert 0 < a_pan < a_body
    share = counts[1] / counts[1].sum()
    assert share[1] == pytest.approx(a_pan / a_body, abs=0.02)
    assert counts[1].sum() == pytest.approx(a_body, rel=0.05)


def test_cue_columns_on_hand_made_parts(runtime):
    """Component shape (``comp_elong`` = log10 longest / middle box side, ``comp_narrow`` =
    middle side / vehicle height, area-weighted over a material's components), the glazing
    band and the lamp zone against the boxes' own dimensions; a plate under the body is seen
    from below only (``bottom_pix``, ``top_pix``)."""
    from ucad_cl.render import render_views

    mats = [Material("paint", (0.6, 0.1, 0.1, 1.0)), Material("strip", (0.02, 0.02, 0.02, 1.0)),
            Material("glass", (0.1, 0.1, 0.1, 1.0)), Material("lamp", (0.9, 0.1, 0.1, 1.0)),
            Material("pan", (0.2, 0.2, 0.2, 1.0))]
    # file frame: length X (4 m), height 0..1.5 m, width Z (1.6 m)
    parts = [(*box([-2, 0.2, -0.8], [2, 0.9, 0.8]), 0, "body"),
             (*box([-1.5, 0.5, 0.8], [1.5, 0.55, 0.82]), 1, "strip_L"),     # 3 m x 5 cm x 2 cm
             (*box([-1.5, 0.5, -0.82], [1.5, 0.55, -0.8]), 1, "strip_R"),
             (*box([-1.0, 0.95, -0.7], [1.0, 1.4, 0.7]), 2, "greenhouse"),
             (*box([2.0, 0.55, -0.7], [2.01, 0.7, -0.4]), 3, "lamp_L"),
             (*box([-0.6, 0.0, -0.3], [0.6, 0.05, 0.3]), 4, "pan")]
    parts.append((*box([-0.5, 1.4, -0.5], [0.5, 1.5, 0.5]), 0, "roof_box"))
    mesh = make_mesh(parts, mats)
    views = render_views(mesh, make_ring(azimuth_step=30, elevations=(15.0,), size=96))
    X = material_table(mesh, views).X
    strip, glass, lamp, pan = 1, 2, 3, 4
    H = 1.5                                                   # the vehicle's height (m)
    assert X[strip, COL["comp_elong"]] == pytest.approx(np.log10(3.0 / 0.05), abs=1e-4)
    assert X[strip, COL["comp_narrow"]] == pytest.approx(0.05 / H, abs=1e-4)
    # a 2 x 0.45 x 1.4 m box: longest 2, middle 1.4
    assert X[glass, COL["comp_elong"]] == pytest.approx(np.log10(2.0 / 1.4), abs=1e-4)
    assert X[glass, COL["glaze_band"]] > 0.8 and X[lamp, COL["glaze_band"]] == 0
    assert X[lamp, COL["lamp_zone"]] > 0.9 and X[glass, COL["lamp_zone"]] == 0
    assert X[pan, COL["top_pix"]] == 0 and X[pan, COL["bottom_pix"]] > 0.1
    assert X[pan, COL["bottom_rel"]] > X[0, COL["bottom_rel"]]
    assert X[0, COL["top_pix"]] > 0.5
