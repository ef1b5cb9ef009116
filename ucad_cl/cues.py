"""Appearance-invariant pose cues: how well a rendered view explains the object in a photo.

``view_cues(views, images, extractor)`` describes rendered views, ``query_cues(image, mask,
extractor)`` a reference photo whose background was replaced by the renders' (see
``ucad_cl.foreground``), and ``cue_distances(query, views)`` compares them, one distance per cue
and view, 0 = perfect agreement. Everything is computed in the square crop frame of
``ucad_cl.features`` (the mask's box, padded, resized to ``size`` x ``size``), so a render and a
photo are compared at the same scale and position whatever their image size.

Cues (all in [0, ~1], lower is better):

* ``hog``: squared L2 distance between the HOG rows of the composited photo and of the render
  (``ucad_cl.features``; max-channel gradients, unsigned orientations: a repainted car keeps its
  edges' orientations). Halved, so it lies in [0, 2].
* ``silhouette``: 1 - soft IoU of the two masks in the crop frame (area-resized masks in [0, 1];
  IoU = sum(min) / sum(max)). Colour-invariant; cannot tell a view from its front/back twin
  (azimuth a and 180 - a have the same outline in orthographic projection).
* ``chamfer``: symmetric truncated edge chamfer: the mean distance (crop pixels, capped at
  ``TAU``) from each photo edge pixel to the nearest render edge pixel and from each render edge
  pixel to the nearest photo edge pixel, averaged and divided by ``TAU``. Photo edges: OpenCV
  Canny of the composited crop (thresholds ``CANNY``, L2 gradient); render edges: the geometric
  and material discontinuities of the rendered maps (``map_edges``): silhouette, depth jumps,
  creases (face normals more than ``CREASE_DEG`` apart) and material boundaries. Distances by
  ``cv2.distanceTransform`` (exact Euclidean, DIST_MASK_PRECISE). An image without edges is at
  distance 1 from everything.
* ``region``: how much of the photo's colour variance the render's regions leave unexplained:
  the crop is partitioned by the render's material ids (background one more region) and the
  score is the within-region sum of squared colour deviations over the total sum of squared
  deviations. A repainted car has one colour per part, so the right view's regions are
  near-uniform whatever the colours.

Retrieval's re-rank (``ucad_cl.fit``) uses three more, outside ``Cues``, in a frame around the
object of the photo itself (not composited; ``photo_edges(image, mask)``), a stored view placed
by stretching its box onto the object's: ``edge_distance(edges, *boundary_points(mat))``, how
far the view's material boundaries lie from the photo's edges; ``edge_recall`` the other way
round, from the photo's edges inside the object to the view's boundaries; and
``region_residual(edges, mat)``, the ``region`` cue on that frame.

``combine(distances, weights)`` is the weighted sum. Ties are not broken here: pose search orders
equal scores by view index.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2  # noqa: TID253  # OpenCV throughout (Canny, distance transforms)
import numpy as np

from .artifacts import BACKGROUND_TRI, Mesh, ViewSet
from .features import FeatureExtractor, crop_window, mask_bounds, square_windows, unit_rows
from .foreground import box_stretch, mask_box
from .shade import face_normals

CUES = ("hog", "silhouette", "chamfer", "region")
SIZE = 64               # crop side of the cue maps (pixels)
TAU = 6.0               # chamfer distance cap (crop pixels)
CANNY = (60, 120)       # photo edge thresholds (cv2.Canny, L2 gradient)
CREASE_DEG = 35.0       # face normals further apart than this make a render edge
DEPTH_JUMP = 0.03       # depth step (canonical units, bbox diagonal 1) that makes a render edge
PAD = 0.1               # crop padding (the features' crop rule)
SHOWN_MARGIN = 1        # a photo's edges count this many crop pixels in from what it does not show


@dataclass
class Cues:
    """Cue maps of B images in the crop frame (B = 1 for a photo).

    hog: (B, D) float32 rows of the extractor. sil: (B, S, S) float32 mask coverage in [0, 1].
    edges: (B, S, S) bool. dist: (B, S, S) float32 distance to the nearest edge pixel, capped at
    TAU. labels: (B, S, S) int32 region ids (0 = background; renders only, else None). colours:
    (B, S, S, 3) float32 RGB (photos only, else None). sides: (B,) longer side of the object box
    in pixels, over the narrower image side. offsets: (B, 2) where the centre of the object's
    box lies, (x, y) from the principal point over the focal length (renders only, else None).
    shown: (1, S, S) bool, the crop pixels the photo shows, ``SHOWN_MARGIN`` pixel(s) in from
    what it does not (Canny's Sobel and non-maximum suppression reach 2 pixels and its
    hysteresis further, so edges near that border still depend a little on what fills the
    rest; 1 measured better than 3 on the tuning draws: docs/FIT.md)
    (photos grown past their edge only, else None: all); hog_dims: (D,) bool, the HOG
    dimensions that describe only shown pixels (``HogExtractor.seen_dims``; else None). The
    distances to a photo with ``shown`` ignore the rest (``cue_distances``).
    """

    hog: np.ndarray
    sil: np.ndarray
    edges: np.ndarray
    dist: np.ndarray
    sides: np.ndarray
    labels: np.ndarray | None = None
    colours: np.ndarray | None = None
    offsets: np.ndarray | None = None
    shown: np.ndarray | None = None
    hog_dims: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.sil.shape[0])


def view_cues(mesh: Mesh, views: ViewSet, images: np.ndarray, extractor: FeatureExtractor,
              size: int = SIZE, normals: np.ndarray | None = None) -> Cues:
    """Cues of shaded renders ``images`` (V, H, W, 3) uint8 of ``views`` (rendered from
    ``mesh``; ``normals``: its ``shade.face_normals`` when the caller has them).

    The silhouette is area-resized into the crop frame; triangle ids, material ids and depth are
    sampled there at the nearest pixel (the source pixel under each crop pixel's centre, indices
    clamped to the image), and the render edges (``map_edges``) found on those samples."""
    if normals is None:
        normals = face_normals(mesh)
    masks = np.isfinite(views.depth)
    with ThreadPoolExecutor(1) as pool:         # the HOG beside the rest (both free the GIL)
        hog = pool.submit(lambda: extractor.extract(images, masks).feats)
        out = _map_cues(views, masks, normals, size)
    return Cues(hog=hog.result(), **out)


def _map_cues(views: ViewSet, masks: np.ndarray, normals: np.ndarray, size: int) -> dict:
    """``view_cues``'s cues from the maps: the fields of ``Cues`` but ``hog``."""
    V, H, W = masks.shape
    bounds = mask_bounds(masks)                 # (y0, x0, y1, x1) inclusive, once for all uses
    windows = square_windows(masks, PAD, bounds)
    sil = np.empty((V, size, size), np.float32)
    for v in range(V):
        sil[v] = crop_window(masks[v], windows[v], size, dtype=np.float32)
    top, left, side = (np.array(c, np.int64)[:, None] for c in zip(*windows))
    at = np.floor((np.arange(size) + 0.5) * (side / size)).astype(np.int64)   # (V, size)
    rows = np.clip(top + at, 0, H - 1)
    cols = np.clip(left + at, 0, W - 1)
    flat = ((np.arange(V)[:, None, None] * H + rows[:, :, None]) * W
            + cols[:, None, :])                 # the sampled pixels, (V, size, size)
    tri = np.asarray(views.tri_id).reshape(-1).take(flat)
    mat = np.asarray(views.mat_id).reshape(-1).take(flat)
    depth = np.asarray(views.depth).reshape(-1).take(flat)
    e = map_edges(tri, mat, depth, normals)
    hw = bounds[:, 2:] - bounds[:, :2] + 1      # (h, w) of each box
    sides = hw.max(axis=1).astype(np.float64) / min(H, W)
    K = views.cameras.K
    offsets = np.stack([(bounds[:, 1] + bounds[:, 3] + 1) / 2.0,
                        (bounds[:, 0] + bounds[:, 2] + 1) / 2.0], axis=1)
    offsets = (offsets - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])
    return dict(sil=sil, edges=e, dist=_distances(e), sides=sides, labels=mat.astype(np.int32),
                offsets=offsets)


def query_cues(image: np.ndarray, mask: np.ndarray, extractor: FeatureExtractor,
               size: int = SIZE, frame: np.ndarray | None = None,
               valid: np.ndarray | None = None) -> Cues:
    """Cues of one photo ``image`` (H, W, 3) uint8 (background already replaced) with its
    object ``mask`` (H, W) bool; the crop window is the mask's (``frame``'s, another (H, W)
    bool mask, when given: e.g. a detector's box when the mask is only an estimate).
    ``valid``: (H, W) bool, the pixels the photo shows (a photo grown past its edge; None:
    all): the edges at and beyond its border are dropped, and ``shown`` / ``hog_dims`` say
    what the distances may compare."""
    frame = mask if frame is None else frame
    window = square_windows(frame[None], PAD)[0]
    crop = crop_window(image, window, size)
    sil = crop_window(mask.astype(np.float32), window, size)
    edges = cv2.Canny(crop, CANNY[0], CANNY[1], L2gradient=True) > 0
    hog = extractor.extract(image[None], frame[None]).feats
    shown = dims = None
    if valid is not None and not np.all(valid):
        whole = crop_window(np.asarray(valid, np.float32), window, size) >= 1.0 - 1e-6
        shown = cv2.erode(whole.astype(np.uint8), np.ones((3, 3), np.uint8),
                          iterations=SHOWN_MARGIN, borderType=cv2.BORDER_REPLICATE) > 0
        edges &= shown
        seen_dims = getattr(extractor, "seen_dims", None)     # (HOG: its blocks)
        dims = seen_dims(valid, frame) if seen_dims is not None else None
    return Cues(hog=hog, sil=sil[None], edges=edges[None], dist=_distances(edges[None]),
                sides=np.array([_side(frame) / min(frame.shape)]),
                colours=crop.astype(np.float32)[None],
                shown=None if shown is None else shown[None], hog_dims=dims)


def cue_distances(query: Cues, views: Cues, names=CUES) -> dict[str, np.ndarray]:
    """{cue: (V,) float64} distances of the photo ``query`` to every view (see module doc), for
    the cues in ``names`` (default all; pose search asks only for the cues it weighs)."""
    out = {}
    if "hog" in names:
        out["hog"] = query_hog_distance(query, views.hog)
    if "silhouette" in names:
        q = query.sil[0].astype(np.float64).ravel()
        s = views.sil.reshape(len(views), -1).astype(np.float64)
        if query.shown is not None:
            keep = query.shown[0].ravel()
            q, s = q[keep], s[:, keep]
        inter = np.minimum(s, q).sum(1)
        union = np.maximum(s, q).sum(1)
        out["silhouette"] = 1.0 - np.divide(inter, union, out=np.zeros_like(inter),
                                            where=union > 0)
    if "chamfer" in names:
        out["chamfer"] = _chamfer(query, views)
    if "region" in names:
        out["region"] = _region(query, views)
    return out


def combine(distances: dict[str, np.ndarray], weights: dict[str, float]) -> np.ndarray:
    """Weighted sum of the cue distances (cues with weight 0 or absent are skipped)."""
    total = None
    for name in CUES:
        w = float(weights.get(name, 0.0))
        if w:
            total = w * distances[name] if total is None else total + w * distances[name]
    if total is None:
        raise ValueError(f"no cue has a non-zero weight in {weights!r}")
    return total


# ----------------------------------------------------------------------------- render edges

def map_edges(tri: np.ndarray, mat: np.ndarray, depth: np.ndarray,
              normals: np.ndarray) -> np.ndarray:
    """(V, H, W) bool geometric and material edges of rendered maps (triangle ids, material ids,
    depth; ``normals`` (F, 3) the mesh's face normals): a pixel is an edge when a 4-neighbour
    (right or below; both pixels are marked) differs in coverage (silhouette), in material id,
    in depth by more than DEPTH_JUMP, or shows another face whose normal is more than CREASE_DEG
    away (two-sided faces: normals compared up to sign)."""
    normals = np.asarray(normals, np.float32)
    fg = tri != BACKGROUND_TRI
    cos = np.float32(np.cos(np.radians(CREASE_DEG)))
    out = np.zeros(tri.shape, bool)
    for axis in (1, 2):
        a = [slice(None)] * 3
        b = [slice(None)] * 3
        a[axis], b[axis] = slice(None, -1), slice(1, None)
        a, b = tuple(a), tuple(b)
        diff = (fg[a] != fg[b]) | (mat[a] != mat[b])
        # pairs inside one material that show two faces: a depth jump or a crease (the pairs
        # by flat index into the pair grid, in C order: one gather a map)
        tri_a, tri_b = tri[a], tri[b]
        two = np.flatnonzero(fg[a] & fg[b] & (tri_a != tri_b) & ~diff)
        ta = tri_a.reshape(-1)[two].astype(np.int64)
        tb = tri_b.reshape(-1)[two].astype(np.int64)
        jump = np.abs(depth[a].reshape(-1)[two] - depth[b].reshape(-1)[two]) > DEPTH_JUMP
        jump |= np.abs(np.einsum("nk,nk->n", normals[ta], normals[tb])) < cos
        diff.reshape(-1)[two[jump]] = True
        out[a] |= diff
        out[b] |= diff
    return out


# ----------------------------------------------------------------------------- photo edges

# Retrieval's re-rank (``ucad_cl.fit``, docs/FIT.md "Stored views' edges against the photo's"
# and "The photo's edges and colours against the view's regions"): how far a stored view's
# material boundaries, placed onto the object's box, lie from the photo's own edges, and the
# other way round. The photo is not composited: clutter adds edges that every candidate may
# land on alike, while a boundary the photo lacks (or a wrong outline) costs; an edge inside
# the object that the view has no boundary for costs too.
EDGE_SIDE = 160             # frame side (pixels): the object's box grown by EDGE_GROW, squared
EDGE_GROW = 0.15            # ... on every side, as a share of the box's longer side
EDGE_CANNY = (40, 100)      # photo edge thresholds (cv2.Canny, L2 gradient, frame grey levels)
EDGE_SLACK_DEG = 67.5       # a photo edge serves a boundary whose normal is this near its gradient
EDGE_TAU = 6.0              # distance cap (frame pixels)
EDGE_SHIFT = 2              # the boundaries are shifted by up to this many frame pixels each way
EDGE_INSIDE = 3             # edge_recall: photo edges this far (frame pixels) inside the object


@dataclass(frozen=True)
class PhotoEdges:
    """A photo's edges and colours in the square frame around its object's box, for
    ``edge_distance``, ``edge_recall`` and ``region_residual``.

    dist: (2, S, S) float32 Euclidean distance (frame pixels, exact) to the nearest Canny edge
    pixel whose gradient lies within ``EDGE_SLACK_DEG`` of the x axis (channel 0) or of the y
    axis (channel 1); ``EDGE_TAU`` everywhere in a channel without edges. to_frame: (2, 3) photo
    pixel coordinates -> frame pixel coordinates. box: the object's box (x0, y0, x1, y1) in
    photo pixels, x1 / y1 exclusive. inside: per channel, (n, 2) int64 (x, y) frame pixels of
    that channel's edges lying at least ``EDGE_INSIDE`` frame pixels inside the object mask
    (its outline left out). colours: (S * S, 3) float64 the frame's RGB (0-255), row-major,
    minus their mean. spread: their sum of squares (the total for ``region_residual``)."""

    dist: np.ndarray
    to_frame: np.ndarray
    box: tuple[int, int, int, int]
    inside: tuple[np.ndarray, np.ndarray]
    colours: np.ndarray
    spread: float


def photo_edges(image: np.ndarray, mask: np.ndarray) -> PhotoEdges:
    """``PhotoEdges`` of ``image`` (H, W, 3) uint8 RGB around the box of ``mask`` (H, W) bool,
    non-empty: the frame is the box's longer side grown by ``EDGE_GROW`` on every side, centred
    on the box, resized to ``EDGE_SIDE`` (area averaging; outside the photo the edge pixels
    repeat); Canny (``EDGE_CANNY``, L2 gradient) on its grey levels; a pixel's gradient angle
    from 3x3 Sobel derivatives; the mask comes into the frame by nearest neighbour and is
    eroded by ``EDGE_INSIDE`` (square structuring element) to select ``inside``."""
    mask = np.asarray(mask, bool)
    x0, y0, x1, y1 = mask_box(mask)
    s = EDGE_SIDE / (max(x1 - x0, y1 - y0) * (1.0 + 2.0 * EDGE_GROW))
    cx, cy = (x0 + x1) / 2.0, (y0 + y1) / 2.0
    to_frame = np.array([[s, 0.0, EDGE_SIDE / 2.0 - s * cx], [0.0, s, EDGE_SIDE / 2.0 - s * cy]])
    image = np.ascontiguousarray(image, np.uint8)
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    crop = cv2.warpAffine(grey, to_frame, (EDGE_SIDE, EDGE_SIDE), flags=cv2.INTER_AREA,
                          borderMode=cv2.BORDER_REPLICATE)
    edges = cv2.Canny(crop, EDGE_CANNY[0], EDGE_CANNY[1], L2gradient=True) > 0
    f = crop.astype(np.float32)
    gx, gy = cv2.Sobel(f, cv2.CV_32F, 1, 0), cv2.Sobel(f, cv2.CV_32F, 0, 1)
    off_x = np.degrees(np.arctan2(np.abs(gy), np.abs(gx)))     # 0 (along x) .. 90 (along y)
    dist = np.full((2, EDGE_SIDE, EDGE_SIDE), EDGE_TAU, np.float32)
    for c, near in enumerate((off_x <= EDGE_SLACK_DEG, off_x >= 90.0 - EDGE_SLACK_DEG)):
        e = edges & near
        if e.any():
            dist[c] = cv2.distanceTransform((~e).astype(np.uint8), cv2.DIST_L2,
                                            cv2.DIST_MASK_PRECISE)
    core = cv2.warpAffine(mask.astype(np.uint8), to_frame, (EDGE_SIDE, EDGE_SIDE),
                          flags=cv2.INTER_NEAREST)
    core = cv2.erode(core, np.ones((2 * EDGE_INSIDE + 1,) * 2, np.uint8)) > 0
    inside = tuple(np.argwhere((dist[c] == 0) & core)[:, ::-1].astype(np.int64)
                   for c in range(2))
    colours = cv2.warpAffine(image, to_frame, (EDGE_SIDE, EDGE_SIDE), flags=cv2.INTER_AREA,
                             borderMode=cv2.BORDER_REPLICATE).reshape(-1, 3).astype(np.float64)
    colours -= colours.mean(axis=0)
    return PhotoEdges(dist=dist, to_frame=to_frame, box=(x0, y0, x1, y1),
                      inside=(inside[0], inside[1]), colours=colours,
                      spread=float((colours * colours).sum()))


def boundary_points(mat: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int, int]]:
    """The boundaries of a material-id map (H, W) (0 = background): ((N, 2) float64 (x, y)
    pixel coordinates of the midpoints between 4-neighbours of different id, the silhouette
    included; (N,) int 0 between horizontal neighbours (normal along x), 1 between vertical
    ones; the non-zero ids' box (x0, y0, x1, y1), x1 / y1 exclusive). An empty map gives no
    points and box (0, 0, 1, 1)."""
    fg = np.asarray(mat) > 0
    if not fg.any():
        return np.zeros((0, 2)), np.zeros(0, np.int64), (0, 0, 1, 1)
    m = np.pad(np.asarray(mat), 1)
    c = m[1:-1, 1:-1]
    ys, xs = np.nonzero(c != m[1:-1, 2:])           # pixel (y, x) against (y, x + 1)
    ys2, xs2 = np.nonzero(c != m[2:, 1:-1])         # pixel (y, x) against (y + 1, x)
    pts = np.concatenate([np.stack([xs + 1.0, ys + 0.5], 1), np.stack([xs2 + 0.5, ys2 + 1.0], 1)])
    normal = np.concatenate([np.zeros(len(xs), np.int64), np.ones(len(xs2), np.int64)])
    return pts, normal, mask_box(fg)


def edge_distance(edges: PhotoEdges, points: np.ndarray, normal: np.ndarray,
                  box: tuple[int, int, int, int]) -> float:
    """How far a stored view's boundaries (``boundary_points``) lie from the photo's edges, in
    [0, 1]: the boundaries' box stretched onto the photo object's box (each axis on its own),
    into the frame, each point rounded to the nearest frame pixel (clamped to the frame) and
    read in the channel of its normal, distances capped at ``EDGE_TAU``, averaged over the
    points, divided by ``EDGE_TAU``; the minimum over integer shifts of up to ``EDGE_SHIFT``
    frame pixels in x and y. 1.0 without points."""
    if len(points) == 0:
        return 1.0
    q = _placed(edges, points, box)
    shift = np.arange(-EDGE_SHIFT, EDGE_SHIFT + 1)
    side = edges.dist.shape[1]
    xi = np.clip(q[None, None, :, 0] + shift[:, None, None], 0, side - 1)
    yi = np.clip(q[None, None, :, 1] + shift[None, :, None], 0, side - 1)
    d = np.minimum(edges.dist[normal[None, None, :], yi, xi], EDGE_TAU)
    return float(d.mean(axis=2, dtype=np.float64).min() / EDGE_TAU)


def edge_recall(edges: PhotoEdges, points: np.ndarray, normal: np.ndarray,
                box: tuple[int, int, int, int]) -> float:
    """How far the photo's edges inside its object (``PhotoEdges.inside``) lie from a stored
    view's boundaries (``boundary_points``), in [0, 1]: ``edge_distance`` the other way round.
    The boundaries are placed in the frame as ``edge_distance`` places them; each inside edge
    pixel reads the exact Euclidean distance to the nearest placed boundary point of its own
    channel, capped at ``EDGE_TAU``; averaged over the edge pixels, divided by ``EDGE_TAU``; the
    minimum over the same shifts. 0.0 when the photo has no inside edge, 1.0 without points."""
    n = len(edges.inside[0]) + len(edges.inside[1])
    if n == 0:
        return 0.0
    if len(points) == 0:
        return 1.0
    side = edges.dist.shape[1]
    q = np.clip(_placed(edges, points, box), 0, side - 1)
    shift = np.arange(-EDGE_SHIFT, EDGE_SHIFT + 1)
    total = np.zeros((len(shift), len(shift)))
    for c in range(2):
        px = edges.inside[c]
        if not len(px):
            continue
        on = q[normal == c]
        dt = np.full((side, side), EDGE_TAU, np.float32)
        if len(on):
            free = np.ones((side, side), np.uint8)
            free[on[:, 1], on[:, 0]] = 0
            dt = cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        # boundaries shifted by (dx, dy): the edge pixel reads the map at (x - dx, y - dy)
        xi = np.clip(px[None, None, :, 0] - shift[:, None, None], 0, side - 1)
        yi = np.clip(px[None, None, :, 1] - shift[None, :, None], 0, side - 1)
        total += np.minimum(dt[yi, xi], EDGE_TAU).sum(axis=2, dtype=np.float64)
    return float(total.min() / n / EDGE_TAU)


def region_residual(edges: PhotoEdges, mat: np.ndarray) -> float:
    """How much of the frame's colour variance a stored view's material regions leave
    unexplained, in [0, 1]: the material-id map ``mat`` (H, W) (0 = background) placed in the
    frame as ``edge_distance`` places its boundaries (its non-zero box stretched onto the
    object's box; nearest neighbour, background outside), the frame partitioned by id (the
    background one more region), the within-region sum of squared RGB deviations over the
    total. A repainted vehicle has one colour per part, so the right mesh's regions are near
    uniform whatever the colours. 0.0 for a uniform frame, 1.0 for an empty map."""
    mat = np.asarray(mat)
    fg = mat > 0
    c, total = edges.colours, edges.spread
    if total <= 0.0:
        return 0.0
    if not fg.any():
        return 1.0
    M = _frame_from_view(edges, mask_box(fg))
    lab = cv2.warpAffine(mat.astype(np.float32), M, (EDGE_SIDE, EDGE_SIDE),
                         flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=0.0).astype(np.int64).ravel()
    explained = float(_explained(c, lab[None])[0])
    return float(np.clip((total - explained) / total, 0.0, 1.0))   # (colours' mean is 0)


# ----------------------------------------------------------------------------- helpers

def _frame_from_view(edges: PhotoEdges, box: tuple[int, int, int, int]) -> np.ndarray:
    """(2, 3) stored-view pixel coordinates -> frame pixel coordinates: the view's box (x0, y0,
    x1, y1) stretched onto the object's box (``foreground.box_stretch``), then ``to_frame``."""
    A = np.vstack([box_stretch(box, edges.box), [0.0, 0.0, 1.0]])
    return (np.vstack([edges.to_frame, [0.0, 0.0, 1.0]]) @ A)[:2]


def _placed(edges: PhotoEdges, points: np.ndarray, box) -> np.ndarray:
    """(N, 2) int64 frame pixels (x, y) of stored-view points: stretched onto the object's box
    by ``foreground.box_stretch``'s scales, rounded to the nearest pixel (not clamped). The
    points are offset from the box corner before scaling (``X0 + (x - x0) sx``), the rounding
    ``edge_distance`` was chosen with; ``_frame_from_view``'s matrix form rounds a point on a
    half pixel differently."""
    x0, y0 = box[0], box[1]
    X0, Y0 = edges.box[0], edges.box[1]
    A = box_stretch(box, edges.box)
    photo = np.stack([X0 + (points[:, 0] - x0) * A[0, 0], Y0 + (points[:, 1] - y0) * A[1, 1]], 1)
    return np.round(photo @ edges.to_frame[:, :2].T + edges.to_frame[:, 2]).astype(np.int64)


def _box(mask: np.ndarray) -> tuple[int, int, int, int]:
    """(y0, x0, y1, x1), y1/x1 exclusive, of a non-empty mask."""
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    return int(rows[0]), int(cols[0]), int(rows[-1]) + 1, int(cols[-1]) + 1


def _side(mask: np.ndarray) -> float:
    y0, x0, y1, x1 = _box(mask)
    return float(max(y1 - y0, x1 - x0))


def _distances(edges: np.ndarray) -> np.ndarray:
    """(B, S, S) float32 Euclidean distance to the nearest edge pixel, capped at TAU (TAU
    everywhere for an image without edges). One distance transform for the batch: the images
    stacked with ``ceil(TAU)`` edge-free rows between them, so that an edge of another image
    lies more than TAU away and the cap hides it (the exact transform's values are the
    distances themselves: the same as one transform an image)."""
    B, S, T = edges.shape
    if not edges.any():
        return np.full(edges.shape, TAU, np.float32)
    gap = int(np.ceil(TAU))
    stack = np.ones((B, S + gap, T), np.uint8)
    stack[:, :S] = ~edges
    d = cv2.distanceTransform(stack.reshape(B * (S + gap), T), cv2.DIST_L2,
                              cv2.DIST_MASK_PRECISE).reshape(B, S + gap, T)[:, :S]
    return np.minimum(d, np.float32(TAU))


def query_hog_distance(query: Cues, db: np.ndarray) -> np.ndarray:
    """(N,) float64: half the squared distance of the photo's unit HOG row to each unit row of
    ``db`` (N, D), over ``query.hog_dims`` alone when the photo does not show everything (each
    side renormalised there)."""
    q, rows = query.hog[0], np.asarray(db)
    if query.hog_dims is not None:
        q, rows = q[query.hog_dims], rows[:, query.hog_dims]
    return 0.5 * hog_distance(q, rows)


def hog_distance(q: np.ndarray, db: np.ndarray) -> np.ndarray:
    """(N,) float64 squared L2 distance of the unit row of ``q`` (D,) to each unit row of ``db``
    (zero rows stay zero: distance 1 to any unit row)."""
    qn, q_nz = unit_rows(np.asarray(q)[None])
    dn, d_nz = unit_rows(db)
    return q_nz[0] + d_nz - 2.0 * (dn @ qn[0])


def _chamfer(query: Cues, views: Cues) -> np.ndarray:
    qe = query.edges[0].ravel()
    ve = views.edges.reshape(len(views), -1)
    if query.shown is not None:                      # render edges where the photo shows
        ve = ve & query.shown[0].ravel()
    n_q = int(qe.sum())
    n_v = ve.sum(1)
    # photo edges -> nearest render edge; render edges -> nearest photo edge
    a = views.dist.reshape(len(views), -1)[:, qe].astype(np.float64).sum(1) / max(n_q, 1)
    b = (ve @ query.dist[0].ravel().astype(np.float64)) / np.maximum(n_v, 1)
    a = np.where(n_q > 0, a, TAU)
    b = np.where(n_v > 0, b, TAU)
    return (a + b) / (2.0 * TAU)


def _region(query: Cues, views: Cues) -> np.ndarray:
    c = query.colours[0].reshape(-1, 3).astype(np.float64)
    labels = views.labels.reshape(len(views), -1)
    if query.shown is not None:
        keep = query.shown[0].ravel()
        c, labels = c[keep], labels[:, keep]
    total = float(((c - c.mean(0)) ** 2).sum())
    if total <= 0:
        return np.zeros(len(views))
    explained = _explained(c, labels.astype(np.int64))
    sq = float((c * c).sum())
    return np.clip((sq - explained) / total, 0.0, None)


def _explained(c: np.ndarray, lab: np.ndarray) -> np.ndarray:
    """(V,) float64 sum over the regions of (sum of colours)^2 / count, channels summed: the
    between-region part of the sum of squares of the colours ``c`` (N, 3) float64 partitioned
    by each row of ``lab`` (V, N) int64 (ids >= 0)."""
    V = len(lab)
    n_lab = int(lab.max()) + 1
    idx = (lab + n_lab * np.arange(V)[:, None]).ravel()
    count = np.bincount(idx, minlength=V * n_lab).reshape(V, n_lab)
    explained = np.zeros(V)
    for k in range(3):
        ch = np.tile(c[:, k], V)
        s = np.bincount(idx, weights=ch, minlength=V * n_lab).reshape(V, n_lab)
        explained += np.divide(s * s, count, out=np.zeros_like(s), where=count > 0).sum(1)
    return explained
