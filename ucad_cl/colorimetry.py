"""Colour spaces and colour difference: sRGB <-> linear RGB <-> CIE XYZ <-> CIELAB, and CIEDE2000.

``delta_e2000(lab1, lab2)`` is the colour difference the fit and its bench report; the
conversions feed it from linear RGB (``linear_to_lab``) or 8-bit sRGB (``srgb8_to_linear``).

Conventions and units:

* Linear RGB: the sRGB primaries (ITU-R BT.709) and white point D65, values in [0, 1] for
  reflectances (larger values pass through: an over-exposed pixel is > 1 before encoding).
* sRGB encoding: the IEC 61966-2-1 piecewise curve (slope 12.92 below 0.0031308 linear /
  0.04045 encoded, else 1.055 x^(1/2.4) - 0.055). 8-bit values are ``round(255 * encoded)``
  after clipping to [0, 1].
* XYZ: Y of the white is 1 (not 100). The matrix is IEC 61966-2-1's, rounded to 4 digits as
  the standard gives it.
* CIELAB: CIE 1976 L*a*b* relative to the D65 white of that matrix (the XYZ of linear (1, 1, 1)),
  L* in [0, 100].
* CIEDE2000: CIE 142-2001 with kL = kC = kH = 1, implemented per G. Sharma, W. Wu and
  E. N. Dalal, "The CIEDE2000 color-difference formula: implementation notes, supplementary
  test data, and mathematical observations", Color Res. Appl. 30(1), 2005 (mean hue and hue
  difference rules of their eqs. 10-14; tests/test_refphoto.py checks their 34 pairs to 1e-4).

Every function takes arrays of any leading shape with the channel (3) last and returns float64.
"""
from __future__ import annotations

import numpy as np

#: linear sRGB (D65) -> CIE XYZ, IEC 61966-2-1
RGB_TO_XYZ = np.array([[0.4124, 0.3576, 0.1805],
                       [0.2126, 0.7152, 0.0722],
                       [0.0193, 0.1192, 0.9505]])
XYZ_TO_RGB = np.linalg.inv(RGB_TO_XYZ)
#: the D65 white of ``RGB_TO_XYZ`` (XYZ of linear white), Y = 1
WHITE_D65 = RGB_TO_XYZ.sum(axis=1)

_LAB_EPS = (6.0 / 29.0) ** 3


def delta_e2000(lab1: np.ndarray, lab2: np.ndarray) -> np.ndarray:
    """CIEDE2000 colour difference of CIELAB colours ``lab1`` and ``lab2`` (..., 3), broadcast;
    returns (...) float64 (kL = kC = kH = 1; Sharma et al. 2005)."""
    a = np.asarray(lab1, np.float64)
    b = np.asarray(lab2, np.float64)
    if a.shape[-1:] != (3,) or b.shape[-1:] != (3,):
        raise ValueError(f"Lab colours need 3 channels last, got {a.shape} and {b.shape}")
    L1, a1, b1 = a[..., 0], a[..., 1], a[..., 2]
    L2, a2, b2 = b[..., 0], b[..., 1], b[..., 2]
    C1 = np.hypot(a1, b1)
    C2 = np.hypot(a2, b2)
    Cbar7 = ((C1 + C2) / 2.0) ** 7
    G = 0.5 * (1.0 - np.sqrt(Cbar7 / (Cbar7 + 25.0 ** 7)))
    a1p = (1.0 + G) * a1
    a2p = (1.0 + G) * a2
    C1p = np.hypot(a1p, b1)
    C2p = np.hypot(a2p, b2)
    # hue angles in degrees [0, 360); 0 where a' = b = 0 (eq. 7)
    h1p = np.where((a1p == 0) & (b1 == 0), 0.0, np.degrees(np.arctan2(b1, a1p)) % 360.0)
    h2p = np.where((a2p == 0) & (b2 == 0), 0.0, np.degrees(np.arctan2(b2, a2p)) % 360.0)
    dLp = L2 - L1
    dCp = C2p - C1p
    prod = C1p * C2p
    dh = h2p - h1p
    dhp = np.where(prod == 0, 0.0,
                   np.where(np.abs(dh) <= 180.0, dh, np.where(dh > 180.0, dh - 360.0, dh + 360.0)))
    dHp = 2.0 * np.sqrt(prod) * np.sin(np.radians(dhp / 2.0))
    Lbp = (L1 + L2) / 2.0
    Cbp = (C1p + C2p) / 2.0
    hsum = h1p + h2p
    hbp = np.where(prod == 0, hsum,
                   np.where(np.abs(h1p - h2p) <= 180.0, hsum / 2.0,
                            np.where(hsum < 360.0, (hsum + 360.0) / 2.0, (hsum - 360.0) / 2.0)))
    T = (1.0 - 0.17 * np.cos(np.radians(hbp - 30.0)) + 0.24 * np.cos(np.radians(2.0 * hbp))
         + 0.32 * np.cos(np.radians(3.0 * hbp + 6.0)) - 0.20 * np.cos(np.radians(4.0 * hbp - 63.0)))
    dtheta = 30.0 * np.exp(-(((hbp - 275.0) / 25.0) ** 2))
    Cbp7 = Cbp ** 7
    RC = 2.0 * np.sqrt(Cbp7 / (Cbp7 + 25.0 ** 7))
    SL = 1.0 + 0.015 * (Lbp - 50.0) ** 2 / np.sqrt(20.0 + (Lbp - 50.0) ** 2)
    SC = 1.0 + 0.045 * Cbp
    SH = 1.0 + 0.015 * Cbp * T
    RT = -np.sin(np.radians(2.0 * dtheta)) * RC
    tL, tC, tH = dLp / SL, dCp / SC, dHp / SH
    return np.sqrt(tL * tL + tC * tC + tH * tH + RT * tC * tH)


def srgb_to_linear(srgb: np.ndarray) -> np.ndarray:
    """Encoded sRGB values in [0, 1] -> linear RGB (IEC 61966-2-1 curve)."""
    s = np.asarray(srgb, np.float64)
    return np.where(s <= 0.04045, s / 12.92, ((s + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """Linear RGB -> encoded sRGB (IEC 61966-2-1 curve); negative inputs give 0, values above 1
    are encoded on the same curve (clip before quantising)."""
    c = np.maximum(np.asarray(linear, np.float64), 0.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1.0 / 2.4) - 0.055)


def srgb8_to_linear(srgb8: np.ndarray) -> np.ndarray:
    """8-bit sRGB (any integer dtype, 0..255) -> linear RGB float64."""
    return srgb_to_linear(np.asarray(srgb8, np.float64) / 255.0)


def linear_to_srgb8(linear: np.ndarray) -> np.ndarray:
    """Linear RGB -> 8-bit sRGB uint8 (clipped to [0, 1] after encoding, rounded half up)."""
    s = np.clip(linear_to_srgb(linear), 0.0, 1.0)
    return np.floor(s * 255.0 + 0.5).astype(np.uint8)


def linear_to_xyz(linear: np.ndarray) -> np.ndarray:
    """Linear sRGB -> CIE XYZ (D65, Y of white = 1)."""
    return np.asarray(linear, np.float64) @ RGB_TO_XYZ.T


def xyz_to_linear(xyz: np.ndarray) -> np.ndarray:
    """CIE XYZ (D65, Y of white = 1) -> linear sRGB (not clipped)."""
    return np.asarray(xyz, np.float64) @ XYZ_TO_RGB.T


def xyz_to_lab(xyz: np.ndarray) -> np.ndarray:
    """CIE XYZ -> CIELAB relative to ``WHITE_D65``."""
    t = np.asarray(xyz, np.float64) / WHITE_D65
    f = np.where(t > _LAB_EPS, np.cbrt(t), t / (3.0 * (6.0 / 29.0) ** 2) + 4.0 / 29.0)
    L = 116.0 * f[..., 1] - 16.0
    a = 500.0 * (f[..., 0] - f[..., 1])
    b = 200.0 * (f[..., 1] - f[..., 2])
    return np.stack([L, a, b], axis=-1)


def lab_to_xyz(lab: np.ndarray) -> np.ndarray:
    """CIELAB (D65 white of ``WHITE_D65``) -> CIE XYZ."""
    lab = np.asarray(lab, np.float64)
    fy = (lab[..., 0] + 16.0) / 116.0
    f = np.stack([fy + lab[..., 1] / 500.0, fy, fy - lab[..., 2] / 200.0], axis=-1)
    t = np.where(f > 6.0 / 29.0, f ** 3, 3.0 * (6.0 / 29.0) ** 2 * (f - 4.0 / 29.0))
    return t * WHITE_D65


def linear_to_lab(linear: np.ndarray) -> np.ndarray:
    """Linear sRGB -> CIELAB (D65)."""
    return xyz_to_lab(linear_to_xyz(linear))


def lab_to_linear(lab: np.ndarray) -> np.ndarray:
    """CIELAB (D65) -> linear sRGB (not clipped)."""
    return xyz_to_linear(lab_to_xyz(lab))


def srgb_hex(linear: np.ndarray) -> str:
    """``#rrggbb`` of one linear RGB colour (8-bit sRGB, as ``linear_to_srgb8``)."""
    r, g, b = (int(v) for v in linear_to_srgb8(np.asarray(linear, np.float64).reshape(3)))
    return f"#{r:02x}{g:02x}{b:02x}"
