"""The paper's l_vgg: masked Gram matrices of a user's ONNX feature extractor, photo vs render.

``refine_colours(features, photo, samples, pixels, fit)`` moves the fitted parts' base colours
from the light model's closed form (``ucad_cl.light.fit_light``) to the least of

    l = l_rgb + 0.1 l_stat + w l_vgg          (UrbanCAD, supplement 8.5: weights 0.1 / 1 / 1)

with the light kept. No weights ship or download: a user points to an ONNX image model
(``onnx:MODEL:CONFIG.json``, ``OnnxFeatures``), e.g. VGG-16 cut after relu1_2, relu2_2 and
relu3_3 and exported with ``torch.onnx.export`` with those layers as its outputs.

**The model.** Input: float32 NCHW RGB, the encoded sRGB values in [0, 1] normalised by the
config's ``mean`` and ``std``; every output named in ``outputs`` (default: all) is a feature
map (N, C, h, w). Config JSON: ``input_size`` [H, W] (required: the working frame is resized
to it, its aspect not kept), ``mean`` and ``std`` (3 floats each; default 0 and 1; ImageNet's
are [0.485, 0.456, 0.406] and [0.229, 0.224, 0.225]), ``outputs`` (names), ``layer_weights``
(one per output; default 1), ``weight`` (w above; default ``VGG_WEIGHT``), ``batch`` (images a
run; default ``BATCH``).

**The term.** For output l with maps F (C_l, h_l, w_l) and part p's mask m resized to
(h_l, w_l) by area (weights in [0, 1]), the masked Gram matrix is
``G_lp = sum_i m_i f_i f_i^T / sum_i m_i`` (C_l x C_l), and

    l_vgg = sum_l layer_weight_l sum_p share_p |G_lp(render) - G_lp(photo)|_F^2 / |G_lp(photo)|_F^2

(``share_p`` the part's share of the fitted pixels; relative, so that layers and models of
any feature scale weigh alike: a choice of ours, the paper does not give its normalisation).
The render is the photo with the fitted pixels replaced by the light model's prediction
(``light.predict`` of the colours), so only the parts' own pixels differ between the two
images. The masks are the fit's eroded part masks (``ucad_cl.fit``, step 4); a part whose
mask weighs less than ``MIN_POSITIONS`` map positions at a layer is left out of that layer's
sum (a Gram over a few positions holds its neighbours' statistics more than its own).

**The solver.** Levenberg-Marquardt on the 3 P base colours (linear RGB) of the fitted parts,
at most ``ITERATIONS`` Jacobians: l_rgb and l_stat are separable per part and channel and their
Gauss-Newton terms are exact (the model's pixels are linear in the colours, ``I = a B + C``);
the Gram terms' Jacobian is by forward differences (``FD_STEP`` on each colour), the 3 P
perturbed renders in one batch through the model. A step is kept only when l falls (else the
damping grows, at most ``TRIALS`` trial steps in all); colours stay >= 0. Cost: one model
run at the start, then 3 P a Jacobian and one a trial step. Deterministic: fixed steps, float64 sums in a fixed order; onnxruntime's
CPU convolutions gave the same bytes on 1, 2 and 4 threads (the tests' network).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .colorimetry import linear_to_srgb
from .labeller import onnx_config, onnx_run, onnx_spec, open_onnx
from .light import STAT_WEIGHT, LightFit, Samples, shaded_objective, shading

VGG_WEIGHT = 1.0        # w of l_vgg against l_rgb (1) and l_stat (0.1): the paper's weights
ITERATIONS = 3          # Levenberg-Marquardt Jacobians at most
TRIALS = 6              # trial steps at most (an accepted one or a rejected one, damping x 4)
FD_STEP = 0.01          # forward-difference step on a linear base colour
DAMPING = 1e-3          # initial damping, share of each diagonal term of the normal matrix
BATCH = 8               # images a model run
MIN_POSITIONS = 16.0    # a part's mask weight at a layer under this: not in that layer's term
MAX_INPUT = 2048        # the longest input side a config may ask for, pixels


class OnnxFeatures:
    """A user ONNX feature extractor and its config (the module docstring); ValueError naming
    the file for a config or model that does not fit the contract (the model is run once on a
    blank image of ``input_size`` when loaded, so that a fit never meets that)."""

    def __init__(self, model_path: str | Path, config: str | Path | dict):
        config, where = onnx_config(config)
        if "input_size" not in config:
            raise ValueError(f"{where}: the config needs 'input_size' [H, W]")
        try:
            self.input_size = tuple(int(x) for x in config["input_size"])
            self.mean = np.asarray(config.get("mean", [0.0] * 3), np.float32).reshape(3)
            self.std = np.asarray(config.get("std", [1.0] * 3), np.float32).reshape(3)
            self.weight = float(config.get("weight", VGG_WEIGHT))
            self.batch = int(config.get("batch", BATCH))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{where}: {exc}") from None
        if len(self.input_size) != 2 or not 8 <= min(self.input_size) <= max(self.input_size) \
                <= MAX_INPUT:
            raise ValueError(f"{where}: input_size must be [H, W], each 8-{MAX_INPUT}, got "
                             f"{config['input_size']}")
        if not (np.all(self.std > 0) and np.all(np.isfinite(self.mean))
                and self.weight >= 0 and self.batch >= 1):
            raise ValueError(f"{where}: std must be > 0, weight >= 0, batch >= 1")
        self.model_path, self.session, self.input_name = open_onnx(model_path)
        names = [o.name for o in self.session.get_outputs()]
        self.outputs = [str(n) for n in config.get("outputs", names)]
        missing = [n for n in self.outputs if n not in names]
        if missing or not self.outputs:
            raise ValueError(f"{self.model_path}: no output named {missing or '(none given)'} "
                             f"(the model's: {names})")
        lw = config.get("layer_weights", [1.0] * len(self.outputs))
        self.layer_weights = np.asarray(lw, np.float64).ravel()
        if len(self.layer_weights) != len(self.outputs) or np.any(self.layer_weights < 0):
            raise ValueError(f"{where}: layer_weights needs {len(self.outputs)} values >= 0")
        self.maps(np.zeros((1, *self.input_size, 3), np.float32))   # the contract, checked now

    @classmethod
    def from_spec(cls, spec: str) -> "OnnxFeatures":
        """From ``onnx:MODEL:CONFIG.json`` (``labeller.onnx_spec``)."""
        return cls(*onnx_spec(spec))

    @property
    def name(self) -> str:
        return self.model_path.name

    def maps(self, images: np.ndarray) -> list[np.ndarray]:
        """Feature maps, one (N, C, h, w) float64 array per output, of ``images`` (N, H, W, 3)
        encoded sRGB in [0, 1] at ``input_size``."""
        x = (np.asarray(images, np.float32) - self.mean) / self.std
        x = np.ascontiguousarray(x.transpose(0, 3, 1, 2))
        runs = []
        for i in range(0, len(x), self.batch):
            got = onnx_run(self.session, self.model_path, self.outputs,
                           {self.input_name: x[i:i + self.batch]},
                           f"the model (input_size {list(self.input_size)})")
            for name, y in zip(self.outputs, got):
                y = np.asarray(y)
                if y.ndim != 4 or y.shape[0] != len(x[i:i + self.batch]) \
                        or not np.issubdtype(y.dtype, np.floating):
                    raise ValueError(f"{self.model_path}: output {name!r} must be (N, C, h, w) "
                                     f"float feature maps, got {y.dtype} {y.shape}")
            runs.append(got)
        return [np.concatenate([r[k] for r in runs]).astype(np.float64)
                for k in range(len(self.outputs))]

    def resize(self, image: np.ndarray) -> np.ndarray:
        """(H, W, ...) float image at the model's input size (area averaging)."""
        import cv2

        h, w = self.input_size
        return cv2.resize(np.asarray(image, np.float32), (w, h), interpolation=cv2.INTER_AREA)


def masked_grams(fmap: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """(N, P, C, C) Gram matrices ``sum_i m_i f_i f_i^T / sum_i m_i`` of feature maps ``fmap``
    (N, C, h, w) under each of ``masks`` (P, h, w) weights (a mask of zero weight: zeros)."""
    N, C = fmap.shape[:2]
    flat = fmap.reshape(N, C, -1)
    out = np.zeros((N, len(masks), C, C))
    for p, m in enumerate(np.asarray(masks, np.float64).reshape(len(masks), -1)):
        on = np.flatnonzero(m > 0)
        if on.size == 0:
            continue
        f = flat[:, :, on] * np.sqrt(m[on])
        out[:, p] = f @ f.transpose(0, 2, 1) / m[on].sum()
    return out


@dataclass
class VggFit:
    """What ``refine_colours`` did: the model, l (the module docstring's total) and l_vgg
    before and after, Jacobians and model runs used, seconds."""

    model: str
    weight: float
    loss_before: float
    loss_after: float
    vgg_before: float
    vgg_after: float
    jacobians: int
    images: int
    seconds: float

    def to_json(self) -> dict:
        return {"model": self.model, "weight": self.weight,
                "loss_before": round(self.loss_before, 8), "loss_after": round(self.loss_after, 8),
                "l_vgg_before": round(self.vgg_before, 8), "l_vgg_after": round(self.vgg_after, 8),
                "jacobians": self.jacobians, "images": self.images,
                "seconds": round(self.seconds, 3)}


def refine_colours(features: OnnxFeatures, photo: np.ndarray, samples: Samples,
                   pixels: tuple[np.ndarray, np.ndarray], fit: LightFit) -> tuple[LightFit, VggFit]:
    """``fit`` with its base colours moved to the least of l_rgb + 0.1 l_stat + w l_vgg (the
    module docstring), its light kept. ``photo`` (h, w, 3) uint8 sRGB, the working frame;
    ``samples`` the fitted pixels at ``pixels`` (rows, columns) of it, in order (their parts
    index ``fit.albedo``); l_rgb and l_stat over the pixels ``fit.kept``, as ``fit_light``."""
    t0 = time.perf_counter()
    B, C = shading(samples, fit.lighting)              # the model's pixels: a[part] B + C
    term = _GramTerm(features, photo, samples, B, C, pixels, len(fit.albedo))
    a = np.array(fit.albedo, np.float64)
    free = np.flatnonzero(np.isfinite(a).all(axis=1))          # parts with kept pixels
    idx = np.flatnonzero(fit.kept)
    kept, Bk, Ck = samples.take(idx), B[idx], C[idx]
    P = len(a)
    base = _BaseTerm(kept, Bk, Ck, free)
    v0, g0 = term.value(a)
    base0 = shaded_objective(kept, Bk, Ck, a, P)
    loss0 = base0 + features.weight * v0
    best, best_v, best_l, best_base = a, v0, loss0, base0
    lam, jacobians, trials = DAMPING, 0, 0
    while jacobians < ITERATIONS and trials < TRIALS and free.size:
        jtj, jtr = base.normal(best)
        vj, vr = term.normal(best, free, g0)
        jtj, jtr = jtj + features.weight * vj, jtr + features.weight * vr
        jacobians += 1
        diag = np.maximum(np.diag(jtj), 1e-12)
        moved = False
        while trials < TRIALS:
            trials += 1
            step = np.linalg.solve(jtj + lam * np.diag(diag), -jtr)
            cand = best.copy()
            cand[free] = np.maximum(best[free] + step.reshape(-1, 3), 0.0)
            v, g = term.value(cand)
            lb = shaded_objective(kept, Bk, Ck, cand, P)
            lc = lb + features.weight * v
            if lc < best_l:
                best, best_v, best_l, best_base, g0 = cand, v, lc, lb, g
                lam /= 4.0
                moved = True
                break
            lam *= 4.0
        if not moved:
            break
    out = replace(fit, albedo=best, loss=float(best_base))
    info = VggFit(model=features.name, weight=features.weight, loss_before=float(loss0),
                  loss_after=float(best_l), vgg_before=float(v0), vgg_after=float(best_v),
                  jacobians=jacobians, images=term.images, seconds=time.perf_counter() - t0)
    return out, info


class _BaseTerm:
    """Gauss-Newton normal matrix (diagonal) and J^T r of l_rgb + 0.1 l_stat in the colours of
    the parts ``free`` (rows (part, channel), part-major), exact: the model is linear in each
    colour and the terms are separable per part and channel, so per-part sums of the pixels'
    B, C (``light.shading`` of ``kept``) and y taken once give them at any colours."""

    def __init__(self, kept: Samples, B: np.ndarray, C: np.ndarray, free: np.ndarray):
        y, part = kept.rgb, kept.part
        self.free, self.N = free, float(len(part))
        rows = []
        for p in free:
            on = part == p
            b, c, yy = B[on], C[on], y[on]                       # (n, 3) each
            mb, mc = b.mean(axis=0), c.mean(axis=0)
            rows.append((float(np.count_nonzero(on)), (b * b).sum(axis=0),
                         (b * (c - yy)).sum(axis=0), mb, mc - yy.mean(axis=0), b.var(axis=0),
                         ((b - mb) * (c - mc)).mean(axis=0), c.var(axis=0), yy.var(axis=0)))
        self.rows = rows

    def normal(self, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        jtj, jtr = np.zeros(3 * len(self.free)), np.zeros(3 * len(self.free))
        for j, (p, (n, sbb, sbr, mb, dm, vb, cbc, vc, vy)) in enumerate(zip(self.free,
                                                                             self.rows)):
            x = a[p]
            share = STAT_WEIGHT * n / self.N
            dv = 2.0 * (x * vb + cbc)                 # d/da of the model's variance
            k = slice(3 * j, 3 * j + 3)
            jtj[k] = sbb / self.N + share * (mb * mb + dv * dv)
            jtr[k] = ((x * sbb + sbr) / self.N + share * mb * (x * mb + dm)
                      + share * dv * (x * x * vb + 2.0 * x * cbc + vc - vy))
        return np.diag(jtj), jtr


class _GramTerm:
    """l_vgg of base colours: the photo's Grams once, a render's per call (module docstring)."""

    def __init__(self, features: OnnxFeatures, photo, samples: Samples, B: np.ndarray,
                 C: np.ndarray, pixels, P: int):
        import cv2

        self.f, self.part, self.B, self.C = features, samples.part, B, C
        self.rows, self.cols = pixels
        self.photo = np.asarray(photo, np.float64) / 255.0
        h, w = self.photo.shape[:2]
        part_masks = np.zeros((P, h, w), np.float32)
        part_masks[samples.part, self.rows, self.cols] = 1.0
        n = np.bincount(samples.part, minlength=P).astype(np.float64)
        self.share = n / max(n.sum(), 1.0)
        self.images = 1
        photo_maps = features.maps(features.resize(self.photo)[None])
        H, W = features.input_size
        at_input = [cv2.resize(m, (W, H), interpolation=cv2.INTER_AREA) for m in part_masks]
        self.masks, self.target, self.scale = [], [], []
        for k, fm in enumerate(photo_maps):
            hl, wl = fm.shape[2:]
            ml = np.stack([cv2.resize(m, (wl, hl), interpolation=cv2.INTER_AREA)
                           for m in at_input])
            g = masked_grams(fm, ml)[0]                                  # (P, C, C)
            norm = (g * g).sum(axis=(1, 2))
            big = ml.reshape(P, -1).sum(axis=1) >= MIN_POSITIONS
            wt = features.layer_weights[k] * self.share * big
            self.masks.append(ml)
            self.target.append(g)
            self.scale.append(np.where(norm > 0, wt / np.maximum(norm, 1e-300), 0.0))

    def render(self, colours: np.ndarray) -> np.ndarray:
        """(H, W, 3) the photo with the fitted pixels predicted from ``colours``, resized."""
        img = self.photo.copy()
        pred = np.nan_to_num(colours)[self.part] * self.B + self.C       # light.predict
        img[self.rows, self.cols] = np.clip(linear_to_srgb(pred), 0.0, 1.0)
        return self.f.resize(img)

    def _grams(self, colour_sets: list[np.ndarray]) -> list[np.ndarray]:
        maps = self.f.maps(np.stack([self.render(c) for c in colour_sets]))
        self.images += len(colour_sets)
        return [masked_grams(fm, m) for fm, m in zip(maps, self.masks)]     # (N, P, C, C)

    def value(self, colours: np.ndarray) -> tuple[float, list[np.ndarray]]:
        """(l_vgg, the render's Grams) of ``colours``."""
        grams = [g[0] for g in self._grams([colours])]
        return self._loss(grams), grams

    def _loss(self, grams: list[np.ndarray]) -> float:
        return float(sum((s * ((g - t) ** 2).sum(axis=(1, 2))).sum()
                         for g, t, s in zip(grams, self.target, self.scale)))

    def normal(self, colours: np.ndarray, free: np.ndarray,
               grams: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Gauss-Newton normal matrix and J^T r of l_vgg at ``colours`` (whose Grams are
        ``grams``), the Jacobian by forward differences of the colours of parts ``free``."""
        sets = []
        for p in free:
            for c in range(3):
                x = colours.copy()
                x[p, c] += FD_STEP
                sets.append(x)
        moved = self._grams(sets)
        K = len(sets)
        jtj, jtr = np.zeros((K, K)), np.zeros(K)
        for g0, gk, t, s in zip(grams, moved, self.target, self.scale):
            w = np.sqrt(s)[:, None, None]
            r = (w * (g0 - t)).reshape(-1)
            J = (w[None] * (gk - g0[None]) / FD_STEP).reshape(K, -1)
            jtj += J @ J.T
            jtr += J @ r
        return jtj, jtr
