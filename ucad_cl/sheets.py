"""PNG contact sheets people can look at: views coloured by material id (or by part).

Colours are fixed per id: id 0 (background) is black; id k > 0 gets the hue ``k * 0.618...``
(golden-ratio steps) at full saturation, alternating value, so neighbouring ids differ strongly and
the same material has the same colour in every view and every run.
"""
from __future__ import annotations

import colorsys
from pathlib import Path
from typing import Sequence

import numpy as np

from .artifacts import PART_NAMES

GOLDEN = 0.6180339887498949


def id_palette(n: int) -> np.ndarray:
    """(n, 3) uint8 RGB colours for ids 0..n-1 (0 = black)."""
    pal = np.zeros((max(n, 1), 3), np.uint8)
    for k in range(1, n):
        h = (k * GOLDEN) % 1.0
        v = 1.0 if k % 2 else 0.7
        pal[k] = np.round(np.array(colorsys.hsv_to_rgb(h, 0.85 if k % 3 else 0.55, v)) * 255)
    return pal


def colorize(ids: np.ndarray, n_ids: int | None = None) -> np.ndarray:
    """(…, H, W) integer ids -> (…, H, W, 3) uint8 RGB with :func:`id_palette`."""
    ids = np.asarray(ids)
    n = int(n_ids if n_ids is not None else (ids.max() + 1 if ids.size else 1))
    return id_palette(max(n, int(ids.max()) + 1 if ids.size else 1))[ids]


def contact_sheet(images: np.ndarray, labels: Sequence[str] | None = None, cols: int | None = None,
                  max_width: int = 2400) -> np.ndarray:
    """Tile (V, H, W, 3) RGB images into one RGB image, with a small label under each tile."""
    import cv2

    V, H, W = images.shape[:3]
    cols = cols or int(np.ceil(np.sqrt(V * H / W)))
    cols = max(1, min(cols, V))
    scale = min(1.0, max_width / (cols * W))
    th, tw = max(1, int(H * scale)), max(1, int(W * scale))
    label_h = 14 if labels is not None else 0
    rows = int(np.ceil(V / cols))
    sheet = np.full((rows * (th + label_h), cols * tw, 3), 32, np.uint8)
    for v in range(V):
        r, c = divmod(v, cols)
        tile = images[v] if scale == 1.0 else cv2.resize(np.ascontiguousarray(images[v]),
                                                         (tw, th), interpolation=cv2.INTER_NEAREST)
        y0 = r * (th + label_h)
        sheet[y0:y0 + th, c * tw:(c + 1) * tw] = tile
        if labels is not None:
            put_label(sheet, str(labels[v]), (c * tw + 2, y0 + th + 11))
    return sheet


DEGREE = "\N{DEGREE SIGN}"


def put_label(img: np.ndarray, text: str, org: tuple[int, int], scale: float = 0.35,
              color=(230, 230, 230)) -> None:
    """Draw ``text`` at ``org`` (bottom-left, pixels) with OpenCV's Hershey font; each degree
    sign, which that font lacks (it would draw '?'), is drawn as a small ring raised to the
    top of the digits."""
    import cv2

    font = cv2.FONT_HERSHEY_SIMPLEX
    x, y = org
    (_, digit_h), _ = cv2.getTextSize("0", font, scale, 1)
    r = max(1, int(round(digit_h * 0.22)))
    for k, piece in enumerate(text.split(DEGREE)):
        if k:
            cv2.circle(img, (x + r + 1, y - digit_h + r), r, color, 1, cv2.LINE_AA)
            x += 2 * r + 3
        if piece:
            cv2.putText(img, piece, (x, y), font, scale, color, 1, cv2.LINE_AA)
            x += cv2.getTextSize(piece, font, scale, 1)[0][0]


def legend(names: Sequence[str], colors: np.ndarray, width: int = 260) -> np.ndarray:
    """A vertical legend image: a swatch and a name per row."""
    import cv2

    img = np.full((16 * max(len(names), 1) + 4, width, 3), 32, np.uint8)
    for k, (name, col) in enumerate(zip(names, colors)):
        y = 4 + 16 * k
        img[y:y + 12, 4:16] = col
        cv2.putText(img, str(name)[:36], (22, y + 10), cv2.FONT_HERSHEY_SIMPLEX, 0.35,
                    (230, 230, 230), 1, cv2.LINE_AA)
    return img


def write_png(path, rgb: np.ndarray) -> Path:
    """Write an RGB uint8 image as PNG (OpenCV stores BGR)."""
    import cv2

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1])):
        raise OSError(f"{path}: could not write PNG")
    return path


# fixed RGB per part (PART_NAMES order); unseen parts grey
PART_COLORS = {
    "body": (200, 40, 40), "window": (60, 160, 230), "wheel": (85, 85, 85),
    "rim": (170, 170, 190), "light": (255, 220, 60), "chrome": (230, 230, 255),
    "plate": (255, 255, 255), "interior": (150, 100, 60), "other": (150, 90, 180),
}


def view_labels(cameras) -> list[str]:
    """'az A° el E°' under each view of a CameraRing (degrees)."""
    return [f"az {a:.0f}{DEGREE} el {e:.0f}{DEGREE}"
            for a, e in zip(cameras.azimuth, cameras.elevation)]


def with_legend(sheet: np.ndarray, leg: np.ndarray) -> np.ndarray:
    """``sheet`` with ``leg`` to its right, on the sheets' dark background."""
    h = max(sheet.shape[0], leg.shape[0])
    out = np.full((h, sheet.shape[1] + leg.shape[1], 3), 32, np.uint8)
    out[:sheet.shape[0], :sheet.shape[1]] = sheet
    out[:leg.shape[0], sheet.shape[1]:] = leg
    return out


def material_sheet(views, material_names: Sequence[str] | None = None, max_width: int = 2400
                   ) -> np.ndarray:
    """Contact sheet of a ViewSet's material-id maps (fixed colour per material) with a legend."""
    n = len(material_names) + 1 if material_names is not None else int(views.mat_id.max()) + 1
    pal = id_palette(n)
    sheet = contact_sheet(pal[views.mat_id], view_labels(views.cameras), max_width=max_width)
    if material_names:
        shown = [k for k in range(len(material_names)) if (views.mat_id == k + 1).any()][:64]
        leg = legend([material_names[k] for k in shown], pal[[k + 1 for k in shown]])
        return with_legend(sheet, leg)
    return sheet


def part_sheet(views, table, max_width: int = 2400) -> np.ndarray:
    """Contact sheet of the views coloured by each material's decided part, with a legend."""
    lut = np.zeros((len(table.rows) + 1, 4), np.uint8)     # RGB + padding: one uint32 per id
    for r in table.rows:
        lut[r.material + 1, :3] = PART_COLORS.get(r.part, (110, 110, 110))  # unseen: grey
    ids = np.asarray(views.mat_id)
    rgb = lut.view(np.uint32).ravel().take(ids).view(np.uint8).reshape(*ids.shape, 4)[..., :3]
    sheet = contact_sheet(rgb, view_labels(views.cameras), max_width=max_width)
    leg = legend(list(PART_NAMES), np.array([PART_COLORS[p] for p in PART_NAMES], np.uint8))
    return with_legend(sheet, leg)
