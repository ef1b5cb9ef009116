"""ucad_cl.edges: batched Canny vs cv2.Canny (zero differing pixels), material-map edges."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from ucad_cl import edges as E
from ucad_cl.edges import canny, colour_ids, material_edges, write_conditioning_pngs
from ucad_cl.artifacts import CameraRing, EdgeSet, ViewSet

pytestmark = pytest.mark.every_device      # tests/conftest.py: UCAD_TEST_DEVICES

THRESHOLDS = [(50, 150), (0, 0), (100, 100), (150, 50), (10.7, 20.2), (-5, 3), (255, 400),
              (2039, 2041), (1e4, 2e4), (0.5, float("inf"))]


def reference(images: np.ndarray, low, high, l2) -> np.ndarray:
    return np.stack([cv2.Canny(im, low, high, apertureSize=3, L2gradient=l2) for im in images])


def assert_same(images, low, high, l2, runtime):
    ours = canny(images, low, high, l2, runtime=runtime)
    ref = reference(images, low, high, l2)
    assert ours.shape == ref.shape and ours.dtype == np.uint8
    diff = int(np.count_nonzero(ours != ref))
    assert diff == 0, f"{diff} pixels differ (low={low}, high={high}, l2={l2})"
    return ours


def shapes_image(h, w, seed):
    rng = np.random.default_rng(seed)
    im = np.zeros((h, w), np.uint8)
    for _ in range(6):
        pts = rng.integers(-5, max(h, w) + 5, (4, 2)).astype(np.int32)
        cv2.fillPoly(im, [cv2.convexHull(pts)], int(rng.integers(0, 256)))
    cv2.circle(im, (w // 3, h // 2), max(2, min(h, w) // 4), 200, 1)
    yy, xx = np.mgrid[0:h, 0:w]
    ramp = ((xx * 3 + yy * 5) % 256).astype(np.uint8)
    return np.where(xx > w // 2, ramp, im).astype(np.uint8)


def hard_images(h=23, w=29):
    out = {}
    out["constant"] = np.full((h, w), 77, np.uint8)
    p = np.zeros((h, w), np.uint8); p[h // 2, w // 2] = 255; out["single_pixel"] = p
    p = np.zeros((h, w), np.uint8); p[0, 0] = p[h - 1, w - 1] = p[0, w - 1] = 255
    out["corner_pixels"] = p
    p = np.zeros((h, w), np.uint8); p[:, 5] = 255; p[7, :] = 128; p[:, w - 1] = 200
    out["thin_lines_and_border"] = p
    p = np.zeros((h, w), np.uint8); p[::2, :] = 255; out["stripes_period2"] = p
    p = np.zeros((h, w), np.uint8); p[(np.add.outer(np.arange(h), np.arange(w)) % 2) == 0] = 255
    out["checkerboard"] = p
    p = np.zeros((h, w), np.uint8); p[:, :w // 2] = 90; p[h // 2:, :] += 90; out["quadrants"] = p
    yy, xx = np.mgrid[0:h, 0:w]
    out["diagonal_step"] = np.where(xx > yy, 200, 10).astype(np.uint8)
    out["anti_diagonal_step"] = np.where(xx + yy > w // 2, 200, 10).astype(np.uint8)
    # equal magnitudes on both NMS sides: a 2-pixel stripe and a 45-degree tie (|dx| == |dy|)
    p = np.zeros((h, w), np.uint8); p[5:7, :] = 100; p[:, 12:14] = 100; out["ties_2px"] = p
    out["plateau_ramp"] = np.clip(xx * 16, 0, 255).astype(np.uint8)
    out["border_content"] = np.pad(np.zeros((h - 2, w - 2), np.uint8), 1, constant_values=180)
    return out


@pytest.mark.parametrize("l2", [False, True])
def test_random_noise_matches_opencv(runtime, l2):
    rng = np.random.default_rng(1)
    imgs = rng.integers(0, 256, (3, 37, 53), dtype=np.uint8)
    for low, high in THRESHOLDS:
        assert_same(imgs, low, high, l2, runtime)


@pytest.mark.parametrize("l2", [False, True])
def test_structured_and_hard_images_match_opencv(runtime, l2):
    hard = hard_images()
    imgs = np.stack(list(hard.values()) + [shapes_image(23, 29, s) for s in range(3)])
    for low, high in THRESHOLDS:
        assert_same(imgs, low, high, l2, runtime)
    # the hard cases are not all trivially empty
    assert canny(hard["single_pixel"], 50, 150, l2, runtime=runtime).any()
    assert not canny(hard["constant"], 0, 0, l2, runtime=runtime).any()


@pytest.mark.parametrize("shape", [(1, 1), (1, 17), (17, 1), (2, 2), (3, 40), (37, 53), (64, 65)])
def test_odd_and_tiny_sizes_match_opencv(runtime, shape):
    rng = np.random.default_rng(shape[0] * 100 + shape[1])
    img = rng.integers(0, 256, shape, dtype=np.uint8)
    img[: shape[0] // 2] //= 4
    for l2 in (False, True):
        for low, high in [(20, 60), (0, 0), (100, 90)]:
            ours = canny(img, low, high, l2, runtime=runtime)
            assert ours.shape == shape
            assert np.array_equal(ours, cv2.Canny(img, low, high, L2gradient=l2))


@pytest.mark.parametrize("shape", [(1, 1), (1, 17), (17, 1), (5, 40), (20, 33)])
def test_three_channel_odd_sizes_match_opencv(runtime, shape):
    rng = np.random.default_rng(shape[0] * 7 + shape[1])
    img = rng.integers(0, 256, (*shape, 3), dtype=np.uint8)
    for l2 in (False, True):
        assert np.array_equal(canny(img, 30, 90, l2, runtime=runtime), cv2.Canny(img, 30, 90, L2gradient=l2))


def test_material_map_images_match_opencv(runtime):
    rng = np.random.default_rng(3)
    ids = cv2.resize(rng.integers(0, 9, (12, 12)).astype(np.uint16), (48, 48),
                     interpolation=cv2.INTER_NEAREST)[None]
    grey = (ids.astype(np.int32) * 29 % 256).astype(np.uint8)
    assert_same(grey, 50, 150, False, runtime)
    col = colour_ids(ids)
    for l2 in (False, True):
        ours = canny(col, 10, 20, l2, runtime=runtime)
        assert np.array_equal(ours[0], cv2.Canny(col[0], 10, 20, L2gradient=l2))


@pytest.mark.parametrize("l2", [False, True])
def test_three_channel_matches_opencv(runtime, l2):
    rng = np.random.default_rng(4)
    noise = rng.integers(0, 256, (2, 31, 45, 3), dtype=np.uint8)
    # channel ties: channel 0 has a vertical edge, channel 1 the same magnitude horizontally
    tie = np.zeros((31, 45, 3), np.uint8)
    tie[:, 20:, 0] = 120
    tie[15:, :, 1] = 120
    tie[:, :, 2] = shapes_image(31, 45, 9)
    imgs = np.concatenate([noise, tie[None]])
    for low, high in [(50, 150), (0, 0), (30.5, 30.5)]:
        ours = canny(imgs, low, high, l2, runtime=runtime)
        for b in range(imgs.shape[0]):
            assert np.array_equal(ours[b], cv2.Canny(imgs[b], low, high, L2gradient=l2))
        assert np.array_equal(canny(imgs[0], low, high, l2, runtime=runtime), ours[0])      # (H, W, 3) input


def test_batched_equals_single_and_is_deterministic(runtime):
    rng = np.random.default_rng(5)
    imgs = rng.integers(0, 256, (5, 40, 33), dtype=np.uint8)
    batch = canny(imgs, 40, 120, runtime=runtime)
    singles = np.stack([canny(im, 40, 120, runtime=runtime) for im in imgs])
    assert np.array_equal(batch, singles)
    assert np.array_equal(canny(imgs, 40, 120, runtime=runtime), batch)                      # reused buffers
    assert np.array_equal(canny(imgs[:, :, :, None], 40, 120, runtime=runtime), batch)      # (B, H, W, 1)
    assert set(np.unique(batch)) <= {0, 255}


def test_chunked_batches_equal_one_launch(runtime, monkeypatch):
    rng = np.random.default_rng(6)
    imgs = rng.integers(0, 256, (5, 16, 16), dtype=np.uint8)
    whole = canny(imgs, 30, 90, runtime=runtime)
    monkeypatch.setattr(E, "MAX_CHUNK_PIXELS", 2 * 16 * 16)
    assert np.array_equal(canny(imgs, 30, 90, runtime=runtime), whole)


def test_thresholds_follow_opencv():
    assert E.opencv_thresholds(150, 50, False) == (50, 150)
    assert E.opencv_thresholds(10.9, 20.1, False) == (10, 20)
    assert E.opencv_thresholds(10.5, 20.0, True) == (110, 400)
    assert E.opencv_thresholds(-3.5, 1e9, True) == (-4, 32767 ** 2)
    assert E.opencv_thresholds(0, float("inf"), False) == (0, -(2 ** 31))


def test_bad_input_is_rejected_with_clear_errors(runtime):
    with pytest.raises(TypeError, match="uint8"):
        canny(np.zeros((8, 8), np.float32), 1, 2, runtime=runtime)
    with pytest.raises(ValueError, match="shape"):
        canny(np.zeros((2, 8, 8, 4), np.uint8), 1, 2, runtime=runtime)
    with pytest.raises(ValueError, match="shape"):
        canny(np.zeros(8, np.uint8), 1, 2, runtime=runtime)
    with pytest.raises(ValueError, match="empty"):
        canny(np.zeros((0, 8, 8), np.uint8), 1, 2, runtime=runtime)
    with pytest.raises(ValueError, match="NaN"):
        canny(np.zeros((8, 8), np.uint8), float("nan"), 2, runtime=runtime)
    with pytest.raises(TypeError, match="threshold"):
        canny(np.zeros((8, 8), np.uint8), "10", 2, runtime=runtime)
    bad = _viewset(np.zeros((1, 8, 8), np.int32))
    with pytest.raises(ValueError, match="uint16"):
        material_edges(bad, runtime=runtime)
    with pytest.raises(ValueError, match="uint8"):
        write_conditioning_pngs(EdgeSet(edges=np.zeros((8, 8), np.uint8)), "/tmp", "x")


# ---------------------------------------------------------------------------------------------
# material_edges

def _viewset(ids: np.ndarray) -> ViewSet:
    V, H, W = ids.shape
    ring = CameraRing(K=np.eye(3), w2c=np.tile(np.eye(4), (V, 1, 1)), width=W, height=H,
                      azimuth=np.zeros(V), elevation=np.zeros(V), distance=1.0, near=0.1)
    return ViewSet(cameras=ring, tri_id=np.zeros((V, H, W), np.uint32), mat_id=ids,
                   depth=np.zeros((V, H, W), np.float32))


def _pairs_missed(ids, edges):
    near = E._dilate8(edges > 0)
    h = (ids[:, :, 1:] != ids[:, :, :-1]) & ~near[:, :, 1:] & ~near[:, :, :-1]
    v = (ids[:, 1:, :] != ids[:, :-1, :]) & ~near[:, 1:, :] & ~near[:, :-1, :]
    return int(h.sum() + v.sum())


def _random_id_maps(seed, S=40):
    rng = np.random.default_rng(seed)
    maps = [rng.integers(0, 2, (S, S)), rng.integers(0, 7, (S, S))]
    poly = np.zeros((S, S), np.int32)
    for _ in range(12):
        pts = rng.integers(0, S, (4, 2)).astype(np.int32)
        cv2.fillPoly(poly, [cv2.convexHull(pts)], int(rng.integers(1, 40)))
    lines = np.zeros((S, S), np.uint16)
    for _ in range(12):
        p = rng.integers(0, S, 4)
        cv2.line(lines, (int(p[0]), int(p[1])), (int(p[2]), int(p[3])), int(rng.integers(1, 6)), 1)
    stripes = np.zeros((S, S), np.int64); stripes[::2] = 3; stripes[:, 20:] = 0; stripes[5:7, 20:] = 9
    maps += [poly, lines, stripes]
    return np.stack(maps).astype(np.uint16)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_every_id_boundary_has_an_edge_within_one_pixel(runtime, seed):
    ids = _random_id_maps(seed)
    e = material_edges(_viewset(ids), runtime=runtime).edges
    assert e.shape == ids.shape and e.dtype == np.uint8
    assert _pairs_missed(ids, e) == 0
    # precision: every edge pixel has two different ids in its 3x3 neighbourhood
    V, H, W = ids.shape
    pad = np.pad(ids.astype(np.int32), ((0, 0), (1, 1), (1, 1)), mode="edge")
    win = np.stack([pad[:, i:i + H, j:j + W] for i in range(3) for j in range(3)])
    mixed = win.min(0) != win.max(0)
    assert not np.any((e > 0) & ~mixed)


def test_canny_alone_misses_period2_stripes_and_repair_fixes_them(runtime):
    ids = np.zeros((1, 12, 12), np.uint16)
    ids[0, ::2] = 1                              # 1-pixel stripes: every Sobel response is 0
    raw = canny(colour_ids(ids), 10, 20, runtime=runtime)
    assert not raw[0, 2:-2].any() and _pairs_missed(ids, raw) > 0   # edges only at the border
    st = E.CannyStats()
    e = material_edges(_viewset(ids), runtime=runtime, stats=st).edges
    assert _pairs_missed(ids, e) == 0 and st.extra["repaired"] > 0
    # a plain two-region map needs no repair and equals Canny of the colouring
    ids2 = np.zeros((1, 20, 20), np.uint16); ids2[0, :, 8:] = 2
    st = E.CannyStats()
    e2 = material_edges(_viewset(ids2), runtime=runtime, stats=st).edges
    assert st.extra["repaired"] == 0
    assert np.array_equal(e2[0], cv2.Canny(colour_ids(ids2)[0], 10, 20))


def test_colouring_separates_touching_ids_strongly():
    rng = np.random.default_rng(7)
    ids = rng.integers(0, 40, (2, 30, 30)).astype(np.uint16)   # dense: many neighbours per id
    col = colour_ids(ids).astype(np.int32)
    degree = max(len({x for p in E._touching_pairs(ids) for x in p if u in p} - {u})
                 for u in np.unique(ids))
    levels = 2
    while levels ** 3 < degree + 1:
        levels += 1
    for axis in (1, 2):
        ia = np.diff(ids.astype(np.int32), axis=axis) != 0
        gap = np.abs(np.diff(col, axis=axis)).max(-1)[ia]
        assert gap.min() >= 255 // (levels - 1), (gap.min(), levels)
    assert np.array_equal(colour_ids(ids), colour_ids(ids))   # deterministic
    pal = E.palette(3)
    assert len(np.unique(pal, axis=0)) == 27
    assert {tuple(int(c) for c in x) for x in pal[:8]} == {
        (r, g, b) for r in (0, 255) for g in (0, 255) for b in (0, 255)}


@pytest.mark.parametrize("shape", [(3, 37, 53), (2, 5, 3), (1, 64, 64)])
def test_canny_of_colour_table_equals_opencv_on_the_colour_images(runtime, shape):
    """material_edges' device path (ids + colour table looked up by canny_id_planes) equals
    cv2.Canny of the host-built colour image, image by image; ids with gaps (absent ids)."""
    rng = np.random.default_rng(sum(shape))
    small = rng.choice(np.array([0, 3, 4, 9, 200], np.uint16), (shape[0], 6, 6))
    ids = np.stack([cv2.resize(m, shape[:0:-1], interpolation=cv2.INTER_NEAREST) for m in small])
    table = E.colour_table(ids)
    col = colour_ids(ids)
    assert np.array_equal(table[ids][..., :3], col)
    for l2 in (False, True):
        ours = E.canny_of_colours(ids, table, 10, 20, l2)
        for b in range(shape[0]):
            assert np.array_equal(ours[b], cv2.Canny(col[b], 10, 20, L2gradient=l2)), (b, l2)
    with pytest.raises(ValueError, match="covering every id"):
        E.canny_of_colours(ids, table[:5], 10, 20)


def test_colour_table_gives_present_ids_the_greedy_colours_of_present_ids_only():
    """Absent ids touch nothing, so adding them to the greedy order changes no present id."""
    rng = np.random.default_rng(11)
    ids = (rng.integers(0, 12, (2, 20, 20)) * 7).astype(np.uint16)
    pairs = E._touching_pairs(ids)
    present = sorted(int(u) for u in np.unique(ids))
    nb = {u: set() for u in present}
    for a, b in pairs:
        nb[int(a)].add(int(b))
        nb[int(b)].add(int(a))
    levels = 2
    while levels ** 3 < max(len(v) for v in nb.values()) + 1:
        levels += 1
    pal, chosen = E.palette(levels), {}
    for u in present:
        used = {chosen[n] for n in nb[u] if n in chosen}
        chosen[u] = next(i for i in range(len(pal)) if i not in used)
    table = E.colour_table(ids)
    for u in present:
        assert tuple(table[u, :3]) == tuple(pal[chosen[u]]), u


def test_boxed_pairs_and_repair_equal_whole_image_definitions():
    """_touching_pairs and _repair_missed_boundaries work inside per-view boxes of non-zero ids;
    compared with the whole-image definitions on maps with empty views, objects touching the
    border and edge maps with stray pixels everywhere."""
    rng = np.random.default_rng(2)
    V, H, W = 6, 30, 41
    ids = np.zeros((V, H, W), np.uint16)
    ids[1, 5:9, 7:20] = rng.integers(0, 4, (4, 13))
    ids[2, :, 30:] = rng.integers(1, 3, (H, 11))
    ids[3] = rng.integers(0, 3, (H, W))
    ids[4, 29, 40] = 5
    ids[5, 0, 0] = 1
    edges = np.where(rng.random((V, H, W)) < 0.2, 255, 0).astype(np.uint8)

    def ref_pairs(ids):
        codes = []
        for a, b in ((ids[..., :, 1:], ids[..., :, :-1]), (ids[..., 1:, :], ids[..., :-1, :])):
            d = a != b
            codes.append((np.minimum(a[d], b[d]).astype(np.uint32) << 16)
                         | np.maximum(a[d], b[d]).astype(np.uint32))
        u = np.unique(np.concatenate(codes))
        return np.stack([u >> 16, u & 0xFFFF], 1)

    def ref_repair(ids, edges):
        near = E._dilate8(edges > 0)
        mh = (ids[:, :, 1:] != ids[:, :, :-1]) & ~near[:, :, 1:] & ~near[:, :, :-1]
        mv = (ids[:, 1:, :] != ids[:, :-1, :]) & ~near[:, 1:, :] & ~near[:, :-1, :]
        edges[:, :, :-1][mh] = 255
        edges[:, :-1, :][mv] = 255
        return int(mh.sum() + mv.sum())

    assert np.array_equal(E._touching_pairs(ids), ref_pairs(ids))
    ours, ref = edges.copy(), edges.copy()
    assert E._repair_missed_boundaries(ids, ours) == ref_repair(ids, ref)
    assert np.array_equal(ours, ref)
    assert E._touching_pairs(np.zeros((2, 4, 4), np.uint16)).shape == (0, 2)


def test_write_conditioning_pngs(tmp_path, runtime):
    ids = np.zeros((2, 16, 20), np.uint16); ids[:, 4:10, 5:15] = 3
    es = material_edges(_viewset(ids), runtime=runtime)
    paths = write_conditioning_pngs(es, tmp_path / "png", "car")
    assert [p.name for p in paths] == ["car_000.png", "car_001.png"]
    for v, p in enumerate(paths):
        back = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        assert back.dtype == np.uint8 and np.array_equal(back, es.edges[v])


def test_material_edges_of_rendered_synthetic_vehicle(runtime):
    synth = pytest.importorskip("ucad_cl.synth")
    from ucad_cl.cameras import make_ring
    from ucad_cl.render import render_views

    mesh = synth.make_vehicle(0).mesh()
    views = render_views(mesh, make_ring(azimuth_step=90.0, size=96), runtime=runtime)
    st = E.CannyStats()
    e = material_edges(views, stats=st, runtime=runtime).edges
    assert e.shape == views.mat_id.shape
    assert _pairs_missed(views.mat_id, e) == 0
    assert e.any()
    # on rendered maps Canny alone finds most boundaries (measured: 190 of 2660 pairs repaired,
    # mostly stripes two pixels thick, where OpenCV's NMS tie rule drops the second side)
    boundary = int(np.count_nonzero(views.mat_id[:, :, 1:] != views.mat_id[:, :, :-1])
                   + np.count_nonzero(views.mat_id[:, 1:] != views.mat_id[:, :-1]))
    assert st.extra["repaired"] <= 0.1 * boundary


def test_sixteen_bit_direction_test_equals_opencv_fixed_point():
    """canny.cl classifies the NMS direction in 16-bit lanes; check the identity exhaustively."""
    a, b = np.meshgrid(np.arange(1021, dtype=np.int64), np.arange(1021, dtype=np.int64))
    tg22x = a * 13573
    horiz_ref = (b << 15) < tg22x
    vert_ref = ~horiz_ref & ((b << 15) > tg22x + (a << 16))
    q, r = (a * 27146) >> 16, (a * 27146) & 0xFFFF
    horiz = (b < q) | ((b == q) & (r != 0))
    vert = ~horiz & ((b - 2 * a) > q)
    assert np.array_equal(horiz, horiz_ref) and np.array_equal(vert, vert_ref)
