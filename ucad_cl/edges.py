"""Batched Canny edges (``ucad_cl/kernels/canny.cl``) and edges of material-index maps.

``canny(images, low, high, l2)`` equals ``cv2.Canny(image, low, high, apertureSize=3,
L2gradient=l2)`` pixel for pixel, image by image, for a whole batch in one launch per pass.

Inputs are uint8: (H, W) or (H, W, 3) for one image, (B, H, W) or (B, H, W, C) with C in {1, 3}
for a batch. A 3-D array whose last axis has length 3 is one colour image (H, W, 3), as OpenCV
reads it; pass a batch of 3-pixel-wide grey images as (B, H, 3, 1). Colour images are treated like
OpenCV treats them: per pixel, the channel with the largest gradient magnitude (the first on ties).
Output is uint8 0 / 255, shape (H, W) or (B, H, W).

Thresholds follow OpenCV exactly: low > high are swapped; with ``l2`` both are clamped to 32767
and squared when positive; both are then floored to integers; a pixel is a candidate when its
magnitude is > low and an edge seed when > high (magnitude |dx| + |dy|, or dx^2 + dy^2 for l2).

Device work per batch (ucad_cl/kernels/canny.cl): [canny_planes: colour to planes, or canny_id_planes:
id maps + colour table to planes], canny_gradient_nms
(Sobel, magnitude, direction, NMS and thresholds fused; 16 x ROWS pixel strips, 16-lane integer
vectors), canny_trace (hysteresis, one work-item per image, depth-first worklist). Programs are
built once per (channels, l2, ROWS) and cached; device buffers are kept for the two most recent
batch shapes. Batches above MAX_CHUNK_PIXELS go in several launches (same result).

``material_edges(views)`` turns material-id maps into edge maps (see its docstring for the colouring
and the guarantee), ``write_conditioning_pngs`` writes them as white-on-black PNGs.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .abi import CANNY_PARAMS
from .runtime import Runtime, get_runtime
from .artifacts import EdgeSet, ViewSet, nonzero_box

VSPAN = 16                   # pixels per work-item along x (VSPAN in canny.cl)
ROWS = 32                    # rows per work-item of canny_gradient_nms (16/32/64 within 10 %)
LOCAL = (1, 1, 1)            # its local size (1..16 along x, 1..4 along y: all within noise)
LOCAL_PLANES = 16            # canny_planes work-items per group along x (1: 2-3x slower)
MAX_SIDE = 32767             # the trace packs (row, column) into one int
MAX_CHUNK_PIXELS = 1 << 25   # pixels per launch; bounds the device scratch (C + 5 or 6 bytes/pixel)
_INT_MIN = -(2**31)


def canny(images: np.ndarray, low: float, high: float, l2: bool = False, *,
          runtime: Runtime | None = None, stats: CannyStats | None = None) -> np.ndarray:
    """Canny edges of one image or a batch, bit-identical to ``cv2.Canny`` (aperture 3), on
    ``runtime`` (default ``get_runtime()``); ``stats``, when given, receives the timings."""
    rt = runtime or get_runtime()
    batch, single = _as_batch(images)
    lo, hi = opencv_thresholds(low, high, l2)
    B, H, W, C = batch.shape
    out = np.empty((B, H, W), np.uint8)
    per = max(1, MAX_CHUNK_PIXELS // (H * W))
    for b0 in range(0, B, per):
        b1 = min(B, b0 + per)
        _run_canny(rt, batch[b0:b1], lo, hi, bool(l2), out[b0:b1], stats=stats)
    return out[0] if single else out


def opencv_thresholds(low: float, high: float, l2: bool) -> tuple[int, int]:
    """The integer thresholds cv::Canny compares magnitudes against (strictly greater)."""
    for name, t in (("low", low), ("high", high)):
        if not isinstance(t, (int, float, np.integer, np.floating)) or isinstance(t, bool):
            raise TypeError(f"canny: {name} threshold must be a number, got {type(t).__name__}")
        if math.isnan(float(t)):
            raise ValueError(f"canny: {name} threshold is NaN")
    lo, hi = float(low), float(high)
    if lo > hi:
        lo, hi = hi, lo
    if l2:
        lo, hi = min(32767.0, lo), min(32767.0, hi)
        lo = lo * lo if lo > 0 else lo
        hi = hi * hi if hi > 0 else hi
    return _cv_floor(lo), _cv_floor(hi)


def _cv_floor(v: float) -> int:
    """OpenCV's cvFloor on x86: floor, and INT_MIN when the result does not fit an int."""
    if not math.isfinite(v):
        return _INT_MIN
    f = math.floor(v)
    return f if _INT_MIN <= f < 2**31 else _INT_MIN


def _as_batch(images) -> tuple[np.ndarray, bool]:
    """(B, H, W, C) contiguous uint8 view of the input and whether it was a single image."""
    a = np.asarray(images)
    if a.dtype != np.uint8:
        raise TypeError(f"canny: images must be uint8, got {a.dtype}")
    if a.ndim == 2:
        a, single = a[None, :, :, None], True
    elif a.ndim == 3 and a.shape[-1] == 3:
        a, single = a[None], True
    elif a.ndim == 3:
        a, single = a[:, :, :, None], False
    elif a.ndim == 4 and a.shape[-1] in (1, 3):
        single = False
    else:
        raise ValueError("canny: images must be (H, W), (H, W, 3), (B, H, W) or (B, H, W, C) "
                         f"with C in (1, 3); got shape {a.shape}")
    B, H, W, _ = a.shape
    if B == 0 or H == 0 or W == 0:
        raise ValueError(f"canny: empty image batch, shape {np.asarray(images).shape}")
    if H > MAX_SIDE or W > MAX_SIDE:
        raise ValueError(f"canny: image side {max(H, W)} exceeds {MAX_SIDE}")
    return np.ascontiguousarray(a), single


@dataclass
class _Buffers:
    src: object       # (B, H, W, C) input
    planes: object    # (B, 3, H, W) for colour input, else None
    map: object       # (B, H, W) map, then the output
    stack: object     # (B, H * W) int32 trace worklist


@dataclass
class CannyStats:
    """Timings (seconds) of ``canny`` calls (upload, kernels, download, summed over launches)
    and ``extra`` counts (``material_edges``: "repaired"); pass one as ``stats=``."""

    upload: float = 0.0
    kernels: float = 0.0
    download: float = 0.0
    extra: dict = field(default_factory=dict)


def _buffers(rt: Runtime, shape: tuple[int, int, int, int]) -> _Buffers:
    """Device buffers for a (B, H, W, C) batch: the runtime's scratch buffers (reused across
    calls, grown when a batch is larger)."""
    B, H, W, C = shape
    n = B * H * W
    return _Buffers(src=rt.scratch("canny.src", n * C),
                    planes=rt.scratch("canny.planes", n * C) if C > 1 else None,
                    map=rt.scratch("canny.map", n), stack=rt.scratch("canny.stack", 4 * n))


def _run_canny(rt: Runtime, batch: np.ndarray, lo: int, hi: int, l2: bool, out: np.ndarray,
               lut: np.ndarray | None = None, stats: CannyStats | None = None) -> None:
    """Canny of ``batch`` (B, H, W, C) uint8 into ``out``; with ``lut`` ((N,) uint32 colours,
    R in the low byte), ``batch`` is (B, H, W) uint16 ids of the colour image lut[ids]."""
    import pyopencl as cl

    q = rt.queue
    B, H, W = batch.shape[:3]
    C = 3 if lut is not None else batch.shape[3]
    opts = (f"-DCANNY_CHANNELS={C}", f"-DCANNY_L2={int(l2)}", f"-DCANNY_ROWS={ROWS}")
    k_nms = rt.kernel("canny", "canny_gradient_nms", opts)
    k_trace = rt.kernel("canny", "canny_trace", opts)
    bufs = _buffers(rt, (B, H, W, C))           # src: 3 bytes a pixel, room for 2-byte ids
    prm = np.array([(W, H, B, C, lo, hi, int(l2), 0)], CANNY_PARAMS)
    t0 = time.perf_counter()
    cl.enqueue_copy(q, bufs.src, batch)
    t1 = time.perf_counter()
    spans = -(-W // VSPAN)
    planes = bufs.src
    if lut is not None:
        d_lut = cl.Buffer(rt.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=lut)
        k_planes = rt.kernel("canny", "canny_id_planes", opts)
        k_planes.set_args(bufs.src, d_lut, prm, bufs.planes)
        cl.enqueue_nd_range_kernel(q, k_planes, (_round_up(spans, LOCAL_PLANES), H, B),
                                   (LOCAL_PLANES, 1, 1))
        planes = bufs.planes
    elif C == 3:
        k_planes = rt.kernel("canny", "canny_planes", opts)
        k_planes.set_args(bufs.src, prm, bufs.planes)
        cl.enqueue_nd_range_kernel(q, k_planes, (_round_up(spans, LOCAL_PLANES), H, B),
                                   (LOCAL_PLANES, 1, 1))
        planes = bufs.planes
    k_nms.set_args(planes, prm, bufs.map)
    gsize = (_round_up(spans, LOCAL[0]), _round_up(-(-H // ROWS), LOCAL[1]), B)
    cl.enqueue_nd_range_kernel(q, k_nms, gsize, LOCAL)
    k_trace.set_args(bufs.map, prm, bufs.stack)
    cl.enqueue_nd_range_kernel(q, k_trace, (B,), (1,))
    q.finish()
    t2 = time.perf_counter()
    cl.enqueue_copy(q, out, bufs.map)
    q.finish()
    if stats is not None:
        stats.upload += t1 - t0
        stats.kernels += t2 - t1
        stats.download += time.perf_counter() - t2


def _round_up(n: int, m: int) -> int:
    return ((n + m - 1) // m) * m


# --------------------------------------------------------------------------------------------
# Material-id maps
# --------------------------------------------------------------------------------------------

def material_edges(views: ViewSet, *, low: float = 10.0, high: float = 20.0,
                   l2: bool = False, runtime: Runtime | None = None,
                   stats: CannyStats | None = None) -> EdgeSet:
    """Edges of the material-id maps of ``views`` (Canny of a colouring, plus a repair).

    Colouring: ids that touch anywhere (4-neighbours, over all views together) get different
    colours by a deterministic greedy colouring (ids in increasing order, each takes the first
    palette entry no touching id already has). The palette is {0, 255/(L-1), ..., 255}^3 with the
    smallest L >= 2 such that L^3 exceeds the largest number of ids touching one id, the 8 corner
    colours first; so touching ids differ by at least 255/(L-1) in some channel (127 for L = 3).
    Every view is coloured with the same table, then Canny runs on the batch (the device looks
    the colours up: ``canny_of_colours``).

    Guarantee: every 4-neighbour pair (p, q) with different ids has an edge pixel within one pixel
    (8-neighbourhood) of p or q. Canny alone cannot promise this for any colouring: inside a
    pattern of period 2 every Sobel response is 0, and on a stripe two pixels thick OpenCV's
    tie rule (strict on the previous side) suppresses the second boundary. Such pairs are found
    after Canny and their first pixel (left or upper) is marked as an edge; ``stats.extra
    ["repaired"]`` counts them. Precision needs no repair: a pixel whose 3x3 neighbourhood holds
    one id has zero gradient, so every edge pixel is within one pixel of an id boundary.
    """
    ids = np.asarray(views.mat_id)
    if ids.ndim != 3 or ids.dtype != np.uint16:
        raise ValueError(f"material_edges: mat_id must be a (V, H, W) uint16 array, got "
                         f"{ids.dtype} {ids.shape}")
    edges = canny_of_colours(ids, colour_table(ids), low, high, l2, runtime=runtime, stats=stats)
    repaired = _repair_missed_boundaries(ids, edges)
    if stats is not None:
        stats.extra["repaired"] = stats.extra.get("repaired", 0) + repaired
    return EdgeSet(edges=edges)


def canny_of_colours(ids: np.ndarray, table: np.ndarray, low: float, high: float,
                     l2: bool = False, *, runtime: Runtime | None = None,
                     stats: CannyStats | None = None) -> np.ndarray:
    """``canny(table[ids][..., :3])`` for (B, H, W) uint16 ids and a (N, 4) uint8 colour table
    (RGB + padding, e.g. ``colour_table``) without building the colour images on the host: the
    device looks the colours up (``canny_id_planes``). Same result, bit for bit."""
    ids = np.ascontiguousarray(ids)
    if ids.ndim != 3 or ids.dtype != np.uint16 or 0 in ids.shape:
        raise ValueError(f"canny_of_colours: ids must be a non-empty (B, H, W) uint16 array, "
                         f"got {ids.dtype} {ids.shape}")
    table = np.ascontiguousarray(table, np.uint8)
    if table.ndim != 2 or table.shape[1] != 4 or int(ids.max()) >= table.shape[0]:
        raise ValueError(f"canny_of_colours: table must be (N, 4) uint8 covering every id, got "
                         f"{table.shape} for ids up to {int(ids.max())}")
    B, H, W = ids.shape
    if H > MAX_SIDE or W > MAX_SIDE:
        raise ValueError(f"canny: image side {max(H, W)} exceeds {MAX_SIDE}")
    lo, hi = opencv_thresholds(low, high, l2)
    lut = table.view(np.uint32).ravel()
    out = np.empty((B, H, W), np.uint8)
    per = max(1, MAX_CHUNK_PIXELS // (H * W))
    for b0 in range(0, B, per):
        b1 = min(B, b0 + per)
        _run_canny(runtime or get_runtime(), ids[b0:b1], lo, hi, bool(l2), out[b0:b1], lut=lut,
                   stats=stats)
    return out


def colour_ids(ids: np.ndarray) -> np.ndarray:
    """(..., H, W) uint16 ids -> (..., H, W, 3) uint8 colours; touching ids differ strongly."""
    ids = np.asarray(ids)
    packed = colour_table(ids).view(np.uint32).ravel().take(ids)
    return np.ascontiguousarray(packed.view(np.uint8).reshape(*ids.shape, 4)[..., :3])


def colour_table(ids: np.ndarray) -> np.ndarray:
    """(max id + 1, 4) uint8: RGB (+ padding) of each id by the greedy colouring of
    ``material_edges``. Ids absent from ``ids`` touch nothing, so their colour (the first
    palette entry) changes no other id's."""
    ids = np.asarray(ids)
    pairs = _touching_pairs(ids)
    top = int(ids.max()) if ids.size else 0
    neighbours: dict[int, set[int]] = {u: set() for u in range(top + 1)}
    for a, b in pairs:
        neighbours[int(a)].add(int(b))
        neighbours[int(b)].add(int(a))
    degree = max((len(s) for s in neighbours.values()), default=0)
    levels = 2
    while levels ** 3 < degree + 1:
        levels += 1
    pal = palette(levels)
    lut = np.zeros((top + 1, 4), np.uint8)          # RGB + padding, gathered as one uint32
    chosen: dict[int, int] = {}
    for u in range(top + 1):
        used = {chosen[n] for n in neighbours[u] if n in chosen}
        chosen[u] = next(i for i in range(len(pal)) if i not in used)
        lut[u, :3] = pal[chosen[u]]
    return lut


def palette(levels: int) -> np.ndarray:
    """(levels^3, 3) uint8 colours on a grid of ``levels`` values per channel, corners first."""
    values = np.round(np.linspace(0, 255, levels)).astype(np.uint8)
    grid = np.stack(np.meshgrid(*[np.arange(levels)] * 3, indexing="ij"), -1).reshape(-1, 3)
    inner = np.sum((grid != 0) & (grid != levels - 1), axis=1)
    order = np.lexsort((grid[:, 2], grid[:, 1], grid[:, 0], inner))
    return values[grid[order]]


def _touching_pairs(ids: np.ndarray) -> np.ndarray:
    """(K, 2) sorted unique (a < b) id pairs that are 4-neighbours somewhere."""
    codes = []
    for img in _boxes(ids, 1):
        for a, b in ((img[:, 1:], img[:, :-1]), (img[1:, :], img[:-1, :])):
            diff = a != b
            lo, hi = np.minimum(a[diff], b[diff]), np.maximum(a[diff], b[diff])
            codes.append((lo.astype(np.uint32) << 16) | hi.astype(np.uint32))
    u = np.unique(np.concatenate(codes)) if codes else np.zeros(0, np.uint32)
    return np.stack([u >> 16, u & 0xFFFF], 1).astype(ids.dtype)


def _boxes(ids: np.ndarray, margin: int, *others: np.ndarray):
    """Per image of ``ids`` (..., H, W): the crop to the box of its non-zero ids grown by
    ``margin`` pixels (clipped to the image), as views, with the same crop of each of
    ``others``; images of zeros only are skipped. Everything outside such a box is id 0, so
    neighbour relations between different ids all lie inside it (margin 1)."""
    flat = ids.reshape(-1, *ids.shape[-2:])
    rest = [o.reshape(-1, *o.shape[-2:]) for o in others]
    for k, img in enumerate(flat):
        b = nonzero_box(img, margin)
        if b is None:
            continue
        box = (slice(b[0], b[1]), slice(b[2], b[3]))
        yield (img[box], *(o[k][box] for o in rest)) if others else img[box]


def _dilate8(mask: np.ndarray) -> np.ndarray:
    """Binary dilation of (V, H, W) masks by the 3x3 square (pixels outside are False)."""
    d = mask.copy()
    d[:, :, 1:] |= mask[:, :, :-1]
    d[:, :, :-1] |= mask[:, :, 1:]
    e = d.copy()
    e[:, 1:, :] |= d[:, :-1, :]
    e[:, :-1, :] |= d[:, 1:, :]
    return e


def _repair_missed_boundaries(ids: np.ndarray, edges: np.ndarray) -> int:
    """Mark the left/upper pixel of every id boundary pair with no edge within 1 px; count.

    Works per view inside the box of non-zero ids grown by 2 pixels: every boundary pair lies
    within 1 pixel of that box, so every edge pixel within 1 pixel of a pair lies inside it."""
    missed = 0
    for img, e in _boxes(ids, 2, edges):
        near = _dilate8((e > 0)[None])[0]
        miss_h = (img[:, 1:] != img[:, :-1]) & ~near[:, 1:] & ~near[:, :-1]
        miss_v = (img[1:, :] != img[:-1, :]) & ~near[1:, :] & ~near[:-1, :]
        e[:, :-1][miss_h] = 255
        e[:-1, :][miss_v] = 255
        missed += int(miss_h.sum() + miss_v.sum())
    return missed


def write_conditioning_pngs(edges: EdgeSet, out_dir, stem: str) -> list[Path]:
    """One white-on-black PNG per view, ``<out_dir>/<stem>_<view:03d>.png``; returns the paths."""
    import cv2

    e = np.asarray(edges.edges)
    if e.ndim != 3 or e.dtype != np.uint8:
        raise ValueError(f"write_conditioning_pngs: edges must be (V, H, W) uint8, got "
                         f"{e.dtype} {e.shape}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for v in range(e.shape[0]):
        path = out / f"{stem}_{v:03d}.png"
        if not cv2.imwrite(str(path), np.where(e[v] > 0, 255, 0).astype(np.uint8)):
            raise OSError(f"write_conditioning_pngs: could not write {path}")
        paths.append(path)
    return paths
