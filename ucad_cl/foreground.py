"""The object in a reference photo: its mask from a given mask or a box, and the photo with the
background replaced by the renders' background.

``object_mask(image, box=..., mask=...)`` is the query-side step of pose search
(``ucad_cl.pose``): renders of a mesh have a flat background (``RENDER_BACKGROUND``), a photo has
a street behind the car, so pose cues are computed on ``composite(image, mask)``: the object's
pixels over the renders' background, exactly as the renders have it.

* With a mask, it is the object (``source='mask'``).
* With a box only, the foreground inside it is estimated with OpenCV's GrabCut
  (``grabcut_box``), seeded by the box: the box grown by ``GROW`` of its size on every side is
  "probably background" around a "probably foreground" box, everything farther out is
  background (a detector's box may cut a few pixels of the car). GrabCut runs on the region
  reduced to at most ``GRABCUT_SIDE`` pixels (speed); its mask is scaled back with nearest
  neighbour, or, with ``follow_edges`` (the fit's object, which retrieval describes), along the
  photo's own edges: ``guided_filter`` with the photo's grey levels as the guide (radius
  ``EDGE_RADIUS`` GrabCut pixels), thresholded at 1/2, so the boundary is not quantised to the
  reduction step (retrieval of real vehicles 101 against 97 of 120 on three held-out draws;
  pose search keeps nearest neighbour: 94.2 against 95.3 % of box poses within 15 deg with it;
  docs/FIT.md, "GrabCut's mask scaled back along the photo's edges"). ``kept`` reports the
  share of the box's pixels it kept. When it keeps less than ``MIN_KEPT`` of the box (it lost
  the object in clutter of the object's colours), the whole box is used instead
  (``source='box'``).
* ``refine_with_silhouette`` reruns GrabCut seeded by a render's silhouette placed over the
  object (pose search does this with its best candidate): "probably foreground" inside the
  silhouette, "probably background" in a band around it, background beyond (with ``core``,
  the silhouette's eroded core is "foreground": the fit seeds it with the first retrieved
  meshes' stored silhouettes, ``ucad_cl.fit``).

* ``past_the_edge`` grows a photo whose object touches its edge past that edge (the renders'
  background there), for the fit's retrieval and the pose search to assume the vehicle goes on
  where the photo stops (``GrownPhoto.shown``: the pixels the photo shows).

Determinism: GrabCut initialises its colour models with k-means seeded from OpenCV's global
random generator; it is reseeded (``cv2.setRNGSeed(0)``) before every call, so the same input
gives the same mask.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import NamedTuple

import cv2  # noqa: TID253  # OpenCV throughout (GrabCut, warps)
import numpy as np

RENDER_BACKGROUND = (128, 128, 128)     # the flat background of the renders pose search compares
GROW = 0.1              # box margin treated as "probably background" (fraction of the box side)
GRABCUT_SIDE = 96       # GrabCut runs on the region reduced to this longer side (pixels)
GRABCUT_ITERS = 5
EDGE_RADIUS = 3.0       # GrabCut's mask scaled back along the photo's edges: guided filter radius
#                         in GrabCut pixels (chosen on tuning photos: 1.5-4 alike, 6 worse)
EDGE_EPS = 1e-3         # ... and its regulariser (grey levels in [0, 1], squared)
MIN_KEPT = 0.15         # below this share of the box, GrabCut's answer is not used
MIN_PIXELS = 8          # objects with fewer mask pixels are refused
ANALYSIS_SIDE = 512     # a large photo is analysed in a window (PhotoWindow) scaled so the
#                         object's box is at most this long ...
ANALYSIS_PIXELS = 1 << 20   # ... when the box is longer or the photo has more pixels than this
ANALYSIS_GROW = 0.3     # the window: the box grown by this share of its longer side on every side
#                         (GrabCut's context is 0.2, the fit's re-rank frame 0.15)
PAST_EDGE = (0.1, 0.25, 0.5)   # an object touching the photo's edge may go on past it by these
#                             shares of its visible extent (``past_the_edge``; docs/FIT.md) ...
EDGE_PIXELS = 1             # ... when its box reaches within this many pixels of that edge


@dataclass
class ObjectMask:
    """The object in a reference image.

    mask: (H, W) bool. source: 'mask' (given), 'grabcut' (estimated inside the box), 'box' (the
    whole box: GrabCut kept less than MIN_KEPT). box: the integer pixel box (x0, y0, x1, y1,
    x1/y1 exclusive) when one was given, else the mask's box. kept: share of the box's pixels
    in the mask (1.0 for a given mask).
    """

    mask: np.ndarray
    source: str
    box: tuple[int, int, int, int]
    kept: float = 1.0


def object_mask(image: np.ndarray, *, box=None, mask=None, grabcut: bool = True,
                follow_edges: bool = False) -> ObjectMask:
    """The object of ``image`` ((H, W, 3) uint8 RGB) given by exactly one of ``box`` (x0, y0,
    x1, y1 pixels, x1/y1 exclusive) or ``mask`` ((H, W), non-zero = object). With a box and
    ``grabcut=False`` the object is the whole box; ``follow_edges``: GrabCut's mask scaled back
    along the photo's edges (module docstring). ValueError naming the problem for a bad
    image, an empty or tiny mask or box, or both/neither given."""
    image = check_image(image)
    if (box is None) == (mask is None):
        raise ValueError("give exactly one of box=(x0, y0, x1, y1) or mask=(H, W) bool")
    H, W = image.shape[:2]
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != (H, W):
            raise ValueError(f"mask shape {m.shape} differs from the image's {(H, W)}")
        m = m.astype(bool) if m.dtype != np.bool_ else m
        n = int(m.sum())
        if n == 0:
            raise ValueError("mask is empty: the reference image has no object to match")
        if n < MIN_PIXELS:
            raise ValueError(f"mask has {n} pixel(s), fewer than {MIN_PIXELS}: too small to "
                             "match a pose")
        return ObjectMask(mask=m, source="mask", box=mask_box(m), kept=1.0)
    b = pixel_box((H, W), box)
    x0, y0, x1, y1 = b
    if (x1 - x0) * (y1 - y0) < MIN_PIXELS or min(x1 - x0, y1 - y0) < 2:
        raise ValueError(f"box {tuple(box)} covers {x1 - x0}x{y1 - y0} pixels of the {W}x{H} "
                         f"image: too small to match a pose (at least {MIN_PIXELS} pixels, "
                         "2 per side)")
    whole = np.zeros((H, W), bool)
    whole[y0:y1, x0:x1] = True
    if not grabcut:
        return ObjectMask(mask=whole, source="box", box=b, kept=1.0)
    fg = grabcut_box(image, b, follow_edges=follow_edges)
    kept = float(fg[y0:y1, x0:x1].mean())
    if kept < MIN_KEPT:
        return ObjectMask(mask=whole, source="box", box=b, kept=kept)
    return ObjectMask(mask=fg, source="grabcut", box=b, kept=kept)


def composite(image: np.ndarray, mask: np.ndarray,
              background=RENDER_BACKGROUND) -> np.ndarray:
    """(H, W, 3) uint8: ``image`` inside ``mask``, ``background`` (RGB) outside."""
    out = np.empty_like(np.asarray(image))
    out[...] = np.asarray(background, np.uint8)
    np.copyto(out, image, where=np.asarray(mask, bool)[..., None])
    return out


def check_image(image) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"reference image must be (H, W, 3) uint8 RGB, got {image.shape} "
                         f"{image.dtype}")
    if min(image.shape[:2]) < 1:
        raise ValueError(f"reference image is empty ({image.shape[1]}x{image.shape[0]})")
    return image


def pixel_box(shape: tuple[int, int], box) -> tuple[int, int, int, int]:
    """Integer (x0, y0, x1, y1) of a pixel box (coordinates rounded, clipped to the image);
    ValueError when it is malformed or empty inside the image."""
    H, W = shape
    try:
        c = [float(v) for v in box]
    except (TypeError, ValueError):
        raise ValueError(f"box must be 4 numbers (x0, y0, x1, y1), got {box!r}") from None
    if len(c) != 4 or not all(np.isfinite(c)):
        raise ValueError(f"box must be 4 finite numbers (x0, y0, x1, y1), got {box!r}")
    x0, y0, x1, y1 = (int(round(v)) for v in c)
    x0, x1 = max(x0, 0), min(x1, W)
    y0, y1 = max(y0, 0), min(y1, H)
    if x1 <= x0 or y1 <= y0:
        raise ValueError(f"box {tuple(box)} is empty inside the {W}x{H} image")
    return x0, y0, x1, y1


def mask_box(mask: np.ndarray) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1), x1/y1 exclusive, of a non-empty (H, W) mask."""
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    return int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1


def box_stretch(src: tuple[int, int, int, int], dst: tuple[int, int, int, int]) -> np.ndarray:
    """(2, 3) float64 affine map taking box ``src`` onto box ``dst`` ((x0, y0, x1, y1), each
    axis scaled on its own, corners onto corners): how a stored view's silhouette or material
    map is placed onto a photo's object."""
    x0, y0, x1, y1 = src
    X0, Y0, X1, Y1 = dst
    sx, sy = (X1 - X0) / (x1 - x0), (Y1 - Y0) / (y1 - y0)
    return np.array([[sx, 0.0, X0 - sx * x0], [0.0, sy, Y0 - sy * y0]])


@dataclass(frozen=True)
class PhotoWindow:
    """The part of a large photo that pose search and the fit analyse: photo pixels [x0, x1) x
    [y0, y1) scaled by ``scale`` (<= 1; a point maps by x' = scale (x - x0), pixel edges at
    integers, as ``cv2.resize`` maps with fx = fy = scale): the object's box grown by
    ``ANALYSIS_GROW`` of its longer side on every side, scaled so the box is at most
    ``ANALYSIS_SIDE`` long. A 12-megapixel photo analysed whole cost the fit ~3 s more than a
    0.2-megapixel one (full-size composites, masks and guided filters, a full-size pose render)
    for nothing the steps use: each looks at the box and a margin at a few hundred pixels at
    most (GrabCut 96, the HOG crops 128). Photos of at most ``ANALYSIS_PIXELS`` pixels whose box
    is at most ``ANALYSIS_SIDE`` long are analysed whole (``around`` gives None)."""

    x0: int
    y0: int
    x1: int
    y1: int
    scale: float

    @staticmethod
    def around(shape: tuple[int, int], box, mask) -> "PhotoWindow | None":
        """The window of a photo of ``shape`` (H, W) around its object (``box``, or ``mask``'s
        box), or None when the photo is analysed whole (small enough, or a box or mask that
        ``object_mask`` will refuse with its own message)."""
        H, W = shape
        try:
            if mask is not None:
                m = np.asarray(mask)
                if m.shape != (H, W) or not m.any():
                    return None
                x0, y0, x1, y1 = mask_box(m)
            elif box is not None:
                x0, y0, x1, y1 = pixel_box((H, W), box)
            else:
                return None
        except ValueError:
            return None
        side = max(x1 - x0, y1 - y0)
        scale = min(1.0, ANALYSIS_SIDE / side)
        if scale == 1.0 and H * W <= ANALYSIS_PIXELS:
            return None
        if min(x1 - x0, y1 - y0) * scale < 8:  # too thin to scale: object_mask decides
            return None
        g = ANALYSIS_GROW * side
        return PhotoWindow(max(0, int(np.floor(x0 - g))), max(0, int(np.floor(y0 - g))),
                           min(W, int(np.ceil(x1 + g))), min(H, int(np.ceil(y1 + g))), scale)

    def cut_mask(self, mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """A (H, W) bool mask of the photo in the window's pixels (``shape``, the window image's
        (h, w)): by area, kept where at least half covered."""
        m = (np.asarray(mask)[self.y0:self.y1, self.x0:self.x1] != 0).astype(np.uint8) * 255
        if self.scale != 1.0:
            m = cv2.resize(m, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)
        return m >= 128

    def cut(self, photo: np.ndarray, box, mask):
        """(window image, box, mask) in the window's pixels (the box as ``pixel_box`` rounds
        it, then scaled; the mask by area, kept where at least half covered)."""
        sub = np.ascontiguousarray(photo[self.y0:self.y1, self.x0:self.x1])
        img = sub if self.scale == 1.0 else cv2.resize(
            sub, (0, 0), fx=self.scale, fy=self.scale, interpolation=cv2.INTER_AREA)
        if mask is not None:
            return img, None, self.cut_mask(mask, img.shape[:2])
        b = pixel_box(photo.shape[:2], box)
        s = self.scale
        return img, (s * (b[0] - self.x0), s * (b[1] - self.y0), s * (b[2] - self.x0),
                     s * (b[3] - self.y0)), None

    def _A(self) -> np.ndarray:
        s = self.scale
        return np.array([[s, 0.0, -s * self.x0], [0.0, s, -s * self.y0], [0.0, 0.0, 1.0]])

    def intrinsics(self, shape: tuple[int, int], fov_deg: float) -> np.ndarray:
        """``photo_intrinsics(shape, fov_deg)`` of the whole photo, in the window's pixels."""
        return self._A() @ photo_intrinsics(shape, fov_deg)

    def photo_K(self, K: np.ndarray) -> np.ndarray:
        """``K`` of the window's pixels -> the photo's (the camera's pose is the same)."""
        return np.linalg.solve(self._A(), np.asarray(K, np.float64))

    def photo_box(self, box) -> tuple[int, int, int, int]:
        """An integer box of the window's pixels -> the photo's (rounded outward)."""
        s = self.scale
        return (self.x0 + int(np.floor(box[0] / s)), self.y0 + int(np.floor(box[1] / s)),
                self.x0 + int(np.ceil(box[2] / s)), self.y0 + int(np.ceil(box[3] / s)))

    def photo_lengths(self, lengths) -> tuple[int, ...]:
        """Lengths in the window's pixels (e.g. ``GrownPhoto.margins``) -> the photo's, rounded."""
        return tuple(int(round(v / self.scale)) for v in lengths)

    def photo_object(self, obj: ObjectMask, shape: tuple[int, int]) -> ObjectMask:
        """``obj`` of the window -> the photo's (H, W) mask (nearest neighbour)."""
        full = np.zeros(shape, bool)
        w, h = self.x1 - self.x0, self.y1 - self.y0
        m = obj.mask.astype(np.uint8)
        up = m if self.scale == 1.0 else cv2.resize(m, (w, h), interpolation=cv2.INTER_NEAREST)
        full[self.y0:self.y1, self.x0:self.x1] = up[:h, :w] > 0
        return replace(obj, mask=full, box=self.photo_box(obj.box))


# --------------------------------------------------------------- past the photo's edge

class GrownPhoto(NamedTuple):
    """A photo grown past its edge (``past_the_edge``): the grown image, the object there,
    (x, y) where the photo's pixel (0, 0) lies in it, and the object as the photo shows it
    (``seen``, in the photo's pixels)."""

    image: np.ndarray
    obj: ObjectMask
    at: tuple[int, int]
    seen: ObjectMask

    def shown(self) -> np.ndarray:
        """(h, w) bool over the grown image: the pixels of the photo."""
        out = np.zeros(self.image.shape[:2], bool)
        (x, y), (H, W) = self.at, self.seen.mask.shape
        out[y:y + H, x:x + W] = True
        return out

    def margins(self) -> tuple[int, int, int, int]:
        """(left, top, right, bottom): the pixels grown past each edge of the photo."""
        (x, y), (h, w), (H, W) = self.at, self.image.shape[:2], self.seen.mask.shape
        return x, y, w - W - x, h - H - y


def past_the_edge(photo: np.ndarray, obj: ObjectMask) -> list[GrownPhoto]:
    """The hypotheses for an object cut by the photo's edge (its box, given or the mask's,
    within ``EDGE_PIXELS`` of it; the fit's retrieval tries each, ``pose.past_edge_choice``
    picks one for a known mesh): for each share e of ``PAST_EDGE``, the photo grown by
    e x the mask's visible width (height) past every side the box touches, the new pixels the
    renders' background, and one mask pixel at the new edge (in the mask's outermost row or
    column there) so that the descriptor's crop frames the whole assumed vehicle; what the
    photo does not show stays background. [] when the box touches no edge."""
    H, W = obj.mask.shape
    bx0, by0, bx1, by1 = obj.box
    sides = (bx0 <= EDGE_PIXELS, by0 <= EDGE_PIXELS, bx1 >= W - EDGE_PIXELS,
             by1 >= H - EDGE_PIXELS)                          # left, top, right, bottom
    if not any(sides):
        return []
    mask = obj.mask
    x0, y0, x1, y1 = mask_box(mask)
    out = []
    for e in PAST_EDGE:
        gx, gy = int(round(e * (x1 - x0))), int(round(e * (y1 - y0)))
        left, top, right, bottom = (g * s for g, s in zip((gx, gy, gx, gy), sides))
        if not left + top + right + bottom:         # an object too small to grow: no change
            continue
        wider = np.empty((H + top + bottom, W + left + right, 3), np.uint8)
        wider[...] = RENDER_BACKGROUND
        wider[top:top + H, left:left + W] = photo
        past = np.zeros(wider.shape[:2], bool)
        past[top:top + H, left:left + W] = mask
        if left:
            past[top + int(np.flatnonzero(mask[:, x0])[0]), 0] = True
        if right:
            past[top + int(np.flatnonzero(mask[:, x1 - 1])[0]), -1] = True
        if top:
            past[0, left + int(np.flatnonzero(mask[y0])[0])] = True
        if bottom:
            past[-1, left + int(np.flatnonzero(mask[y1 - 1])[0])] = True
        out.append(GrownPhoto(wider, ObjectMask(mask=past, source="mask", box=mask_box(past)),
                              (left, top), obj))
    return out


# ----------------------------------------------------------------------------- GrabCut

def grabcut_box(image: np.ndarray, box: tuple[int, int, int, int], *,
                follow_edges: bool = False) -> np.ndarray:
    """(H, W) bool foreground estimated by GrabCut inside the integer pixel ``box``."""
    x0, y0, x1, y1 = box
    g = GROW * max(x1 - x0, y1 - y0)
    seeds = _Seeds(image.shape[:2], (x0 - 2 * g, y0 - 2 * g, x1 + 2 * g, y1 + 2 * g))
    seeds.fill((x0 - g, y0 - g, x1 + g, y1 + g), cv2.GC_PR_BGD)
    seeds.fill((x0, y0, x1, y1), cv2.GC_PR_FGD)
    return seeds.run(image, follow_edges)


def refine_with_silhouette(image: np.ndarray, silhouette: np.ndarray,
                           band: float = 0.06, core: float = 0.0,
                           follow_edges: bool = False) -> np.ndarray:
    """(H, W) bool foreground from GrabCut seeded by ``silhouette`` ((H, W) bool, a render's
    mask placed over the object): "probably foreground" inside it, "probably background" in a
    band of ``band`` x its box side around it, background beyond; with ``core`` > 0 the
    silhouette eroded by ``core`` x its box side is "foreground" (GrabCut cannot drop it: a
    dark car on dark asphalt keeps its body, only the boundary band is decided by colour)."""
    x0, y0, x1, y1 = mask_box(silhouette)
    side = max(x1 - x0, y1 - y0)
    g = max(band * side, 1.0)
    seeds = _Seeds(image.shape[:2], (x0 - 2 * g, y0 - 2 * g, x1 + 2 * g, y1 + 2 * g))
    k = 2 * int(np.ceil(g * seeds.scale)) + 1
    sil = seeds.crop(silhouette.astype(np.uint8))
    near = cv2.dilate(sil, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))) > 0
    seeds.labels[near] = cv2.GC_PR_BGD
    seeds.labels[sil > 0] = cv2.GC_PR_FGD
    if core > 0:
        c = 2 * int(np.ceil(core * side * seeds.scale)) + 1
        inner = cv2.erode(sil, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (c, c))) > 0
        seeds.labels[inner] = cv2.GC_FGD
    return seeds.run(image, follow_edges)


class _Seeds:
    """GrabCut labels of a region of the image reduced to at most GRABCUT_SIDE pixels."""

    def __init__(self, shape, region):
        H, W = shape
        self.shape = shape
        rx0, ry0 = max(int(np.floor(region[0])), 0), max(int(np.floor(region[1])), 0)
        rx1, ry1 = min(int(np.ceil(region[2])), W), min(int(np.ceil(region[3])), H)
        self.region = (rx0, ry0, rx1, ry1)
        self.scale = min(1.0, GRABCUT_SIDE / max(rx1 - rx0, ry1 - ry0))
        self.size = (max(int(round((rx1 - rx0) * self.scale)), 1),
                     max(int(round((ry1 - ry0) * self.scale)), 1))
        self.labels = np.full(self.size[::-1], cv2.GC_BGD, np.uint8)

    def fill(self, rect, label):
        rx0, ry0 = self.region[:2]
        s = self.scale
        c0 = max(int(np.floor((rect[0] - rx0) * s)), 0)
        r0 = max(int(np.floor((rect[1] - ry0) * s)), 0)
        c1 = int(np.ceil((rect[2] - rx0) * s))
        r1 = int(np.ceil((rect[3] - ry0) * s))
        self.labels[r0:r1, c0:c1] = label

    def crop(self, img):
        rx0, ry0, rx1, ry1 = self.region
        return cv2.resize(img[ry0:ry1, rx0:rx1], self.size, interpolation=cv2.INTER_NEAREST)

    def run(self, image, follow_edges: bool = False) -> np.ndarray:
        rx0, ry0, rx1, ry1 = self.region
        out = np.zeros(self.shape, bool)
        lab = self.labels
        fg_seed = (lab == cv2.GC_PR_FGD) | (lab == cv2.GC_FGD)
        bg_seed = (lab == cv2.GC_PR_BGD) | (lab == cv2.GC_BGD)
        if not fg_seed.any():
            return out
        if not bg_seed.any():                   # the object fills the image: nothing to cut
            out[ry0:ry1, rx0:rx1] = cv2.resize(fg_seed.astype(np.uint8), (rx1 - rx0, ry1 - ry0),
                                               interpolation=cv2.INTER_NEAREST) > 0
            return out
        small = cv2.resize(np.ascontiguousarray(image[ry0:ry1, rx0:rx1]), self.size,
                           interpolation=cv2.INTER_AREA)
        bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
        cv2.setRNGSeed(0)
        try:
            cv2.grabCut(small, lab, None, bgd, fgd, GRABCUT_ITERS, cv2.GC_INIT_WITH_MASK)
        except cv2.error:                       # too few samples for a colour model
            return out
        fg = ((lab == cv2.GC_FGD) | (lab == cv2.GC_PR_FGD)).astype(np.float32)
        up = cv2.resize(fg, (rx1 - rx0, ry1 - ry0), interpolation=cv2.INTER_NEAREST)
        if follow_edges and EDGE_RADIUS > 0 and self.scale < 1.0:
            r = max(1, int(round(EDGE_RADIUS / self.scale)))
            up = guided_filter(image[ry0:ry1, rx0:rx1], up, r, EDGE_EPS)
        out[ry0:ry1, rx0:rx1] = up > 0.5
        return out


def guided_filter(guide: np.ndarray, src: np.ndarray, radius: int, eps: float) -> np.ndarray:
    """(H, W) float32: ``src`` ((H, W) float32) filtered by the guided filter (He, Sun and Tang,
    ECCV 2010) with the grey level of ``guide`` ((H, W, 3) uint8, mean of the channels / 255) as
    the guide; box windows of side 2 ``radius`` + 1 (reflected at the borders) and ``eps`` the
    regulariser: an edge of the guide stays an edge of the output, so a mask upsampled from
    GrabCut's grid moves onto the photo's own boundary."""
    g = guide.astype(np.float32).mean(axis=2) * np.float32(1.0 / 255.0)
    k = (2 * radius + 1, 2 * radius + 1)

    def box(x):
        return cv2.boxFilter(x, -1, k, borderType=cv2.BORDER_REFLECT)

    mg, ms = box(g), box(src)
    a = (box(g * src) - mg * ms) / (box(g * g) - mg * mg + np.float32(eps))
    b = ms - a * mg
    return box(a) * g + box(b)


# ----------------------------------------------------------------------------- centring

@dataclass
class CentredPhoto:
    """A reference photo turned (virtually) so that its object lies on the optical axis.

    image: (h, w, 3) uint8, mask: (h, w) bool: what a camera with the photo's centre and focal
    length ``f`` (pixels), turned by ``R`` (3x3, photo camera -> centred camera frame), sees
    around the object. ``K``: the photo's assumed intrinsics (3x3). ``frame``, ``valid``:
    ``centre_on_axis``'s, warped alike.
    """

    image: np.ndarray
    mask: np.ndarray
    R: np.ndarray
    K: np.ndarray
    f: float
    frame: np.ndarray | None = None
    valid: np.ndarray | None = None


def centre_on_axis(image: np.ndarray, mask: np.ndarray, fov_deg: float,
                   frame: np.ndarray | None = None, K: np.ndarray | None = None,
                   valid: np.ndarray | None = None) -> CentredPhoto:
    """Warp ``image``/``mask`` so that the centre of the mask's box (of ``frame``'s box when
    given: another (H, W) bool mask, e.g. the detector's box, warped alike into
    ``CentredPhoto.frame``) is on the optical axis.

    A vehicle seen away from the image centre is seen obliquely by the image plane: its image is
    that of a camera looking at it, warped by the homography ``K R^T K^-1`` of the camera's turn
    ``R``. Renders always look at the vehicle's centre, so the photo is warped back by
    ``K R K^-1``. The photo's intrinsics are not known: ``K`` assumes a field of view of
    ``fov_deg`` over the narrower image side and the principal point at the image centre (an
    error there only leaves part of the obliquity). The turn is a yaw about the camera's y axis
    then a pitch about the new x axis (an upright camera stays upright). The output is the
    warped box grown by 25 % on each side (bilinear image, nearest-neighbour masks, edge pixels
    repeated). ``K``: the photo's intrinsics when they are known (``image`` a ``PhotoWindow``
    of a larger photo); ``fov_deg`` is then not used. ``valid``: (H, W) bool, the pixels the
    photo shows (None: all), warped alike into ``CentredPhoto.valid`` (False outside the
    photo)."""
    K = photo_intrinsics(mask.shape, fov_deg) if K is None else np.asarray(K, np.float64)
    f = float(K[0, 0])
    x0, y0, x1, y1 = mask_box(mask if frame is None else frame)
    R = axis_turn(K, ((x0 + x1) / 2.0, (y0 + y1) / 2.0))
    Hm = K @ R @ np.linalg.inv(K)
    corners = np.array([[x0, y0, 1.0], [x1, y0, 1.0], [x0, y1, 1.0], [x1, y1, 1.0]]) @ Hm.T
    corners = corners[:, :2] / corners[:, 2:]
    lo, hi = corners.min(0), corners.max(0)
    g = 0.25 * (hi - lo).max()
    lo, hi = np.floor(lo - g), np.ceil(hi + g)
    w, h = int(hi[0] - lo[0]), int(hi[1] - lo[1])
    T = np.array([[1.0, 0.0, -lo[0]], [0.0, 1.0, -lo[1]], [0.0, 0.0, 1.0]])
    M = T @ Hm
    out = cv2.warpPerspective(image, M, (w, h), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_REPLICATE)

    def warp(a):
        return cv2.warpPerspective(a.view(np.uint8), M, (w, h), flags=cv2.INTER_NEAREST) > 0

    m = warp(mask)
    fr = warp(frame) if frame is not None else None
    if not m.any() or (fr is not None and not fr.any()):   # degenerate: keep the photo
        return CentredPhoto(image=image, mask=mask, R=np.eye(3), K=K, f=float(f), frame=frame,
                            valid=valid)
    return CentredPhoto(image=out, mask=m, R=R, K=K, f=float(f), frame=fr,
                        valid=None if valid is None else warp(np.asarray(valid, bool)))


def photo_intrinsics(shape: tuple[int, int], fov_deg: float) -> np.ndarray:
    """(3, 3) K assumed for a photo of ``shape`` (H, W) whose camera is not known: the
    principal point at the image centre, a field of view of ``fov_deg`` over the narrower
    side (pose search's prior, ``centre_on_axis``)."""
    H, W = shape
    f = 0.5 * min(H, W) / np.tan(np.radians(fov_deg) / 2.0)
    return np.array([[f, 0.0, W / 2.0], [0.0, f, H / 2.0], [0.0, 0.0, 1.0]])


def axis_turn(K: np.ndarray, point) -> np.ndarray:
    """(3, 3) rotation R (camera -> turned camera) that brings the ray through image ``point``
    (x, y pixels) of a camera with intrinsics ``K`` onto the optical axis: a yaw about the
    camera's y axis, then a pitch about the new x axis."""
    ray = np.linalg.solve(K, np.array([point[0], point[1], 1.0]))
    yaw = np.arctan2(ray[0], ray[2])
    cy, sy = np.cos(yaw), np.sin(yaw)
    Ry = np.array([[cy, 0.0, -sy], [0.0, 1.0, 0.0], [sy, 0.0, cy]])
    r = Ry @ ray
    pitch = np.arctan2(r[1], r[2])
    cp, sp = np.cos(pitch), np.sin(pitch)
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]])
    return Rx @ Ry
