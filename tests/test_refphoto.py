"""Colour science (ucad_cl/colorimetry.py) and the photo-like references (ucad_cl/refphoto.py).

References: Sharma, Wu and Dalal (2005)'s 34 CIEDE2000 test pairs; Bruce Lindbloom's sRGB values
of the ColorChecker patches (Lab D65 -> 8-bit sRGB); OpenCV's own RGB -> Lab.
"""
from __future__ import annotations

import numpy as np
import pytest

from ucad_cl import colorimetry as cm

# Sharma, Wu, Dalal, Color Res. Appl. 30(1) 2005, Table 1: L1 a1 b1 L2 a2 b2 dE00
SHARMA = [
    (50.0000, 2.6772, -79.7751, 50.0000, 0.0000, -82.7485, 2.0425),
    (50.0000, 3.1571, -77.2803, 50.0000, 0.0000, -82.7485, 2.8615),
    (50.0000, 2.8361, -74.0200, 50.0000, 0.0000, -82.7485, 3.4412),
    (50.0000, -1.3802, -84.2814, 50.0000, 0.0000, -82.7485, 1.0000),
    (50.0000, -1.1848, -84.8006, 50.0000, 0.0000, -82.7485, 1.0000),
    (50.0000, -0.9009, -85.5211, 50.0000, 0.0000, -82.7485, 1.0000),
    (50.0000, 0.0000, 0.0000, 50.0000, -1.0000, 2.0000, 2.3669),
    (50.0000, -1.0000, 2.0000, 50.0000, 0.0000, 0.0000, 2.3669),
    (50.0000, 2.4900, -0.0010, 50.0000, -2.4900, 0.0009, 7.1792),
    (50.0000, 2.4900, -0.0010, 50.0000, -2.4900, 0.0010, 7.1792),
    (50.0000, 2.4900, -0.0010, 50.0000, -2.4900, 0.0011, 7.2195),
    (50.0000, 2.4900, -0.0010, 50.0000, -2.4900, 0.0012, 7.2195),
    (50.0000, -0.0010, 2.4900, 50.0000, 0.0009, -2.4900, 4.8045),
    (50.0000, -0.0010, 2.4900, 50.0000, 0.0010, -2.4900, 4.8045),
    (50.0000, -0.0010, 2.4900, 50.0000, 0.0011, -2.4900, 4.7461),
    (50.0000, 2.5000, 0.0000, 50.0000, 0.0000, -2.5000, 4.3065),
    (50.0000, 2.5000, 0.0000, 73.0000, 25.0000, -18.0000, 27.1492),
    (50.0000, 2.5000, 0.0000, 61.0000, -5.0000, 29.0000, 22.8977),
    (50.0000, 2.5000, 0.0000, 56.0000, -27.0000, -3.0000, 31.9030),
    (50.0000, 2.5000, 0.0000, 58.0000, 24.0000, 15.0000, 19.4535),
    (50.0000, 2.5000, 0.0000, 50.0000, 3.1736, 0.5854, 1.0000),
    (50.0000, 2.5000, 0.0000, 50.0000, 3.2972, 0.0000, 1.0000),
    (50.0000, 2.5000, 0.0000, 50.0000, 1.8634, 0.5757, 1.0000),
    (50.0000, 2.5000, 0.0000, 50.0000, 3.2592, 0.3350, 1.0000),
    (60.2574, -34.0099, 36.2677, 60.4626, -34.1751, 39.4387, 1.2644),
    (63.0109, -31.0961, -5.8663, 62.8187, -29.7946, -4.0864, 1.2630),
    (61.2901, 3.7196, -5.3901, 61.4292, 2.2480, -4.9620, 1.8731),
    (35.0831, -44.1164, 3.7933, 35.0232, -40.0716, 1.5901, 1.8645),
    (22.7233, 20.0904, -46.6940, 23.0331, 14.9730, -42.5619, 2.0373),
    (36.4612, 47.8580, 18.3852, 36.2715, 50.5065, 21.2231, 1.4146),
    (90.8027, -2.0831, 1.4410, 91.1528, -1.6435, 0.0447, 1.4441),
    (90.9257, -0.5406, -0.9208, 88.6381, -0.8985, -0.7239, 1.5381),
    (6.7747, -0.2908, -2.4247, 5.8714, -0.0985, -2.2286, 0.6377),
    (2.0776, 0.0795, -1.1350, 0.9033, -0.0636, -0.5514, 0.9082),
]

# Bruce Lindbloom's ColorChecker table: Lab (D65) and the 8-bit sRGB it encodes to
LINDBLOOM_SRGB = [
    (36.657, 8.250, 12.270, 106, 81, 67), (64.202, 9.433, 14.710, 182, 149, 130),
    (50.845, 1.004, -19.450, 103, 122, 154), (43.637, -12.265, 20.263, 95, 108, 69),
    (55.237, 10.727, -24.123, 129, 128, 174), (72.420, -22.337, 3.820, 133, 189, 170),
    (57.421, 22.476, 49.944, 194, 121, 48), (40.818, 15.837, -39.953, 79, 91, 162),
    (46.848, 35.976, 9.351, 170, 85, 97), (30.276, 18.962, -21.537, 84, 62, 105),
    (72.107, -22.442, 53.614, 167, 186, 73), (69.671, 8.791, 59.073, 213, 162, 57),
    (30.394, 25.037, -48.957, 54, 62, 149), (56.556, -29.605, 32.966, 101, 148, 76),
    (36.163, 43.930, 18.429, 152, 48, 58), (80.527, -4.273, 70.711, 228, 199, 55),
    (95.095, -0.589, 2.575, 242, 241, 236), (50.884, 0.149, 0.710, 122, 121, 120),
    (22.160, -0.017, 0.017, 53, 53, 53),
]


def test_ciede2000_matches_sharma_test_pairs():
    t = np.array(SHARMA)
    de = cm.delta_e2000(t[:, :3], t[:, 3:6])
    np.testing.assert_allclose(de, t[:, 6], atol=5e-5)
    # symmetric, zero on itself, broadcasts
    np.testing.assert_allclose(cm.delta_e2000(t[:, 3:6], t[:, :3]), t[:, 6], atol=5e-5)
    assert np.all(cm.delta_e2000(t[:, :3], t[:, :3]) == 0)
    assert cm.delta_e2000(t[0, :3], t[:5, 3:6]).shape == (5,)


def test_lab_to_srgb8_matches_lindbloom_colorchecker():
    t = np.array(LINDBLOOM_SRGB, np.float64)
    got = cm.linear_to_srgb8(cm.lab_to_linear(t[:, :3])).astype(int)
    assert np.abs(got - t[:, 3:]).max() <= 1
    back = cm.linear_to_lab(cm.srgb8_to_linear(t[:, 3:]))
    assert np.all(cm.delta_e2000(back, t[:, :3]) < 0.6)


def test_srgb_curve_and_lab_round_trip():
    # IEC 61966-2-1: 8-bit 128 is linear 0.21586; 255 is 1; the knee is continuous
    np.testing.assert_allclose(cm.srgb8_to_linear([128, 255, 0]), [0.2158605, 1.0, 0.0],
                               atol=1e-6)
    np.testing.assert_allclose(cm.linear_to_srgb(0.0031308), 0.04045, atol=1e-6)
    rng = np.random.default_rng(0)
    rgb = rng.random((500, 3))
    np.testing.assert_allclose(cm.srgb_to_linear(cm.linear_to_srgb(rgb)), rgb, atol=1e-12)
    np.testing.assert_allclose(cm.lab_to_linear(cm.linear_to_lab(rgb)), rgb, atol=1e-9)
    np.testing.assert_allclose(cm.linear_to_lab(np.ones(3)), [100.0, 0.0, 0.0], atol=1e-9)
    assert cm.srgb_hex([1.0, 0.0, 0.2158605]) == "#ff0080"
    # 8-bit round trip is exact
    levels = np.arange(256)
    assert np.array_equal(cm.linear_to_srgb8(cm.srgb8_to_linear(levels)), levels)


def test_lab_agrees_with_opencv():
    cv2 = pytest.importorskip("cv2")
    rng = np.random.default_rng(1)
    srgb = rng.random((1, 400, 3)).astype(np.float32)
    ref = cv2.cvtColor(srgb, cv2.COLOR_RGB2Lab)[0].astype(np.float64)   # D65, its own matrix
    ours = cm.linear_to_lab(cm.srgb_to_linear(srgb[0].astype(np.float64)))
    assert np.abs(ours - ref).max() < 0.5
    assert np.median(cm.delta_e2000(ours, ref)) < 0.1


# ----------------------------------------------------------------------------- the renderer

from ucad_cl.artifacts import PART_NAMES, CameraRing, Material, Mesh  # noqa: E402
from ucad_cl.refphoto import (CAR_COLOR_FREQUENCIES, RefLight, draw_car_colors,  # noqa: E402
                              draw_light, photo_camera, render_reference)


def _box_mesh(parts_per_face_pair=None, materials=None) -> Mesh:
    """A box 0.8 x 0.4 x 0.4 (diagonal < 1) centred at the origin, its 6 sides each one
    material (order -x, +x, -y, +y, -z, +z); outward-wound faces."""
    lo, hi = np.array([-0.4, -0.2, -0.2]), np.array([0.4, 0.2, 0.2])
    V = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                  for z in (lo[2], hi[2])])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    F = []
    for a, b, c, d in quads:
        F += [(a, b, c), (a, c, d)]
    mats = materials or [Material(name=f"side{k}") for k in range(6)]
    fm = np.repeat(np.arange(6) % len(mats), 2).astype(np.uint16)
    return Mesh(path="box.obj", sha256="0" * 64, vertices=V.astype(np.float64),
                faces=np.array(F, np.uint32), face_material=fm, materials=mats)


def _uniform_sky(L=0.5, exposure=1.0) -> RefLight:
    c = (L, L, L)
    return RefLight(sun_dir=(0.0, 1.0, 0.0), sun_color=(0.0, 0.0, 0.0), sky_zenith=c,
                    sky_horizon=c, ground=c, exposure=exposure, ao_rays=4)


def _clean(**kw):
    return dict(background="plain", noise=0.0, jpeg_quality=None, **kw)


def _synth(seed):
    from ucad_cl.synth import make_vehicle

    v = make_vehicle(seed)
    parts = dict(v.truth["materials"])
    mesh = v.mesh()
    return mesh, [parts.get(m.name, "other") for m in mesh.materials]


def test_mask_and_parts_match_the_rasterizer_at_the_same_camera():
    from ucad_cl.render import render_views

    mesh, pom = _synth(3)
    rng = np.random.default_rng(7)
    ref = render_reference(mesh, pom, draw_car_colors(rng), azimuth=37.3, elevation=11.9,
                           size=(150, 200), fov=50.0, fill=0.8, offset=(0.6, -0.4),
                           light=draw_light(rng), seed=3)
    ring = CameraRing(K=ref.K, w2c=ref.w2c[None], width=200, height=150,
                      azimuth=np.array([ref.azimuth]), elevation=np.array([ref.elevation]),
                      distance=ref.distance, near=0.01 * ref.distance)
    views = render_views(mesh, ring)
    cover = views.mat_id[0] > 0
    assert cover.sum() > 2000                                   # the vehicle is in the frame
    assert (ref.mask == cover).mean() >= 0.99
    part_of_id = np.array([-1] + [PART_NAMES.index(p) if p in PART_NAMES else
                                  PART_NAMES.index("other") for p in pom])
    both = ref.mask & cover
    assert (ref.part_map[both] == part_of_id[views.mat_id[0][both]]).mean() >= 0.98
    assert np.all(ref.part_map[~ref.mask] == -1)
    # truth colours: the drawn ones, the prior's for the rest; none for 'other' (one per material)
    assert "other" in pom and "other" not in ref.colors
    assert ref.colors["body"] == tuple(draw_car_colors(np.random.default_rng(7))["body"])
    assert ref.colors["chrome"] == (0.549, 0.556, 0.554)
    # off-centre: the vehicle's centre does not project to the image centre
    c = ref.K @ (ref.w2c[:3, 3])
    assert abs(c[0] / c[2] - 100) > 10
    # the camera centre is at the reported azimuth/elevation/distance (the pose convention)
    from ucad_cl.cameras import camera_position
    centre = -ref.w2c[:3, :3].T @ ref.w2c[:3, 3]
    np.testing.assert_allclose(centre, camera_position(37.3, 11.9, ref.distance), atol=1e-9)
    x0, y0, x1, y1 = ref.box
    rows, cols = np.flatnonzero(cover.any(1)), np.flatnonzero(cover.any(0))
    assert abs(x0 - cols[0]) <= 1 and abs(x1 - cols[-1] - 1) <= 1
    assert abs(y0 - rows[0]) <= 1 and abs(y1 - rows[-1] - 1) <= 1


def test_white_furnace_every_opaque_part_returns_the_sky():
    # albedo 1 everywhere under a uniform sky, no sun: every material model returns L
    # (energy conservation of the diffuse + Schlick + clear coat layering)
    from ucad_cl.colorimetry import linear_to_srgb8

    box = _box_mesh()
    pom = ["body", "rim", "interior", "plate", "wheel", "chrome"]
    white = {p: (1.0, 1.0, 1.0) for p in pom}
    for az, el in ((20.0, 25.0), (200.0, -10.0)):
        ref = render_reference(box, pom, white, azimuth=az, elevation=el, size=(90, 120),
                               light=_uniform_sky(0.5), fill=0.9, **_clean())
        inner = _eroded(ref.mask)
        want = linear_to_srgb8(np.array([0.5, 0.5, 0.5]))
        assert inner.sum() > 500
        assert np.abs(ref.image[inner].astype(int) - want.astype(int)).max() <= 1


def _eroded(mask):
    m = mask.copy()
    for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        m &= np.roll(mask, (di, dj), axis=(0, 1))
    return m


@pytest.mark.parametrize("part", ["interior", "body"])
def test_flat_front_facing_panel_has_its_known_colour(part):
    # the box's +x side seen head-on (azimuth 0, elevation 0) under a uniform sky of radiance
    # L, no sun: the documented layering at normal incidence (n.v = 1 at the image centre)
    from ucad_cl.colorimetry import linear_to_srgb8

    box = _box_mesh()
    c = np.array([0.6, 0.1, 0.05])
    pom = [part] * 6
    L, ex = 0.6, 1.2
    ref = render_reference(box, pom, {part: tuple(c)}, azimuth=0.0, elevation=0.0,
                           size=(61, 81), light=_uniform_sky(L, ex), **_clean())
    if part == "interior":                              # metallic 0, no coat
        want = L * (0.96 * c + 0.04)
    else:               # metallic 0.5 under a clear coat: the base's dielectric half reflects
        base = 0.5 * c * L + 0.5 * c * L                # nothing (resin, not air), its metal c
        want = 0.96 * base + 0.04 * L
    centre = ref.image[28:33, 38:43].reshape(-1, 3).astype(int)
    assert np.abs(centre - linear_to_srgb8(ex * want).astype(int)).max() <= 1
    assert ref.colors[part] == tuple(c)
    np.testing.assert_allclose(ref.material_colors, np.tile(c, (6, 1)))


def test_sun_and_shadow_change_the_image_and_the_ground_shadow_falls_on_the_background():
    box = _box_mesh()
    pom = ["interior"] * 6
    sky = _uniform_sky(0.3)
    sun = RefLight(sun_dir=(-0.5, 0.6, 0.5), sun_color=(0.6, 0.6, 0.6), sky_zenith=(0.3,) * 3,
                   sky_horizon=(0.3,) * 3, ground=(0.3,) * 3, exposure=1.0, ao_rays=0)
    a = render_reference(box, pom, {}, azimuth=30, elevation=20, size=(90, 120), light=sky,
                         **_clean())
    b = render_reference(box, pom, {}, azimuth=30, elevation=20, size=(90, 120), light=sun,
                         **_clean())
    top = b.mask & (b.image.astype(int).sum(-1) > a.image.astype(int).sum(-1) + 30)
    assert top.sum() > 50                               # the sunlit top is brighter
    bg_dark = ~b.mask & (b.image[..., 0] < a.image[..., 0] - 20)
    assert bg_dark.sum() > 50                           # the box's shadow on the ground


def test_same_seed_same_bytes_other_seed_other_photo():
    mesh, pom = _synth(4)
    kw = dict(azimuth=123.4, elevation=17.0, size=(96, 128), fill=0.9)
    r1 = render_reference(mesh, pom, {"body": (0.4, 0.05, 0.03)}, seed=11, **kw)
    r2 = render_reference(mesh, pom, {"body": (0.4, 0.05, 0.03)}, seed=11, **kw)
    r3 = render_reference(mesh, pom, {"body": (0.4, 0.05, 0.03)}, seed=12, **kw)
    assert r1.image.tobytes() == r2.image.tobytes()
    assert np.array_equal(r1.part_map, r2.part_map) and np.array_equal(r1.mask, r3.mask)
    assert r1.image.tobytes() != r3.image.tobytes()
    assert r1.image.dtype == np.uint8 and r1.image.shape == (96, 128, 3)
    assert r1.part_map.dtype == np.int16


def test_car_colours_follow_the_published_frequencies():
    from ucad_cl.colorimetry import linear_to_lab

    rng = np.random.default_rng(0)
    n = 3000
    bodies = np.array([draw_car_colors(rng)["body"] for _ in range(n)])
    lab = linear_to_lab(bodies)
    chroma = np.hypot(lab[:, 1], lab[:, 2])
    white = (lab[:, 0] > 85) & (chroma < 6)
    black = (lab[:, 0] < 22) & (chroma < 6)
    assert abs(white.mean() - CAR_COLOR_FREQUENCIES["white"]) < 0.03
    assert abs(black.mean() - CAR_COLOR_FREQUENCIES["black"]) < 0.03
    red = (lab[:, 1] > 35) & (lab[:, 2] > 15)
    assert abs(red.mean() - CAR_COLOR_FREQUENCIES["red"]) < 0.02
    assert bodies.min() >= 0 and bodies.max() <= 1
    light = draw_light(rng)
    assert light.sun_dir[1] > 0 and light.exposure > 0


def test_photo_camera_centres_the_vehicle_without_offset():
    K, w2c, d = photo_camera(75.0, 20.0, 200, 100, fov=40.0, fill=0.5)
    c = K @ w2c[:3, 3]
    np.testing.assert_allclose(c[:2] / c[2], [100.0, 50.0], atol=1e-9)
    assert abs(np.degrees(np.arcsin(0.5 / d)) - 0.5 * 20.0) < 1e-9


def test_bad_arguments_name_the_problem():
    box = _box_mesh()
    with pytest.raises(ValueError, match="box.obj: part_of_material has 2 entries"):
        render_reference(box, ["body", "rim"], {}, azimuth=0, elevation=0)
    with pytest.raises(ValueError, match="unknown part 'roof'"):
        render_reference(box, ["body"] * 6, {"roof": (1, 0, 0)}, azimuth=0, elevation=0)
    with pytest.raises(ValueError, match="linear values in"):
        render_reference(box, ["body"] * 6, {"body": (2, 0, 0)}, azimuth=0, elevation=0)
    with pytest.raises(ValueError, match="background="):
        render_reference(box, ["body"] * 6, {}, azimuth=0, elevation=0, background="x")


def test_white_balance_makes_a_grey_surface_facing_up_neutral():
    # a blue sky, no sun: the camera's balance makes the grey top of the box neutral (within
    # the sky's 4 % specular reflection); without the gains it would be clearly blue
    from ucad_cl.refphoto import white_balance

    box = _box_mesh()
    blue = RefLight(sun_dir=(0.0, 1.0, 0.0), sun_color=(0.0, 0.0, 0.0),
                    sky_zenith=(0.18, 0.27, 0.45), sky_horizon=(0.3, 0.34, 0.4),
                    ground=(0.1, 0.1, 0.1), exposure=2.0, ao_rays=0)
    g = white_balance(blue)
    assert g[0] > 1.2 > 1.0 > g[2]
    ref = render_reference(box, ["wheel"] * 6, {"wheel": (0.5, 0.5, 0.5)}, azimuth=10.0,
                           elevation=70.0, size=(80, 80), fill=0.5, light=blue, **_clean())
    top = ref.image[ref.part_map >= 0].astype(int)
    centre = ref.image[38:42, 38:42].reshape(-1, 3).astype(int)
    assert np.abs(centre[:, 0] - centre[:, 2]).max() <= 3
    assert len(top) > 100


def test_antialiased_image_agrees_with_the_centre_sample_truth():
    # 2 x 2 samples per pixel: inside the mask (away from its edge) every pixel is the vehicle,
    # outside it the plain background (sRGB 128) exactly, along the edge a mix
    box = _box_mesh()
    ref = render_reference(box, ["interior"] * 6, {"interior": (0.9, 0.05, 0.05)},
                           azimuth=25.0, elevation=20.0, size=(70, 90), fill=0.7,
                           offset=(0.5, 0.3), light=_uniform_sky(0.5), **_clean())
    inner = _eroded(ref.mask)
    outer = _eroded(~ref.mask)
    assert inner.sum() > 300 and outer.sum() > 1000
    assert np.all(ref.image[outer] == 128)
    red = ref.image[..., 0].astype(int) > ref.image[..., 1].astype(int) + 60
    assert red[inner].mean() > 0.9                  # the red box (grazing faces reflect the sky)
    assert not red[outer].any()
    edge = ~inner & ~outer
    r = ref.image[..., 0]
    mixed = edge & (r > 133) & (r < np.percentile(r[inner], 10) - 5)
    assert mixed.sum() > 20                         # antialiased: part box, part background


def test_skyline_shows_in_sharp_reflections_only():
    # buildings on the horizon: a chrome box (roughness 0.05) seen level mirrors them, a rough
    # interior-trim box (roughness 0.75: fully blurred) does not change at all
    from dataclasses import replace

    box = _box_mesh()
    sky = replace(_uniform_sky(0.5), ao_rays=0)
    city = replace(sky, skyline=tuple((20.0, 0.1, 0.1, 0.1) for _ in range(12)))
    kw = dict(azimuth=30.0, elevation=3.0, size=(60, 80), fill=0.8, **_clean())
    for part, changes in (("chrome", True), ("interior", False)):
        a = render_reference(box, [part] * 6, {}, light=sky, **kw)
        b = render_reference(box, [part] * 6, {}, light=city, **kw)
        diff = np.abs(a.image.astype(int) - b.image.astype(int)).max(-1)
        assert not diff[_eroded(~a.mask)].any()             # the background is not the sky
        assert (diff[a.mask] > 20).mean() > 0.2 if changes else not diff.any()
    light = draw_light(np.random.default_rng(5), skyline=True)
    plain = draw_light(np.random.default_rng(5))
    assert len(light.skyline) == 24 and replace(light, skyline=()) == plain
