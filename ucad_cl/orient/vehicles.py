"""Several vehicles in one file: apart (separate clusters of surface, ``largest_vehicle``),
side by side (nothing crosses the mirror plane) or on top of each other (node groups that
each look like a whole vehicle); the estimate flags ``multiple_vehicles``.
"""
from __future__ import annotations

import numpy as np

from .geometry import Context, Samples
from .names import NameTable


def largest_vehicle(S: Samples, major: np.ndarray) -> Samples | None:
    """Several vehicles apart in one file: the samples of the largest one, or None. The
    area samples are clustered on voxels of 1/20 of their extent along their principal
    axis ``major`` (touching voxels, diagonals too, join); two or more clusters each holding
    15 % of the samples and spanning 30 % of that extent are vehicles. The largest (most
    samples; tie: the one holding the earliest
    sample, an order that does not depend on the pose) keeps its area samples and the face
    samples in its voxels."""
    from scipy import ndimage

    p = S.points
    lo = p.min(axis=0)
    cell = float(np.ptp(p @ major)) / 20.0
    if not cell > 0.0:
        return None
    i = np.floor((p - lo) / cell).astype(np.intp)
    dims = i.max(axis=0) + 1
    if np.prod(dims) > 4_000_000:
        return None
    g = np.zeros(dims, bool)
    g[i[:, 0], i[:, 1], i[:, 2]] = True
    lab, k = ndimage.label(g, structure=np.ones((3, 3, 3)))
    if k < 2:
        return None
    who = lab[i[:, 0], i[:, 1], i[:, 2]]
    cnt = np.bincount(who, minlength=k + 1)
    big = [c for c in range(1, k + 1) if cnt[c] >= 0.15 * len(p)
           and float(np.ptp(p[who == c] @ major)) >= 0.3 * 20.0 * cell]
    if len(big) < 2:
        return None
    first = {c: int(np.argmax(who == c)) for c in big}
    keep = min(big, key=lambda c: (-cnt[c], first[c]))
    on = who == keep
    j = np.floor((S.detail_points - lo) / cell).astype(np.intp)
    inside = np.all((j >= 0) & (j < dims), axis=1)
    don = np.zeros(len(j), bool)
    don[inside] = lab[j[inside, 0], j[inside, 1], j[inside, 2]] == keep
    return Samples(p[on], S.normals[on], S.face[on], S.detail_points[don],
                    S.detail_normals[don], S.face_centroid, S.face_area2)


# ----------------------------------------------------------------------------- many vehicles

def overlapping_vehicles(ctx: Context, names: NameTable) -> bool:
    """Vehicles on top of each other (a game's vehicle pack at the origin): two or more node
    groups (node names without trimesh's '_xxxxxx' suffix) that each look like a whole
    vehicle: two or more materials, glazing or lamps among them, and at least half of the
    length and 40 % of the height of the model."""
    groups = names.names.node_groups()
    if groups is None:
        return False
    group, K, whole_like = groups                 # at least 4 faces and 2 materials
    if np.count_nonzero(whole_like) < 2:
        return False
    special = (names.glass | names.lamp)[names.groupings[0][0]]
    # glazing or lamp faces per group
    cand = np.flatnonzero(whole_like & (np.bincount(group, weights=special.astype(float),
                                                    minlength=K) > 0))
    if cand.size < 2:
        return False
    fc = ctx.S.face_centroid
    fs, ft = fc @ ctx.a, fc @ ctx.b
    span_s, span_t = float(np.ptp(fs)), float(np.ptp(ft))
    whole = 0
    for k in cand:
        sel = group == k
        if np.ptp(fs[sel]) >= 0.5 * span_s and np.ptp(ft[sel]) >= 0.4 * span_t:
            whole += 1
    return whole >= 2

def _dilate(g: np.ndarray) -> np.ndarray:
    """``scipy.ndimage.binary_dilation(g)`` of a 3-D bool array (one step, the six face
    neighbours), by shifted ors."""
    d = g.copy()
    d[1:] |= g[:-1]
    d[:-1] |= g[1:]
    d[:, 1:] |= g[:, :-1]
    d[:, :-1] |= g[:, 1:]
    d[:, :, 1:] |= g[:, :, :-1]
    d[:, :, :-1] |= g[:, :, 1:]
    return d


def several_vehicles(ctx: Context) -> bool:
    """Vehicles side by side: nothing crosses the mirror plane (under 0.3 % of the samples
    within 3 % of the half-width of it; a single vehicle's roof, bumpers and floor cross it).
    Or two or more separate clusters of surface (voxels of 1/40 of the length, one voxel of
    gap joins), each holding at least 15 % of the samples and 30 % of the length."""
    from scipy import ndimage

    if np.mean(np.abs(ctx.q) < 0.03) < 0.003 and min(np.mean(ctx.q > 0), np.mean(ctx.q < 0)) > 0.3:
        return True
    p = ctx.S.points
    cell = 2 * ctx.half_len / 40.0
    i = np.floor((p - p.min(axis=0)) / cell).astype(np.intp)
    dims = i.max(axis=0) + 1
    if np.prod(dims) > 4_000_000:
        return False
    g = np.zeros(dims, bool)
    g[i[:, 0], i[:, 1], i[:, 2]] = True
    lab, k = ndimage.label(_dilate(g), structure=np.ones((3, 3, 3)))
    if k < 2:
        return False
    who = lab[i[:, 0], i[:, 1], i[:, 2]]
    cnt = np.bincount(who, minlength=k + 1)
    big = [c for c in range(1, k + 1) if cnt[c] >= 0.15 * len(p)
           and np.ptp(ctx.s[who == c]) >= 0.6]
    return len(big) >= 2
