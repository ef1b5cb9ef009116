"""Pose cues against independent references: silhouette IoU (NumPy sets), edge chamfer (SciPy's
exact Euclidean distance transform), colour regions (per-label sums in a Python loop), render
edges (a dense NumPy version of the rule), crop sampling (direct indexing)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from ucad_cl import cues
from ucad_cl.cameras import make_ring
from ucad_cl.features import HogExtractor, crop_window, square_windows
from ucad_cl.foreground import RENDER_BACKGROUND
from ucad_cl.render import render_views
from ucad_cl.shade import face_normals, shade_views

synth = pytest.importorskip("ucad_cl.synth")


@pytest.fixture(scope="module")
def rendered(runtime):
    mesh = synth.make_vehicle(5, "hatchback").mesh()
    ring = make_ring(azimuths=[20.0, 95.0, 200.0], elevations=[10.0], size=96)
    views = render_views(mesh, ring)
    images = shade_views(mesh, views, background=RENDER_BACKGROUND)
    return mesh, views, images, cues.view_cues(mesh, views, images, HogExtractor())


def _fake_cues(rng, V, S=24, n_labels=5):
    sil = (rng.random((V, S, S)) > 0.5).astype(np.float32)
    edges = rng.random((V, S, S)) > 0.9
    labels = rng.integers(0, n_labels, (V, S, S)).astype(np.int32)
    return cues.Cues(hog=rng.random((V, 8)).astype(np.float32), sil=sil, edges=edges,
                     dist=cues._distances(edges), sides=np.ones(V), labels=labels)


def test_silhouette_is_one_minus_iou_of_the_masks():
    rng = np.random.default_rng(0)
    views = _fake_cues(rng, 4)
    q = _fake_cues(rng, 1)
    q.colours = rng.random((1, 24, 24, 3)).astype(np.float32) * 255
    got = cues.cue_distances(q, views)["silhouette"]
    a = q.sil[0] > 0.5
    for v in range(4):
        b = views.sil[v] > 0.5
        assert got[v] == pytest.approx(1.0 - (a & b).sum() / (a | b).sum(), abs=1e-12)
    # soft masks: sum(min) / sum(max)
    views.sil[1] *= 0.5
    got = cues.cue_distances(q, views)["silhouette"]
    ref = 1 - np.minimum(views.sil[1], q.sil[0]).sum() / np.maximum(views.sil[1], q.sil[0]).sum()
    assert got[1] == pytest.approx(ref, abs=1e-6)


def test_chamfer_equals_scipy_distance_transform_reference():
    rng = np.random.default_rng(1)
    views = _fake_cues(rng, 5, S=32)
    views.edges[3] = False                                  # a view without edges
    views.dist = cues._distances(views.edges)
    q = _fake_cues(rng, 1, S=32)
    q.colours = np.zeros((1, 32, 32, 3), np.float32)
    got = cues.cue_distances(q, views)["chamfer"]

    def capped_edt(e):
        if not e.any():
            return np.full(e.shape, cues.TAU)
        return np.minimum(ndimage.distance_transform_edt(~e), cues.TAU)

    dq = capped_edt(q.edges[0])
    for v in range(5):
        dv = capped_edt(views.edges[v])
        a = dv[q.edges[0]].mean()
        b = dq[views.edges[v]].mean() if views.edges[v].any() else cues.TAU
        assert got[v] == pytest.approx((a + b) / (2 * cues.TAU), abs=1e-5), v
    assert got[3] == pytest.approx((cues.TAU + cues.TAU) / (2 * cues.TAU), abs=1e-6)


def test_region_cue_equals_per_label_loop():
    rng = np.random.default_rng(2)
    views = _fake_cues(rng, 3, S=16, n_labels=4)
    q = _fake_cues(rng, 1, S=16)
    q.colours = rng.random((1, 16, 16, 3)).astype(np.float32) * 255
    got = cues.cue_distances(q, views)["region"]
    c = q.colours[0].reshape(-1, 3).astype(np.float64)
    total = ((c - c.mean(0)) ** 2).sum()
    for v in range(3):
        lab = views.labels[v].ravel()
        within = sum(((c[lab == k] - c[lab == k].mean(0)) ** 2).sum() for k in np.unique(lab))
        assert got[v] == pytest.approx(within / total, abs=1e-9)
    # a photo whose colours follow one view's labels exactly: that view explains everything
    q.colours[0] = rng.random((4, 3))[views.labels[1]] * 255
    assert cues.cue_distances(q, views)["region"][1] == pytest.approx(0.0, abs=1e-9)


def _dense_edges(tri, mat, depth, normals):
    """The render-edge rule written densely: every neighbour pair, every test."""
    bg = np.uint32(0xFFFFFFFF)
    fg = tri != bg
    n = np.where(fg[..., None], normals[np.where(fg, tri, 0).astype(np.int64)], 0.0)
    out = np.zeros(tri.shape, bool)
    cos = np.cos(np.radians(cues.CREASE_DEG))
    for axis in (1, 2):
        sl_a = [slice(None)] * 3
        sl_b = [slice(None)] * 3
        sl_a[axis], sl_b[axis] = slice(None, -1), slice(1, None)
        a, b = tuple(sl_a), tuple(sl_b)
        both = fg[a] & fg[b]
        e = (fg[a] != fg[b]) | (mat[a] != mat[b])
        with np.errstate(invalid="ignore"):             # inf - inf off the object
            jump = np.abs(depth[a] - depth[b]) > cues.DEPTH_JUMP
        e |= both & (tri[a] != tri[b]) & jump
        e |= both & (tri[a] != tri[b]) & (np.abs((n[a] * n[b]).sum(-1)) < cos)
        out[a] |= e
        out[b] |= e
    return out


def test_distances_of_a_batch_equal_one_transform_an_image():
    """``_distances`` runs one distance transform over the stacked batch (edge-free rows between
    the images): the same bytes as OpenCV's transform of each image alone, capped at TAU, and
    within float32 rounding of SciPy's exact transform. Edges on the rows next to the seams, an
    image without edges, one all edges, and a batch without any edge."""
    import cv2

    rng = np.random.default_rng(7)
    S = 40
    edges = np.stack([rng.random((S, S)) < p for p in (0.002, 0.01, 0.05, 0.3, 0.0, 1.0, 0.01)])
    edges[1, 0, :] = edges[1, -1, :] = False
    edges[1, 0, 5] = edges[1, -1, 30] = True        # alone at the top and bottom rows
    edges[2, -1, :] = True                          # a whole bottom row next to the seam
    edges[6] = False
    edges[6, 0, 0] = True                           # one pixel in the first row
    got = cues._distances(edges)
    assert got.dtype == np.float32 and got.shape == edges.shape
    for b in range(len(edges)):
        if not edges[b].any():
            ref = np.full((S, S), cues.TAU, np.float32)
        else:
            ref = np.minimum(cv2.distanceTransform((~edges[b]).astype(np.uint8), cv2.DIST_L2,
                                                   cv2.DIST_MASK_PRECISE), cues.TAU)
            exact = np.minimum(ndimage.distance_transform_edt(~edges[b]), cues.TAU)
            np.testing.assert_allclose(got[b], exact, atol=1e-5)
        assert np.array_equal(got[b], ref), b
    assert np.all(got[4] == cues.TAU) and np.all(got[5] == 0.0)
    none = cues._distances(np.zeros((3, S, S), bool))
    assert none.dtype == np.float32 and np.all(none == cues.TAU)


def test_map_edges_equal_dense_reference_and_crop_sampling(rendered):
    mesh, views, images, c = rendered
    normals = face_normals(mesh).astype(np.float32)
    got = cues.map_edges(views.tri_id, views.mat_id, views.depth, normals)
    ref = _dense_edges(views.tri_id, views.mat_id, views.depth, normals)
    assert np.array_equal(got, ref)
    assert got.any() and not got.all()
    # crop sampling: labels are the material ids under each crop pixel's centre
    masks = np.isfinite(views.depth)
    for v, (top, left, side) in enumerate(square_windows(masks, cues.PAD)):
        S = c.labels.shape[1]
        at = np.floor((np.arange(S) + 0.5) * side / S).astype(int)
        r = np.clip(top + at, 0, views.mat_id.shape[1] - 1)
        q = np.clip(left + at, 0, views.mat_id.shape[2] - 1)
        assert np.array_equal(c.labels[v], views.mat_id[v][np.ix_(r, q)])
    # the crop's edges are the rule applied to the sampled maps
    assert c.edges.shape == c.labels.shape and c.edges.any()


def test_a_render_is_nearest_to_itself(rendered):
    """The photo made from render 1 itself (its mask, its image): silhouette 0, HOG 0, and the
    combined score picks view 1."""
    mesh, views, images, c = rendered
    m = np.isfinite(views.depth[1])
    q = cues.query_cues(images[1], m, HogExtractor())
    d = cues.cue_distances(q, c)
    assert d["silhouette"][1] == pytest.approx(0.0, abs=1e-6)
    assert d["hog"][1] == pytest.approx(0.0, abs=1e-6)
    assert d["region"][1] < 0.15              # flat shading: faces of one material differ
    for name in cues.CUES:
        assert int(np.argmin(d[name])) == 1, name
    assert int(np.argmin(cues.combine(d, {"hog": 1, "silhouette": 1, "chamfer": 1}))) == 1
    # asking for some cues gives exactly those, with the same values
    some = cues.cue_distances(q, c, ("hog", "chamfer"))
    assert set(some) == {"hog", "chamfer"}
    for name in some:
        np.testing.assert_array_equal(some[name], d[name])


def test_what_the_photo_does_not_show_changes_no_distance(rendered):
    """A photo of render 1 with its left 40 % not shown (``valid``; e.g. grown past its edge):
    whatever fills the part not shown (the renders' grey, noise, the render itself), every cue
    distance to every view is the same (HOG to rounding, chamfer within 0.02); the photo's edges and the HOG dimensions kept lie
    where it shows; with everything shown the cues are exactly those of a call without
    ``valid``; and the render stays nearest to itself."""
    mesh, views, images, c = rendered
    m = np.isfinite(views.depth[1])
    H, W = m.shape
    cols = np.flatnonzero(m.any(0))
    cut = int(cols[0] + 0.4 * (cols[-1] - cols[0]))
    valid = np.zeros((H, W), bool)
    valid[:, cut:] = True
    rng = np.random.default_rng(0)
    fills = [np.full_like(images[1], RENDER_BACKGROUND),
             rng.integers(0, 256, images[1].shape, dtype=np.uint8), images[1]]
    got = []
    for fill in fills:
        photo = np.where(valid[..., None], images[1], fill)
        q = cues.query_cues(photo, m, HogExtractor(), valid=valid)
        got.append(cues.cue_distances(q, c))
    for other in got[1:]:                   # Canny's reach past SHOWN_MARGIN: chamfer near
        for name in cues.CUES:              # the border may move a little
            if name == "chamfer":
                np.testing.assert_allclose(other[name], got[0][name], atol=0.02)
            elif name == "hog":                 # the kept rows renormalised: float rounding
                np.testing.assert_allclose(other[name], got[0][name], atol=1e-7)
            else:
                np.testing.assert_array_equal(other[name], got[0][name], err_msg=name)
    for name in cues.CUES:
        assert int(np.argmin(got[0][name])) == 1, name
    assert got[0]["hog"][1] == pytest.approx(0.0, abs=1e-6)
    win = square_windows(m[None], cues.PAD)[0]
    shown = crop_window(valid.astype(np.float32), win, cues.SIZE) >= 1.0 - 1e-6
    assert q.shown is not None and not (q.shown[0] & ~shown).any() and q.shown[0].any()
    assert not (q.edges[0] & ~q.shown[0]).any()
    ex = HogExtractor()
    dims = ex.seen_dims(valid, m)
    assert q.hog_dims is not None and np.array_equal(q.hog_dims, dims)
    assert 0 < dims.sum() < dims.size
    whole = cues.query_cues(images[1], m, ex, valid=np.ones((H, W), bool))
    plain = cues.query_cues(images[1], m, ex)
    assert whole.shown is None and whole.hog_dims is None
    for name in ("hog", "edges", "dist", "sil"):
        np.testing.assert_array_equal(getattr(whole, name), getattr(plain, name))


def test_seen_dims_keep_the_blocks_wholly_shown():
    """``HogExtractor.seen_dims`` against a per-block loop over the crop: a block (2 x 2
    cells) is kept when its pixels and one pixel around (the gradients' reach, clamped at the
    crop's edge) are all shown; every dimension of a kept block and none of another."""
    ex = HogExtractor()
    mask = np.zeros((100, 140), bool)
    mask[20:80, 10:130] = True
    for x_cut in (0, 45, 70, 139):
        valid = np.zeros_like(mask)
        valid[:, x_cut:] = True
        dims = ex.seen_dims(valid, mask)
        win = square_windows(mask[None], ex.pad)[0]
        shown = crop_window(valid.astype(np.float32), win, ex.size) >= 1.0 - 1e-6
        nb, cell = ex.n_cells - 1, ex.cell
        want = []
        for by in range(nb):
            for bx in range(nb):
                r = np.clip(np.arange(by * cell - 1, by * cell + 2 * cell + 1), 0, ex.size - 1)
                k = np.clip(np.arange(bx * cell - 1, bx * cell + 2 * cell + 1), 0, ex.size - 1)
                want += [bool(shown[np.ix_(r, k)].all())] * (4 * ex.bins)
        assert dims.tolist() == want, x_cut
    assert ex.seen_dims(np.ones_like(mask), mask).all()


def test_combine_and_offsets(rendered):
    mesh, views, images, c = rendered
    d = {"hog": np.array([1.0, 2.0]), "silhouette": np.array([0.5, 0.0])}
    np.testing.assert_allclose(cues.combine(d, {"hog": 1.0, "silhouette": 2.0}), [2.0, 2.0])
    with pytest.raises(ValueError, match="no cue"):
        cues.combine(d, {"chamfer": 0.0})
    # offsets: box centre from the principal point over the focal length
    K = views.cameras.K
    for v in range(views.n_views):
        ys, xs = np.nonzero(np.isfinite(views.depth[v]))
        cx = (xs.min() + xs.max() + 1) / 2.0
        cy = (ys.min() + ys.max() + 1) / 2.0
        np.testing.assert_allclose(c.offsets[v], [(cx - K[0, 2]) / K[0, 0],
                                                  (cy - K[1, 2]) / K[1, 1]])
        # sides: the box's longer side over the narrower image side; the silhouette: the
        # mask's square window area-resized (crop_window of the float mask)
        side = max(xs.max() - xs.min() + 1, ys.max() - ys.min() + 1)
        assert c.sides[v] == side / min(views.depth.shape[1:])
        mask = np.isfinite(views.depth[v])
        window = square_windows(mask[None], cues.PAD)[0]
        assert np.array_equal(c.sil[v], crop_window(mask.astype(np.float32), window,
                                                     c.sil.shape[1]))


# ----------------------------------------------------------------------------- photo edges

def test_boundary_points_equal_pixel_pair_loop():
    rng = np.random.default_rng(4)
    mat = np.zeros((12, 15), np.uint16)
    mat[3:9, 2:11] = rng.integers(1, 4, (6, 9))
    pts, normal, box = cues.boundary_points(mat)
    ref = set()
    padded = np.pad(mat, 1)
    for y in range(-1, 12):
        for x in range(-1, 15):
            a = padded[y + 1, x + 1]
            if x < 14 and a != padded[y + 1, x + 2] and y >= 0:
                ref.add((x + 1.0, y + 0.5, 0))
            if y < 11 and a != padded[y + 2, x + 1] and x >= 0:
                ref.add((x + 0.5, y + 1.0, 1))
    got = {(float(p[0]), float(p[1]), int(n)) for p, n in zip(pts, normal)}
    assert got == ref and len(pts) == len(ref)
    assert box == (2, 3, 11, 9)
    assert cues.boundary_points(np.zeros((4, 4), np.uint16))[0].shape == (0, 2)


def test_photo_edges_equal_independent_reference():
    """The frame: the box's centre at the frame's centre, its longer side at EDGE_SIDE / (1 +
    2 EDGE_GROW) pixels; the two channels: SciPy's exact distance transform of the Canny edges
    whose Sobel gradient lies within EDGE_SLACK_DEG of the x / y axis."""
    import cv2

    rng = np.random.default_rng(5)
    img = np.full((240, 320, 3), 90, np.uint8)
    cv2.ellipse(img, (150, 120), (90, 40), 20, 0, 360, (220, 40, 40), -1)
    cv2.rectangle(img, (100, 100), (170, 130), (20, 200, 90), -1)
    img = np.clip(img + rng.normal(0, 3, img.shape), 0, 255).astype(np.uint8)
    mask = np.zeros((240, 320), bool)
    mask[70:171, 60:241] = True                       # box (60, 70, 241, 171) ...
    mask[105:171, 60:150] = False                     # ... with a corner cut away
    e = cues.photo_edges(img, mask)
    assert e.box == (60, 70, 241, 171)
    A = e.to_frame
    centre = A[:, :2] @ [150.5, 120.5] + A[:, 2]
    np.testing.assert_allclose(centre, [cues.EDGE_SIDE / 2] * 2)
    assert A[0, 0] * 181 == pytest.approx(cues.EDGE_SIDE / (1 + 2 * cues.EDGE_GROW))
    crop = cv2.warpAffine(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), A, (cues.EDGE_SIDE,) * 2,
                          flags=cv2.INTER_AREA, borderMode=cv2.BORDER_REPLICATE)
    edges = cv2.Canny(crop, *cues.EDGE_CANNY, L2gradient=True) > 0
    gx = ndimage.sobel(crop.astype(np.float64), axis=1, mode="reflect")
    gy = ndimage.sobel(crop.astype(np.float64), axis=0, mode="reflect")
    t = np.tan(np.radians(cues.EDGE_SLACK_DEG))
    for c, near in enumerate((np.abs(gy) <= t * np.abs(gx), np.abs(gx) <= t * np.abs(gy))):
        ref = ndimage.distance_transform_edt(~(edges & near))
        inside = (slice(2, -2), slice(2, -2))            # Sobel borders differ in convention
        np.testing.assert_allclose(e.dist[c][inside], ref[inside], atol=1e-3)
        assert (edges & near).sum() > 20
        # the edges inside the object: the mask in the frame (nearest) eroded by EDGE_INSIDE
        core = cv2.warpAffine(mask.astype(np.uint8), A, (cues.EDGE_SIDE,) * 2,
                              flags=cv2.INTER_NEAREST) > 0
        core = ndimage.binary_erosion(core, np.ones((2 * cues.EDGE_INSIDE + 1,) * 2),
                                      border_value=1)
        want = {(int(x), int(y)) for y, x in np.argwhere((e.dist[c] == 0) & core)}
        assert {(int(x), int(y)) for x, y in e.inside[c]} == want
        assert 0 < len(want) < (e.dist[c] == 0).sum()
    # the frame's colours, centred: the box's centre pixel sits at the frame's centre
    rgb = cv2.warpAffine(img, A, (cues.EDGE_SIDE,) * 2, flags=cv2.INTER_AREA,
                         borderMode=cv2.BORDER_REPLICATE).reshape(-1, 3).astype(np.float64)
    np.testing.assert_allclose(e.colours, rgb - rgb.mean(0), atol=1e-9)
    assert e.spread == pytest.approx(float(((rgb - rgb.mean(0)) ** 2).sum()), rel=1e-12)
    centre = (e.colours + rgb.mean(0)).reshape(cues.EDGE_SIDE, cues.EDGE_SIDE, 3)[80, 80]
    np.testing.assert_allclose(centre, img[120, 150], atol=12)


def test_edge_distance_equals_point_loop():
    rng = np.random.default_rng(6)
    S = cues.EDGE_SIDE
    dist = np.stack([ndimage.distance_transform_edt(rng.random((S, S)) > 0.02)
                     for _ in range(2)]).astype(np.float32)
    A = np.array([[0.8, 0.0, 10.0], [0.0, 0.8, -5.0]])
    e = cues.PhotoEdges(dist=dist, to_frame=A, box=(30, 40, 190, 120),
                        inside=(np.zeros((0, 2), np.int64),) * 2, colours=np.zeros((S * S, 3)),
                        spread=0.0)
    mat = np.zeros((64, 64), np.uint16)
    mat[20:40, 10:50] = 1
    mat[25:30, 15:25] = 2
    pts, normal, box = cues.boundary_points(mat)
    got = cues.edge_distance(e, pts, normal, box)
    best = np.inf
    for dx in range(-cues.EDGE_SHIFT, cues.EDGE_SHIFT + 1):
        for dy in range(-cues.EDGE_SHIFT, cues.EDGE_SHIFT + 1):
            total = 0.0
            for (x, y), n in zip(pts, normal):
                px = 30 + (x - box[0]) * (160 / (box[2] - box[0]))
                py = 40 + (y - box[1]) * (80 / (box[3] - box[1]))
                fx = min(max(int(np.round(0.8 * px + 10.0)) + dx, 0), S - 1)
                fy = min(max(int(np.round(0.8 * py - 5.0)) + dy, 0), S - 1)
                total += min(float(dist[n, fy, fx]), cues.EDGE_TAU)
            best = min(best, total / len(pts) / cues.EDGE_TAU)
    assert got == pytest.approx(best, abs=1e-9)
    assert cues.edge_distance(e, np.zeros((0, 2)), np.zeros(0, int), (0, 0, 1, 1)) == 1.0


def test_edge_recall_equals_point_loop():
    """Each inside edge pixel's distance to the nearest placed boundary point of its channel,
    brute force over the points (Euclidean), capped, averaged; best shift."""
    rng = np.random.default_rng(16)
    S = cues.EDGE_SIDE
    A = np.array([[0.8, 0.0, 10.0], [0.0, 0.8, -5.0]])
    inside = tuple(rng.integers(20, 140, (n, 2)).astype(np.int64) for n in (40, 25))
    e = cues.PhotoEdges(dist=np.zeros((2, S, S), np.float32), to_frame=A,
                        box=(30, 40, 190, 120), inside=inside, colours=np.zeros((S * S, 3)),
                        spread=0.0)
    mat = np.zeros((64, 64), np.uint16)
    mat[20:40, 10:50] = 1
    mat[25:30, 15:25] = 2
    pts, normal, box = cues.boundary_points(mat)
    placed = []
    for x, y in pts:
        px = 30 + (x - box[0]) * (160 / (box[2] - box[0]))
        py = 40 + (y - box[1]) * (80 / (box[3] - box[1]))
        placed.append((min(max(int(np.round(0.8 * px + 10.0)), 0), S - 1),
                       min(max(int(np.round(0.8 * py - 5.0)), 0), S - 1)))
    placed_np = np.array(placed, np.float64)
    best = np.inf
    for dx in range(-cues.EDGE_SHIFT, cues.EDGE_SHIFT + 1):
        for dy in range(-cues.EDGE_SHIFT, cues.EDGE_SHIFT + 1):
            total = 0.0
            for c in range(2):
                own = placed_np[normal == c] + [dx, dy]      # the boundaries shifted
                for x, y in inside[c]:                        # (20-139: no edge clamping)
                    d = np.sqrt(((own - [x, y]) ** 2).sum(1)).min()
                    total += min(d, cues.EDGE_TAU)
            best = min(best, total / 65 / cues.EDGE_TAU)
    got = cues.edge_recall(e, pts, normal, box)
    assert got == pytest.approx(best, abs=1e-6)
    assert 0.05 < got < 0.95
    assert cues.edge_recall(e, np.zeros((0, 2)), np.zeros(0, int), (0, 0, 1, 1)) == 1.0
    none = cues.PhotoEdges(dist=e.dist, to_frame=A, box=e.box, colours=e.colours,
                           spread=0.0, inside=(np.zeros((0, 2), np.int64),) * 2)
    assert cues.edge_recall(none, pts, normal, box) == 0.0


def test_region_residual_equals_per_label_loop():
    """The map's non-zero box lands on the object's box in the frame; the residual is the
    within-region sum of squares (a loop over the ids) over the total."""
    import cv2

    rng = np.random.default_rng(17)
    S = cues.EDGE_SIDE
    A = np.array([[0.8, 0.0, 10.0], [0.0, 0.8, -5.0]])
    colours = rng.random((S * S, 3)) * 255

    def frame(rgb):                           # PhotoEdges keeps the colours centred
        c = rgb - rgb.mean(0)
        return cues.PhotoEdges(dist=np.zeros((2, S, S), np.float32), to_frame=A,
                               box=(30, 40, 170, 120), inside=(np.zeros((0, 2), np.int64),) * 2,
                               colours=c, spread=float((c * c).sum()))

    e = frame(colours)
    mat = np.zeros((64, 64), np.uint16)
    mat[20:40, 10:50] = 1
    mat[25:30, 15:25] = 2
    M = np.array([[0.8 * 3.5, 0.0, 0.8 * (30 - 3.5 * 10) + 10.0],
                  [0.0, 0.8 * 4.0, 0.8 * (40 - 4.0 * 20) - 5.0]])
    lab = cv2.warpAffine(mat.astype(np.float32), M, (S, S), flags=cv2.INTER_NEAREST)
    ys, xs = np.nonzero(lab)                  # frame box of the object: x 34-146, y 27-91
    assert abs(xs.min() - 34) <= 1 and abs(xs.max() + 1 - 146) <= 1
    assert abs(ys.min() - 27) <= 1 and abs(ys.max() + 1 - 91) <= 1
    lab = lab.ravel()
    within = sum(float(((colours[lab == k] - colours[lab == k].mean(0)) ** 2).sum())
                 for k in np.unique(lab))
    total = float(((colours - colours.mean(0)) ** 2).sum())
    assert cues.region_residual(e, mat) == pytest.approx(within / total, rel=1e-9)
    # colours that follow the placed regions leave nothing unexplained
    flat = frame(np.array([[0, 0, 0], [200, 10, 10], [10, 10, 200]],
                          np.float64)[lab.astype(int)])
    assert cues.region_residual(flat, mat) == pytest.approx(0.0, abs=1e-9)
    assert cues.region_residual(frame(np.full((S * S, 3), 7.0)), mat) == 0.0
    assert cues.region_residual(e, np.zeros((8, 8), np.uint16)) == 1.0


def test_a_view_lies_on_the_edges_of_a_photo_of_itself(rendered):
    """A photo made of render 1 placed on clutter, smaller: its own boundaries lie on its
    edges (not all: boundaries between materials of one shade show no edge); those of the
    other views, stretched onto the same box, lie much further."""
    import cv2

    mesh, views, images, _ = rendered
    rng = np.random.default_rng(7)
    photo = rng.integers(0, 256, (300, 400, 3)).astype(np.uint8)
    photo = cv2.GaussianBlur(photo, (0, 0), 6)                  # soft clutter
    small = cv2.resize(images[1], (72, 72), interpolation=cv2.INTER_NEAREST)
    m = cv2.resize(np.isfinite(views.depth[1]).astype(np.uint8), (72, 72),
                   interpolation=cv2.INTER_NEAREST) > 0
    photo[100:172, 150:222][m] = small[m]
    mask = np.zeros(photo.shape[:2], bool)
    mask[100:172, 150:222] = m
    e = cues.photo_edges(photo, mask)
    d = [cues.edge_distance(e, *cues.boundary_points(views.mat_id[v]))
         for v in range(views.n_views)]
    assert d[1] < 0.35
    assert d[1] < min(d[0], d[2]) - 0.2
    # the other way round: the photo's edges inside the object lie on its own boundaries, and
    # its own material regions explain its colours best
    rc = [cues.edge_recall(e, *cues.boundary_points(views.mat_id[v]))
          for v in range(views.n_views)]
    rg = [cues.region_residual(e, views.mat_id[v]) for v in range(views.n_views)]
    assert rc[1] < min(rc[0], rc[2]) - 0.1, rc
    assert rg[1] < min(rg[0], rg[2]) - 0.1, rg
