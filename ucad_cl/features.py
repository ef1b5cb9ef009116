"""Pose features: crop the object, resize to one resolution, describe it with one vector.

Every extractor has the interface ``FeatureExtractor.extract(images, masks) -> Features`` with
``images`` (B, H, W, 3) uint8 RGB and ``masks`` (B, H, W) bool (True = object). Output rows are
float32 and L2-normalised (an image whose descriptor is all zero keeps a zero row).

Crop (shared by all extractors, so references and renders are treated alike, ``crop_square``):
the mask's bounding box (rows y0..y1, columns x0..x1, inclusive) gives a square of side
``ceil(max(h, w) * (1 + 2 * pad))`` pixels centred on the box centre (top-left corner rounded
down); pixels outside the image repeat the nearest edge pixel. The square is resized to
``size x size`` with ``cv2.resize(..., INTER_AREA)``. Renders get their mask from finite depth;
a reference image from a user-given mask or box (``box_mask``).

Extractors:

* ``HogExtractor`` (built in, no weights): histogram of oriented gradients computed by
  ``ucad_cl/kernels/features.cl`` for the whole batch at once (see there for the exact definition: max
  colour-channel gradient, linear orientation voting, 2x2-cell L2-Hys blocks, global L2), with an
  optional coarse silhouette channel (mask resized to ``silhouette x silhouette``). Defaults (64 px
  crop, 8 px cells, 9 unsigned bins, eps 1, no silhouette) were chosen by the azimuth error
  measured with the pose benchmark before issue 12 (10 generated vehicles x 8 box references,
  median error / share within 15 deg, coarse 10 deg ring and with refinement): 9 unsigned bins
  3.07 / 95.0 % and 1.56 / 95.0 %; 12 signed 6.18 / 67.5 % and 4.92 / 66.2 % (a repainted car
  flips the gradient sign); 18 unsigned 3.26 / 95.0 % and 1.45 / 95.0 % (2x longer, no gain);
  min_grad 0.03-0.1 and eps 4 no better; the silhouette channel 1.61 / 95.0 % refined with true
  masks (pose search now compares silhouettes as its own cue, ``ucad_cl.cues``).
* ``OnnxExtractor``: any image encoder exported to ONNX (e.g. DINOv2), run with onnxruntime; its
  patch-feature map (B, C, h, w) or tokens (B, N, C) are flattened and L2-normalised.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import cv2  # noqa: TID253  # OpenCV throughout (crops, resizes)
import numpy as np

from .abi import HOG_PARAMS, MAX_BINS
from .artifacts import Features, ViewSet
from .runtime import Runtime, get_runtime

BATCH = 512             # images per kernel launch (bounds device memory: ~BATCH * 70 KiB)


class FeatureExtractor(Protocol):
    kind: str

    def extract(self, images: np.ndarray, masks: np.ndarray) -> Features:
        """(B, D) float32 L2-normalised features of the object under each mask."""


def view_features(extractor: FeatureExtractor, images: np.ndarray, views: ViewSet) -> Features:
    """Features of shaded renders ``images`` (V, H, W, 3) of ``views``: mask = finite depth.
    A view that sees nothing (a flat or thin mesh seen edge-on) gets an all-zero row."""
    masks = np.isfinite(views.depth)
    seen = masks.any(axis=(1, 2))
    if seen.all():
        return extractor.extract(images, masks)
    probe = seen if seen.any() else np.arange(len(seen)) == 0     # D from one view at least
    got = extractor.extract(images[probe], masks[probe] | ~seen[probe, None, None])
    feats = np.zeros((len(seen), got.feats.shape[1]), got.feats.dtype)
    feats[seen] = got.feats[seen[probe]]
    return Features(feats=feats, kind=got.kind)


# ----------------------------------------------------------------------------- cropping

def crop_square(images: np.ndarray, masks: np.ndarray, size: int, pad: float = 0.1, *,
                with_masks: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Square, padded crops around each mask, resized: ((B,S,S,3) uint8, (B,S,S) float32 mask,
    or None when ``with_masks`` is False)."""
    images, masks = _check_batch(images, masks)
    if size < 1:
        raise ValueError(f"crop size must be >= 1, got {size}")
    B = masks.shape[0]
    windows = square_windows(masks, pad)
    crops = np.empty((B, size, size, 3), np.uint8)
    mcrops = np.empty((B, size, size), np.float32) if with_masks else None
    for b in range(B):
        crops[b] = crop_window(images[b], windows[b], size)
        if with_masks:
            mcrops[b] = crop_window(masks[b], windows[b], size, dtype=np.float32)
    return crops, mcrops


def mask_bounds(masks: np.ndarray) -> np.ndarray:
    """(B, 4) int64 (y0, x0, y1, x1) of each (B, H, W) bool mask's bounding box, y1/x1 inclusive
    (the first and last rows and columns holding a True pixel); -1 everywhere for an empty mask.
    One reduction over the batch per axis (the per-mask ``any`` loops cost ~3x more)."""
    masks = np.asarray(masks, bool)
    B, H, W = masks.shape
    rows = masks.any(axis=2)
    cols = masks.any(axis=1)
    out = np.stack([rows.argmax(axis=1), cols.argmax(axis=1),
                    H - 1 - rows[:, ::-1].argmax(axis=1), W - 1 - cols[:, ::-1].argmax(axis=1)],
                   axis=1).astype(np.int64)
    out[~rows.any(axis=1)] = -1
    return out


def square_windows(masks: np.ndarray, pad: float = 0.1,
                   bounds: np.ndarray | None = None) -> list[tuple[int, int, int]]:
    """(top, left, side) in pixels of the square crop of each (B, H, W) bool mask (the crop rule
    of the module docstring); ``bounds``: the masks' ``mask_bounds`` when the caller has them.
    ValueError for an empty mask."""
    if pad < 0:
        raise ValueError(f"pad must be >= 0, got {pad}")
    out = []
    for b, (y0, x0, y1, x1) in enumerate(mask_bounds(masks) if bounds is None else bounds):
        if y0 < 0:
            raise ValueError(f"image {b}: mask is empty (no object to crop)")
        y0, x0, y1, x1 = int(y0), int(x0), int(y1), int(x1)
        side = int(math.ceil(max(y1 - y0 + 1, x1 - x0 + 1) * (1.0 + 2.0 * pad)))
        top = int(math.floor((y0 + y1 + 1) / 2.0 - side / 2.0))
        left = int(math.floor((x0 + x1 + 1) / 2.0 - side / 2.0))
        out.append((top, left, side))
    return out


def crop_window(image: np.ndarray, window: tuple[int, int, int], size: int,
                interpolation: int = cv2.INTER_AREA, dtype: type | None = None) -> np.ndarray:
    """The square ``window`` (top, left, side) of one (H, W[, C]) image, resized to ``size``;
    pixels outside the image repeat the nearest edge pixel. ``dtype``: the window's pixels are
    converted to it first (e.g. a bool mask to float32: only the window is converted)."""
    top, left, side = window
    H, W = image.shape[:2]
    r0, r1 = max(top, 0), min(top + side, H)
    c0, c1 = max(left, 0), min(left + side, W)
    border = (r0 - top, top + side - r1, c0 - left, left + side - c1)
    a = image[r0:r1, c0:c1]
    if dtype is not None:
        a = a.astype(dtype)
    if any(border):
        a = cv2.copyMakeBorder(a, *border, cv2.BORDER_REPLICATE)
    return cv2.resize(a, (size, size), interpolation=interpolation)


def box_mask(shape: tuple[int, int], box) -> np.ndarray:
    """(H, W) bool mask of the pixel box ``(x0, y0, x1, y1)``: columns x0..x1-1, rows y0..y1-1."""
    H, W = shape
    x0, y0, x1, y1 = (int(round(float(c))) for c in box)
    x0, x1 = max(x0, 0), min(x1, W)
    y0, y1 = max(y0, 0), min(y1, H)
    if x1 <= x0 or y1 <= y0:
        raise ValueError(f"box {tuple(box)} is empty inside the {W}x{H} image")
    m = np.zeros((H, W), bool)
    m[y0:y1, x0:x1] = True
    return m


def _check_batch(images: np.ndarray, masks: np.ndarray):
    images = np.asarray(images)
    masks = np.asarray(masks)
    if images.dtype != np.uint8 or images.ndim != 4 or images.shape[-1] != 3:
        raise ValueError(f"images must be (B, H, W, 3) uint8, got {images.shape} {images.dtype}")
    if masks.dtype != np.bool_ or masks.shape != images.shape[:3]:
        raise ValueError(f"masks must be (B, H, W) = {images.shape[:3]} bool, "
                         f"got {masks.shape} {masks.dtype}")
    return images, masks


# ----------------------------------------------------------------------------- HOG (OpenCL)

@dataclass
class HogExtractor:
    """Built-in descriptor: OpenCL HOG of the square crop (+ optional silhouette).

    size: crop side (pixels, multiple of ``cell``); cell: cell side; bins: orientation bins;
    signed: orientations over 360 deg instead of 180; eps, clip: L2-Hys block normalisation;
    min_grad: soft threshold subtracted from each pixel's gradient magnitude (max 1.41);
    silhouette: side of the resized mask appended (0 = none), weighted to norm ``sil_weight``
    relative to the HOG part; pad: crop padding (fraction of the box side on each side);
    runtime: the OpenCL runtime it runs on (None: ``get_runtime()``), like ``FeatureIndex``'s.
    """

    size: int = 64
    cell: int = 8
    bins: int = 9
    signed: bool = False
    eps: float = 1.0
    clip: float = 0.2
    min_grad: float = 0.0
    silhouette: int = 0
    sil_weight: float = 0.5
    pad: float = 0.1
    local_cells: int | None = None      # work-group size of the cell kernel (None: PoCL picks)
    local_pixels: int = 64              # work-group size of the per-pixel gradient kernel
    kind: str = "hog"
    runtime: Runtime | None = field(default=None, compare=False, repr=False)

    def __post_init__(self):
        if self.size < 2 * self.cell or self.size % self.cell:
            raise ValueError(f"size={self.size} must be a multiple of cell={self.cell} "
                             "with at least 2 cells per side")
        if not 1 <= self.bins <= MAX_BINS:
            raise ValueError(f"bins={self.bins} must be in 1..{MAX_BINS}")
        if min(self.silhouette, self.eps, self.sil_weight, self.min_grad) < 0 or self.clip <= 0:
            raise ValueError("silhouette, eps, sil_weight, min_grad must be >= 0 and clip > 0")

    @property
    def n_cells(self) -> int:
        return self.size // self.cell

    @property
    def dim(self) -> int:
        nb = self.n_cells - 1
        return nb * nb * 4 * self.bins + self.silhouette ** 2

    def params(self) -> np.ndarray:
        nc = self.n_cells
        return np.array([(self.size, self.cell, nc, self.bins, int(self.signed), nc - 1,
                          (nc - 1) ** 2 * 4 * self.bins, self.silhouette ** 2, self.eps,
                          self.clip, self.sil_weight, self.min_grad)], HOG_PARAMS)

    def extract(self, images: np.ndarray, masks: np.ndarray) -> Features:
        crops, mcrops = crop_square(images, masks, self.size, self.pad,
                                    with_masks=self.silhouette > 0)
        return Features(feats=self.describe(crops, mcrops), kind=self.kind)

    def seen_dims(self, valid: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """(D,) bool: the descriptor's dimensions that describe only pixels the photo shows,
        for the object ``mask`` (H, W) bool (cropped around it, as ``extract`` crops) in a
        photo whose shown pixels are ``valid`` (H, W) bool (e.g. a photo grown past its edge):
        a block is kept when every crop pixel it and its gradients read (its cells and one
        pixel around) is wholly shown; a silhouette dimension when its area is."""
        window = square_windows(np.asarray(mask, bool)[None], self.pad)[0]
        shown = crop_window(np.asarray(valid, np.float32), window, self.size) >= 1.0 - 1e-6
        nb, c = self.n_cells - 1, self.cell
        pad = np.pad(shown, 1, mode="edge")[None]      # the kernel clamps at the crop edge
        blocks = np.array([[pad[0, by * c:by * c + 2 * c + 2, bx * c:bx * c + 2 * c + 2].all()
                            for bx in range(nb)] for by in range(nb)])
        dims = [np.repeat(blocks.ravel(), 4 * self.bins)]
        if self.silhouette:
            dims.append(cv2.resize(shown.astype(np.float32), (self.silhouette,) * 2,
                                   interpolation=cv2.INTER_AREA).ravel() >= 1.0 - 1e-6)
        return np.concatenate(dims)

    def describe(self, crops: np.ndarray, mask_crops: np.ndarray | None = None) -> np.ndarray:
        """(B, D) float32 descriptors of already-cropped (B, S, S, 3) uint8 images."""
        crops = np.ascontiguousarray(crops, np.uint8)
        if crops.ndim != 4 or crops.shape[1:] != (self.size, self.size, 3):
            raise ValueError(f"crops must be (B, {self.size}, {self.size}, 3), got {crops.shape}")
        B = crops.shape[0]
        d_sil = self.silhouette ** 2
        sil = np.zeros((B, max(d_sil, 1)), np.float32)
        if d_sil:
            if mask_crops is None:
                raise ValueError("the silhouette channel needs mask crops")
            sil = np.stack([cv2.resize(m, (self.silhouette,) * 2, interpolation=cv2.INTER_AREA)
                            for m in mask_crops]).reshape(B, d_sil).astype(np.float32)
        out = np.empty((B, self.dim), np.float32)
        for b0 in range(0, B, BATCH):
            out[b0:b0 + BATCH] = self._run(crops[b0:b0 + BATCH], sil[b0:b0 + BATCH])
        return out

    def _run(self, crops: np.ndarray, sil: np.ndarray) -> np.ndarray:
        import pyopencl as cl

        rt = self.runtime or get_runtime()
        k = {n: rt.kernel("features", n) for n in ("hog_pixel_gradients", "hog_cell_histograms",
                                                   "hog_block_normalise", "hog_finalise")}
        B = crops.shape[0]
        nc, nb = self.n_cells, self.n_cells - 1
        prm = self.params()
        mf = cl.mem_flags
        d_img = cl.Buffer(rt.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=crops)
        d_sil = cl.Buffer(rt.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(sil))
        d_grad = cl.Buffer(rt.ctx, mf.READ_WRITE, 8 * B * self.size * self.size)
        d_hist = cl.Buffer(rt.ctx, mf.READ_WRITE, 4 * B * nc * nc * self.bins)
        d_blocks = cl.Buffer(rt.ctx, mf.READ_WRITE, 4 * B * int(prm["d_hog"][0]))
        d_out = cl.Buffer(rt.ctx, mf.WRITE_ONLY, 4 * B * self.dim)
        q = rt.queue
        lc = self.local_cells
        g0 = _round_up(nc * nc, lc) if lc else nc * nc
        lp = self.local_pixels
        k["hog_pixel_gradients"](q, (_round_up(self.size ** 2, lp), B), (lp, 1), d_img, d_grad,
                                 prm)
        k["hog_cell_histograms"](q, (g0, B), (lc, 1) if lc else None, d_grad, d_hist, prm)
        k["hog_block_normalise"](q, (nb * nb, B), None, d_hist, d_blocks, prm)
        k["hog_finalise"](q, (B,), None, d_blocks, d_sil, d_out, prm, np.int32(B))
        out = np.empty((B, self.dim), np.float32)
        cl.enqueue_copy(q, out, d_out)
        return out


def _round_up(n: int, m: int) -> int:
    return ((n + m - 1) // m) * m


# ----------------------------------------------------------------------------- ONNX encoder

class OnnxExtractor:
    """A user-supplied ONNX image encoder (e.g. DINOv2 ViT) as a pose feature extractor.

    The crop (``size`` x ``size``, same rule as every extractor) is scaled to [0, 1], normalised
    with ``mean``/``std`` per channel (ImageNet defaults) and fed as NCHW float32 to the model's
    first input. The first output, a patch-feature map (B, C, h, w) or tokens (B, N, C) (the first
    ``skip_tokens`` tokens, e.g. 1 for a CLS token, are dropped), is flattened and L2-normalised.
    """

    kind = "onnx"

    def __init__(self, model_path, size: int = 224, *, skip_tokens: int = 0, pad: float = 0.1,
                 mean=(0.485, 0.456, 0.406), std=(0.229, 0.224, 0.225), providers=None):
        import onnxruntime as ort

        self.size, self.skip_tokens, self.pad = int(size), int(skip_tokens), float(pad)
        self.mean = np.asarray(mean, np.float32).reshape(1, 3, 1, 1)
        self.std = np.asarray(std, np.float32).reshape(1, 3, 1, 1)
        try:
            self.session = ort.InferenceSession(
                str(model_path), providers=providers or ["CPUExecutionProvider"])
        except Exception as exc:
            raise ValueError(f"cannot load ONNX encoder {str(model_path)!r}: {exc}") from exc
        self.input_name = self.session.get_inputs()[0].name

    def extract(self, images: np.ndarray, masks: np.ndarray) -> Features:
        crops, _ = crop_square(images, masks, self.size, self.pad, with_masks=False)
        x = crops.transpose(0, 3, 1, 2).astype(np.float32) / np.float32(255.0)
        x = ((x - self.mean) / self.std).astype(np.float32)
        y = np.asarray(self.session.run(None, {self.input_name: x})[0], np.float32)
        if y.ndim == 3:
            y = y[:, self.skip_tokens:, :]
        elif y.ndim != 4 and y.ndim != 2:
            raise ValueError(f"encoder output must be (B, C, h, w) or (B, N, C), got {y.shape}")
        return Features(feats=l2_rows(y.reshape(y.shape[0], -1)), kind=self.kind)


def l2_rows(x: np.ndarray) -> np.ndarray:
    """Rows scaled to unit L2 norm, float32 (see ``unit_rows``); zero rows stay zero."""
    return unit_rows(x)[0].astype(np.float32)


def unit_rows(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Float64 unit rows and per row 1.0 (non-zero) / 0.0 (zero row, kept zero).

    Rows are divided by their largest magnitude first, so huge values (1e300) do not overflow.
    """
    x = np.asarray(x, np.float64)
    scale = np.max(np.abs(x), axis=1, keepdims=True)
    y = np.divide(x, scale, out=np.zeros_like(x), where=scale > 0)
    n = np.linalg.norm(y, axis=1, keepdims=True)
    return np.divide(y, n, out=np.zeros_like(y), where=n > 0), (n[:, 0] > 0).astype(np.float64)
