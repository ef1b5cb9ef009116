"""Colour science (ucad_cl/colorimetry.py) and the photo-like reference renderer (ucad_cl/refphoto.py).

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
