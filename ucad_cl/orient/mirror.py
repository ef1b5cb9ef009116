"""The mirror plane (step 2 of the estimate, ``ucad_cl.orient``): candidate normals ranked by
how many reflected samples land on the surface, the best refined by a point-to-plane
symmetric ICP.
"""
from __future__ import annotations

import math

import numpy as np

from .geometry import FULL, Budget, quantile

# ----------------------------------------------------------------------------- mirror plane

def _reflect_many(p: np.ndarray, n: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(K, N, 3): the points ``p`` (N, 3) reflected in each plane ``x . n[k] = d[k]``."""
    return p[None] - 2.0 * (n @ p.T - d[:, None])[:, :, None] * n[:, None, :]


def mirror_plane(p: np.ndarray, nrm: np.ndarray, mu: np.ndarray, pca: np.ndarray,
                  evals: np.ndarray | None = None, budget: Budget = FULL):
    """(unit normal n, offset d, quality) of the best mirror plane ``x . n = d``.

    Candidates: the principal axes, the file axes and in-between directions (15-degree steps
    between the two minor axes, whose order is arbitrary when width and height are alike;
    45 degrees between the major and each minor one), each through the centroid; for a clearly
    elongated body (``evals``: largest variance twice the next) none within 30 degrees of its
    length axis. They are ranked by the share of 128 (``budget.mirror_rank``) reflected
    samples landing near a sample (KD tree of every 2 x ``budget.mirror_stride``-th sample);
    the best six (``budget.mirror_refined``) get two refinement steps (``_refine_planes``, on the
    same
    samples; neighbouring candidates can fall into different basins), and the two best
    distinct results (``budget.mirror_final``) are refined in full. The winner has the most
    of every ``budget.mirror_stride``-th sample whose reflection lands within one sample
    spacing of a sample (a tight test: a long box's diagonal planes pass a loose one), except
    that among planes within 0.05 of the best the one whose normal is the longest extent (1.5
    times another's) is dropped: a vehicle is longer than wide, so a front/back-symmetric body
    keeps its width axis. Quality (returned): the share within 2.5 sample spacings."""
    cands = [pca[:, 0], pca[:, 1], pca[:, 2], *np.eye(3)]
    for i, j, angles in ((1, 2, (15, 30, 45, 60, 75, 105, 120, 135, 150, 165)),
                         (0, 1, (45, 135)), (0, 2, (45, 135))):
        for t in angles:
            r = math.radians(t)
            cands.append(math.cos(r) * pca[:, i] + math.sin(r) * pca[:, j])
    C = np.array(cands)
    cos = np.abs(C @ C.T).tolist()                         # |cosine| between candidates
    cos10 = math.cos(math.radians(10.0))
    distinct: list[int] = []
    for i in range(len(C)):                                # drop repeats (within 10 degrees)
        if all(cos[i][k] < cos10 for k in distinct):
            distinct.append(i)
    C = C[distinct]
    if evals is not None and evals[0] >= 2.0 * evals[1]:
        # clearly elongated: the mirror plane contains the length axis, so its normal is
        # not within 30 degrees of it (a bus's front/back symmetry is not its mirror plane)
        C = C[np.abs(C @ pca[:, 0]) < math.cos(math.radians(30))]
    sub, sub_n = p[::budget.mirror_stride], nrm[::budget.mirror_stride]
    tree = _tree(sub)
    spacing, _ = tree.query(sub[::8], k=2)
    step = float(quantile(spacing[:, 1], 0.5)) + 1e-12    # typical sample spacing
    coarse, coarse_n = sub[::2], sub_n[::2]                # ranking and refining: half of them
    ctree = _tree(coarse)
    few = coarse[::max(1, len(coarse) // budget.mirror_rank)]
    # every candidate's reflections in one KD query (the same per-point answers)
    hit = _near(ctree, _reflect_many(few, C, C @ mu).reshape(-1, 3), 4.0 * step)[0] < 4.0 * step
    scores = hit.reshape(len(C), -1).mean(axis=1).tolist()
    order = sorted(range(len(C)), key=lambda i: (-scores[i], i))   # tie: candidate order
    # two refinement steps for the six best (all at once), then the two best distinct
    # results in full
    top6 = C[order[:budget.mirror_refined]]
    n6, d6 = _refine_planes(ctree, coarse, coarse_n, top6, top6 @ mu, 1.4 * step, iters=2)
    half = coarse[::2]
    hit = _near(ctree, _reflect_many(half, n6, d6).reshape(-1, 3), 1.5 * step)[0] < 1.5 * step
    hits = hit.reshape(len(n6), -1).mean(axis=1).tolist()
    rough = sorted(zip(hits, range(len(n6)), n6, d6.tolist()),
                   key=lambda r: (-r[0], r[1]))                    # tie: the earlier rank
    picked: list = []
    for _, _, n, d in rough:
        if len(picked) < budget.mirror_final and all(
                abs(float(n @ k[0])) < math.cos(math.radians(3.0)) for k in picked):
            picked.append((n, d))
    nk, dk = _refine_planes(ctree, coarse, coarse_n, np.array([k[0] for k in picked]),
                            np.array([k[1] for k in picked]), 1.4 * step)
    dist = _near(tree, _reflect_many(sub, nk, dk).reshape(-1, 3), 2.5 * step)[0]
    dist = dist.reshape(len(nk), -1)
    refined = [(float(np.mean(dist[k] < step)), float(np.ptp(sub @ nk[k])), nk[k], float(dk[k]),
                float(np.mean(dist[k] < 2.5 * step))) for k in range(len(nk))]
    top = max(r[0] for r in refined)
    tied = [r for r in refined if r[0] >= top - 0.05]
    if len(tied) >= 2 and max(r[1] for r in tied) > 1.5 * min(r[1] for r in tied):
        # a vehicle is longer than wide: a plane across the length axis (a bus or a van
        # with both ends alike) is not its mirror plane
        tied = [r for r in tied if r[1] < max(r_[1] for r_ in tied)]
    best = max(tied, key=lambda r: r[0])                   # tie: the earlier one
    return best[2], best[3], best[4]


def _tree(points: np.ndarray):
    """A KD tree of ``points`` (N, 3) for exact nearest-neighbour queries, built by sliding
    midpoint splits without shrinking the boxes to the data, 24 points a leaf (cheaper to
    build and query than the defaults for the few hundred samples here; the same neighbours
    and distances)."""
    from scipy.spatial import cKDTree

    return cKDTree(points, leafsize=24, balanced_tree=False, compact_nodes=False)


def _near(tree, x: np.ndarray, bound: float) -> tuple[np.ndarray, np.ndarray]:
    """(distance, index) of each point's nearest neighbour in ``tree`` when closer than
    ``bound``; distance inf and index 0 beyond it (the search stops there: reflections
    that land far from the surface cost little)."""
    dist, j = tree.query(x, k=1, distance_upper_bound=bound)
    return dist, np.where(dist < bound, j, 0)


def _refine_planes(tree, p: np.ndarray, nrm: np.ndarray, n: np.ndarray, d: np.ndarray,
                   step: float, iters: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Symmetric ICP, point to plane, for K planes in lockstep (normals ``n`` (K, 3), offsets
    ``d`` (K,); each moves as if refined alone, one KD query per step for all of them): each
    sample x is reflected, paired with the nearest sample y (kept when closer than tau and
    when the reflected normal of x agrees with the normal of y within 45 degrees), and the
    plane is moved to minimise the squared distances of the reflected samples to the tangent
    planes at their partners (Gauss-Newton on the normal's two degrees of freedom and the
    offset). tau halves from 6 to 1.5 sample spacings (``step``); a plane stops when its
    normal moves less than 0.02 degree at tau = 1.5 spacings, or when fewer than 16 pairs
    are kept. Converges from about 10 degrees off to a few hundredths of a degree on a
    mirror-symmetric surface."""
    n, d = np.array(n, np.float64), np.array(d, np.float64)
    live = np.ones(len(n), bool)
    tau_min = 1.5 * step
    tau = 6.0 * step
    ridge = 1e-12 * np.eye(3)                             # keeps the normal equations regular
    for it in range(iters):
        k_live = np.flatnonzero(live)
        if k_live.size == 0:
            break
        stride = 2 if it < 2 else 1                       # the first steps on fewer samples
        half, half_n = p[::stride], nrm[::stride]
        nl, dl = n[k_live], d[k_live]
        xn = nl @ half.T - dl[:, None]                    # (K, H) signed distances
        rx = half[None] - 2.0 * xn[:, :, None] * nl[:, None, :]   # reflections (K, H, 3)
        dist, j = _near(tree, rx.reshape(-1, 3), tau)
        dist, j = dist.reshape(len(k_live), -1), j.reshape(len(k_live), -1)
        m = nrm[j]                                        # (K, H, 3) partners' normals
        E = _plane_frames(nl)                             # (K, 3, 3): columns n, u, v
        me = m @ E                                        # partner normal on n, u, v
        # the reflected normal of x against its partner's: x_n . m - 2 (n . x_n)(n . m)
        agree = np.einsum("hi,khi->kh", half_n, m) - 2.0 * (nl @ half_n.T) * me[:, :, 0]
        ok = (dist < tau) & (np.abs(agree) > 0.7)
        enough = ok.sum(axis=1) >= 16
        # Gauss-Newton for all live planes at once (unpaired samples weigh 0), on the
        # normal's two degrees of freedom (u, v) and the offset
        xe, mn = half @ E[:, :, 1:], me[:, :, :1]
        J = np.empty(me.shape)
        J[:, :, :2] = -2.0 * (xe * mn + xn[:, :, None] * me[:, :, 1:])
        J[:, :, 2] = 2.0 * mn[:, :, 0]
        e0 = ((rx - p[j]) * m).sum(axis=2)
        Jw = (J * ok[:, :, None]).transpose(0, 2, 1)      # (K, 3, H)
        delta = np.linalg.solve(Jw @ J + ridge, -(Jw @ e0[:, :, None]))[:, :, 0]
        n2 = nl + delta[:, :1] * E[:, :, 1] + delta[:, 1:2] * E[:, :, 2]
        n2 /= np.sqrt((n2 * n2).sum(axis=1))[:, None]
        moved = (n2 * nl).sum(axis=1)
        k_on = k_live[enough]                             # fewer than 16 pairs: stop
        n[k_on], d[k_on] = n2[enough], dl[enough] + delta[enough, 2]
        live[k_live[~enough]] = False
        if tau <= tau_min:
            live[k_on[moved[enough] > math.cos(math.radians(0.02))]] = False
        tau = max(0.5 * tau, tau_min)
    return n, d


def _plane_frames(n: np.ndarray) -> np.ndarray:
    """(K, 3, 3): for each unit normal n[k] the columns n, u, v, with u = n x e_x (n x e_y
    when n is within 26 degrees of e_x) made unit and v = n x u."""
    out = []
    for a, b, c in n.tolist():
        u = (0.0, c, -b) if abs(a) < 0.9 else (-c, 0.0, a)
        s = 1.0 / math.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2])
        u0, u1, u2 = u[0] * s, u[1] * s, u[2] * s
        out.append(((a, u0, b * u2 - c * u1), (b, u1, c * u0 - a * u2), (c, u2, a * u1 - b * u0)))
    return np.array(out)
