"""The object in a reference photo: masks, boxes and their errors, GrabCut against the rendered
truth, compositing, centring on the optical axis against a render from the turned camera."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from ucad_cl import foreground as fg
from ucad_cl.artifacts import CameraRing
from ucad_cl.cameras import camera_position, make_ring
from ucad_cl.render import render_views
from ucad_cl.shade import shade_views

synth = pytest.importorskip("ucad_cl.synth")


@pytest.fixture(scope="module")
def car():
    return synth.make_vehicle(11, "sedan").mesh()


def _stripes(H, W):
    yy, xx = np.mgrid[0:H, 0:W]
    on = ((xx + 2 * yy) // 9) % 2 == 1
    img = np.empty((H, W, 3), np.uint8)
    img[on] = (30, 160, 60)
    img[~on] = (200, 60, 170)
    return img


def _sedan_over_stripes(car, size, grow):
    """(true mask, photo, box): the sedan at azimuth 35, elevation 12 over stripes, ``size``
    (W, H); the box is the mask's grown by ``grow`` (left, top, right, bottom) pixels."""
    views = render_views(car, make_ring(azimuths=[35.0], elevations=[12.0], size=size))
    truth = np.isfinite(views.depth[0])
    img = shade_views(car, views, background=_stripes(size[1], size[0]))[0]
    ys, xs = np.nonzero(truth)
    return truth, img, (xs.min() - grow[0], ys.min() - grow[1], xs.max() + grow[2],
                        ys.max() + grow[3])


def test_mask_and_box_errors_name_the_problem():
    img = np.zeros((40, 60, 3), np.uint8)
    with pytest.raises(ValueError, match="mask is empty"):
        fg.object_mask(img, mask=np.zeros((40, 60), bool))
    tiny = np.zeros((40, 60), bool)
    tiny[3:5, 3:6] = True                                     # 6 pixels
    with pytest.raises(ValueError, match="6 pixel.*fewer than 8"):
        fg.object_mask(img, mask=tiny)
    with pytest.raises(ValueError, match="is empty inside the 60x40 image"):
        fg.object_mask(img, box=(70, 0, 90, 10))
    with pytest.raises(ValueError, match="is empty inside"):
        fg.object_mask(img, box=(10, 10, 10, 30))             # zero width
    with pytest.raises(ValueError, match="too small"):
        fg.object_mask(img, box=(10, 10, 11, 30))             # one pixel wide
    with pytest.raises(ValueError, match="4 finite numbers"):
        fg.object_mask(img, box=(0, 0, np.nan, 5))
    with pytest.raises(ValueError, match="4 numbers"):
        fg.object_mask(img, box="abc")
    with pytest.raises(ValueError, match="exactly one of box"):
        fg.object_mask(img)
    with pytest.raises(ValueError, match="exactly one of box"):
        fg.object_mask(img, box=(0, 0, 5, 5), mask=np.ones((40, 60), bool))
    with pytest.raises(ValueError, match="uint8 RGB"):
        fg.object_mask(img.astype(float), box=(0, 0, 5, 5))
    with pytest.raises(ValueError, match="differs from the image"):
        fg.object_mask(img, mask=np.ones((10, 10), bool))


def test_given_mask_and_plain_box():
    img = np.zeros((40, 60, 3), np.uint8)
    m = np.zeros((40, 60), bool)
    m[0:9, 50:60] = True                                      # touches two borders
    o = fg.object_mask(img, mask=m)
    assert o.source == "mask" and o.kept == 1.0 and o.box == (50, 0, 60, 9)
    assert o.mask is m or np.array_equal(o.mask, m)
    b = fg.object_mask(img, box=(-5.4, 2.6, 20.2, 70), grabcut=False)
    assert b.source == "box" and b.box == (0, 3, 20, 40) and b.mask.sum() == 20 * 37


def test_grabcut_finds_the_vehicle_in_the_box(car, runtime):
    """A sedan over stripes of other colours: GrabCut's mask against the rendered truth."""
    truth, img, box = _sedan_over_stripes(car, (200, 150), (3, 2, 4, 3))
    o = fg.object_mask(img, box=box)
    assert o.source == "grabcut"
    iou = (o.mask & truth).sum() / (o.mask | truth).sum()
    assert iou > 0.85, iou
    x0, y0, x1, y1 = o.box
    assert o.kept == pytest.approx(o.mask[y0:y1, x0:x1].mean())
    # deterministic, also with one OpenCV thread
    again = fg.object_mask(img, box=box)
    n = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        single = fg.object_mask(img, box=box)
    finally:
        cv2.setNumThreads(n)
    assert np.array_equal(o.mask, again.mask) and np.array_equal(o.mask, single.mask)
    # seeded by the true silhouette, GrabCut keeps it (refinement against a render)
    ref = fg.refine_with_silhouette(img, truth)
    assert (ref & truth).sum() / (ref | truth).sum() > 0.9


def _guided_reference(guide, src, r, eps):
    """The guided filter (He et al. 2010, eq. 7-8) in float64 with explicit window means over
    the reflected image (OpenCV's BORDER_REFLECT: ...cba|abc...)."""
    g = guide.astype(np.float64).mean(axis=2) / 255.0
    p = src.astype(np.float64)

    def mean(x):
        xp = np.pad(x, r, mode="symmetric")
        H, W = x.shape
        return np.array([[xp[i:i + 2 * r + 1, j:j + 2 * r + 1].mean() for j in range(W)]
                         for i in range(H)])

    mg, mp = mean(g), mean(p)
    a = (mean(g * p) - mg * mp) / (mean(g * g) - mg * mg + eps)
    b = mp - a * mg
    return mean(a) * g + mean(b)


def test_guided_filter_against_a_reference():
    rng = np.random.default_rng(3)
    guide = rng.integers(0, 256, (23, 31, 3), dtype=np.uint8)
    guide[:, 15:] //= 4                                       # a strong vertical edge
    src = (rng.uniform(size=(23, 31)) > 0.5).astype(np.float32)
    for r, eps in ((1, 1e-3), (3, 1e-2), (5, 1e-4)):
        got = fg.guided_filter(guide, src, r, eps)
        assert got.dtype == np.float32 and got.shape == src.shape
        np.testing.assert_allclose(got, _guided_reference(guide, src, r, eps), atol=2e-4)


def test_grabcut_mask_follows_the_photos_edges_at_full_size(car, runtime):
    """GrabCut runs at GRABCUT_SIDE px; on a photo several times larger, with ``follow_edges``
    its mask is scaled back along the photo's own edges (``EDGE_RADIUS``): nearer the rendered
    truth than the nearest-neighbour upsampling, whose boundary is quantised to the reduction
    step; and the same seeded by a silhouette (the fit's refinement)."""
    truth, img, box = _sedan_over_stripes(car, (640, 480), (6, 5, 7, 6))

    def iou(m):
        return (m & truth).sum() / (m | truth).sum()

    edge_aware = fg.object_mask(img, box=box, follow_edges=True).mask
    nearest = fg.object_mask(img, box=box).mask
    assert iou(edge_aware) > iou(nearest) and iou(edge_aware) > 0.95, (iou(edge_aware),
                                                                       iou(nearest))
    seeded = fg.refine_with_silhouette(img, truth, core=0.04, follow_edges=True)
    assert iou(seeded) > iou(fg.refine_with_silhouette(img, truth, core=0.04))


def test_grabcut_that_keeps_too_little_falls_back_to_the_box():
    """A flat image has no object: whatever GrabCut answers, the result is a usable mask."""
    img = np.full((60, 80, 3), 90, np.uint8)
    o = fg.object_mask(img, box=(20, 10, 60, 50))
    assert o.source in ("grabcut", "box")
    if o.kept < fg.MIN_KEPT:
        assert o.source == "box" and o.mask.sum() == 40 * 40
    assert o.mask.any()


def test_composite_replaces_the_background():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (20, 30, 3), dtype=np.uint8)
    m = rng.random((20, 30)) > 0.5
    out = fg.composite(img, m)
    ref = np.where(m[..., None], img, np.array(fg.RENDER_BACKGROUND, np.uint8))
    assert np.array_equal(out, ref) and out.dtype == np.uint8


def _level_camera(az, el, dist, fov, W, H, heading) -> CameraRing:
    """An upright, level camera (no tilt) at (az, el, dist) whose heading is ``heading`` radians
    away from the vehicle's centre; heading=None: the look-at camera of the renders."""
    f = 0.5 * min(W, H) / np.tan(np.radians(fov) / 2)
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    pos = camera_position(az, el, dist)
    to = -pos / np.linalg.norm(pos)
    if heading is None:
        fwd = to
    else:
        h = np.arctan2(to[2], to[0]) + heading
        fwd = np.array([np.cos(h), 0.0, np.sin(h)])
    right = np.cross(fwd, [0, 1.0, 0])
    right /= np.linalg.norm(right)
    R = np.stack([right, np.cross(fwd, right), fwd])
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, -R @ pos
    return CameraRing(K=K, w2c=w2c[None], width=W, height=H, azimuth=np.array([az]),
                      elevation=np.array([el]), distance=dist, near=0.01 * dist)


def test_centre_on_axis_undoes_a_turned_camera(car, runtime):
    """A vehicle seen near the image corner by a level camera (the vehicle below the horizon and
    to the side), centred with the true field of view, has the outline the look-at camera of the
    renders sees (compared in the crop frame)."""
    from ucad_cl.features import crop_square

    W, H, fov, dist = 320, 240, 50.0, 3.0
    turned = render_views(car, _level_camera(60.0, 14.0, dist, fov, W, H, 0.3))
    straight = render_views(car, _level_camera(60.0, 14.0, dist, fov, W, H, None))
    m_turned = np.isfinite(turned.depth[0])
    m_straight = np.isfinite(straight.depth[0])
    c = fg.centre_on_axis(np.zeros((H, W, 3), np.uint8), m_turned, fov)
    # the turn found is the one applied (box centre vs projected centre: within a few pixels)
    assert c.R.shape == (3, 3) and np.allclose(c.R @ c.R.T, np.eye(3), atol=1e-12)
    a = crop_square(np.zeros((1,) + c.mask.shape + (3,), np.uint8), c.mask[None], 64)[1][0]
    b = crop_square(np.zeros((1, H, W, 3), np.uint8), m_straight[None], 64)[1][0]
    c0 = crop_square(np.zeros((1, H, W, 3), np.uint8), m_turned[None], 64)[1][0]

    def iou(x, y):
        return np.minimum(x, y).sum() / np.maximum(x, y).sum()

    assert iou(a, b) > 0.95, iou(a, b)
    assert iou(a, b) > iou(c0, b) + 0.02                      # the turn mattered


def test_axis_turn_puts_the_point_on_the_axis():
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    for pt in ((10.0, 20.0), (300.0, 200.0), (160.0, 120.0)):
        R = fg.axis_turn(K, pt)
        ray = np.linalg.solve(K, [pt[0], pt[1], 1.0])
        r = R @ ray
        assert abs(r[0]) < 1e-12 and abs(r[1]) < 1e-12 and r[2] > 0
        assert np.allclose(R @ R.T, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
        assert abs(R[0, 1]) < 1e-12            # yaw, then pitch: the new x axis stays level


def test_photo_window_only_for_large_photos_and_its_maps():
    """PhotoWindow: none for a photo of at most ANALYSIS_PIXELS pixels whose box is at most
    ANALYSIS_SIDE long (analysed whole: the same answers as before); else the box grown by
    ANALYSIS_GROW of its side, clipped, scaled so the box is ANALYSIS_SIDE long. The maps agree
    with the pixels cv2.resize gives (a marked pixel lands where x' = s (x - x0) says), the box
    and the whole photo's camera map by the same affine, and a bad box or mask gives none (so
    object_mask refuses it with its own message)."""
    assert fg.PhotoWindow.around((360, 480), (100, 80, 400, 300), None) is None
    assert fg.PhotoWindow.around((1080, 1920), (100, 80, 400, 300), None) is not None  # pixels
    H, W = 3000, 4000
    box = (1400.4, 800.2, 3200.0, 2000.0)
    w = fg.PhotoWindow.around((H, W), box, None)
    side = 3200 - 1400
    assert w.scale == pytest.approx(fg.ANALYSIS_SIDE / side)
    g = fg.ANALYSIS_GROW * side
    assert (w.x0, w.y0, w.x1, w.y1) == (int(np.floor(1400 - g)), int(np.floor(800 - g)),
                                        int(np.ceil(3200 + g)), int(np.ceil(2000 + g)))
    img = np.zeros((H, W, 3), np.uint8)
    img[1500:1520, 2000:2020] = 255                     # a 20 px square, centre (2010, 1510)
    cut, b, m = w.cut(img, box, None)
    assert m is None and cut.shape[:2] == (round((w.y1 - w.y0) * w.scale),
                                            round((w.x1 - w.x0) * w.scale))
    ys, xs = np.nonzero(cut[..., 0] > 127)
    centre = np.array([xs.mean() + 0.5, ys.mean() + 0.5])      # pixel edges at integers
    assert np.abs(centre - w.scale * (np.array([2010.0, 1510.0]) - (w.x0, w.y0))).max() < 0.6
    assert b == pytest.approx((w.scale * (1400 - w.x0), w.scale * (800 - w.y0),
                               w.scale * (3200 - w.x0), w.scale * (2000 - w.y0)))
    f = 0.5 * H / np.tan(np.radians(45.0) / 2.0)
    K = np.array([[f, 0.0, W / 2.0], [0.0, f, H / 2.0], [0.0, 0.0, 1.0]])
    Kw = w.intrinsics((H, W), 45.0)
    assert Kw[0, 0] == pytest.approx(w.scale * f) and Kw[0, 2] == pytest.approx(
        w.scale * (W / 2.0 - w.x0))
    assert np.allclose(w.photo_K(Kw), K)
    mask = np.zeros((H, W), bool)
    mask[1000:1900, 1500:3100] = True
    wm = fg.PhotoWindow.around((H, W), None, mask)
    _, b2, m2 = wm.cut(img, None, mask)
    assert b2 is None and m2.sum() == pytest.approx(mask.sum() * wm.scale ** 2, rel=0.01)
    shown = np.zeros((H, W), bool)                            # another mask, cut alone
    shown[:, 1700:] = True
    cut_alone = wm.cut_mask(shown, m2.shape)
    assert np.array_equal(cut_alone, wm.cut(img, None, shown)[2])
    assert cut_alone.sum() == pytest.approx(
        shown[wm.y0:wm.y1, wm.x0:wm.x1].sum() * wm.scale ** 2, rel=0.01)
    obj = fg.ObjectMask(mask=m2, source="mask", box=fg.mask_box(m2))
    back = wm.photo_object(obj, (H, W))
    assert back.mask.shape == (H, W) and (back.mask ^ mask).sum() < 0.01 * mask.sum()
    for bad in ((5000, 10, 5100, 20), (1, 2, 3)):            # outside the photo; malformed
        assert fg.PhotoWindow.around((H, W), bad, None) is None
    assert fg.PhotoWindow.around((H, W), None, np.zeros((H, W), bool)) is None
    assert fg.PhotoWindow.around((H, W), None, np.ones((10, 10), bool)) is None


def test_past_the_edge_grows_the_photo_on_the_sides_the_box_touches():
    """The hypotheses of a vehicle cut by the photo's edge: the photo grown past each side its
    box touches by the share x the mask's visible extent, the renders' background there, the
    photo unchanged inside, one mask pixel at the new edge; none for a box inside the photo."""
    from ucad_cl.foreground import PAST_EDGE, RENDER_BACKGROUND, ObjectMask, past_the_edge

    rng = np.random.default_rng(0)
    photo = rng.integers(0, 255, (60, 80, 3), np.uint8)
    mask = np.zeros((60, 80), bool)
    mask[20:41, 0:30] = True                            # 30 wide, 21 high, at the left edge
    seen = ObjectMask(mask=mask, source="grabcut", box=(0, 18, 32, 44))
    hyps = past_the_edge(photo, seen)
    assert len(hyps) == len(PAST_EDGE)
    for e, hyp in zip(PAST_EDGE, hyps):
        wider, past, at, was = hyp
        g = int(round(e * 30))
        assert at == (g, 0)
        assert wider.shape == (60, 80 + g, 3)
        assert np.array_equal(wider[:, g:], photo)
        assert (wider[:, :g] == np.array(RENDER_BACKGROUND, np.uint8)).all()
        assert np.array_equal(past.mask[:, g:], mask) and past.source == "mask"
        assert np.argwhere(past.mask[:, :g]).tolist() == [[20, 0]]
        assert past.box == (0, 20, g + 30, 41)
        assert was is seen and hyp.margins() == (g, 0, 0, 0)
        shown = np.zeros(wider.shape[:2], bool)
        shown[:, g:] = True
        assert np.array_equal(hyp.shown(), shown)
    inside = ObjectMask(mask=mask, source="grabcut", box=(3, 18, 32, 44))
    assert past_the_edge(photo, inside) == []
    both = past_the_edge(photo, ObjectMask(mask=mask, source="mask", box=(0, 0, 80, 60)))
    g, h = int(round(PAST_EDGE[0] * 30)), int(round(PAST_EDGE[0] * 21))
    assert both[0][0].shape == (60 + 2 * h, 80 + 2 * g, 3) and both[0][2] == (g, h)
    assert both[0].margins() == (g, h, g, h)
    dot = np.zeros((60, 80), bool)
    dot[30, 0] = True                                   # one pixel: nothing to grow by
    assert past_the_edge(photo, ObjectMask(mask=dot, source="mask", box=(0, 30, 1, 31))) == []
