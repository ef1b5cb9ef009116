"""Pose search: which camera around a mesh best explains a reference photo of it.

``estimate_pose(image, mesh, box=...)`` follows UrbanCAD: crop the vehicle in the reference and in
renders of the mesh on a camera ring, resize both to one resolution, compute features
(``ucad_cl.features``), take the views with the smallest L2 distance. Then coarse-to-fine: around
the best coarse views, extra views are rendered on demand at a finer azimuth step (and at
elevations half-way to the neighbouring coarse ones), so catalogues need not store fine rings.

Conventions (``ucad_cl/artifacts.py``): azimuth/elevation in degrees (azimuth 0 looks from +X, grows
counter-clockwise seen from +Y), distance in canonical units (bbox diagonal 1). Azimuths are
reported in [0, 360).

* score: squared L2 distance between L2-normalised feature rows (0 best, 4 worst; an all-zero
  row, e.g. a textureless crop, is at distance |other|^2). Computed in float64.
* Ties: equal scores are ordered by the lower view index (coarse views before fine ones, in
  the order they were rendered); ``rank_features`` documents the rule, tests pin it.
* Front/back ambiguity: near-symmetric vehicles look alike from opposite sides. The best
  candidate at least ``FLIP_MIN_DEG`` away in azimuth from the best one is reported as the second
  candidate with ``flipped=True`` (refined like the best), instead of being hidden.
* distance: estimated from the box size, assuming the reference camera has the ring's field of
  view over its narrower image side: ``d = ring_distance * (s_render / n_render) / (s_ref /
  n_ref)`` with s the longer box side and n the narrower image side, in pixels.

``search_catalog`` is the catalogue-wide variant: one query against stored features of many
(mesh, view) rows.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .cameras import make_ring
from .features import FeatureExtractor, HogExtractor, box_mask, unit_rows, view_features
from .render import render_views
from .shade import shade_views
from .artifacts import CameraRing, Mesh

FLIP_MIN_DEG = 135.0
EXACT_ROWS = 50_000         # search_catalog ranks up to this many rows exactly on the host
PRESELECT = 64              # rows taken from the OpenCL search for the exact re-rank (k <= 64)
RENDER_BACKGROUND = (128, 128, 128)


@dataclass
class PoseCandidate:
    """One pose hypothesis. ``view``: index of the coarse-ring view it came from (its seed)."""

    azimuth: float
    elevation: float
    distance: float
    score: float
    view: int
    refined: bool = False       # found on a fine ring around the seed view
    flipped: bool = False       # ~180 deg from the best candidate (front/back ambiguity)


def estimate_pose(image: np.ndarray, mesh: Mesh, *, box: Sequence[float] | None = None,
                  mask: np.ndarray | None = None, extractor: FeatureExtractor | None = None,
                  azimuth_step: float = 10.0, elevations: Sequence[float] = (0.0, 15.0, 30.0),
                  fov_deg: float = 40.0, size: int = 128, top: int = 5, refine: bool = True,
                  fine_step: float = 2.0, seeds: int = 3,
                  coarse: "PoseRing | None" = None) -> list[PoseCandidate]:
    """Best ``top`` poses of ``mesh`` for the object in ``image`` (H, W, 3) uint8 RGB.

    The object is given by ``box`` (x0, y0, x1, y1) pixels or ``mask`` (H, W) bool. The coarse
    ring has ``azimuth_step`` and ``elevations`` (or is ``coarse``, precomputed by
    ``pose_ring``, e.g. from a catalogue; its parameters then win). Hypotheses are the ``seeds``
    best coarse views at least ``azimuth_step`` apart, plus the best flipped one (second). With
    ``refine`` each hypothesis is replaced by the best view of a fine ring around it
    (``fine_step`` within +-azimuth_step, elevations half-way to the neighbouring coarse ones)
    and the refined hypotheses are re-ranked by score. Only the ``top`` first hypotheses are
    refined (so ``top=1`` refines the best coarse view only). Output: the best candidate, the best
    one at least FLIP_MIN_DEG away (``flipped``), then others, best first, at least
    ``azimuth_step`` apart in azimuth from those already chosen.
    """
    qmask = reference_mask(image, box=box, mask=mask)
    if top < 1:
        raise ValueError(f"top={top} must be >= 1")
    if coarse is None:
        coarse = pose_ring(mesh, extractor or HogExtractor(), azimuth_step=azimuth_step,
                           elevations=elevations, fov_deg=fov_deg, size=size)
    extractor = coarse.extractor
    query = extractor.extract(np.asarray(image)[None], qmask[None]).feats[0]
    q_side = _box_side(qmask) / min(qmask.shape)
    ring = coarse.ring
    step = coarse.azimuth_step
    pool = _candidates(query, ring, coarse.feats, coarse.sides, seed=None, q_side=q_side)
    ranked = sorted(pool, key=lambda c: c.score)          # stable: ties -> lower view index
    flip = _flip_of(ranked, ranked[0])
    hyps = _distinct(ranked, seeds if refine else 1, step)
    if flip is not None and all(h.view != flip.view for h in hyps):
        hyps.insert(1, flip)
    hyps = hyps[:top]                                     # refine only what is reported
    if refine:
        el_step = _elevation_step(ring.elevation)
        fov = float(np.degrees(2 * np.arctan(0.5 * min(ring.width, ring.height) / ring.K[0, 0])))
        hyps = [_refine(query, mesh, extractor, ring, h, step, fine_step, el_step, fov, q_side)
                for h in hyps]
        hyps.sort(key=lambda c: c.score)                  # stable: ties keep the coarse order
    best = hyps[0]
    out = [best]
    flip = _flip_of(hyps + ranked, best)
    if flip is not None and top > 1:
        flip.flipped = True
        out.append(flip)
    for c in hyps + ranked:
        if len(out) >= top:
            break
        if all(_az_diff(c.azimuth, o.azimuth) >= step for o in out):
            out.append(c)
    return out


@dataclass
class PoseRing:
    """Features of a coarse ring of one mesh: what a catalogue stores for pose search."""

    ring: CameraRing
    feats: np.ndarray           # (V, D) float32
    sides: np.ndarray           # (V,) longer side of each view's object box, pixels
    extractor: FeatureExtractor
    azimuth_step: float


def pose_ring(mesh: Mesh, extractor: FeatureExtractor, *, azimuth_step: float = 10.0,
              elevations: Sequence[float] = (0.0, 15.0, 30.0), fov_deg: float = 40.0,
              size: int = 128) -> PoseRing:
    """Render, shade and describe the coarse ring of ``mesh`` once (reuse for many queries)."""
    ring = make_ring(azimuth_step, elevations, fov_deg=fov_deg, size=size)
    feats, sides = render_features(mesh, ring, extractor)
    return PoseRing(ring=ring, feats=feats, sides=sides, extractor=extractor,
                    azimuth_step=float(azimuth_step))


def reference_mask(image: np.ndarray, *, box=None, mask=None) -> np.ndarray:
    """(H, W) bool object mask of a reference image from a box or a mask (exactly one)."""
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"reference image must be (H, W, 3) uint8 RGB, got {image.shape} "
                         f"{image.dtype}")
    if (box is None) == (mask is None):
        raise ValueError("give exactly one of box=(x0, y0, x1, y1) or mask=(H, W) bool")
    if box is not None:
        return box_mask(image.shape[:2], box)
    m = np.asarray(mask)
    if m.shape != image.shape[:2]:
        raise ValueError(f"mask shape {m.shape} differs from the image's {image.shape[:2]}")
    m = m.astype(bool) if m.dtype != np.bool_ else m
    if not m.any():
        raise ValueError("mask is empty: the reference image has no object to match")
    return m


def render_features(mesh: Mesh, ring: CameraRing, extractor: FeatureExtractor,
                    **shade_kwargs) -> tuple[np.ndarray, np.ndarray]:
    """Features (V, D) of shaded renders of ``ring`` and each view's longer box side (pixels)."""
    shade_kwargs.setdefault("background", RENDER_BACKGROUND)
    views = render_views(mesh, ring)
    masks = np.isfinite(views.depth)
    empty = np.flatnonzero(~masks.any(axis=(1, 2)))
    if empty.size:
        raise ValueError(f"mesh {mesh.path!r}: nothing visible in view(s) {empty.tolist()}")
    images = shade_views(mesh, views, **shade_kwargs)
    feats = view_features(extractor, images, views).feats
    sides = np.array([_box_side(m) for m in masks], np.float64)
    return feats, sides


def rank_features(query: np.ndarray, db: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All rows of ``db`` (N, D) ordered by squared L2 distance to ``query`` (D,).

    Both sides are L2-normalised first (float64, after dividing by the largest magnitude, so huge
    values rank like small ones); the distance is ``[q != 0] + [d != 0] - 2 q.d`` with the
    normalised rows, so an all-zero row is at distance 1 from any unit row and identical rows get
    identical distances (same row-wise sum). Returns (order (N,) int64, sq_dists (N,) float64 in
    that order). Ties go to the lower row index.
    """
    q = np.asarray(query)
    db = np.asarray(db)
    if db.ndim != 2 or q.shape != (db.shape[1],):
        raise ValueError(f"query must be (D,) and db (N, D); got {q.shape} and {db.shape}")
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(db))):
        raise ValueError("features contain NaN or infinity")
    qn, q_nz = unit_rows(q[None])
    dn, d_nz = unit_rows(db)
    d = q_nz[0] + d_nz - 2.0 * (dn * qn).sum(axis=1)
    order = np.lexsort((np.arange(d.size), d))
    return order, d[order]


@dataclass
class CatalogMatch:
    """One catalogue row matched by ``search_catalog``."""

    row: int
    mesh: int
    view: int
    azimuth: float
    elevation: float
    score: float


def search_catalog(query: np.ndarray, feats: np.ndarray, mesh_ids: np.ndarray,
                   views: np.ndarray, azimuth: np.ndarray, elevation: np.ndarray,
                   top: int = 5, *, index=None) -> list[CatalogMatch]:
    """Best ``top`` (mesh, view) rows of a feature database for one query feature (D,).

    ``feats`` (N, D) L2-normalised rows with per-row ``mesh_ids``, ``views``, ``azimuth``,
    ``elevation`` (N,). Up to ``EXACT_ROWS`` rows (and no ``index``) the ranking is exact in
    float64 (``rank_features``). Larger databases, or a given ``index`` (a
    ``ucad_cl.search.FeatureIndex`` over ``feats`` without ids, built once for many queries),
    take the ``PRESELECT`` nearest rows from the OpenCL float32 search and re-rank those exactly;
    ties go to the lower row either way. Hook for the catalogue: pass its stored arrays.
    """
    feats = np.asarray(feats)
    n = feats.shape[0] if feats.ndim == 2 else -1
    cols = [np.asarray(a) for a in (mesh_ids, views, azimuth, elevation)]
    if any(c.shape != (n,) for c in cols):
        raise ValueError(f"mesh_ids, views, azimuth, elevation must all be ({n},)")
    if not 1 <= top <= n:
        raise ValueError(f"top={top} must be in 1..{n} (database rows)")
    if index is None and n <= EXACT_ROWS:
        rows, d = rank_features(query, feats)
    else:
        from .search import search

        k = min(n, max(PRESELECT, top))
        qn = unit_rows(np.asarray(query)[None])[0].astype(np.float32)
        cand = (index.search(qn, k) if index is not None else search(qn[None], feats, k))[0][0]
        order, d_sorted = rank_features(query, feats[cand])
        d = np.empty_like(d_sorted)
        d[order] = d_sorted
        o = np.lexsort((cand, d))
        rows, d = cand[o], d[o]
    return [CatalogMatch(row=int(r), mesh=int(cols[0][r]), view=int(cols[1][r]),
                         azimuth=float(cols[2][r]), elevation=float(cols[3][r]),
                         score=float(s)) for r, s in zip(rows[:top], d[:top])]


# ----------------------------------------------------------------------------- helpers

def _refine(query, mesh, extractor, ring, seed, step, fine_step, el_step, fov, q_side):
    """Best of the seed and a fine ring around it (+-step azimuth, +-el_step/2 elevation)."""
    azs = seed.azimuth + np.arange(-step, step + 1e-9, fine_step)
    els = [e for e in (seed.elevation - el_step / 2, seed.elevation, seed.elevation + el_step / 2)
           if abs(e) < 89.0]
    fine = make_ring(azimuths=azs, elevations=els, fov_deg=fov,
                     size=(ring.width, ring.height), distance=ring.distance)
    feats, sides = render_features(mesh, fine, extractor)
    cands = [seed] + _candidates(query, fine, feats, sides, seed=seed.view, q_side=q_side)
    return min(cands, key=lambda c: c.score)              # first minimum: the seed wins ties


def _candidates(query, ring, feats, sides, *, seed, q_side) -> list[PoseCandidate]:
    order, d = rank_features(query, feats)
    score = np.empty_like(d)
    score[order] = d
    n_side = min(ring.width, ring.height)
    return [PoseCandidate(azimuth=float(ring.azimuth[v] % 360.0),
                          elevation=float(ring.elevation[v]),
                          distance=float(ring.distance * (sides[v] / n_side) / q_side),
                          score=float(score[v]), view=v if seed is None else int(seed),
                          refined=seed is not None)
            for v in range(ring.n_views)]


def _az_diff(a: float, b: float) -> float:
    d = abs(a - b) % 360.0
    return min(d, 360.0 - d)


def _flip_of(ranked: list[PoseCandidate], best: PoseCandidate) -> PoseCandidate | None:
    return next((c for c in ranked if _az_diff(c.azimuth, best.azimuth) >= FLIP_MIN_DEG), None)


def _distinct(ranked: list[PoseCandidate], n: int, min_sep: float) -> list[PoseCandidate]:
    out: list[PoseCandidate] = []
    for c in ranked:
        if len(out) >= n:
            break
        if all(_az_diff(c.azimuth, o.azimuth) >= min_sep for o in out):
            out.append(c)
    return out


def _elevation_step(elevations: Sequence[float]) -> float:
    e = np.unique(np.asarray(elevations, np.float64))
    return float(np.min(np.diff(e))) if e.size > 1 else 10.0


def _box_side(mask: np.ndarray) -> float:
    """Side of the mask's bounding box in pixels (the longer one); 0 for an empty mask."""
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return 0.0
    return float(max(rows[-1] - rows[0] + 1, cols[-1] - cols[0] + 1))
