"""Up cues (step 5 of the estimate, ``ucad_cl.orient``): which side is the ground. Each cue
scores in [-1, 1] (positive: the provisional up is right); weights ``UP_WEIGHTS``. Also the
ground sheet (a cloth or base under the vehicle), which says which way is up.
"""
from __future__ import annotations

import math

import numpy as np

from ..artifacts import Mesh
from .geometry import FULL, Budget, Context, Geometry, Samples, quantile, surface_samples
from .names import IS_FLOOR, IS_ROOF, IS_WHEEL, NameTable, vote
from .wheels import Wheels


def ground_sheet(mesh: Mesh, S: Samples, budget: Budget = FULL,
                  geometry: Geometry | None = None):
    """A ground plane, cloth or display base under the vehicle: one material holding at
    least 25 % of the surface that is flat-ish (its smallest spread under 40 % of its
    largest: a draped cloth counts), at least 1.3 times as broad as the rest of the model in
    both of its long directions, with at least 90 % of the rest on one side of it. Returns
    (new samples of the rest as many as ``budget`` says, unit normal toward the rest)
    or None."""
    fm = np.asarray(mesh.face_material)[S.face]
    cnt = np.bincount(fm, minlength=len(mesh.materials))
    p = S.points
    for m in np.flatnonzero(cnt >= 0.25 * len(fm)):
        on = fm == m
        rest = p[~on]
        if rest.shape[0] < 0.1 * len(fm):
            continue
        c = p[on].mean(axis=0)
        ev, V = np.linalg.eigh(np.cov((p[on] - c).T))
        if ev[0] > (0.4 ** 2) * ev[2]:
            continue                                       # not a sheet
        span = np.ptp(p[on] @ V[:, 1:], axis=0)
        if np.any(span < 1.3 * np.ptp(rest @ V[:, 1:], axis=0)):
            continue                                       # not broader than the vehicle
        side = (rest - c) @ V[:, 0]
        above = float(np.mean(side > 0))
        if max(above, 1.0 - above) < 0.9:
            continue
        return (surface_samples(mesh, budget.samples, skip_material=int(m), geometry=geometry,
                                 n_faces=budget.face_samples),
                V[:, 0] if above >= 0.5 else -V[:, 0])
    return None


# ----------------------------------------------------------------------------- up cues

def up_cue_scores(ctx: Context, wheels: Wheels | None, names: NameTable) -> dict[str, float]:
    """Each cue in [-1, 1]: positive = the height axis b points up."""
    cues: dict[str, float] = {}
    if wheels is not None:
        cues["wheels"] = _wheel_up(ctx, wheels)
    fm = names.material_of_sample
    glass = names.glass[fm]
    if 0.005 <= glass.mean() < 0.6:
        cues["glass_high"] = float(np.clip(2.5 * ctx.t[glass].mean(), -1, 1))
    lamps = names.lamp[fm]
    if lamps.sum() >= 3 and lamps.mean() < 0.2:
        cues["lamps_low"] = float(np.clip(-1.5 * ctx.t[lamps].mean(), -1, 1))
    ft = ctx.S.face_centroid @ ctx.b                       # every face centroid's height, like t
    ft -= ctx.t0
    ft /= ctx.half_h
    votes = names.votes(IS_ROOF, ft) + [(w, -v) for w, v in names.votes(IS_FLOOR, ft)]
    if votes:
        cues["names_up"] = vote(votes)
    votes = [(w, -v) for w, v in names.votes(IS_WHEEL, ft)]
    if votes:
        cues["wheel_names_low"] = vote(votes)
    cues["hull_base"] = _hull_base(ctx)
    cues["roof_narrow"] = _roof_narrow(ctx)
    return cues


def _wheel_up(ctx: Context, wheels: Wheels) -> float:
    """+1 when the line touching the wheels' undersides (for b up) has no sample beyond it
    and the line touching their tops (for b down) has the body beyond it; the wheel centres
    lying low adds to it."""
    pts = ctx.side_points()
    c = wheels.side_view(ctx)
    beyond = []
    for sgn in (1.0, -1.0):
        line = float(np.min(sgn * c[:, 1] - wheels.radii))   # lowest wheel point along +-b
        beyond.append(float(np.mean(sgn * pts[:, 1] < line - 0.02 * ctx.half_len)))
    low = -float(np.mean(c[:, 1])) / ctx.half_h
    return float(np.clip(4.0 * (beyond[1] - beyond[0]) + low, -1, 1))


def _hull_base(ctx: Context) -> float:
    """The side view's convex hull has a long level edge at the bottom (floor, sills, the
    tyres' common tangent) and a rounded top: + when the longest level edge is low."""
    hull = ctx.side_hull()
    if hull is None:
        return 0.0
    e = np.roll(hull, -1, axis=0) - hull
    ln = np.hypot(e[:, 0], e[:, 1])
    level = np.abs(e[:, 1]) < math.tan(math.radians(10.0)) * np.abs(e[:, 0])
    mid = hull[:, 1] + 0.5 * e[:, 1]
    lo = ln[level & (mid < 0)].max(initial=0.0)
    hi = ln[level & (mid > 0)].max(initial=0.0)
    return float(np.clip(1.5 * (lo - hi) / (2 * ctx.half_len), -1, 1))


def _roof_narrow(ctx: Context) -> float:
    """Tumblehome: the top of a vehicle is narrower than its lower body."""
    q = np.abs(ctx.q)
    top, bot = q[ctx.t > 0.7], q[(ctx.t < -0.1) & (ctx.t > -0.8)]
    if top.size < 8 or bot.size < 8:
        return 0.0
    return float(np.clip(3.0 * (quantile(bot, 0.9) - quantile(top, 0.9)), -1, 1))
