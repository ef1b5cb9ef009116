"""Material -> part classification from rendered material maps and part masks (UrbanCAD, IoU rule).

``classify_parts(mesh, views, masks)`` gives every material of ``mesh`` one part of
``PART_NAMES`` (or ``'unseen'``). Units: pixels; scores are fractions in [0, 1].

One OpenCL launch (``ucad_cl/kernels/parts.cl``) builds, for every view, the joint histogram
``n[v, m, p] = |material m ∩ part p|`` plus ``|m|`` (and ``|p|`` as a column sum), on the full
material maps and on their core pixels (both batched in the same launch). For a material m
visible in view v:

* ``score = |m ∩ p| / |m|`` (the paper's part score), ``iou = |m ∩ p| / |m ∪ p|``.
* Paper's rule (``best-view``): the view where m is visible with the highest mean mask confidence
  (mean over parts with a non-empty mask); part = argmax score if > ``threshold``.
* Our rule (``vote``): robust to mask boundaries that are off by a few pixels. Each view where m
  is visible elects one part: the highest score counted on m's *core* pixels (pixels farther than
  ``core_radius`` px from any other id, see ``core_ids``; all pixels when m has no core in any
  view), ties -> higher IoU (the more specific mask: a lamp inside a slightly dilated body mask
  goes to the lamp mask), then PART_NAMES order. A view's choice counts only if its score
  > ``threshold``; it weighs ``conf_v * |m|_v`` (``conf_v`` = the view's mean mask confidence).
  Part = most weight; equal weights -> the best-view part if among them, then PART_NAMES order.
* Final label: the vote when any view voted, else the best-view label when it passes.
  ``decision`` = ``'best-view'`` when the paper's rule gives the same label (it decided, the vote
  agrees), ``'vote'`` when only the vote decided or the two disagree (the vote wins). ``score``,
  ``iou`` and ``view`` are those of the deciding view (for ``'vote'``, the heaviest view voting
  for the part), counted on all pixels.
* Leftovers (no rule passes): small ones (at most ``merge_max_fraction`` of all visible material
  pixels) whose image neighbours are mostly body merge into body (``'merged-body'``) unless
  ``priors`` names another part for them (``'prior'``); the rest become ``other``
  (``'below-threshold'``); their score/iou/view describe the best candidate in the best view.
  Materials seen in fewer than ``min_pixels`` pixels (all views together) are ``'unseen'``.
* Mirror pairs (left/right across the plane of symmetry, see ``symmetric_pairs``) get one label,
  the more confident decision of the two; the one that changed gets ``'symmetric'``.
* Masks from a per-material labeller (``masks.labels``, see ``ucad_cl.labeller``): a material
  with fewer than ``min_pixels`` pixels in the views but at least that many in the layer behind
  glass takes the labeller's part (``'behind-glass'``, pixels = that layer's); one with neither
  takes a part from its geometry (``'never-visible'``: inside a wheel -> rim, under the floor
  -> other, else interior; pixels 0), so only the other segmenters leave ``'unseen'``
  rows; in a mirror pair it ranks as unseen (the seen twin's label wins, the flag stays);
  every row reports
  the labeller's probability of its final part (``prob``) and a shared material's split into
  component groups (``split``).

Tie rules: best-view: equal scores -> the part earlier in ``PART_NAMES``, equal view confidences ->
the lower view index; vote: as above; pairs: equal confidence -> the lower material index keeps
its label. The histogram is integer counts, so results are bit-identical run to run.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from .abi import MAX_PARTS, PART_HIST_PARAMS
from .runtime import Runtime, get_runtime
from .artifacts import PART_NAMES, Mesh, MaterialPart, PartMasks, PartTable, ViewSet, pack_masks

PIXELS_PER_ITEM = 1024      # contiguous pixels per work-item; measured in bench/parts.py
LOCAL_SIZE = 16             # work-items per group; measured in bench/parts.py


def classify_parts(mesh: Mesh, views: ViewSet, masks: PartMasks, *, threshold: float = 0.5,
                   min_pixels: int = 4, merge_max_fraction: float = 0.02,
                   priors: Mapping[int, str] | None = None, core_radius: int = 2,
                   symmetry: bool = True, runtime: Runtime | None = None) -> PartTable:
    """One ``MaterialPart`` row per material of ``mesh`` (material index order); the histogram
    runs on ``runtime`` (default ``get_runtime()``)."""
    parts = _validate(mesh, views, masks)
    n_mat = len(mesh.materials)
    V = views.mat_id.shape[0]
    core = core_ids(views.mat_id, core_radius)
    # full and core maps in one launch, both against the packed masks
    both = part_histogram([views.mat_id, core], bits=[masks.bits, masks.bits],
                          n_parts=len(parts), n_ids=n_mat + 1, runtime=runtime)
    hist, core_hist = both[:V].astype(np.int64), both[V:].astype(np.int64)
    conf = np.asarray(masks.confidence, np.float64)
    nonempty = masks.nonempty()
    view_conf = np.where(nonempty.any(axis=1),
                         (conf * nonempty).sum(axis=1) / np.maximum(nonempty.sum(axis=1), 1), 0.0)
    part_area = hist[:, :, 1:].sum(axis=1)  # (V, P) |part| per view, background included
    order = _part_order(parts)              # column order that realises the PART_NAMES tie rule
    rows = [_decide(m, mesh.materials[m].name, hist[:, m + 1], core_hist[:, m + 1], view_conf,
                    part_area, parts, order, threshold, min_pixels) for m in range(n_mat)]
    labels = getattr(masks, "labels", None)
    if labels is not None:
        _behind_glass(rows, labels, min_pixels)
        _never_visible(rows, labels)
    total = max(int(hist[:, 1:, 0].sum()), 1)
    _merge_leftovers(rows, views.mat_id, merge_max_fraction * total, priors or {})
    if symmetry:
        for a, b in symmetric_pairs(mesh):
            _unify_pair(rows, a, b)
    if labels is not None:
        for r in rows:
            if r.part in PART_NAMES:
                r.prob = float(labels.prob[r.material, PART_NAMES.index(r.part)])
            r.split = labels.splits.get(r.material)
    return PartTable(rows=[MaterialPart(r.material, r.name, r.part, r.score, r.iou, r.view,
                                        r.decision, r.pixels, r.prob, r.split) for r in rows])


def _behind_glass(rows, labels, min_pixels) -> None:
    """Unseen materials seen through glass take the labeller's part (decision 'behind-glass')."""
    for r in rows:
        behind = int(labels.behind_pixels[r.material])
        if r.decision == "unseen" and behind >= max(min_pixels, 1):
            r.part = PART_NAMES[int(labels.part[r.material])]
            r.decision, r.pixels = "behind-glass", behind


def _never_visible(rows, labels) -> None:
    """Materials still unseen (no pixel in the views nor behind glass) take their part from
    geometry (``labels.hidden_part``, ``labeller.never_visible_part``: inside a wheel -> rim,
    under the floor -> other, else interior; the labeller's argmax when absent): decision
    'never-visible', pixels 0."""
    hidden = labels.part if getattr(labels, "hidden_part", None) is None else labels.hidden_part
    for r in rows:
        if r.decision == "unseen":
            r.part = PART_NAMES[int(hidden[r.material])]
            r.decision = "never-visible"


def part_histogram(mat_id: np.ndarray | Sequence[np.ndarray], masks: np.ndarray | None = None,
                   *, bits: np.ndarray | Sequence[np.ndarray] | None = None,
                   n_parts: int | None = None, n_ids: int | None = None,
                   local_size: int = LOCAL_SIZE, pixels_per_item: int = PIXELS_PER_ITEM,
                   use_local: bool | None = None, runtime: Runtime | None = None,
                   stats: dict | None = None) -> np.ndarray:
    """(V, n_ids, 1 + P) uint32: column 0 = |id| per view, column 1 + p = |id ∩ part p|, counted
    on ``runtime`` (default ``get_runtime()``); ``stats``, when given, receives "histogram": the
    seconds of the kernels and the copy back.

    mat_id: (V, H, W) uint16 material maps, or a list of such arrays (same H, W) counted as one
    stack of V views (stacked in device memory: no host-side concatenation). The part masks of
    those V views, one of: ``masks`` (V, P, H, W) bool, or ``bits`` with ``n_parts`` = P: packed
    (V, H, W) uint16 masks (bit p set = pixel in mask p, see ``PartMasks``; no bit >= P may be
    set), or a list of those stacked like ``mat_id``. ``n_ids`` defaults to max id + 1.
    |part p| in view v is ``hist[v, :, 1 + p].sum()`` (the background row 0 included).
    """
    import pyopencl as cl

    mats = _view_stack(mat_id, "mat_id")
    V, H, W = sum(a.shape[0] for a in mats), *mats[0].shape[1:]
    if (masks is None) == (bits is None):
        raise ValueError("give the part masks either as masks or as bits")
    if masks is not None:
        masks = np.asarray(masks)
        if masks.ndim != 4 or masks.dtype != np.bool_:
            raise ValueError(f"masks must be a (V, P, H, W) bool array, got {masks.dtype} "
                             f"{masks.shape}")
        P = masks.shape[1]
        if masks.shape != (V, P, H, W):
            raise ValueError(f"masks shape {masks.shape} does not match the views "
                             f"{(V, P, H, W)}")
    else:
        if n_parts is None:
            raise ValueError("bits need n_parts")
        P = int(n_parts)
        bits = _view_stack(bits, "bits")
        shape = (sum(b.shape[0] for b in bits), *bits[0].shape[1:])
        if shape != (V, H, W):
            raise ValueError(f"bits shape {shape} does not match the views {(V, H, W)}")
    if not 1 <= P <= MAX_PARTS:
        raise ValueError(f"need 1..{MAX_PARTS} part masks, got {P}")
    top = max((int(a.max()) for a in mats if a.size), default=0) + 1
    n_ids = top if n_ids is None else int(n_ids)
    if n_ids < top:
        raise ValueError(f"material id {top - 1} present but n_ids={n_ids}")
    if V == 0 or H * W == 0:
        return np.zeros((V, n_ids, 1 + P), np.uint32)
    if masks is not None:
        bits = [pack_masks(masks)]
    elif P < MAX_PARTS and max(int(b.max()) for b in bits if b.size) >> P:
        # the kernel would count a bit >= P into the next id's row
        raise ValueError(f"bits has bits set beyond the {P} parts")
    rt = runtime or get_runtime()
    n_pix = H * W
    items = -(-n_pix // pixels_per_item)
    gx = -(-items // local_size) * local_size
    prm = np.array([(n_pix, V, n_ids, P, pixels_per_item, 0)], PART_HIST_PARAMS)
    table_bytes = 4 * n_ids * (1 + P)
    if use_local is None:
        use_local = table_bytes <= rt.device.local_mem_size // 2
    # reused device buffers (runtime scratch): no allocation and no first touch per call
    q = rt.queue
    d_mat = rt.scratch("parts.mat_id", 2 * V * n_pix)
    d_bits = rt.scratch("parts.bits", 2 * V * n_pix)
    for d, chunks in ((d_mat, mats), (d_bits, bits)):
        off = 0
        for a in chunks:
            if a.size:
                cl.enqueue_copy(q, d, np.ascontiguousarray(a), dst_offset=off)
            off += a.nbytes
    out = np.empty((V, n_ids, 1 + P), np.uint32)
    d_hist = rt.scratch("parts.hist", out.nbytes)
    cl.enqueue_fill_buffer(q, d_hist, np.uint32(0), 0, out.nbytes)
    t0 = time.perf_counter()
    if use_local:
        knl = rt.kernel("parts", "material_part_histogram")
        knl(q, (gx, V), (local_size, 1), d_mat, d_bits, prm, d_hist,
            cl.LocalMemory(table_bytes))
    else:
        knl = rt.kernel("parts", "material_part_histogram_global")
        knl(q, (gx, V), (local_size, 1), d_mat, d_bits, prm, d_hist)
    cl.enqueue_copy(q, out, d_hist)
    q.finish()
    if stats is not None:
        stats["histogram"] = time.perf_counter() - t0
    return out


def _view_stack(x, name: str) -> list[np.ndarray]:
    """``x`` as a non-empty list of (V_i, H, W) uint16 arrays of one H, W (the view stack)."""
    arrays = [np.asarray(a) for a in x] if isinstance(x, (list, tuple)) else [np.asarray(x)]
    if not arrays:
        raise ValueError(f"{name}: empty list of views")
    for a in arrays:
        if a.ndim != 3 or a.dtype != np.uint16:
            raise ValueError(f"{name} must be a (V, H, W) uint16 array, got {a.dtype} {a.shape}")
        if a.shape[1:] != arrays[0].shape[1:]:
            raise ValueError(f"{name}: views of sizes {a.shape[1:]} and {arrays[0].shape[1:]}")
    return arrays



def symmetric_pairs(mesh: Mesh, *, tol: float = 0.01, min_match: float = 0.8,
                    plane_match: float = 0.5, max_samples: int = 2000) -> list[tuple[int, int]]:
    """Mirror material pairs (a < b) across the model's plane of symmetry.

    The plane is the canonical bounding-box mid-plane of the narrower horizontal axis (X or Z; the
    width axis), accepted when at least ``plane_match`` of all (sampled) vertices reflect onto a
    vertex within ``tol`` (canonical units; bbox diagonal 1). Materials a != b pair when at least
    ``min_match`` of each one's vertices reflect onto the other's and a matches itself less well
    than it matches b. Each material pairs at most once (best match; ties -> lower index).
    """
    from scipy.spatial import cKDTree

    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces)
    if v.shape[0] == 0 or f.shape[0] == 0 or len(mesh.materials) < 2:
        return []
    lo, hi = v.min(axis=0), v.max(axis=0)
    axis = 0 if (hi[0] - lo[0]) <= (hi[2] - lo[2]) else 2
    mid = 0.5 * (lo[axis] + hi[axis])

    def reflect(x):
        y = x.copy()
        y[:, axis] = 2.0 * mid - y[:, axis]
        return y

    all_s = _sample(np.unique(f), max_samples * 4)
    tree = cKDTree(v[all_s])
    d, _ = tree.query(reflect(v[all_s]), distance_upper_bound=tol)
    if np.mean(np.isfinite(d)) < plane_match:
        return []
    n_mat = len(mesh.materials)
    fm = np.asarray(mesh.face_material)
    order = np.argsort(fm, kind="stable")                 # faces grouped by material
    bounds = np.searchsorted(fm[order], np.arange(n_mat + 1))
    pts, refl, trees = {}, {}, {}
    for m in range(n_mat):
        if bounds[m + 1] > bounds[m]:
            idx = np.unique(f[order[bounds[m]:bounds[m + 1]]])
            pts[m] = v[_sample(idx, max_samples)]
            refl[m] = reflect(pts[m])

    def match(a, b):
        if b not in trees:
            trees[b] = cKDTree(pts[b])
        d, _ = trees[b].query(refl[a], distance_upper_bound=tol)
        return float(np.mean(np.isfinite(d)))

    # a pair needs >= min_match of a's reflected points within tol of b's points, so a's reflected
    # bounding box must meet b's box grown by tol: a necessary test that skips most KD queries
    mats = sorted(pts)
    lo = np.array([pts[m].min(axis=0) for m in mats])
    hi = np.array([pts[m].max(axis=0) for m in mats])
    rlo, rhi = lo.copy(), hi.copy()                   # bounding boxes of the reflections
    rlo[:, axis], rhi[:, axis] = 2.0 * mid - hi[:, axis], 2.0 * mid - lo[:, axis]
    # all candidate pairs at once: a's reflected box meets b's box grown by tol
    meets = (np.all(rlo[:, None, :] <= hi[None, :, :] + tol, axis=2)
             & np.all(rhi[:, None, :] >= lo[None, :, :] - tol, axis=2))
    grow = tol * (1.0 + 1e-6)                         # looser than tol: stays a necessary test

    def shares_inside(x, boxes):
        """For each box index of ``boxes``, the share of material ``mats[x]``'s reflected points
        inside that material's box grown by tol. A share >= min_match is necessary for
        match(a, b) >= min_match (a point within tol of b's points is in that box); ~5x
        cheaper than the KD query it saves. One array operation per material."""
        r = refl[mats[x]][:, None, :]
        inside = np.all((r >= lo[boxes] - grow) & (r <= hi[boxes] + grow), axis=2)
        return np.count_nonzero(inside, axis=0) / inside.shape[0]

    ia_all, ib_all = np.nonzero(np.triu(meets, k=1))
    need: dict[int, list[int]] = {}                   # material -> box indices to test
    for x, y in zip(np.concatenate([ia_all, ib_all]), np.concatenate([ib_all, ia_all])):
        need.setdefault(int(x), [int(x)]).append(int(y))  # own box too: bounds the self match
    share: dict[tuple[int, int], float] = {}          # (material, box) -> share inside
    for x, ys in need.items():
        ys = sorted(set(ys))
        share.update(((x, y), float(s)) for y, s in zip(ys, shares_inside(x, np.array(ys))))

    self_match: dict[int, float] = {}

    def beats_self(i, m, x):
        """x > match(m, m) (material m = mats[i]); the KD query is skipped when the share
        of m's reflected points in its own grown box, an upper bound of that match, is < x."""
        if share[i, i] < x:
            return True
        if m not in self_match:
            self_match[m] = match(m, m)
        return x > self_match[m]

    cands = []
    for ia, ib in zip(ia_all.tolist(), ib_all.tolist()):
        a, b = mats[ia], mats[ib]
        if not (share[ia, ib] >= min_match and share[ib, ia] >= min_match):
            continue
        ab = match(a, b)
        if ab < min_match:
            continue
        ba = match(b, a)
        if ba >= min_match and beats_self(ia, a, ab) and beats_self(ib, b, ba):
            cands.append((-(ab + ba), a, b))
    used, pairs = set(), []
    for _, a, b in sorted(cands):
        if a not in used and b not in used:
            used.update((a, b))
            pairs.append((a, b))
    return sorted(pairs)


# ----------------------------------------------------------------------------------------------
def _validate(mesh: Mesh, views: ViewSet, masks: PartMasks) -> list[str]:
    """Checks shapes and dtypes (of whichever form of the masks ``masks`` holds: no unpacking)."""
    V, H, W = views.mat_id.shape
    if not masks.packed:
        m = np.asarray(masks.masks)
        if m.ndim != 4 or m.dtype != np.bool_:
            raise ValueError(f"PartMasks.masks must be (V, P, H, W) bool, got {m.dtype} "
                             f"{m.shape}")
        if len(masks.parts) != m.shape[1]:
            raise ValueError(f"PartMasks has {len(masks.parts)} part names for {m.shape[1]} "
                             "masks")
    else:
        b = np.asarray(masks.bits)
        if b.ndim != 3 or b.dtype != np.uint16:
            raise ValueError(f"PartMasks.bits must be (V, H, W) uint16, got {b.dtype} {b.shape}")
        if not 1 <= len(masks.parts) <= MAX_PARTS:
            raise ValueError(f"PartMasks.bits holds 1..{MAX_PARTS} parts, got "
                             f"{len(masks.parts)} part names")
    shape = masks.shape
    if shape[0] != V or shape[2:] != (H, W):
        raise ValueError(f"PartMasks.masks shape {shape} does not match the views "
                         f"({V}, P, {H}, {W})")
    unknown = [p for p in masks.parts if p not in PART_NAMES]
    if unknown:
        raise ValueError(f"unknown part names {unknown}; expected names from {PART_NAMES}")
    if len(set(masks.parts)) != len(masks.parts):
        raise ValueError(f"duplicate part names in {masks.parts}")
    c = np.asarray(masks.confidence)
    if c.shape != shape[:2]:
        raise ValueError(f"PartMasks.confidence must be {shape[:2]}, got {c.shape}")
    if not np.all(np.isfinite(c)) or c.min(initial=0) < 0 or c.max(initial=0) > 1:
        raise ValueError("PartMasks.confidence must be finite and inside [0, 1]")
    top = int(views.mat_id.max()) if views.mat_id.size else 0
    if top > len(mesh.materials):
        raise ValueError(f"material id {top} in the views but the mesh has "
                         f"{len(mesh.materials)} materials")
    return list(masks.parts)


def _part_order(parts: list[str]) -> np.ndarray:
    """Column indices in PART_NAMES rank order: argmax over them takes the earliest part on ties."""
    return np.array(sorted(range(len(parts)), key=lambda i: PART_NAMES.index(parts[i])), int)


def _decide(m, name, h, hc, view_conf, part_area, parts, order, threshold, min_pixels) -> "_Row":
    """Decision for one material from its (V, 1 + P) histogram rows (all pixels, core pixels)."""
    area = h[:, 0]
    pixels = int(area.sum())
    if pixels < max(min_pixels, 1):
        return _Row(m, name, "unseen", 0.0, 0.0, -1, "unseen", pixels)
    seen = np.flatnonzero(area > 0)
    a = area[seen].astype(np.float64)
    joint = h[seen][:, 1:].astype(np.float64)
    score = joint / a[:, None]                                   # (S, P)
    iou = joint / (a[:, None] + part_area[seen] - joint)
    # paper: the view of highest mean confidence (ties -> lower view index: argmax takes the
    # first), part = argmax score (ties -> PART_NAMES order via ``order``)
    bv_i = int(np.argmax(view_conf[seen]))
    bv_part = order[int(np.argmax(score[bv_i, order]))]
    bv_ok = score[bv_i, bv_part] > threshold
    # ours: per view, the winner by (score on core pixels when the material has any, IoU,
    # PART_NAMES order) votes with weight conf_v * |m|_v if its score > threshold
    src = hc if hc[:, 0].sum() > 0 else h
    sa = src[seen, 0].astype(np.float64)
    vs = np.divide(src[seen][:, 1:], sa[:, None], out=np.zeros_like(score), where=sa[:, None] > 0)
    w = view_conf[seen] * sa
    if w.sum() <= 0:
        w = sa.copy()                                            # no confidences: area only
    # every view's winner at once: the largest vs, then the largest IoU among those, then the
    # first in ``order`` (comparisons only, no arithmetic: the per-view lexsort's choice)
    vs_o, iou_o = vs[:, order], iou[:, order]
    tied = vs_o == vs_o.max(axis=1, keepdims=True)
    iou_t = np.where(tied, iou_o, -np.inf)
    tied &= iou_t == iou_t.max(axis=1, keepdims=True)
    best = order[np.argmax(tied, axis=1)]
    rows_i = np.arange(len(seen))
    votes = (vs[rows_i, best] > threshold) & (w > 0)
    winner = np.where(votes, best, -1)
    tot = np.zeros(len(parts))
    np.add.at(tot, best[votes], w[votes])           # in view order, as a loop adds them
    vt_ok = bool(tot.max() > 0)
    if vt_ok:
        top = np.flatnonzero(tot == tot.max())
        vt_part = bv_part if bv_part in top else [c for c in order if c in top][0]
        part = vt_part
        decision = "best-view" if (bv_ok and bv_part == vt_part) else "vote"
        i = bv_i if decision == "best-view" else int(np.argmax(w * (winner == part)))
        strength = float(tot[part] / w.sum())
    elif bv_ok:
        part, decision, i, strength = bv_part, "best-view", bv_i, 0.0
    else:
        part, decision, i, strength = bv_part, "below-threshold", bv_i, 0.0
    return _Row(m, name, parts[part] if decision != "below-threshold" else "other",
                float(score[i, part]), float(iou[i, part]), int(seen[i]), decision, pixels,
                strength=strength)


def core_ids(mat_id: np.ndarray, radius: int) -> np.ndarray:
    """Material maps with every pixel closer than ``radius`` + 1 px (square window) to another id
    set to background: the pixels a mask boundary error of up to ``radius`` px cannot reach."""
    import cv2

    if radius <= 0:
        return mat_id.copy()
    k = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    out = mat_id.copy()
    for v in range(mat_id.shape[0]):
        m = mat_id[v]
        out[v][(cv2.erode(m, k, borderType=cv2.BORDER_REPLICATE) != m)
               | (cv2.dilate(m, k, borderType=cv2.BORDER_REPLICATE) != m)] = 0
    return out


@dataclass
class _Row(MaterialPart):
    strength: float = 0.0   # vote share of the chosen part (pair unification)


def _merge_leftovers(rows, mat_id, max_pixels, priors) -> None:
    """Small unlabelled materials bordered mostly by body pixels join body (or their prior)."""
    left = [r for r in rows if r.decision == "below-threshold"]
    if not left:
        return
    n = len(rows) + 1
    adj = _adjacency(mat_id, n)
    changed = True
    while changed:
        changed = False
        body_ids = np.array([r.part == "body" and r.decision != "below-threshold" for r in rows])
        for r in left:
            if r.decision != "below-threshold" or r.pixels > max_pixels:
                continue
            nb = adj[r.material + 1, 1:]
            nb = np.delete(nb, r.material)
            fg = nb.sum()
            if fg == 0:
                continue
            body = np.delete(adj[r.material + 1, 1:] * body_ids, r.material).sum()
            if body / fg >= 0.5:
                prior = priors.get(r.material)
                if prior and prior != "body":
                    r.part, r.decision = prior, "prior"
                else:
                    r.part, r.decision = "body", "merged-body"
                changed = True


def _adjacency(mat_id: np.ndarray, n: int) -> np.ndarray:
    """(n, n) counts of 4-neighbour pixel pairs with different ids, summed over views."""
    adj = np.zeros(n * n, np.int64)
    for a, b in ((mat_id[:, :, 1:], mat_id[:, :, :-1]), (mat_id[:, 1:, :], mat_id[:, :-1, :])):
        d = a != b
        x, y = a[d].astype(np.int64), b[d].astype(np.int64)
        adj += np.bincount(x * n + y, minlength=n * n) + np.bincount(y * n + x, minlength=n * n)
    return adj.reshape(n, n)


def _unify_pair(rows, a, b) -> None:
    ra, rb = rows[a], rows[b]
    if ra.part == rb.part:
        return
    rank = {"unseen": 0, "never-visible": 0, "below-threshold": 1}
    ka = (rank.get(ra.decision, 2), ra.strength)
    kb = (rank.get(rb.decision, 2), rb.strength)
    src, dst = (ra, rb) if ka >= kb else (rb, ra)          # equal -> lower index (a) wins
    dst.part = src.part
    if dst.decision != "never-visible":                    # that flag stays: no pixel at all
        dst.decision = "symmetric"


def _sample(idx: np.ndarray, k: int) -> np.ndarray:
    """At most k entries of sorted ``idx``, evenly strided (deterministic)."""
    if idx.size <= k:
        return idx
    return idx[np.linspace(0, idx.size - 1, k).round().astype(np.int64)]
