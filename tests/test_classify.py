"""IoU part classification: the histogram kernel against NumPy, decision rules, hard cases, and
accuracy with ground-truth (and degraded) part masks on rendered vehicles."""
from __future__ import annotations

import json

import numpy as np
import pytest
from ucad_cl.classify import classify_parts, part_histogram, symmetric_pairs
from ucad_cl.segment import masks_from_labels
from tests.reference import flat_mesh, flat_views
from ucad_cl.artifacts import PART_NAMES, Material, Mesh, PartMasks

pytestmark = pytest.mark.every_device      # tests/conftest.py: UCAD_TEST_DEVICES


def numpy_histogram(mat_id, masks, n_ids):
    """Reference: bincount of ids per view, and of ids inside each part mask."""
    V, P = masks.shape[:2]
    out = np.zeros((V, n_ids, 1 + P), np.int64)
    for v in range(V):
        out[v, :, 0] = np.bincount(mat_id[v].ravel(), minlength=n_ids)
        for p in range(P):
            out[v, :, 1 + p] = np.bincount(mat_id[v][masks[v, p]], minlength=n_ids)
    return out




def part_masks(V, H, W, spec: dict, conf=None) -> PartMasks:
    """spec: {part: (V, H, W) bool}; parts in the given order."""
    parts = list(spec)
    masks = np.stack([spec[p] for p in parts], axis=1)
    c = np.ones((V, len(parts)), np.float32) if conf is None else np.asarray(conf, np.float32)
    return PartMasks(parts=parts, masks=masks, confidence=np.where(masks.any(axis=(2, 3)), c, 0))


# -- the kernel ---------------------------------------------------------------------------------
@pytest.mark.parametrize("use_local", [True, False])
@pytest.mark.parametrize("local,ppi", [(1, 7), (16, 256), (64, 1024)])
def test_histogram_matches_numpy(runtime, use_local, local, ppi):
    rng = np.random.default_rng(local + ppi)
    V, H, W, P, n_ids = 5, 37, 53, 9, 11
    mat = rng.integers(0, n_ids, (V, H, W)).astype(np.uint16)
    mat[:, 5:20, 3:40] = 4                      # long runs, as in real maps
    masks = rng.random((V, P, H, W)) < 0.3
    masks[:, 2, 10:30] = True
    h = part_histogram(mat, masks, n_ids=n_ids, local_size=local, pixels_per_item=ppi,
                       use_local=use_local, runtime=runtime)
    assert h.dtype == np.uint32 and h.shape == (V, n_ids, 1 + P)
    np.testing.assert_array_equal(h, numpy_histogram(mat, masks, n_ids))


def test_histogram_bit_identical_across_runs_and_launch_shapes(runtime):
    rng = np.random.default_rng(1)
    mat = rng.integers(0, 30, (8, 64, 64)).astype(np.uint16)
    masks = rng.random((8, 16, 64, 64)) < 0.5       # 16 parts: every bit of the packing used
    ref = part_histogram(mat, masks, runtime=runtime)
    for local, ppi, loc in [(1, 1, True), (4, 33, False), (16, 256, True), (16, 256, True)]:
        assert np.array_equal(part_histogram(mat, masks, local_size=local, pixels_per_item=ppi,
                                             use_local=loc, runtime=runtime), ref)
    np.testing.assert_array_equal(ref, numpy_histogram(mat, masks, 30))


def test_histogram_rejects_bad_input(runtime):
    mat = np.zeros((2, 4, 4), np.uint16)
    with pytest.raises(ValueError, match="uint16"):
        part_histogram(mat.astype(np.int32), np.zeros((2, 1, 4, 4), bool), runtime=runtime)
    with pytest.raises(ValueError, match="does not match"):
        part_histogram(mat, np.zeros((2, 1, 4, 5), bool), runtime=runtime)
    with pytest.raises(ValueError, match="1..16 part masks"):
        part_histogram(mat, np.zeros((2, 17, 4, 4), bool), runtime=runtime)
    with pytest.raises(ValueError, match="bool"):
        part_histogram(mat, np.zeros((2, 1, 4, 4), np.uint8), runtime=runtime)
    bits = np.zeros((2, 4, 4), np.uint16)
    with pytest.raises(ValueError, match="either"):
        part_histogram(mat, np.zeros((2, 1, 4, 4), bool), bits=bits, n_parts=1, runtime=runtime)
    with pytest.raises(ValueError, match="n_parts"):
        part_histogram(mat, bits=bits, runtime=runtime)
    with pytest.raises(ValueError, match="does not match"):
        part_histogram(mat, bits=bits[:1], n_parts=1, runtime=runtime)
    with pytest.raises(ValueError, match="uint16"):
        part_histogram(mat, bits=bits.astype(np.uint8), n_parts=1, runtime=runtime)
    bits[1, 2, 3] = 1 << 3                                # part 3 of 3 parts (0..2): no row
    with pytest.raises(ValueError, match="beyond the 3 parts"):
        part_histogram(mat, bits=bits, n_parts=3, runtime=runtime)


@pytest.mark.parametrize("use_local", [True, False])
def test_histogram_of_packed_bits_and_stacked_views(runtime, use_local):
    """bits input = masks input; a list of maps counts as their concatenation along views."""
    rng = np.random.default_rng(11)
    V, H, W, P, n_ids = 4, 29, 41, 12, 70
    mat = rng.integers(0, n_ids, (V, H, W)).astype(np.uint16)
    mat[:, 3:20, 5:30] = 9
    core = np.where(rng.random((V, H, W)) < 0.6, mat, 0).astype(np.uint16)
    masks = rng.random((V, P, H, W)) < 0.4
    bits = sum(masks[:, p].astype(np.uint16) << p for p in range(P)).astype(np.uint16)
    want = numpy_histogram(np.concatenate([mat, core]), np.concatenate([masks, masks]), n_ids)
    kw = dict(n_ids=n_ids, use_local=use_local, local_size=8, pixels_per_item=100)
    np.testing.assert_array_equal(part_histogram(mat, masks, **kw, runtime=runtime), want[:V])
    np.testing.assert_array_equal(part_histogram(mat, bits=bits, n_parts=P, **kw, runtime=runtime), want[:V])
    np.testing.assert_array_equal(
        part_histogram([mat, core], bits=[bits, bits], n_parts=P, **kw, runtime=runtime), want)
    np.testing.assert_array_equal(                        # again: reused device buffers
        part_histogram([mat[:1], mat[1:], core], bits=[bits, bits[:2], bits[2:]], n_parts=P,
                       **kw, runtime=runtime), want)


# -- decision rules and hard cases --------------------------------------------------------------
def test_scores_and_iou_match_numpy_reference(runtime):
    rng = np.random.default_rng(7)
    V, H, W = 3, 40, 40
    mat = np.zeros((V, H, W), np.uint16)
    mat[:, 5:35, 5:20] = 1
    mat[:, 5:35, 20:35] = 2
    win = np.zeros((V, H, W), bool)
    win[:, 0:30, 0:22] = True                   # covers most of material 1 plus background
    light = rng.random((V, H, W)) < 0.2
    pm = part_masks(V, H, W, {"window": win, "light": light}, conf=[[0.9, 0.5], [0.8, 0.5],
                                                                    [0.7, 0.5]])
    table = classify_parts(flat_mesh(2), flat_views(mat), pm, symmetry=False, runtime=runtime)
    r = table.rows[0]
    assert r.part == "window" and r.view == 0 and r.decision == "best-view"
    m = mat[0] == 1
    inter = np.count_nonzero(m & win[0])
    assert r.score == pytest.approx(inter / m.sum(), abs=0)
    assert r.iou == pytest.approx(inter / np.count_nonzero(m | win[0]), abs=0)
    assert r.pixels == 3 * m.sum()
    assert table.rows[1].part == "other" and table.rows[1].decision == "below-threshold"


def test_empty_part_masks(runtime):
    mat = np.zeros((2, 16, 16), np.uint16)
    mat[:, 4:12, 4:12] = 1
    pm = part_masks(2, 16, 16, {p: np.zeros((2, 16, 16), bool) for p in PART_NAMES})
    (r,) = classify_parts(flat_mesh(1), flat_views(mat), pm, runtime=runtime).rows
    assert (r.part, r.decision, r.score, r.iou, r.pixels) == ("other", "below-threshold", 0.0,
                                                              0.0, 128)


def test_material_visible_in_one_pixel(runtime):
    mat = np.zeros((1, 8, 8), np.uint16)
    mat[0, 3, 3] = 1
    win = np.zeros((1, 8, 8), bool)
    win[0, 3, 3] = True
    pm = part_masks(1, 8, 8, {"window": win})
    (r,) = classify_parts(flat_mesh(1), flat_views(mat), pm, min_pixels=1, runtime=runtime).rows
    assert (r.part, r.score, r.iou, r.pixels, r.view) == ("window", 1.0, 1.0, 1, 0)
    (r,) = classify_parts(flat_mesh(1), flat_views(mat), pm, min_pixels=2, runtime=runtime).rows
    assert (r.part, r.decision, r.view) == ("unseen", "unseen", -1)


def test_part_mask_covering_whole_image(runtime):
    mat = np.zeros((2, 10, 10), np.uint16)
    mat[:, :, :4] = 1
    mat[:, :, 4:7] = 2
    pm = part_masks(2, 10, 10, {"body": np.ones((2, 10, 10), bool)})
    rows = classify_parts(flat_mesh(3), flat_views(mat), pm, runtime=runtime).rows
    assert [r.part for r in rows] == ["body", "body", "unseen"]
    assert rows[0].score == 1.0 and rows[0].iou == pytest.approx(40 / 100)
    assert rows[1].iou == pytest.approx(30 / 100)


@pytest.mark.parametrize("order", [("light", "window"), ("window", "light")])
def test_equal_overlap_tie_goes_to_part_names_order(runtime, order):
    mat = np.zeros((1, 8, 8), np.uint16)
    mat[0, 2:6, 2:6] = 1
    left = np.zeros((1, 8, 8), bool)
    left[0, :, :4] = True
    masks = {"window": left, "light": ~left}
    pm = part_masks(1, 8, 8, {p: masks[p] for p in order})
    (r,) = classify_parts(flat_mesh(1), flat_views(mat), pm, threshold=0.4, runtime=runtime).rows
    assert PART_NAMES.index("window") < PART_NAMES.index("light")
    assert (r.part, r.score) == ("window", 0.5)
    (r,) = classify_parts(flat_mesh(1), flat_views(mat), pm, runtime=runtime).rows      # 0.5 is not > 0.5
    assert r.decision == "below-threshold"


def test_equal_view_confidence_tie_goes_to_lower_view(runtime):
    mat = np.zeros((2, 8, 8), np.uint16)
    mat[:, 2:6, 2:6] = 1
    win = np.zeros((2, 8, 8), bool)
    light = np.zeros((2, 8, 8), bool)
    win[0], light[1] = True, True               # the two views disagree, equal weight
    pm = part_masks(2, 8, 8, {"window": win, "light": light}, conf=[[0.7, 0.7], [0.7, 0.7]])
    (r,) = classify_parts(flat_mesh(1), flat_views(mat), pm, runtime=runtime).rows
    assert (r.part, r.view, r.decision) == ("window", 0, "best-view")
    pm.masks = pm.masks[::-1].copy()
    (r,) = classify_parts(flat_mesh(1), flat_views(mat), pm, runtime=runtime).rows
    assert (r.part, r.view, r.decision) == ("light", 0, "best-view")


def test_vote_overrides_single_confident_view(runtime):
    V = 4
    mat = np.zeros((V, 12, 12), np.uint16)
    mat[:, 2:10, 2:10] = 1
    mat[0, 2:10, 2:10] = 0
    mat[0, 5, 5] = 1                            # view 0: seen in one pixel only
    light = np.zeros((V, 12, 12), bool)
    win = np.zeros((V, 12, 12), bool)
    light[0], win[1:] = True, True
    conf = [[0.0, 0.99]] + [[0.6, 0.0]] * 3
    pm = part_masks(V, 12, 12, {"window": win, "light": light}, conf=conf)
    (r,) = classify_parts(flat_mesh(1), flat_views(mat), pm, runtime=runtime).rows
    assert (r.part, r.decision) == ("window", "vote")
    assert r.view == 1 and r.score == 1.0


def test_small_leftover_merges_into_body_unless_prior(runtime):
    mat = np.ones((2, 40, 40), np.uint16)
    mat[:, :, :5] = 0
    mat[:, 18:22, 18:22] = 2                    # a small badge on the body
    body = mat == 1
    pm = part_masks(2, 40, 40, {"body": body})
    rows = classify_parts(flat_mesh(2), flat_views(mat), pm, runtime=runtime).rows
    assert (rows[1].part, rows[1].decision) == ("body", "merged-body")
    rows = classify_parts(flat_mesh(2), flat_views(mat), pm, priors={1: "plate"}, runtime=runtime).rows
    assert (rows[1].part, rows[1].decision) == ("plate", "prior")
    rows = classify_parts(flat_mesh(2), flat_views(mat), pm, merge_max_fraction=0.001, runtime=runtime).rows
    assert (rows[1].part, rows[1].decision) == ("other", "below-threshold")


def _mirror_mesh():
    """Body box in the middle (material 0), two lamps (1, 2) mirrored across x = 0 (the width
    axis: x extent < z extent), and an asymmetric badge (3) on one side only."""
    import trimesh

    parts, mats = [], []
    for centre, extent, m in [((0, 0, 0), (0.6, 0.4, 1.6), 0),
                              ((-0.25, 0.1, 0.8), (0.1, 0.1, 0.05), 1),
                              ((0.25, 0.1, 0.8), (0.1, 0.1, 0.05), 2),
                              ((0.29, -0.1, -0.3), (0.02, 0.05, 0.1), 3)]:
        b = trimesh.creation.box(extents=extent)
        b.apply_translation(centre)
        parts.append(b)
        mats.append(np.full(len(b.faces), m, np.uint16))
    off = np.cumsum([0] + [len(p.vertices) for p in parts])
    v = np.concatenate([p.vertices for p in parts])
    f = np.concatenate([p.faces + o for p, o in zip(parts, off)]).astype(np.uint32)
    return Mesh(path="mirror", sha256="1" * 64, vertices=v, faces=f,
                face_material=np.concatenate(mats),
                materials=[Material(name=n) for n in ("body", "lamp_l", "lamp_r", "badge")])


def test_symmetric_pairs_found_by_reflection():
    mesh = _mirror_mesh()
    assert symmetric_pairs(mesh) == [(1, 2)]
    broken = mesh.vertices.copy()
    used = np.unique(mesh.faces[mesh.face_material == 2])
    broken[used, 1] += 0.2                              # lamp_r no longer mirrors lamp_l
    assert symmetric_pairs(Mesh(**{**mesh.__dict__, "vertices": broken})) == []


def _pairs_by_brute_force(mesh, tol=0.01, min_match=0.8, plane_match=0.5, max_samples=2000):
    """symmetric_pairs' rule (its docstring) with full NumPy distance matrices: no KD tree, no
    box tests, no skipped self matches. Returns (pairs, {(a, b): match share})."""
    v, f, fm = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces), mesh.face_material

    def sample(idx, k):
        return idx if idx.size <= k else idx[np.linspace(0, idx.size - 1, k).round().astype(int)]

    lo, hi = v.min(axis=0), v.max(axis=0)
    axis = 0 if hi[0] - lo[0] <= hi[2] - lo[2] else 2
    mid = 0.5 * (lo[axis] + hi[axis])

    def reflect(x):
        y = x.copy()
        y[:, axis] = 2.0 * mid - y[:, axis]
        return y

    def share(x, y):                 # share of x's points within tol of one of y's points
        d = np.sqrt(((x[:, None, :] - y[None, :, :]) ** 2).sum(axis=2))
        return float(np.mean(d.min(axis=1) <= tol))

    s = v[sample(np.unique(f), max_samples * 4)]
    if share(reflect(s), s) < plane_match:
        return [], {}
    pts = {m: v[sample(np.unique(f[fm == m]), max_samples)] for m in np.unique(fm).tolist()}
    match = {(a, b): share(reflect(pts[a]), pts[b]) for a in pts for b in pts}
    cands = sorted((-(match[a, b] + match[b, a]), a, b) for a in pts for b in pts
                   if a < b and match[a, b] >= min_match and match[b, a] >= min_match
                   and match[a, b] > match[a, a] and match[b, a] > match[b, b])
    used, pairs = set(), []
    for _, a, b in cands:
        if a not in used and b not in used:
            used.update((a, b))
            pairs.append((a, b))
    return sorted(pairs), match


@pytest.mark.parametrize("seed", [3, 11])
def test_symmetric_pairs_match_brute_force_reference(seed):
    """The pruned search (box shares, skipped self matches) finds exactly the pairs of the
    exhaustive rule, on generated vehicles, posed as generated and with the pairs' vertices
    moved off the mirror (so that no pair remains)."""
    synth = pytest.importorskip("ucad_cl.synth")
    mesh = synth.make_vehicle(seed, target_triangles=2500).mesh()
    pairs = symmetric_pairs(mesh)
    ref, match = _pairs_by_brute_force(mesh)
    assert pairs and pairs == ref
    moved = mesh.vertices.copy()
    moved[np.unique(mesh.faces[np.isin(mesh.face_material, [b for _, b in pairs])]), 1] += 0.05
    other = Mesh(**{**mesh.__dict__, "vertices": moved})
    assert symmetric_pairs(other) == _pairs_by_brute_force(other)[0]
    # a copy of the most mirror-symmetric material matches it as well as that material matches
    # itself: no pair, so the self match decides (the case the skipped queries must keep)
    fm = np.asarray(mesh.face_material)
    sym = max(sorted({a for a, _ in match}), key=lambda m: match[m, m])
    assert match[sym, sym] >= 0.8
    M = len(mesh.materials)
    twin = Mesh(**{**mesh.__dict__, "faces": np.concatenate([mesh.faces, mesh.faces[fm == sym]]),
                   "face_material": np.concatenate([fm, np.full((fm == sym).sum(), M, fm.dtype)]),
                   "materials": [*mesh.materials, Material(name="twin")]})
    got = symmetric_pairs(twin)
    assert got == _pairs_by_brute_force(twin)[0] and not any(M in p for p in got)


def test_symmetric_pair_gets_one_label(runtime):
    mesh = _mirror_mesh()
    mat = np.ones((1, 20, 20), np.uint16)               # body (id 1) on top
    mat[0, 10:, :10] = 2                                # lamp_l
    mat[0, 10:, 10:] = 3                                # lamp_r
    light = mat == 2
    light[0, 10:13, 10:] = True                         # 30 % of lamp_r
    chrome = (mat == 3) & ~light                        # 70 % of lamp_r
    pm = part_masks(1, 20, 20, {"body": mat == 1, "light": light, "chrome": chrome})
    rows = classify_parts(mesh, flat_views(mat), pm, symmetry=False, runtime=runtime).rows
    assert (rows[1].part, rows[2].part) == ("light", "chrome")
    rows = classify_parts(mesh, flat_views(mat), pm, runtime=runtime).rows
    assert (rows[1].part, rows[1].decision) == ("light", "best-view")
    assert (rows[2].part, rows[2].decision) == ("light", "symmetric")
    assert rows[2].score == pytest.approx(0.7)          # evidence of its own view kept


# -- accuracy with ground-truth masks on rendered vehicles --------------------------------------
def degrade(masks: PartMasks, seed: int) -> PartMasks:
    """Erode or dilate every mask by 2 px (cv2), drop 10 % of the non-empty masks, jitter the
    confidences by +-0.15; all seeded."""
    import cv2

    rng = np.random.default_rng(seed)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    out = masks.masks.copy()
    V, P = out.shape[:2]
    for v in range(V):
        for p in range(P):
            if not out[v, p].any():
                continue
            img = out[v, p].astype(np.uint8)
            img = cv2.erode(img, k) if rng.random() < 0.5 else cv2.dilate(img, k)
            out[v, p] = img.astype(bool) if rng.random() >= 0.1 else False
    conf = np.clip(masks.confidence + rng.uniform(-0.15, 0.15, masks.confidence.shape), 0, 1)
    conf = np.where(out.any(axis=(2, 3)), conf, 0).astype(np.float32)
    return PartMasks(parts=masks.parts, masks=out, confidence=conf, source="degraded")


GT_MODELS = ["o3dv_car.glb", "openmaterial_vehicle/vehicle_example.gltf",
             "openmaterial_truck/truck_example.gltf", "ferrari_348_lowpoly.glb",
             "cesium_milk_truck.glb", "a_frame_car/car.obj"]


@pytest.fixture(scope="module")
def rendered_real(vehicles_dir, runtime):
    from ucad_cl.cameras import make_ring
    from ucad_cl.ingest import load_mesh
    from ucad_cl.render import render_views

    manifest = {m["file"]: m["materials"]
                for m in json.loads((vehicles_dir / "manifest.json").read_text())["models"]}
    ring = make_ring(azimuth_step=15.0, elevations=(15.0,), size=128)
    out = []
    for f in GT_MODELS:
        mesh = load_mesh(vehicles_dir / f)
        truth = {i: manifest[f][m.name] for i, m in enumerate(mesh.materials)}
        out.append((mesh, render_views(mesh, ring, runtime=runtime), truth))
    return out


def _synth_cases(n=4, size=128):
    synth = pytest.importorskip("ucad_cl.synth")
    from ucad_cl.cameras import make_ring
    from ucad_cl.render import render_views

    ring = make_ring(azimuth_step=15.0, elevations=(15.0,), size=size)
    out = []
    for seed in range(n):
        veh = synth.make_vehicle(seed)
        mesh = veh.mesh()
        truth = {i: veh.truth["materials"][m.name] for i, m in enumerate(mesh.materials)}
        out.append((mesh, render_views(mesh, ring), truth))
    return out


def _accuracy(cases, degrade_seed=None):
    ok = n = 0
    for k, (mesh, views, truth) in enumerate(cases):
        gt = masks_from_labels(views, truth, confidence=0.9)
        pm = gt if degrade_seed is None else degrade(gt, degrade_seed + k)
        for r in classify_parts(mesh, views, pm).rows:
            if r.part != "unseen":
                n += 1
                ok += r.part == truth[r.material]
    assert n > 0
    return ok / n


def test_ground_truth_masks_real_vehicles(rendered_real):
    assert _accuracy(rendered_real) >= 0.98


def test_degraded_masks_real_vehicles(rendered_real):
    assert _accuracy(rendered_real, degrade_seed=100) >= 0.93


def test_ground_truth_masks_synth_vehicles(runtime):
    assert _accuracy(_synth_cases(6)) >= 0.98


def test_degraded_masks_synth_vehicles(runtime):
    # 256 px: a 2 px boundary error swallows whole thin parts (pillars, sills, lamps) at 128 px,
    # where the measured accuracy is 80-89 % depending on the degradation seed (see report)
    # target: mean over three degradation seeds >= 93 %, no seed below 90 %
    cases = _synth_cases(6, size=256)
    acc = [_accuracy(cases, degrade_seed=seed) for seed in (200, 300, 400)]
    assert np.mean(acc) >= 0.93 and min(acc) >= 0.90, acc


def test_classify_is_deterministic(rendered_real):
    mesh, views, truth = rendered_real[1]
    pm = degrade(masks_from_labels(views, truth, confidence=0.9), 5)
    a = classify_parts(mesh, views, pm)
    b = classify_parts(mesh, views, pm)
    assert a == b


def _other_form(pm: PartMasks) -> PartMasks:
    """The same masks built from the other form (bits <-> masks), copies of the arrays."""
    if pm.packed:
        return PartMasks(list(pm.parts), pm.masks.copy(), pm.confidence.copy(), pm.source)
    return PartMasks.from_bits(list(pm.parts), pm.bits.copy(), pm.confidence.copy(), pm.source)


def test_bits_and_masks_give_identical_tables(runtime):
    """Packed and unpacked PartMasks classify alike (every field of every row, exactly), on
    disjoint (ground-truth, prior) and overlapping (degraded) masks of generated vehicles; a
    packed PartMasks is never unpacked by classification."""
    from ucad_cl.names import name_priors
    from ucad_cl.segment import PriorSegmenter

    for k, (mesh, views, truth) in enumerate(_synth_cases(3)):
        gt = masks_from_labels(views, truth, confidence=0.9)
        prior = PriorSegmenter().segment(mesh, views)
        deg = degrade(masks_from_labels(views, truth, confidence=0.9), 50 + k)   # overlapping
        assert gt.packed and prior.packed and not deg.packed
        for pm in (gt, prior, deg):
            packed = pm.packed
            a = classify_parts(mesh, views, pm, priors=name_priors(mesh), runtime=runtime)
            assert pm.packed == packed                     # no (V, P, H, W) masks were built
            other = _other_form(pm)
            assert other.packed != packed
            b = classify_parts(mesh, views, other, priors=name_priors(mesh), runtime=runtime)
            assert a == b and len(a.rows) == len(mesh.materials)


def test_classify_rejects_bad_packed_masks(runtime):
    mat = np.zeros((2, 8, 8), np.uint16)
    mat[:, 2:4, 2:4] = 1
    views, mesh = flat_views(mat), flat_mesh(1)
    bits = (mat == 1).astype(np.uint16)
    conf = np.ones((2, 1), np.float32)
    with pytest.raises(ValueError, match="does not match the views"):
        classify_parts(mesh, views, PartMasks.from_bits(["body"], bits[:, :4], conf), runtime=runtime)
    with pytest.raises(ValueError, match="uint16"):
        classify_parts(mesh, views, PartMasks.from_bits(["body"], bits.astype(bool), conf), runtime=runtime)
    with pytest.raises(ValueError, match="1..16 parts"):
        classify_parts(mesh, views, PartMasks.from_bits([f"p{i}" for i in range(17)], bits,
                                                        np.ones((2, 17), np.float32)), runtime=runtime)
    with pytest.raises(ValueError, match=r"confidence must be \(2, 1\)"):
        classify_parts(mesh, views, PartMasks.from_bits(["body"], bits, conf[:1]), runtime=runtime)
    with pytest.raises(ValueError, match="beyond the 1 parts"):
        classify_parts(mesh, views, PartMasks.from_bits(["body"], bits * 2, conf), runtime=runtime)
    (r,) = classify_parts(mesh, views, PartMasks.from_bits(["body"], bits, conf), runtime=runtime).rows
    assert (r.part, r.score, r.pixels) == ("body", 1.0, 8)


def test_classify_rejects_bad_masks(runtime):
    mat = np.zeros((2, 8, 8), np.uint16)
    mat[:, 2:4, 2:4] = 1
    views, mesh = flat_views(mat), flat_mesh(1)
    good = part_masks(2, 8, 8, {"body": mat == 1})
    with pytest.raises(ValueError, match="unknown part names"):
        classify_parts(mesh, views, PartMasks(["roof"], good.masks, good.confidence), runtime=runtime)
    with pytest.raises(ValueError, match="does not match the views"):
        classify_parts(mesh, views, PartMasks(["body"], good.masks[:, :, :4], good.confidence), runtime=runtime)
    with pytest.raises(ValueError, match=r"inside \[0, 1\]"):
        classify_parts(mesh, views, PartMasks(["body"], good.masks, good.confidence + 2), runtime=runtime)
    with pytest.raises(ValueError, match="material id 1 in the views"):
        classify_parts(flat_mesh(0), views, good, runtime=runtime)


def test_never_visible_material_takes_the_labellers_part_with_its_own_flag(runtime):
    from ucad_cl.labeller import MaterialLabels
    mat = np.zeros((2, 10, 10), np.uint16)
    mat[:, :, :4] = 1
    mat[:, :, 4:7] = 2                          # material 2 (index 2) never drawn
    pm = part_masks(2, 10, 10, {"body": mat == 1, "window": mat == 2})
    prob = np.array([[0.8, 0.1, 0, 0, 0, 0, 0, 0.1, 0], [0.1, 0.9, 0, 0, 0, 0, 0, 0, 0],
                     [0.1, 0, 0, 0, 0, 0, 0, 0.6, 0.3]], np.float32)
    pm.labels = MaterialLabels(prob=prob, part=prob.argmax(axis=1), behind_pixels=np.zeros(3))
    rows = classify_parts(flat_mesh(3), flat_views(mat), pm, runtime=runtime).rows
    assert [(r.part, r.decision) for r in rows] == [
        ("body", "best-view"), ("window", "best-view"), ("interior", "never-visible")]
    assert (rows[2].pixels, rows[2].view, rows[2].prob) == (0, -1, pytest.approx(0.6))
    pm.labels = None                            # no labeller: it stays unseen
    assert classify_parts(flat_mesh(3), flat_views(mat), pm, runtime=runtime).rows[2].part == \
        "unseen"
