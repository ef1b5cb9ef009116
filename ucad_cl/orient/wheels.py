"""Wheels (step 4 of the estimate, ``ucad_cl.orient``): a Hough vote with normals for circles
in the side view, checked to be whole, round tyres on both sides of the mirror plane, low on
the body, two or more on one line standing on the ground.
"""
from __future__ import annotations

import math

import numpy as np

from .geometry import FULL, WHEEL_MIN_VOTES, Budget, Context

# ----------------------------------------------------------------------------- wheels

class Wheels:
    """Wheel circles: centres (K, 3) in the mesh frame (on the mirror plane), radii (K,),
    Hough votes (K,), the ground direction (unit, along the line of the centres)."""

    def __init__(self, centres, radii, votes, ground_dir):
        self.centres, self.radii, self.votes, self.ground_dir = centres, radii, votes, ground_dir

    def side_view(self, ctx: Context) -> np.ndarray:
        """(K, 2) centres in the context's current side view, mesh units."""
        return np.stack([self.centres @ ctx.a - ctx.s0, self.centres @ ctx.b - ctx.t0], axis=1)

    def axles(self, ctx: Context) -> np.ndarray:
        """Sorted distinct axle positions along the length axis, in [-1, 1]."""
        x = np.sort(self.side_view(ctx)[:, 0]) / ctx.half_len
        return x[np.r_[True, np.diff(x) > 0.05]]

    def settle(self, ctx: Context) -> np.ndarray:
        """With b up: keep the wheels that stand on the ground and return the ground
        direction. Each wheel's contact is the lowest mesh vertex under its centre (the
        detected circle may be a rim inside the tyre); the ground is the longest edge of the
        lower convex hull of the contacts, and wheels more than a third of their radius above
        it (a spare wheel on the tailgate) are dropped."""
        c = self.side_view(ctx)
        v = np.asarray(ctx.mesh.vertices, np.float64)
        vt = v @ ctx.b
        vt -= ctx.t0
        vs = v @ ctx.a
        vs -= ctx.s0
        # the vertices in the height band of any wheel's window (the windows test them)
        band = np.flatnonzero((vt > np.min(c[:, 1] - 2.0 * self.radii)) & (vt < np.max(c[:, 1])))
        vs, vt = vs[band], vt[band]
        bottom = np.empty(len(c))
        for k, ((cs, ct), r) in enumerate(zip(c, self.radii)):
            near = (np.abs(vs - cs) < 0.35 * r) & (vt < ct) & (vt > ct - 2.0 * r)
            bottom[k] = float(vt[near].min()) if near.any() else ct - r
        order = np.argsort(c[:, 0], kind="stable")
        pts = np.stack([c[order, 0], bottom[order]], axis=1)
        lower = [0]                                        # lower hull, left to right
        for k in range(1, len(pts)):
            while len(lower) >= 2 and _cross2(pts[lower[-2]], pts[lower[-1]], pts[k]) <= 0:
                lower.pop()
            lower.append(k)
        seg = max(range(len(lower) - 1), key=lambda i: pts[lower[i + 1], 0] - pts[lower[i], 0])
        p0, p1 = pts[lower[seg]], pts[lower[seg + 1]]
        g = (p1 - p0) / np.hypot(*(p1 - p0))
        height = (pts - p0) @ np.array([-g[1], g[0]])      # above the ground line
        keep = np.zeros(len(c), bool)
        keep[order] = height <= self.radii[order] / 3.0
        self.centres, self.radii, self.votes = (self.centres[keep], self.radii[keep],
                                                self.votes[keep])
        return g[0] * ctx.a + g[1] * ctx.b


def _cross2(o, a, b) -> float:
    return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))


def find_wheels(ctx: Context, budget: Budget = FULL) -> Wheels | None:
    """Road wheels in the side view, or None. Tyre treads: samples (area and face samples)
    away from the mirror plane whose normals are perpendicular to the width axis vote, for
    each of 8 radii (``budget.radii``) from 2.5 % to 13 % of the length, for the circle
    centre p - r n (a Hough transform with normals; cells of 0.15 r summed over 3 x 3). The 5
    (``budget.peaks``) highest peaks per radius that are not at mid-height are checked
    (``_check_circle``: a whole, round tyre pair); of concentric circles (tyre, rim, hub) the
    outermost is kept; the wheels are the best group standing on the ground (``_wheel_group``),
    on a line within 30 degrees of the length axis."""
    L, H = ctx.half_len, ctx.half_h
    S = ctx.S
    frame = np.stack([ctx.a, ctx.b, ctx.w])                # rows a, b, w
    # area samples and face samples on a, b, w (rows)
    pts = frame @ np.concatenate([S.points, S.detail_points]).T
    nrm = frame @ np.concatenate([S.normals, S.detail_normals]).T
    q = (pts[2] - ctx.wd) / ctx.half_w
    sel = (np.abs(nrm[2]) < 0.35) & (np.abs(q) > 0.3)
    if np.count_nonzero(sel) < 12:
        return None
    x, y = pts[0, sel] - ctx.s0, pts[1, sel] - ctx.t0
    mx, my = nrm[0, sel], nrm[1, sel]                     # unit normals in the side view
    norm = np.maximum(np.sqrt(mx * mx + my * my), 1e-12)
    mx, my = mx / norm, my / norm
    left, aq = q[sel] > 0, np.abs(q[sel])
    found, tried = [], []
    radii = 2 * L * np.geomspace(0.025, 0.13, budget.radii)
    cell = 0.15 * radii                                   # Hough cells of 0.15 r
    # the centre votes p - r n and their cells for every radius at once (rows)
    cxs, cys = x - radii[:, None] * mx, y - radii[:, None] * my
    ixs = np.floor((cxs + L) / cell[:, None]).astype(np.intp)
    iys = np.floor((cys + H + radii[:, None]) / cell[:, None]).astype(np.intp)
    for r, h, cx, cy, ix, iy in zip(radii, cell, cxs, cys, ixs, iys):
        nx, ny = int(2 * L / h) + 2, int((2 * H + 2 * r) / h) + 2
        ok = (ix.view(np.uintp) < nx) & (iy.view(np.uintp) < ny)   # negative: huge
        peak, votes = _hough_peaks(ix[ok] * ny + iy[ok], nx, ny, budget.wheel_votes)
        if peak.size == 0:
            continue
        peak = peak[np.argsort(-votes, kind="stable")[:budget.peaks]]
        for i, j in zip(*np.divmod(peak, ny)):
            centre = np.array([(i + 1.0) * h - L, (j + 1.0) * h - H - r])    # 3 x 3 middle
            if abs(centre[1]) < 0.25 * H or r > 0.32 * L:
                continue                                  # mid-height or too big: a body arc
            if any(abs(r / r_ - 1.0) < 0.3 and np.hypot(*(centre - c_)) < 0.3 * r
                   for r_, c_ in tried):
                continue                                  # the same circle, one step apart
            tried.append((r, centre))
            mem = np.flatnonzero(ok & (np.abs(ix - i) <= 1) & (np.abs(iy - j) <= 1))
            c0 = np.array([np.add.reduce(cx[mem]) / mem.size, np.add.reduce(cy[mem]) / mem.size])
            box_ = np.flatnonzero((np.abs(x - c0[0]) < 1.5 * r) & (np.abs(y - c0[1]) < 1.5 * r))
            wheel = _check_circle(x[box_], y[box_], mx[box_], my[box_], left[box_], aq[box_],
                                  c0, r, L, H, budget.wheel_votes)
            if wheel is not None:
                found.append(wheel)
    if not found:
        return None
    found.sort(key=lambda f: (-f[0], f[1], f[2][0], f[2][1]))     # ties: smaller, then position
    kept: list = []
    for c in found:
        near = [i for i, k in enumerate(kept)
                if np.hypot(*(c[2] - k[2])) < 0.6 * max(c[1], k[1])]
        if not near:
            kept.append(c)
            continue
        k = kept[near[0]]
        # the same wheel: concentric circles are tyre, rim, hub; the tyre is the outermost
        if (np.hypot(*(c[2] - k[2])) < 0.3 * min(c[1], k[1]) and c[1] > k[1]
                and c[0] >= 0.3 * k[0]):
            kept[near[0]] = c
    wheels = _wheel_group(kept, ctx.side_points(), L)
    if wheels is None:
        return None
    centres = np.array([k[2] for k in wheels])
    votes = np.array([k[0] for k in wheels], float)
    _, _, vt = np.linalg.svd((centres - centres.mean(axis=0)) * np.sqrt(votes)[:, None],
                             full_matrices=False)
    g = vt[0] if vt[0][0] >= 0 else -vt[0]
    if abs(g[1]) > math.sin(math.radians(30)):
        return None                                       # on a steep line: not road wheels
    c3 = (np.outer(centres[:, 0] + ctx.s0, ctx.a) + np.outer(centres[:, 1] + ctx.t0, ctx.b)
          + ctx.wd * ctx.w)
    return Wheels(c3, np.array([k[1] for k in wheels]), votes, g[0] * ctx.a + g[1] * ctx.b)


def _wheel_group(circles: list, side: np.ndarray, half_len: float) -> list | None:
    """The road wheels among verified circles [(score, radius, centre)]: the group with the
    highest total score of at least two circles of radii within 0.6-1.67 of each other, two
    radii or more apart along the length, on the same side of the middle, on a line within
    20 degrees of the length axis, that stands on
    the ground: for one of the two height directions, the line through the undersides of
    its first and last circle has less than 1 % of the side-view samples ``side`` beyond it
    (a rounded body seen from the side, or wheel arches, have the sills or the tyres below
    them). A lone circle is never a wheel set. None when no group qualifies."""
    best, best_score = None, 0.0
    for k in circles:
        group = [c for c in circles if 0.6 <= c[1] / k[1] <= 1.67
                 and c[2][1] * k[2][1] > 0 and (
                     c is k or abs(c[2][1] - k[2][1]) <= math.tan(math.radians(20)) * abs(
                         c[2][0] - k[2][0]))]
        if len(group) < 2:
            continue
        group.sort(key=lambda c: c[2][0])
        if group[-1][2][0] - group[0][2][0] < 2.0 * max(c[1] for c in group):
            continue
        score = sum(c[0] for c in group)
        if score > best_score and _stands(group, side, half_len):
            best, best_score = group, score
    return best


def _stands(group: list, side: np.ndarray, half_len: float) -> bool:
    """True when, for b up or for b down, no more than 1 % of the side-view samples lie
    beyond the line touching the first and the last circle of ``group`` on that side."""
    (_, r0, c0), (_, r1, c1) = group[0], group[-1]
    for sgn in (1.0, -1.0):
        p0 = np.array([c0[0], c0[1] - sgn * r0])
        p1 = np.array([c1[0], c1[1] - sgn * r1])
        d = (p1 - p0) / np.hypot(*(p1 - p0))
        normal = sgn * np.array([-d[1], d[0]]) * np.sign(d[0])       # toward +-b
        beyond = (side - p0) @ normal < -0.02 * half_len
        if beyond.mean() < 0.01:
            return True
    return False


def _check_circle(x, y, mx, my, left, aq, c, r, half_len, half_h, min_votes=WHEEL_MIN_VOTES):
    """(score, radius, centre) of the wheel pair around a Hough peak (centre ``c``, radius
    ``r``), or None. Its support: the voters within 15 % of r from the circle whose normal
    points along the radius (either sign); centre and radius are refitted to it (algebraic
    circle fit, twice). A wheel pair: a radius at most 15 % of the length; a centre in the
    lower or upper 32.5 % of the height (wheels sit low); support from both sides of the mirror
    plane, 60 % of it within a quarter of the half-width across (a tyre, not a body arc),
    all around the circle (no gap wider than 90 degrees; sector entropy at least 0.8 of the
    maximum), with normals in at least 6 of 16 directions (an octagonal wheel has 8; a box
    that a circle touches on four sides has 4) and at least WHEEL_MIN_VOTES samples.
    Score = support x evenness."""
    for _ in range(2):
        dx, dy = x - c[0], y - c[1]
        d2 = dx * dx + dy * dy                            # squared: no square roots
        along = dx * mx + dy * my
        near = ((d2 > (0.85 * r) ** 2) & (d2 < (1.15 * r) ** 2)
                & (along * along > 0.81 * d2))
        if np.count_nonzero(near) < min_votes:
            return None
        X, Y = x[near], y[near]
        c, r = _fit_circle(X, Y)
        if r is None:
            return None
    if r > 0.3 * half_len or abs(c[1]) < 0.35 * half_h:
        return None                                       # too big, or not low: a body arc
    sides = np.count_nonzero(left[near])
    if sides == 0 or sides == X.size:
        return None                                       # one side only: not a wheel pair
    if _band_share(aq[near], 0.25) < 0.6:
        return None                                       # spread across: a body arc
    a = np.sort(np.arctan2(Y - c[1], X - c[0]))
    if np.max(np.diff(np.concatenate((a, [a[0] + 2 * math.pi])))) > math.radians(90):
        return None                                       # an arc (a wheel arch), not a circle
    hist = np.bincount((np.floor((a + math.pi) / (2 * math.pi) * 8) % 8).astype(np.intp),
                       minlength=8)
    share = hist[hist > 0] / hist.sum()
    even = float(-(share * np.log(share)).sum() / math.log(8))
    if even < 0.8:
        return None                                       # not supported around a circle
    mxn, myn = mx[near], my[near]
    sgn = np.sign((X - c[0]) * mxn + (Y - c[1]) * myn)     # the normal turned outward
    turns = np.floor((np.arctan2(myn * sgn, mxn * sgn) + math.pi) / (2 * math.pi) * 16) % 16
    if np.count_nonzero(np.bincount(turns.astype(np.intp), minlength=16)) < 6:   # distinct
        return None                                       # a few flat faces (a box), not round
    return float(near.sum()) * even, r, c


def _fit_circle(X: np.ndarray, Y: np.ndarray):
    """Algebraic (Kasa) least-squares circle through points: (centre, radius), or (None,
    None) when they are collinear. Centred normal equations, 2 x 2."""
    mx, my = np.add.reduce(X) / X.size, np.add.reduce(Y) / Y.size   # X.mean(), same bits
    u, v = X - mx, Y - my
    suu, svv, suv = u @ u, v @ v, u @ v
    det = suu * svv - suv * suv
    if not abs(det) > 1e-30:
        return None, None
    rhs_u = 0.5 * (u @ (u * u) + u @ (v * v))
    rhs_v = 0.5 * (v @ (v * v) + v @ (u * u))
    uc = (rhs_u * svv - rhs_v * suv) / det
    vc = (rhs_v * suu - rhs_u * suv) / det
    r2 = uc * uc + vc * vc + (suu + svv) / X.size
    return np.array([uc + mx, vc + my]), math.sqrt(r2)


def _band_share(v: np.ndarray, width: float) -> float:
    """Largest share of the values inside one window [x, x + width]."""
    v = np.sort(v)
    return float((np.searchsorted(v, v + width, side="right") - np.arange(v.size)).max()
                 / v.size)


def _hough_peaks(cell: np.ndarray, nx: int, ny: int,
                 min_votes: int) -> tuple[np.ndarray, np.ndarray]:
    """Peaks of a Hough grid of ``nx`` x ``ny`` cells (``cell``: the flat, C-order cell of
    each vote): (flat cells where the votes summed over the 3 x 3 cells around reach
    ``min_votes`` and no neighbour's sum is larger, ascending; their sums). Integer counts
    with a zero border (int16 when the votes fit: a sum counts each vote at most once)."""
    grid = np.zeros((nx + 2, ny + 2), np.int16 if len(cell) < 2**15 else np.int64)
    grid[1:-1, 1:-1] = np.bincount(cell, minlength=nx * ny).reshape(nx, ny)
    rows = grid[:-2] + grid[1:-1]
    rows += grid[2:]
    box = np.zeros_like(grid)                             # 3 x 3 sums, a zero border
    inner = box[1:-1, 1:-1]
    np.add(rows[:, :-2], rows[:, 1:-1], out=inner)
    inner += rows[:, 2:]
    rows = np.maximum(box[:-2], box[1:-1])                # sums >= 0: the border is no peak
    np.maximum(rows, box[2:], out=rows)
    top = np.maximum(rows[:, :-2], rows[:, 1:-1])
    np.maximum(top, rows[:, 2:], out=top)                 # 3 x 3 maxima of the sums
    peak = np.flatnonzero((inner >= min_votes) & (inner == top))
    i, j = np.divmod(peak, ny)
    return peak, inner[i, j]
