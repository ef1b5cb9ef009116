"""The fit's light model: sky, sun and clear-coat reflection, linear in each part's base colour.

``fit_light(samples)`` estimates a ``Lighting`` and one base colour per part from pixels of a
photo (linear RGB) whose surface normal, view direction, part and material prior are known (the
render at the matched pose, ``ucad_cl.fit``). Every pixel i of part p is modelled per channel c as

    I_ic = a_pc * B_ic + C_ic

* ``a_pc`` the part's base colour (linear RGB), the unknown the fit solves in closed form;
* ``B_ic = (1 - m)(1 - k F_i) E_c(n_i) + m L_c(r_i)``: diffuse light through the clear coat for
  the dielectric share, the reflected environment for the metallic share ``m`` (the prior's
  metallic factor), both tinted by the base colour;
* ``C_ic = k F_i L_c(r_i)``: the clear coat's (or glass's) reflection, not tinted: it is what
  makes painted panels lighter at grazing angles. ``k`` is the prior's clear-coat factor (1 for
  car paint, 1 for see-through parts, else 0), ``F_i = F0 + (1 - F0)(1 - n.v)^5`` Schlick's
  Fresnel with ``F0 = 0.04`` (refractive index 1.5).

Light, in the vehicle's canonical frame (+Y up; ``docs/CONVENTIONS.md``):

* ``E_c(n) = sky_c (1 + n_y) / 2 + GROUND (1 - n_y) / 2 + sun_c max(n.l, 0)``: a uniform sky of
  radiance ``sky_c`` over the upper hemisphere, a grey ground of radiance ``GROUND`` below, a
  sun of irradiance ``sun_c`` from the unit direction ``l`` (no cast shadows: shadowed pixels
  are residuals the trimming removes);
* ``L_c(r) = sky_c s(r_y) + GROUND (1 - s(r_y))``: the environment seen in the mirror direction
  ``r`` (a smooth step over ``r_y`` in [-w, w], ``w = 0.05 + ENV_BLUR * roughness``); the sun's
  glint is not modelled (saturated pixels are dropped, bright residuals trimmed).

**Scale convention.** A single photo cannot separate albedo from light intensity: the light is
fixed so that a horizontal surface facing up receives ``E_up = sky + sun * max(l_y, 0) = 1``
(before the white balance, below). Base colours are therefore relative to the photo's exposure
(comparisons use one exposure factor per photo, ``bench/fit.py``); ``GROUND = 0.1`` of
``E_up`` (the radiance of an asphalt-like ground of albedo ~0.1 under the same light). The
light's shape is then one number, the sky share ``g = sky / E_up`` in [0, 1]
(``sun = (1 - g) / l_y``), the same for the three channels (``SHARED_SKY``); B and C are affine
in it. **White balance** (``balance``): half (``BALANCE_SHARE``, in log gains) of a photo's
colour cast is moved into the light's colour by per-channel gains towards what would make
parts known to be neutral grey (the fit uses the tyres) come out grey; without them the light
stays neutral.

**Search.** Sun directions on a grid (``SUN_AZIMUTHS`` x ``SUN_ELEVATIONS``, then a finer grid
around the best, elevations within ``SUN_RANGE``), and for each the sky share on ``SKY_STEPS``
values refined by a parabola; for each candidate light the base colours are solved in closed
form (least squares of ``l_rgb`` plus the mean term of ``l_stat``, clipped at 0) and the
candidate is scored by the objective ``l = l_rgb + 0.1 l_stat`` (``l_rgb``: mean squared pixel
difference over all pixels; ``l_stat``: over parts, squared difference of the mean plus squared
difference of the variance of the part's pixels, photo vs model, weighted by the part's pixel
share). The variance term enters the score, not the closed form. Scores come from per-part sums
of products of the affine terms (``_Moments``), so a candidate costs O(parts), not O(pixels);
the terms and sums that do not depend on the sun's direction (``_Scorer``) are computed once
per search and the three channels are scored together (the same numbers as each direction
computed whole: 1.7 -> 0.5 ms a direction, ~60 directions a fit).
**Robustness:** the fit runs twice; the second pass keeps only pixels whose RGB residual is
within ``TRIM_SIGMA`` robust standard deviations (1.4826 x the median distance, at least
``MIN_SIGMA``) of their part's median residual, and searches only the fine grid around the
first pass's sun.
**Reflection folded into the colour.** The clear coat's reflection ``C`` is the least reliable
term (the photo's environment is not the model's sky and ground: buildings, a lighter or darker
ground, occlusion); subtracting it from a dark paint amplifies its error (a black body comes out
at 0, a neutral one tinted). So after the final solve, a coated part (``k > 0``) whose modelled
reflection carries more than ``REFLECTION_MAX`` of its light in every channel (mean ``C`` over
the mean pixel; a saturated paint, dark in some channels only, keeps its modelled reflection) is
re-solved with ``C = 0``: its reflection is folded into its colour, like a flat mean of its
pixels but shaded by ``B`` (``Lighting.coat_scale`` is 0 for it, 1 otherwise; ``predict`` uses
it).
**Determinism:** fixed grids, float64 sums in a fixed order; ties go to the earlier grid point.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

F0 = 0.04                   # Fresnel reflectance at normal incidence (clear coat, glass)
GROUND = 0.1                # ground radiance, share of E_up
SUN_AZIMUTHS = 12           # coarse sun azimuths (every 30 degrees)
SUN_ELEVATIONS = (15.0, 30.0, 45.0, 60.0)   # coarse sun elevations, degrees
SUN_RANGE = (10.0, 70.0)    # sun elevations searched, degrees (daylight photos)
SKY_STEPS = 11              # sky share grid per channel: 0, 0.1, ..., 1
TRIM_SIGMA = 2.5            # residual trim, robust standard deviations
MIN_SIGMA = 0.01            # floor of the robust standard deviation (linear RGB)
BALANCE_RANGE = (0.8, 1.25)  # white-balance gains allowed per channel (else none)
BALANCE_SHARE = 0.5         # share of the neutral parts' cast (as log gains) the light takes
E_MAX = 1.2                 # mean diffuse irradiance allowed on the visible surfaces (x E_up)
ENV_BLUR = 1.0              # mirror-direction step half-width per unit of roughness
SHARED_SKY = True           # one sky share for the three channels
STAT_WEIGHT = 0.1           # weight of l_stat against l_rgb (the paper's 0.1 / 1)
REFLECTION_MAX = 0.5        # a coated part whose modelled reflection carries more of its light in
#                             every channel has it folded into its colour (module docstring)
LUMA = np.array([0.2126, 0.7152, 0.0722])   # linear-RGB luminance (Rec. 709)


@dataclass
class Lighting:
    """Estimated light in the canonical vehicle frame (see the module docstring): ``sky`` and
    ``sun`` (3,) linear RGB with ``sky + sun * max(sun_dir_y, 0) = white_balance`` (1 before
    ``balance``); ``sun_dir`` (3,) unit
    vector toward the sun; ``ground`` the ground's radiance; ``white_balance`` the per-channel
    gains ``balance`` moved from the colours into the light (1 without); ``coat_scale`` (P,)
    the factor on each fitted part's clear-coat reflection (1; 0 where it is folded into the
    part's colour), None: 1 for every part."""

    sky: np.ndarray
    sun: np.ndarray
    sun_dir: np.ndarray
    ground: float = GROUND
    white_balance: np.ndarray = field(default_factory=lambda: np.ones(3))
    coat_scale: np.ndarray | None = None

    def to_json(self) -> dict:
        d = self.sun_dir
        az = float(np.degrees(np.arctan2(-d[2], d[0])) % 360.0)
        el = float(np.degrees(np.arcsin(np.clip(d[1], -1.0, 1.0))))
        return {"model": "sky + sun + ground, clear-coat Schlick reflection",
                "sky_linear": _r(self.sky), "sun_linear": _r(self.sun),
                "sun_direction": _r(d), "sun_azimuth": round(az, 2),
                "sun_elevation": round(el, 2), "ground": round(float(self.ground), 6),
                "fresnel_f0": F0, "white_balance": _r(self.white_balance),
                "scale": "E_up = sky + sun * max(sun_y, 0) = 1 per channel; colours are "
                         "relative to the photo's exposure"}


@dataclass
class Samples:
    """Pixels to fit. rgb (N, 3) linear photo values; normal (N, 3) unit surface normals facing
    the camera and view (N, 3) unit directions toward the camera, canonical frame; part (N,)
    int index into the fitted parts; coat, metallic, roughness (N,) the pixel's material prior
    (clear-coat weight k, metallic m, roughness)."""

    rgb: np.ndarray
    normal: np.ndarray
    view: np.ndarray
    part: np.ndarray
    coat: np.ndarray
    metallic: np.ndarray
    roughness: np.ndarray

    def take(self, idx: np.ndarray) -> "Samples":
        return Samples(*(getattr(self, f)[idx] for f in
                         ("rgb", "normal", "view", "part", "coat", "metallic", "roughness")))


@dataclass
class LightFit:
    """``fit_light``'s answer: the light, base colours (P, 3) (NaN for a part with no kept
    pixel), the objective, and the mask of pixels kept by the trimming."""

    lighting: Lighting
    albedo: np.ndarray
    loss: float
    kept: np.ndarray


def fit_light(samples: Samples, n_parts: int, *, search_pixels: int = 3000) -> LightFit:
    """Light and per-part base colours of ``samples`` (parts 0..n_parts-1), see the module
    docstring. The light search uses at most ``search_pixels`` pixels (every k-th, in order);
    the base colours of the final light use them all."""
    n = len(samples.rgb)
    if n == 0:
        raise ValueError("no pixel to fit")
    keep = np.ones(n, bool)
    light = None
    for _ in range(2):
        idx = np.flatnonzero(keep)
        sub = idx[:: max(1, len(idx) // search_pixels)]
        light = _search(samples.take(sub), n_parts, around=light)
        albedo = solve_albedo(samples.take(idx), light, n_parts)
        keep = _trim(samples, light, albedo, n_parts) & keep
    assert light is not None
    kept = samples.take(np.flatnonzero(keep))
    albedo = solve_albedo(kept, light, n_parts)
    light, albedo = _fold_reflections(kept, light, albedo, n_parts)
    loss = objective(kept, light, albedo, n_parts)
    return LightFit(lighting=light, albedo=albedo, loss=loss, kept=keep)


def shading(s: Samples, light: Lighting) -> tuple[np.ndarray, np.ndarray]:
    """(B, C), each (N, 3): the model is ``albedo[part] * B + C`` (module docstring)."""
    B0, B1, C0, C1 = _affine(s, light.sun_dir)
    sky = np.asarray(light.sky, np.float64)
    C = C0 + C1 * sky
    if light.coat_scale is not None:
        C = C * np.asarray(light.coat_scale, np.float64)[s.part][:, None]
    return B0 + B1 * sky, C


def predict(s: Samples, light: Lighting, albedo: np.ndarray) -> np.ndarray:
    """(N, 3) modelled linear RGB of the samples."""
    return _modelled(s, *shading(s, light), albedo)


def _modelled(s: Samples, B: np.ndarray, C: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """(N, 3) ``albedo[part] * B + C`` (a part without a colour: 0), the samples' shading given."""
    return np.nan_to_num(albedo[s.part]) * B + C


def solve_albedo(s: Samples, light: Lighting, n_parts: int) -> np.ndarray:
    """(P, 3) closed-form base colours under ``light`` (l_rgb + the mean term of l_stat)."""
    B, C = shading(s, light)
    out = np.full((n_parts, 3), np.nan)
    for c in range(3):
        out[:, c] = _closed_form(B[:, c][None], C[:, c][None], s.rgb[:, c], s.part, n_parts)[0]
    return out


def objective(s: Samples, light: Lighting, albedo: np.ndarray, n_parts: int) -> float:
    """``l_rgb + STAT_WEIGHT * l_stat`` of the samples (module docstring)."""
    return shaded_objective(s, *shading(s, light), albedo, n_parts)


def shaded_objective(s: Samples, B: np.ndarray, C: np.ndarray, albedo: np.ndarray,
                     n_parts: int) -> float:
    """``objective`` with the samples' ``shading`` (B, C) given: for a caller that evaluates
    many colours under one light."""
    pred = _modelled(s, B, C, albedo)
    return float(sum(_loss(pred[:, c][None], s.rgb[:, c], s.part, n_parts)[0]
                     for c in range(3)))


def balance(fit: LightFit, neutral: dict[int, float]) -> tuple[LightFit, np.ndarray]:
    """The fit white-balanced on parts known to be neutral grey (``neutral``: part index ->
    weight, e.g. its pixel count): the per-channel gains ``c`` (luminance 1) that would make
    the weighted mean chromaticity of those parts' colours neutral are taken ``BALANCE_SHARE``
    of the way, ``g = c ** BALANCE_SHARE`` (luminance 1 again): the photo's camera has
    balanced most of its cast already, and a tyre's few pixels, shaded and often mixed with
    a rim or the road, are a noisy witness of what is left (docs/FIT.md, "The white balance
    half-way"). Every colour is divided by ``g`` and the light multiplied by it, so the
    model's pixels are unchanged (the light's colour, not the paint's, takes the cast).
    Returns (fit, g); g = 1 without a usable neutral part, or when a gain of ``c`` falls
    outside ``BALANCE_RANGE`` (a cast that strong means the "neutral" part's mask holds
    something else, e.g. paint)."""
    rows = [(fit.albedo[p], w) for p, w in neutral.items()
            if w > 0 and np.all(np.isfinite(fit.albedo[p])) and fit.albedo[p].mean() > 1e-4]
    if not rows:
        return fit, np.ones(3)
    chroma = sum(w * a / a.mean() for a, w in rows) / sum(w for _, w in rows)
    c = neutral_gains(chroma)
    if not plausible_cast(c):
        return fit, np.ones(3)              # not a plausible cast: the "grey" part is not grey
    g = neutral_gains(c ** BALANCE_SHARE)
    light = replace(fit.lighting, sky=fit.lighting.sky * g, sun=fit.lighting.sun * g,
                    white_balance=g)
    return LightFit(lighting=light, albedo=fit.albedo / g, loss=fit.loss, kept=fit.kept), g


def neutral_gains(color: np.ndarray) -> np.ndarray:
    """(3,) per-channel gains of luminance 1 that would make ``color`` (linear RGB) grey."""
    c = np.asarray(color, np.float64)
    return c / float(LUMA @ c)


def plausible_cast(gains: np.ndarray) -> bool:
    """Whether white-balance ``gains`` lie within ``BALANCE_RANGE`` (a daylight cast left by a
    camera's white balance), so the part they come from can be grey under a coloured light."""
    g = np.asarray(gains, np.float64)
    return bool(np.all(np.isfinite(g)) and g.min() >= BALANCE_RANGE[0]
                and g.max() <= BALANCE_RANGE[1])


# ----------------------------------------------------------------------------- internals

def _fold_reflections(s: Samples, light: Lighting, albedo: np.ndarray,
                      n_parts: int) -> tuple[Lighting, np.ndarray]:
    """The light with ``coat_scale`` set and the colours re-solved: a coated part whose
    modelled reflection carries more than ``REFLECTION_MAX`` of its light in every channel
    gets coat_scale 0 (module docstring)."""
    B, C = shading(s, light)
    cnt = np.bincount(s.part, minlength=n_parts).astype(np.float64)
    safe = np.maximum(cnt, 1.0)
    coated = np.bincount(s.part, weights=s.coat, minlength=n_parts) > 0
    mean_c = _sums(C.T, s.part, n_parts).T / safe[:, None]          # (P, 3)
    mean_y = _sums(s.rgb.T, s.part, n_parts).T / safe[:, None]
    share = (mean_c / np.maximum(mean_y, 1e-9)).min(axis=1)       # the least-reflecting channel
    fold = coated & (cnt > 0) & (share > REFLECTION_MAX)
    if not fold.any():
        return light, albedo
    scale = np.where(fold, 0.0, 1.0)
    out = replace(light, coat_scale=scale)
    return out, np.where(fold[:, None], solve_albedo(s, out, n_parts), albedo)


def sun_direction(azimuth: float, elevation: float) -> np.ndarray:
    """Unit vector toward a sun at (azimuth, elevation) degrees, the camera ring's convention
    (azimuth 0 = +X, the vehicle's front; 90 = -Z, its left)."""
    a, e = np.radians(azimuth), np.radians(elevation)
    return np.array([np.cos(e) * np.cos(a), np.sin(e), -np.cos(e) * np.sin(a)])


def _affine(s: Samples, sun_dir: np.ndarray):
    """B = B0 + B1 * sky, C = C0 + C1 * sky (each (N, 1), broadcast over channels)."""
    free = _SunFree(s)
    B0, B1, _, _ = free.sun_terms(sun_dir)
    return B0[:, None], B1[:, None], free.C0[:, None], free.C1[:, None]


class _SunFree:
    """The per-pixel terms of ``_affine`` that do not depend on the sun's direction, computed
    once for the ~60 directions a search scores on the same samples (``sun_terms``: the rest,
    in the same order as computing each direction whole, so the same numbers)."""

    def __init__(self, s: Samples):
        n, v = s.normal, s.view
        ndotv = np.clip(np.einsum("ij,ij->i", n, v), 0.0, 1.0)
        r = 2.0 * ndotv[:, None] * n - v
        w = 0.05 + ENV_BLUR * s.roughness
        t = np.clip((r[:, 1] + w) / (2.0 * w), 0.0, 1.0)
        step = t * t * (3.0 - 2.0 * t)                  # sky share of the mirror direction
        ny = n[:, 1]
        # E(n) = sky (1+ny)/2 + G (1-ny)/2 + (1 - sky) / ly * ndotl
        self.normal = n
        self.ground = GROUND * (1.0 - ny) / 2.0         # E0 without the sun
        self.up = (1.0 + ny) / 2.0                      # E1 without the sun
        L0 = GROUND * (1.0 - step)
        L1 = step
        F = F0 + (1.0 - F0) * (1.0 - ndotv) ** 5
        m, k = s.metallic, s.coat
        self.diffuse = (1.0 - m) * (1.0 - k * F)
        self.mL0, self.mL1 = m * L0, m * L1
        self.C0 = k * F * L0
        self.C1 = k * F * L1

    def sun_terms(self, sun_dir: np.ndarray):
        """(B0, B1, E0, E1), each (N,), for the sun direction ``sun_dir``."""
        ly = max(float(sun_dir[1]), 1e-3)
        ndotl = np.clip(self.normal @ sun_dir, 0.0, None)
        E0 = self.ground + ndotl / ly
        E1 = self.up - ndotl / ly
        return self.diffuse * E0 + self.mL0, self.diffuse * E1 + self.mL1, E0, E1


def _closed_form(B: np.ndarray, C: np.ndarray, y: np.ndarray, part: np.ndarray,
                 n_parts: int) -> np.ndarray:
    """(S, P) base colours minimising, per part, mean((aB + C - y)^2) + 0.1 (a mean(B) +
    mean(C) - mean(y))^2 for S candidate (B, C) rows (S, N) of one channel; NaN without
    pixels."""
    cnt = np.bincount(part, minlength=n_parts).astype(np.float64)
    safe = np.maximum(cnt, 1.0)
    r = y[None] - C
    sbb = _sums(B * B, part, n_parts) / safe
    sbr = _sums(B * r, part, n_parts) / safe
    mb = _sums(B, part, n_parts) / safe
    mr = _sums(r, part, n_parts) / safe
    num = sbr + STAT_WEIGHT * mb * mr
    den = sbb + STAT_WEIGHT * mb * mb
    a = np.divide(num, den, out=np.full_like(num, np.nan), where=den > 1e-12)
    a = np.maximum(a, 0.0)                  # the constrained optimum of a 1-D convex problem
    a[:, cnt == 0] = np.nan
    return a


def _sums(x: np.ndarray, part: np.ndarray, n_parts: int) -> np.ndarray:
    """(S, P) per-part sums of the rows of x (S, N)."""
    S = x.shape[0]
    idx = (np.arange(S)[:, None] * n_parts + part[None]).ravel()
    return np.bincount(idx, weights=x.ravel(), minlength=S * n_parts).reshape(S, n_parts)


def _loss(pred: np.ndarray, y: np.ndarray, part: np.ndarray, n_parts: int) -> np.ndarray:
    """(S,) l_rgb + 0.1 l_stat of S candidate predictions (S, N) of one channel."""
    n = y.shape[0]
    cnt = np.bincount(part, minlength=n_parts).astype(np.float64)
    safe = np.maximum(cnt, 1.0)
    d = pred - y[None]
    l_rgb = (d * d).sum(axis=1) / n
    mp, my = _sums(pred, part, n_parts) / safe, _sums(y[None], part, n_parts) / safe
    vp = _sums(pred * pred, part, n_parts) / safe - mp * mp
    vy = _sums(y[None] * y[None], part, n_parts) / safe - my * my
    l_stat = (((mp - my) ** 2 + (vp - vy) ** 2) * (cnt / n)).sum(axis=1)
    return l_rgb + STAT_WEIGHT * l_stat


class _Moments:
    """Per-part sums of the products of B0, B1, C0, C1 and the photo's channels y, from which
    l_rgb, l_stat and the closed-form colours of any sky share follow in O(parts) (B = B0 + g B1,
    C = C0 + g C1 are affine in the sky share g). One sun direction's: the sums of C and y
    alone come from ``scorer`` (``_Scorer``, shared by the directions)."""

    def __init__(self, scorer: "_Scorer", B0: np.ndarray, B1: np.ndarray):
        sc, free = scorer, scorer.free
        self.n, self.N = sc.n, sc.N
        self.S = [sc.sum(B0), sc.sum(B1), sc.SC[0], sc.SC[1]]
        u = [B0, B1, free.C0, free.C1]
        self.SS = {(k, m): sc.SSC[k, m] if k >= 2 else sc.sum(u[k] * u[m])
                   for k in range(4) for m in range(k, 4)}
        # sums of B0 y, B1 y, C0 y, C1 y, y, y^2: six (3, P) arrays, a row per channel
        rows = [(sc.sum(B0 * sc.rgb[:, c]), sc.sum(B1 * sc.rgb[:, c]), *sc.chan[c])
                for c in range(3)]
        self.T = [np.stack([r[j] for r in rows]) for j in range(6)]

    def losses(self, g: np.ndarray, channels) -> np.ndarray:
        """(G,) l_rgb + 0.1 l_stat at sky shares g (G,), colours in closed form, summed over
        ``channels`` (indices into RGB, added in that order); the channels are evaluated
        together, as (channels, G, P) arrays."""
        S, SS = self.S, self.SS
        g = np.asarray(g, np.float64)[:, None]
        n = np.maximum(self.n, 1.0)
        sB = S[0] + g * S[1]
        sBB = SS[0, 0] + 2 * g * SS[0, 1] + g * g * SS[1, 1]
        sBC = SS[0, 2] + g * (SS[0, 3] + SS[1, 2]) + g * g * SS[1, 3]
        sC = S[2] + g * S[3]
        sCC = SS[2, 2] + 2 * g * SS[2, 3] + g * g * SS[3, 3]
        mb = sB / n
        den = sBB / n + STAT_WEIGHT * mb * mb
        idx = list(channels)
        T0, T1, T2, T3, Y, YY = (t[idx][:, None] for t in self.T)   # each (channels, 1, P)
        sBy = T0 + g * T1
        sCy = T2 + g * T3
        mr = (Y - sC) / n
        num = (sBy - sBC) / n + STAT_WEIGHT * mb * mr
        a = np.maximum(np.divide(num, den, out=np.zeros_like(num), where=den > 1e-12), 0.0)
        sp = a * sB + sC
        spp = a * a * sBB + 2 * a * sBC + sCC
        spy = a * sBy + sCy
        l_rgb = (spp - 2 * spy + YY).sum(axis=2) / self.N
        mp, my = sp / n, Y / n
        vp, vy = spp / n - mp * mp, YY / n - my * my
        l_stat = (((mp - my) ** 2 + (vp - vy) ** 2) * (self.n / self.N)).sum(axis=2)
        loss = l_rgb + STAT_WEIGHT * l_stat                     # (channels, G)
        total = loss[0]
        for c in range(1, len(loss)):
            total = total + loss[c]
        return total


def _channel_search(mom: _Moments, c: int) -> tuple[float, float]:
    """(best sky share, its loss) of channel ``c`` for one sun direction."""
    return _best_share(np.linspace(0.0, 1.0, SKY_STEPS), lambda g: mom.losses(g, (c,)))


def _best_share(grid: np.ndarray, losses) -> tuple[float, float]:
    """(sky share, loss): the grid's best share (ties: the first), moved to the vertex of the
    parabola through it and its two neighbours when that scores lower (``losses(g)``: (G,)
    losses at shares g (G,))."""
    ls = losses(grid)
    k = int(np.argmin(ls))
    best_g, best_l = float(grid[k]), float(ls[k])
    if 0 < k < len(grid) - 1:                       # parabola through the three points
        l0, l1, l2 = ls[k - 1], ls[k], ls[k + 1]
        den = l0 - 2.0 * l1 + l2
        if den > 0:
            g = float(grid[k] + 0.5 * (l0 - l2) / den * (grid[1] - grid[0]))
            lg = float(losses(np.array([g]))[0])
            if lg < best_l:
                best_g, best_l = g, lg
    return best_g, best_l


def _irradiance_cap(E0: np.ndarray, E1: np.ndarray) -> float:
    """The smallest sky share g whose mean diffuse irradiance over the samples, E0 + g E1
    averaged, stays within ``E_MAX`` (0 when every share does; > 1 when none does)."""
    e0 = float(np.mean(E0))
    e1 = float(np.mean(E1))
    if e0 <= E_MAX:
        return 0.0
    return (E_MAX - e0) / e1 if e1 < 0 else 2.0


class _Scorer:
    """Scores sun directions on one set of samples (``_search``): the per-pixel terms
    (``_SunFree``) and the per-part sums that do not depend on the sun (of C0, C1 and the
    photo's channels) computed once."""

    def __init__(self, s: Samples, n_parts: int):
        self.free = free = _SunFree(s)
        self.part, self.P, self.rgb = s.part, n_parts, s.rgb
        self.n = np.bincount(s.part, minlength=n_parts).astype(np.float64)
        self.N = float(len(s.part))
        self.SC = [self.sum(free.C0), self.sum(free.C1)]
        self.SSC = {(2, 2): self.sum(free.C0 * free.C0), (2, 3): self.sum(free.C0 * free.C1),
                    (3, 3): self.sum(free.C1 * free.C1)}
        # per channel: sums of C0 y, C1 y, y, y^2
        self.chan = [(self.sum(free.C0 * y), self.sum(free.C1 * y), self.sum(y), self.sum(y * y))
                     for y in (s.rgb[:, c] for c in range(3))]

    def sum(self, x: np.ndarray) -> np.ndarray:
        """(P,) per-part sums of x (N,)."""
        return np.bincount(self.part, weights=x, minlength=self.P)

    def score(self, d: np.ndarray) -> tuple[float, np.ndarray]:
        """(loss, sky (3,)) of the best sky share for sun direction ``d``: one share for the
        three channels (``SHARED_SKY``; the light's colour is set by ``balance``), else one per
        channel. Shares that light the visible surfaces more than ``E_MAX`` on average are not
        allowed (loss +inf)."""
        B0, B1, E0, E1 = self.free.sun_terms(d)
        g_min = _irradiance_cap(E0, E1)
        if g_min > 1.0:
            return float("inf"), np.ones(3)
        mom = _Moments(self, B0, B1)
        if not SHARED_SKY:
            sky, total = np.zeros(3), 0.0
            for c in range(3):
                g, lc = _channel_search(mom, c)
                sky[c] = g
                total += lc
            return total, sky
        best_g, best_l = _best_share(np.linspace(g_min, 1.0, SKY_STEPS),
                                     lambda g: mom.losses(g, range(3)))
        return best_l, np.full(3, best_g)


def _search(s: Samples, n_parts: int, around: Lighting | None = None) -> Lighting:
    """Best light on the coarse then the fine sun grid (ties: the earlier direction);
    ``around``: only the fine grid around that light's sun (the second, trimmed pass)."""
    step = 360.0 / SUN_AZIMUTHS
    if around is None:
        coarse = [(a * step, e) for e in SUN_ELEVATIONS for a in range(SUN_AZIMUTHS)]
    else:
        d = around.sun_dir
        coarse = [(float(np.degrees(np.arctan2(-d[2], d[0])) % 360.0),
                   float(np.degrees(np.arcsin(np.clip(d[1], -1.0, 1.0)))))]
    scorer = _Scorer(s, n_parts)
    best = None
    for az, el in coarse:
        loss, sky = scorer.score(sun_direction(az, el))
        if best is None or loss < best[0]:
            best = (loss, az, el, sky)
    assert best is not None
    _, az0, el0, _ = best
    for daz in (-step / 3, 0.0, step / 3):
        for de in (-8.0, 0.0, 8.0):
            if daz == 0.0 and de == 0.0:
                continue
            az, el = (az0 + daz) % 360.0, float(np.clip(el0 + de, *SUN_RANGE))
            loss, sky = scorer.score(sun_direction(az, el))
            if loss < best[0]:
                best = (loss, az, el, sky)
    _, az, el, sky = best
    d = sun_direction(az, el)
    return Lighting(sky=sky, sun=(1.0 - sky) / max(d[1], 1e-3), sun_dir=d)


def _trim(s: Samples, light: Lighting, albedo: np.ndarray, n_parts: int) -> np.ndarray:
    """Pixels whose RGB residual is within TRIM_SIGMA robust sigmas of their part's median
    residual (Euclidean distance; sigma = 1.4826 x the median distance, at least MIN_SIGMA)."""
    res = s.rgb - predict(s, light, albedo)
    keep = np.ones(len(res), bool)
    for p in range(n_parts):
        sel = np.flatnonzero(s.part == p)
        if sel.size == 0:
            continue
        r = res[sel]
        dist = np.linalg.norm(r - np.median(r, axis=0), axis=1)
        sigma = max(1.4826 * float(np.median(dist)), MIN_SIGMA)
        keep[sel] = dist <= TRIM_SIGMA * sigma
    return keep


def _r(v) -> list[float]:
    return [round(float(x), 6) for x in np.asarray(v).ravel()]
