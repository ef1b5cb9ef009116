"""Front cues (step 6 of the estimate, ``ucad_cl.orient``): which end is the nose. Each cue
scores in [-1, 1] (positive: the provisional front is right); weights ``FRONT_WEIGHTS``.
"""
from __future__ import annotations

import numpy as np

from .geometry import N_SAMPLES, Context
from .names import IS_FRONT, IS_REAR, NameTable, vote
from .wheels import Wheels

# ----------------------------------------------------------------------------- front cues

def front_cue_scores(ctx: Context, wheels: Wheels | None, names: NameTable) -> dict[str, float]:
    """Each cue in [-1, 1]: positive = the length axis a points to the front (b is up)."""
    cues: dict[str, float] = {}
    fs = ctx.face_s()
    votes = ([(w, v) for w, v in names.votes(IS_FRONT, fs)]
             + [(w, -v) for w, v in names.votes(IS_REAR, fs)])
    if votes:
        cues["names"] = vote(votes)
    share = names.share[0]
    lamp = np.flatnonzero((names.colour != 0) & (share > 0) & (share <= 0.05))
    if lamp.size:
        # a lamp material's surface at the front end minus at the back end: one at both
        # ends (or in the middle) cancels
        ends = names.means_on(0, lamp, lambda f: (fs[f] > 0.5).astype(float) - (fs[f] < -0.5))
        w = np.sqrt(np.minimum(share[lamp] * N_SAMPLES, 50.0))
        cues["lamp_colours"] = vote(list(zip(w.tolist(), (names.colour[lamp] * ends).tolist())))
    fm = names.material_of_sample
    glass = names.glass[fm]
    if glass.sum() >= 4:
        cues.update(_glass_cues(ctx, glass))
    cues["mirrors"] = _mirrors(ctx)
    ax = wheels.axles(ctx) if wheels is not None else np.zeros(0)
    if ax.size >= 3:
        gaps = np.diff(ax)
        cues["axles"] = float(np.clip(3.0 * (gaps[-1] - gaps[0]), -1, 1))
    cues["profile"] = _profile(ctx)
    cues["cabin"] = _cabin(ctx)
    cues["bed"] = _bed(ctx)
    return cues


def _bed(ctx: Context) -> float:
    """An open load bed (a pickup's, an open truck's) is at the rear: in each of 20 columns
    along the length, the top of the middle (|q| < 0.4) lower by 0.15 of the half height
    than the top of the sides (|q| > 0.7), with the sides a quarter of the height below the
    highest point (a glassless window opening's pillars are higher), is a hollow column;
    score: sign(d) (|d| - 2) / 3 clipped to [0, 1] in size, d = hollow columns in the back
    half - in the front half. A closed body or a bonnet (highest in the middle) has none."""
    col = np.minimum(((ctx.s + 1.0) * 10.0).astype(np.intp), 19)
    aq = np.abs(ctx.q)
    mid_top, side_top = np.full(20, -np.inf), np.full(20, -np.inf)
    np.maximum.at(mid_top, col[aq < 0.4], ctx.t[aq < 0.4])
    np.maximum.at(side_top, col[aq > 0.7], ctx.t[aq > 0.7])
    both = np.isfinite(mid_top) & np.isfinite(side_top)
    if both.sum() < 10:
        return 0.0
    roof = float(np.maximum(mid_top, side_top)[both].max())
    hollow = both & (side_top - mid_top > 0.15) & (side_top < roof - 0.5)
    d = int(hollow[:10].sum()) - int(hollow[10:].sum())      # back half - front half
    return float(np.sign(d) * np.clip((abs(d) - 2) / 3.0, 0.0, 1.0))


def _cabin(ctx: Context) -> float:
    """The cabin sits behind the middle of the length (a bonnet in front of it is longer
    than a boot behind it; a hatchback's, an SUV's or a van's roof runs to the tail), with
    or without glazing and lamps. The side view's top edge (the highest sample in each of 40
    columns along the length) above the level halfway from the higher end's top (the mean
    of its 4 outermost columns) to the highest point is the roof; m is the roof's middle
    (the columns' positions weighted by their height above that level, so a column near the
    level weighs nearly nothing and the cue varies continuously). Score -3 (m - 0.025 sign
    m), 0 within 0.025 (half a column), clipped. Pickups (cab ahead of the bed) and cab-over
    trucks with a tall box can mislead it, hence its modest weight."""
    col = np.minimum(((ctx.s + 1.0) * 20.0).astype(np.intp), 39)
    top = np.full(40, -np.inf)
    np.maximum.at(top, col, ctx.t)
    seen = np.flatnonzero(np.isfinite(top))
    if seen.size < 20:
        return 0.0
    h = top[seen]
    level = 0.5 * (max(float(h[:4].mean()), float(h[-4:].mean())) + float(h.max()))
    w = np.maximum(h - level, 0.0)
    if w.sum() <= 0.0:
        return 0.0
    mid = float(((seen + 0.5) / 20.0 - 1.0) @ w / w.sum())
    return float(np.clip(-3.0 * np.sign(mid) * max(abs(mid) - 0.025, 0.0), -1, 1))


def _glass_cues(ctx: Context, glass: np.ndarray) -> dict[str, float]:
    """windscreen: the glazing facing along the length (not the side windows) lies more at
    the front end of the glazed region than at its back (a windscreen is bigger than a rear
    window, and trucks have none); by position, so inverted or double-sided glass faces do
    not matter. cab_glass: glazing only near one end (a truck's or a van's cab) is the
    front; glazing around the middle (a car's greenhouse) says nothing."""
    s = ctx.s[glass]
    lo, hi = s.min(), s.max()
    ref = 0.5 * (lo + hi) if hi - lo >= 0.4 else 0.0       # the glazed region's middle
    end = np.abs(ctx.ns[glass])
    end = end * (np.abs(ctx.nq[glass]) < 0.6)
    out = {}
    if end.sum() > 0:
        out["windscreen"] = float(np.clip(1.5 * (np.sign(s - ref) * end).sum() / end.sum(),
                                          -1, 1))
    centre = float(s.mean())
    if abs(centre) > 0.35:
        out["cab_glass"] = float(np.sign(centre) * min((abs(centre) - 0.35) / 0.25, 1.0))
    return out


def _mirrors(ctx: Context) -> float:
    """Side mirrors: local spikes of the vehicle's width above the wheels. The width
    profile (largest |q|) in cells of 0.1 of the height by 0.05 of the length; a cell wider
    by 0.06 than every cell 2-4 cells away along the length at the same height is a spike
    (a broad shoulder is not). Mirrors sit in the front half (at the A pillars, or at a
    truck's cab): (spikes in the front half - spikes in the back half) / (all spikes + 2)."""
    t, q, s = ctx.t, np.abs(ctx.q), ctx.s
    band = (t > -0.3) & (t < 0.85)
    if band.sum() < 40:
        return 0.0
    lv = np.floor((t[band] + 0.3) / 0.1).astype(np.intp)
    sb = np.clip(np.floor((s[band] + 1.0) / 0.05).astype(np.intp), 0, 39)
    W = np.zeros((12, 40))
    np.maximum.at(W, (np.minimum(lv, 11), sb), q[band])
    P = np.zeros((12, 48))
    P[:, 4:44] = W
    nb = np.max([P[:, 4 + d:44 + d] for d in (-4, -3, -2, 2, 3, 4)], axis=0)
    spike = (W - nb > 0.06) & (W > 0)
    pos = (np.nonzero(spike)[1] + 0.5) * 0.05 - 1.0
    front, back = int((pos > 0).sum()), int((pos < 0).sum())
    return float((front - back) / (front + back + 2.0))


def _profile(ctx: Context) -> float:
    """The nose is lower than the tail (a bonnet in front of the windscreen; a tailgate, a
    boot, fins or a cargo box behind): the side view's top edge (the highest sample in each
    of 40 columns along the length) averaged over the last 6 columns at each end."""
    col = np.minimum(((ctx.s + 1.0) * 20.0).astype(np.intp), 39)
    top = np.full(40, np.nan)
    end = np.flatnonzero((col < 6) | (col >= 34))          # only the end columns count
    col, t = col[end], ctx.t[end]
    order = np.lexsort((t, col))
    last = np.r_[col[order][1:] != col[order][:-1], True]
    top[col[order][last]] = t[order][last]
    front, rear = top[-6:], top[:6]
    if np.isnan(front).all() or np.isnan(rear).all():
        return 0.0
    return float(np.clip(1.5 * (np.nanmean(rear) - np.nanmean(front)), -1, 1))
