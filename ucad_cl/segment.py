"""Part segmenters: rendered views of a mesh -> per-view part masks (``PartMasks``).

Every segmenter has one method, ``segment(mesh, views) -> PartMasks`` with masks (V, P, H, W)
bool or packed (V, H, W) uint16 bits (see ``PartMasks``) and confidence (V, P) float32 in [0, 1];
``classify.classify_parts`` turns those into material -> part labels. Part names are
``ucad_cl.artifacts.PART_NAMES``. Four implementations:

* ``LabellerSegmenter(model=None, use_names=True)``: the offline default. The learned labeller
  (``ucad_cl.labeller``: per-material features -> ONNX gradient-boosted trees) gives every
  material part probabilities; each material's pixels are painted with its most probable part,
  and a part's confidence in a view is that probability averaged over the part's pixels. The
  masks carry the labeller's answer (``PartMasks.labels``), so ``classify_parts`` reports its
  probability, labels materials seen only through glass and reports shared-material splits.

* ``MasksSegmenter(root)``: masks made elsewhere (e.g. ControlNet + Grounded SAM on a GPU box),
  read from the folder layout written by ``write_masks``::

      ROOT/<mesh sha256>/view_<vvv>/<part>.png   8-bit grey (or colour: first channel), > 127 = in
      ROOT/<mesh sha256>/confidence.json         {"<view index>": {"<part>": conf in [0, 1]}}

  A missing PNG is an empty mask with confidence 0; a missing confidence entry for a present mask
  is confidence 1. A PNG whose size is not the views' size is an error naming the file.
* ``OnnxSegmenter(model_path, config)``: a user ONNX model run with onnxruntime on the CPU.
  Contract: input NCHW float32 in [0, 1], the view's colour-coded material map as RGB
  (``material_image``: fixed colour per material id, background black), resized to the config's
  ``input_size`` [H, W] with nearest-neighbour; output either a class map (N, H, W) of integers
  (confidence 1 for every non-empty mask) or logits (N, C, H, W) (softmax over C; mask = argmax;
  confidence = mean max-probability inside the mask). Outputs are resized back with nearest
  neighbour. ``config = {"classes": {"<index>": "<part or anything else>"}, "input_size": [H, W],
  "batch": 8}``; classes whose name is not a part (e.g. "background") are ignored.
* ``PriorSegmenter()``: the former offline default, without any model. It guesses a part per material from
  its name (many languages), its properties (transparency, emission, metal, colour) and its
  geometry in the canonical frame (+Y up; the longer horizontal axis is the length), and paints
  each material's pixels with its most probable part. Confidence of a part in a view = that
  guess's probability averaged over the part's pixels in the view.
"""
from __future__ import annotations

import colorsys
import json
from pathlib import Path
from typing import Protocol

import numpy as np

from .artifacts import PART_NAMES, Mesh, PartMasks, ViewSet
from .labeller import (MODEL_PATH, LabellerModel, label_materials, onnx_config, onnx_run,
                       onnx_spec, open_onnx)
from .names import name_prior
from .runtime import Runtime
from .system import IsolatedCallFailed, call_isolated


class Segmenter(Protocol):
    def segment(self, mesh: Mesh, views: ViewSet) -> PartMasks: ...


def masks_from_labels(views: ViewSet, labels: dict[int, str], *, confidence: float = 1.0,
                      source: str = "labels") -> PartMasks:
    """Part masks painting material index m's pixels with part ``labels[m]`` (ground truth, ...)."""
    lut = np.zeros(int(views.mat_id.max(initial=0)) + 2 + max(labels, default=0), np.uint16)
    for m, part in labels.items():
        if part not in PART_NAMES:
            raise ValueError(f"material {m}: unknown part {part!r}; expected one of {PART_NAMES}")
        lut[m + 1] = 1 << PART_NAMES.index(part)
    pm = PartMasks.from_bits(list(PART_NAMES), lut[views.mat_id], None, source=source)
    pm.confidence = np.where(pm.nonempty(), np.float32(confidence), np.float32(0))
    return pm


# ---------------------------------------------------------------------------------------------
# Masks from a folder
# ---------------------------------------------------------------------------------------------
class MasksSegmenter:
    """Reads ``ROOT/<sha256>/view_<vvv>/<part>.png`` and ``confidence.json`` (see module doc)."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        if not self.root.is_dir():
            raise FileNotFoundError(f"masks folder {self.root} does not exist")

    def segment(self, mesh: Mesh, views: ViewSet) -> PartMasks:
        import cv2

        V, H, W = views.mat_id.shape
        P = len(PART_NAMES)
        base = self.root / mesh.sha256
        masks = np.zeros((V, P, H, W), bool)
        conf = np.zeros((V, P), np.float32)
        table = {}
        cpath = base / "confidence.json"
        if cpath.exists():
            try:
                table = json.loads(cpath.read_text(encoding="utf-8-sig"))   # a BOM dropped
            except json.JSONDecodeError as exc:
                raise ValueError(f"{cpath}: not valid JSON ({exc})") from exc
        for v in range(V):
            for p, part in enumerate(PART_NAMES):
                f = base / f"view_{v:03d}" / f"{part}.png"
                if not f.exists():
                    continue
                img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
                if img is None:
                    raise ValueError(f"{f}: cannot be read as an image")
                if img.dtype != np.uint8:
                    raise ValueError(f"{f}: expected an 8-bit image, got {img.dtype}")
                if img.ndim == 3:
                    img = img[:, :, 0]
                if img.shape != (H, W):
                    raise ValueError(f"{f}: mask is {img.shape[1]}x{img.shape[0]} pixels but the "
                                     f"views are {W}x{H}")
                masks[v, p] = img > 127
                c = table.get(str(v), {}).get(part, 1.0)
                if not 0.0 <= float(c) <= 1.0:
                    raise ValueError(f"{cpath}: confidence {c} of view {v} part {part} "
                                     "not in [0, 1]")
                conf[v, p] = float(c) if masks[v, p].any() else 0.0
        return PartMasks(parts=list(PART_NAMES), masks=masks, confidence=conf,
                         source=f"masks:{self.root}")


def write_masks(root: str | Path, sha: str, masks: PartMasks) -> Path:
    """Write ``masks`` in the ``MasksSegmenter`` layout (non-empty masks only); returns the dir."""
    import cv2

    base = Path(root) / sha
    base.mkdir(parents=True, exist_ok=True)
    table: dict[str, dict[str, float]] = {}
    nonempty = masks.nonempty()
    for v in range(nonempty.shape[0]):
        for p, part in enumerate(masks.parts):
            if part not in PART_NAMES:
                raise ValueError(f"unknown part {part!r}; expected one of {PART_NAMES}")
            if not nonempty[v, p]:
                continue
            d = base / f"view_{v:03d}"
            d.mkdir(exist_ok=True)
            if not cv2.imwrite(str(d / f"{part}.png"), masks.masks[v, p].astype(np.uint8) * 255):
                raise OSError(f"cannot write {d / f'{part}.png'}")
            table.setdefault(str(v), {})[part] = float(masks.confidence[v, p])
    (base / "confidence.json").write_text(json.dumps(table, indent=1), encoding="utf-8")
    return base


# ---------------------------------------------------------------------------------------------
# ONNX model
# ---------------------------------------------------------------------------------------------
def material_colors(n_ids: int) -> np.ndarray:
    """(n_ids, 3) uint8 RGB: id 0 black, id k a fixed colour (golden-ratio hue, two values)."""
    out = np.zeros((n_ids, 3), np.uint8)
    for k in range(1, n_ids):
        h = (k * 0.6180339887498949) % 1.0
        r, g, b = colorsys.hsv_to_rgb(h, 0.85, 1.0 if k % 2 else 0.6)
        out[k] = np.round(np.array([r, g, b]) * 255)
    return out


def material_image(mat_id: np.ndarray) -> np.ndarray:
    """(V, H, W, 3) uint8 RGB colour-coded material maps (``material_colors``)."""
    return material_colors(int(mat_id.max(initial=0)) + 1)[mat_id]


# The --segmenter spellings, one table for every command (kind -> (spelling, what it is)).
SEGMENTER_SPECS: dict[str, tuple[str, str]] = {
    "labeller": ("labeller[:MODEL.onnx]", "the learned per-material labeller shipped with the "
                 "package (default, offline), or another labeller model"),
    "prior": ("prior", "hand-written rules (names, colours, geometry)"),
    "masks": ("masks:DIR", "part masks made elsewhere: DIR/<sha256>/view_<vvv>/<part>.png"),
    "onnx": ("onnx:MODEL:CONFIG.json", "a user ONNX image segmentation model and its config"),
}


def segmenter_help() -> str:
    """The spellings of ``SEGMENTER_SPECS`` for ``--help`` texts."""
    return "; ".join(f"{spell}: {what}" for spell, what in SEGMENTER_SPECS.values())


def segmenter_from_spec(spec: str, runtime: Runtime | None = None):
    """A segmenter from a ``--segmenter`` SPEC (``SEGMENTER_SPECS``); ValueError naming the
    accepted spellings otherwise. ``runtime``: the device of segmenters that render."""
    kind, _, arg = str(spec).partition(":")
    if kind == "onnx":                      # one reading of onnx:MODEL:CONFIG for every command
        try:
            model, config = onnx_spec(spec)
        except ValueError as exc:
            raise ValueError(f"--segmenter {spec}: {exc}") from None
        return make_segmenter(kind, model, config, runtime=runtime)
    return make_segmenter(kind, arg or None, runtime=runtime)


def check_segmenter_spec(spec: str, *, timeout: float = 300.0) -> None:
    """Build the segmenter ``spec`` names in a child process and drop it: ValueError /
    FileNotFoundError as ``segmenter_from_spec`` raises them (a missing or stale model, a bad
    config, a file onnxruntime cannot load), ValueError when loading it crashes the child. The
    build driver checks a spec this way before starting workers: an onnxruntime session would
    otherwise stay in its memory."""
    try:
        call_isolated(_segmenter_loads, str(spec), timeout=timeout)
    except IsolatedCallFailed as exc:
        raise ValueError(f"--segmenter {spec}: loading it failed: {exc}") from None


def _segmenter_loads(spec: str) -> None:
    """The child side of ``check_segmenter_spec``."""
    segmenter_from_spec(spec)


def make_segmenter(kind: str, arg: str | None = None, config: str | Path | dict | None = None,
                   *, runtime: Runtime | None = None):
    """The one factory behind every CLI spelling: ``labeller`` (optionally with a model ``arg``),
    ``prior``, ``masks`` with a folder ``arg``, or ``onnx`` with a model ``arg`` and a
    ``config`` (JSON path or dict). ValueError otherwise."""
    if kind == "labeller":
        return LabellerSegmenter(arg or None, runtime=runtime)
    if kind == "prior" and not arg:
        return PriorSegmenter()
    if kind == "masks" and arg:
        return MasksSegmenter(arg)
    if kind == "onnx" and arg:
        if config is None:
            raise ValueError("the onnx segmenter needs a config JSON (classes, input_size)")
        return OnnxSegmenter(arg, config)
    raise ValueError(f"unknown segmenter {kind!r}{':' + arg if arg else ''}: expected "
                     + ", ".join(spell for spell, _ in SEGMENTER_SPECS.values()))


class OnnxSegmenter:
    """Runs a user ONNX segmentation model under the contract in the module docstring."""

    def __init__(self, model_path: str | Path, config: dict | str | Path):
        config, where = onnx_config(config)
        if "classes" not in config or "input_size" not in config:
            raise ValueError(f"{where}: an ONNX config needs 'classes' {{index: part}} and "
                             "'input_size' [H, W]")
        try:
            self.classes = {int(k): str(v) for k, v in dict(config["classes"]).items()}
            self.input_size = tuple(int(x) for x in config["input_size"])
            self.batch = int(config.get("batch", 8))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{where}: {exc}") from None
        if len(self.input_size) != 2 or min(self.input_size) < 1:
            raise ValueError(f"{where}: input_size must be [H, W] > 0, got "
                             f"{config['input_size']}")
        self.model_path, self.session, self.input_name = open_onnx(model_path)

    def segment(self, mesh: Mesh, views: ViewSet) -> PartMasks:
        import cv2

        V, H, W = views.mat_id.shape
        h, w = self.input_size
        rgb = material_image(views.mat_id)
        P = len(PART_NAMES)
        masks = np.zeros((V, P, H, W), bool)
        conf = np.zeros((V, P), np.float32)
        for v0 in range(0, V, self.batch):
            x = np.stack([cv2.resize(im, (w, h), interpolation=cv2.INTER_NEAREST)
                          for im in rgb[v0:v0 + self.batch]])
            x = np.ascontiguousarray(x.transpose(0, 3, 1, 2), np.float32) / np.float32(255)
            y = np.asarray(onnx_run(self.session, self.model_path, None, {self.input_name: x},
                                    f"the segmenter (input_size {list(self.input_size)})")[0])
            n = x.shape[0]
            if y.ndim == 3 and np.issubdtype(y.dtype, np.integer):
                cls, prob = y.astype(np.int64), None
            elif y.ndim == 4 and np.issubdtype(y.dtype, np.floating):
                z = y.astype(np.float64)
                z = np.exp(z - z.max(axis=1, keepdims=True))
                z /= z.sum(axis=1, keepdims=True)
                cls, prob = z.argmax(axis=1), z.max(axis=1)          # ties -> lower class index
            else:
                raise ValueError(f"{self.model_path}: output must be an (N, H, W) integer class "
                                 f"map "
                                 f"or (N, C, H, W) float logits, got {y.dtype} {y.shape}")
            if y.shape[0] != n or cls.shape[1:] != (h, w):
                raise ValueError(f"{self.model_path}: output {y.shape} does not match the input "
                                 f"batch {n} x {h} x {w}")
            for k in range(n):
                c_full = cv2.resize(cls[k].astype(np.int32), (W, H),
                                    interpolation=cv2.INTER_NEAREST)
                for ci, part in self.classes.items():
                    if part not in PART_NAMES:
                        continue
                    p = PART_NAMES.index(part)
                    m = c_full == ci
                    masks[v0 + k, p] |= m
                    inside = cls[k] == ci
                    if inside.any():
                        conf[v0 + k, p] = 1.0 if prob is None else float(prob[k][inside].mean())
        return PartMasks(parts=list(PART_NAMES), masks=masks, confidence=conf,
                         source=f"onnx:{self.model_path.name}")


# ---------------------------------------------------------------------------------------------
# Priors: names, properties, geometry
def material_features(mesh: Mesh, views: ViewSet | None = None) -> dict[str, np.ndarray]:
    """Per-material geometry in the vehicle frame (all (M,) float64, area-weighted over faces).

    Vehicle frame: h = height above the bbox bottom / bbox height in [0, 1]; u = position along the
    longer horizontal axis / half-length in [-1, 1]; w = across / half-width. Keys: area (share of
    the surface), h, abs_u, abs_w (means), wheel_zone (share of area low, near the ends, at the
    sides), end_zone (share at the extreme front/back at mid height), upper (share above the belt
    line h > 0.55), centre_w (share with |w| < 0.35), plate_zone (share at the extreme ends near
    the centre line, low), cabin (share inside the cabin volume: central, mid height), roof (share
    facing up or down within 32 degrees, high on the vehicle), flat (largest eigenvalue of the
    area-weighted normal scatter: 1 for a plane), visible
    (share of visible pixels over all views) and exposure (visible share / surface share).
    """
    M = len(mesh.materials)
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces, np.int64)
    fm = np.asarray(mesh.face_material, np.int64)
    out = {k: np.zeros(M) for k in ("area", "h", "abs_u", "abs_w", "wheel_zone", "end_zone",
                                     "upper", "centre_w", "plate_zone", "cabin", "roof", "flat",
                                     "visible",
                                     "exposure")}
    if f.shape[0] == 0:
        return out
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])       # 2 * area * unit normal
    norm = np.linalg.norm(n, axis=1)
    area = 0.5 * norm
    c = (tri[:, 0] + tri[:, 1] + tri[:, 2]) / 3                       # = tri.mean(axis=1)
    used = np.zeros(v.shape[0], bool)
    used[f.ravel()] = True
    lo, hi = v[used].min(axis=0), v[used].max(axis=0)                # referenced vertices only
    mid, half = 0.5 * (lo + hi), np.maximum(0.5 * (hi - lo), 1e-12)
    la, wa = (0, 2) if half[0] >= half[2] else (2, 0)
    h = (c[:, 1] - lo[1]) / (2 * half[1])
    au = np.abs(c[:, la] - mid[la]) / half[la]
    aw = np.abs(c[:, wa] - mid[wa]) / half[wa]
    tot = np.bincount(fm, weights=area, minlength=M)
    tot_safe = np.maximum(tot, 1e-30)

    def share(mask):
        return np.bincount(fm, weights=area * mask, minlength=M) / tot_safe

    out["area"] = tot / max(tot.sum(), 1e-30)
    out["h"] = share(h)
    out["abs_u"] = share(au)
    out["abs_w"] = share(aw)
    out["wheel_zone"] = share((h < 0.42) & (au > 0.35) & (au < 0.9) & (aw > 0.5))
    out["plate_zone"] = share((au > 0.9) & (aw < 0.4) & (h < 0.6))
    out["cabin"] = share((au < 0.5) & (aw < 0.55) & (h > 0.15) & (h < 0.7))
    safe = np.maximum(norm, 1e-30)
    ny = np.abs(n[:, 1]) / safe
    out["roof"] = share((ny > 0.85) & (h > 0.8))
    unit = n / safe[:, None]
    # per-material sums of area * u u^T: one weighted bincount per entry (in face order, as a
    # scatter-add would sum them)
    scatter = (area[:, None, None] * unit[:, :, None] * unit[:, None, :]).reshape(-1, 9)
    outer = np.stack([np.bincount(fm, weights=scatter[:, k], minlength=M) for k in range(9)],
                     axis=1).reshape(M, 3, 3)
    out["flat"] = np.linalg.eigvalsh(outer / tot_safe[:, None, None])[:, -1]
    out["end_zone"] = share((au > 0.82) & (h > 0.1) & (h < 0.85))
    out["upper"] = share(h > 0.55)
    out["centre_w"] = share(aw < 0.35)
    if views is not None:
        seen = views.material_counts().sum(axis=0)[1:M + 1]       # ids above M are ignored
        vis = np.zeros(M)
        vis[:seen.size] = seen
        out["visible"] = vis / max(vis.sum(), 1.0)
        out["exposure"] = out["visible"] / np.maximum(out["area"], 1e-9)
    return out


def _srgb_luma(rgb) -> float:
    r, g, b = (float(x) for x in rgb[:3])
    return 0.2126 * r + 0.7152 * g + 0.0722 * b


def _appearance(mat) -> tuple:
    """Materials that look alike (the same paint on several panels) share this key."""
    if mat.has_texture:                      # colour unknown: never grouped with another
        return (id(mat),)
    return (tuple(np.round(np.asarray(mat.base_color, float) / 0.02).astype(int)),
            round(mat.metallic / 0.05), round(mat.roughness / 0.05), mat.has_texture,
            mat.alpha_mode, max(mat.emissive) > 0.1)


def _body_group(mesh: Mesh, share: np.ndarray) -> set[int]:
    """Materials of the appearance group with the largest visible (or surface) share: the paint."""
    groups: dict[tuple, list[int]] = {}
    for m, mat in enumerate(mesh.materials):
        groups.setdefault(_appearance(mat), []).append(m)
    if not groups:
        return set()
    best = max(groups.values(), key=lambda ms: (float(share[ms].sum()), -ms[0]))
    return set(best)


class PriorSegmenter:
    """Guesses parts per material from names, properties and geometry (see ``guess``)."""

    NAME_WEIGHT = 8.0

    def __init__(self, use_names: bool = True):
        self.use_names = use_names

    def guess(self, mesh: Mesh, views: ViewSet | None = None) -> np.ndarray:
        """(M, len(PART_NAMES)) float64 per-material part probabilities (rows sum to 1)."""
        M, P = len(mesh.materials), len(PART_NAMES)
        idx = {p: i for i, p in enumerate(PART_NAMES)}
        g = material_features(mesh, views)
        logit = np.zeros((M, P))
        logit[:, idx["body"]] += 0.5
        logit[:, idx["other"]] += 0.3
        body_group = _body_group(mesh, g["visible"] if views is not None else g["area"])
        for m, mat in enumerate(mesh.materials):
            L = logit[m]
            if self.use_names:
                part = name_prior(mat.name)
                if part:
                    L[idx[part]] += self.NAME_WEIGHT
            luma = _srgb_luma(mat.base_color) if not mat.has_texture else 0.5
            rgb = np.asarray(mat.base_color[:3], float)
            sat = float(rgb.max() - rgb.min()) / max(float(rgb.max()), 1e-6)
            clear = mat.transmission > 0.05 or mat.base_color[3] < 0.95 or mat.alpha_mode == "BLEND"
            wz = float(np.clip((g["wheel_zone"][m] - 0.3) / 0.3, 0.0, 1.0))
            ez, up, cab = g["end_zone"][m], g["upper"][m], g["cabin"][m]
            corner = g["centre_w"][m] < 0.35          # lamps sit off the centre line
            small = g["area"][m] < 0.06
            colourful = sat > 0.4 and luma > 0.03
            # (b) properties
            if clear:
                L[idx["window"]] += 0.5 + 2.5 * up
                L[idx["light"]] += 2.5 * ez * corner
            if max(mat.emissive) > 0.1 and not mat.has_texture:
                L[idx["light"]] += 2.5
            if mat.metallic >= 0.5 and mat.roughness <= 0.45:
                L[idx["chrome"]] += 2.0
                L[idx["rim"]] += 2.5 * wz
            # (c) geometry: wheels low near the ends of the long axis at the sides; a textured
            # material there is the whole wheel (tyre + hub), a dark one the tyre, a bright one rim
            tyre_like = mat.has_texture or luma < 0.1
            L[idx["wheel"]] += 4.0 * wz * (1.0 if tyre_like else 0.2)
            L[idx["rim"]] += 4.0 * wz * (0.2 if tyre_like else 1.0)
            if small and ez > 0.5 and (corner or colourful):
                L[idx["light"]] += 1.5 * ez + (1.5 if (colourful or luma > 0.5 or clear) else 0.0)
            if (g["area"][m] < 0.015 and g["plate_zone"][m] > 0.4 and g["flat"][m] > 0.75
                    and not colourful and not clear):
                L[idx["plate"]] += 2.0 + (1.0 if mat.has_texture else 0.0)
            if cab > 0.5 and not clear:
                L[idx["interior"]] += 3.0 * cab
            if views is not None:
                expo = g["exposure"][m]
                if g["area"][m] > 0.005 and expo < 0.25:
                    L[idx["interior"]] += 2.5 * (1.0 - expo / 0.25)
            if m in body_group:
                L[idx["body"]] += 4.0
            elif up > 0.85 and g["area"][m] < 0.3 and g["roof"][m] < 0.5:
                L[idx["window"]] += 2.0                     # the glazing band above the belt
        z = np.exp(logit - logit.max(axis=1, keepdims=True))
        return z / z.sum(axis=1, keepdims=True)

    def segment(self, mesh: Mesh, views: ViewSet) -> PartMasks:
        return paint_materials(views, self.guess(mesh, views), source="prior")


def paint_materials(views: ViewSet, prob: np.ndarray, *, source: str) -> PartMasks:
    """Packed part masks painting each material's pixels with its most probable part (argmax of
    ``prob`` (M, P) over ``PART_NAMES``; ties -> PART_NAMES order). Confidence of (view, part) =
    the chosen parts' probabilities averaged over the part's pixels in the view."""
    M, P = prob.shape[0], len(PART_NAMES)
    cnt = views.material_counts(M + 1)                         # (V, M + 1) pixels per id
    part_of = np.argmax(prob, axis=1)                          # ties -> PART_NAMES order
    # packed masks: one gather of each material id's part bit (id 0 = background: none)
    lut = np.zeros(M + 1, np.uint16)
    lut[1:] = np.left_shift(1, part_of).astype(np.uint16)
    bits = _gather(lut, views.mat_id)
    # confidence of (view, part) = the part's probability averaged over its pixels, from the
    # per-view pixel counts of the material ids: (V, M + 1) @ (M + 1, P) matrices
    member = np.zeros((M + 1, P), np.int64)
    member[np.arange(1, M + 1), part_of] = 1
    weight = np.zeros((M + 1, P))
    weight[np.arange(1, M + 1), part_of] = prob[np.arange(M), part_of]
    n = cnt @ member                                           # (V, P) pixels per part
    sums = cnt.astype(np.float64) @ weight
    conf = np.where(n > 0, sums / np.maximum(n, 1), 0.0).astype(np.float32)
    return PartMasks.from_bits(list(PART_NAMES), bits, conf, source=source)


def _gather(lut: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """``lut[ids]`` for (V, H, W) uint16 ids all < lut.size (checked by the caller): OpenCV's
    table lookup on 8-bit ids when the table fits 256 entries (4x np.take, which widens every
    id to a 64-bit index), else np.take view by view (the widened ids of one view stay in cache:
    2x one whole take). Same values either way."""
    import cv2

    out = np.empty(ids.shape, lut.dtype)
    if lut.size <= 256 and ids.ndim == 3 and ids.size:
        table = np.zeros(256, lut.dtype)
        table[:lut.size] = lut
        flat = ids.reshape(-1, ids.shape[-1]).astype(np.uint8)
        cv2.LUT(flat, table, dst=out.reshape(flat.shape))
        return out
    for v, view in enumerate(ids):
        lut.take(view, out=out[v])
    return out


class LabellerSegmenter:
    """The learned per-material labeller (``ucad_cl.labeller``) painted into part masks.

    ``model``: an ONNX model path (default: the shipped ``ucad_cl/models/labeller.onnx``);
    ``use_names=False`` ignores material and node names (the names-hidden evaluation);
    ``runtime``: where the layer behind glass renders (default ``get_runtime()``)."""

    def __init__(self, model: str | Path | None = None, use_names: bool = True,
                 runtime: Runtime | None = None):
        self.runtime = runtime

        self.model = LabellerModel(model or MODEL_PATH)   # a missing or stale model fails here
        self.use_names = use_names

    def segment(self, mesh: Mesh, views: ViewSet) -> PartMasks:

        labels = label_materials(mesh, views, use_names=self.use_names, model=self.model,
                                 runtime=self.runtime)
        masks = paint_materials(views, labels.prob.astype(np.float64),
                                source=f"labeller:{self.model.path.name}")
        masks.labels = labels
        return masks
