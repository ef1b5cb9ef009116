"""The learned offline labeller: per-material features -> part probabilities (ONNX trees).

``label_materials(mesh, views) -> MaterialLabels`` is the whole stage: it computes one feature row
per material (``material_table``), runs the shipped gradient-boosted tree models
(``ucad_cl/models/labeller.onnx``: three, each trained by ``scripts/train_labeller.py`` on its own
draw of the procedural generator's truth, averaged in the graph; the data recipe, seeds and
reached metrics are in ``labeller.json`` beside it) with onnxruntime, and adds the
see-through-glass layer and the split of shared materials.
``segment.LabellerSegmenter`` paints the result into per-view part masks for ``classify_parts``.

Frame: the canonical vehicle frame (+Y up, the vehicle's length along the longer horizontal
axis, X or Z; with the orientation stage that is X). Every geometric feature is symmetric under
front/back and left/right flips (|u|, |w|), so a mesh whose front is -X gets the same features.
Units: canonical (bbox diagonal 1); h = height above the lowest vertex / vehicle height in [0, 1];
u = signed length position / half-length in [-1, 1]; w = width position / half-width.

Features (``FEATURE_NAMES``, one row per material, float32):

* position: area-weighted mean/std/min/max of h, mean/max |u|, mean/max |w|, bbox extents;
  shares of area in zones (low corners = wheels, ends, belt line and above, cabin volume, roof,
  plate zone, underside).
* shape: area share (log10), faces share, normals (mean |n| per axis, mean up-component),
  flatness (largest eigenvalue of the area-weighted normal scatter; 1 = a plane).
* components (faces joined through shared, position-welded vertices, per material): count, share
  of the largest, share of area in wheel-like components (a ring or disc seen from the side:
  circular length x height extent, thin across, centre about one radius above the ground) and
  the radial spread inside them (ring: r/R near 1 with a small spread; disc: spread wide).
* wheel axles: detected wheels are the wheel-like components of all materials, merged by centre;
  per face rho = distance to the nearest wheel axle in the side view / that wheel's radius (only
  wheels on the face's side); shares of area with rho < 0.55 (hub), 0.55-0.8 (rim), 0.8-1.1
  (tyre), 1.1-1.6 (arch) and mean min(rho, 3).
* mirror pair: another material whose centroid is this one's mirror image across w = 0 with a
  similar area; off-centre share.
* appearance: CIELAB of the base colour, chroma, metallic, roughness, alpha, transmission, alpha
  mode, emission, textured, glTF-default (untouched) material, see-through; colour distance and
  lightness difference to the material with the most visible pixels ("the paint").
* visibility from the rendered views: pixel share, exposure (pixel share / area share), share of
  views that see it, pixel-weighted |cos azimuth| (seen from the ends vs the sides), share of its
  image boundary against background, see-through materials and the largest material; share of its
  visibility that comes only through glass (layer behind glass, see ``behind_glass``).
* names: ``names.name_prior`` of the material name (one-hot over parts, all zero for a name
  that says nothing, e.g. ``Material.001``), and the area share of faces whose node name says
  each part. ``use_names=False`` zeros both (the "names hidden" evaluation).
* context (same for every material of a mesh): length/height and width/height, material count,
  wheels found, see-through material present.
* relative (``RELATIVE_NAMES``, ``relative_features``; appended last): each material against
  the others of its vehicle: area and pixels against the largest, the share of materials darker
  / more colourful, of materials of the same colour, emission against the brightest, height and
  length position against the paint and against the main glass, colour distance to the main
  glass and pixels against it (a lamp lens is a small see-through material, the windows the
  large one).
* cues (``CUE_GROUPS``, ``CUE_NAMES``; appended after the relative ones; issue 24): *glaze*:
  area shares in the glazing band (h 0.5-0.95 between the ends, |u| < 0.85) and in the lamp
  zone (|u| > 0.75, h 0.15-0.65, facing the ends, |n_u| > 0.5); *under*: pixel shares in one
  view from straight above and one from straight below (``top_bottom_counts``: what the ring
  never shows: frame rails, axles, tanks, a ground sheet) and log10 of the bottom share over
  the ring's pixel share (seen mostly from below); *trim*: component shape, area-weighted over
  the material's components: log10 of the longest over the middle side of the component's box
  (``comp_elong``: a strip along a panel edge is long and thin) and the middle side over the
  vehicle height (``comp_narrow``).

See through glass (the documented rule): a material is *see-through* when its transmission
> 0.05, or its alpha < 0.95 with alpha mode BLEND, or its alpha < 0.9 in any mode. When a mesh
has one that is visible in the views, a second layer is rendered without the faces of the
visible see-through materials (a see-through material hidden behind another, like a lamp's inner
glass behind its cover, stays and can be seen there), on every k-th view of the ring
(at most ``BEHIND_VIEWS`` views) at most ``BEHIND_SIZE`` px: a pixel whose first layer is a
see-through material shows in the second layer what lies behind it. A material with pixels there
is seen through glass; one with no first-layer pixels at all is labelled from that layer
(``classify`` decision ``'behind-glass'``) instead of ``'unseen'``. A material with no pixel in
either layer stays ``'unseen'``.

Shared materials: where one material's connected components fall both inside detected wheels and
elsewhere (one paint for body and rims, one black for tyres and trim), the components are split
into groups: inside a wheel (rim if their mean rho < 0.8, else wheel) and elsewhere (the
material's label); reported when at least two groups each hold >= ``SPLIT_MIN_SHARE`` of the
material's area, with each group's area share, face count and component boxes.

Rules after the trees (``wheel_assembly``, ``never_visible_part``): tyre against rim by radial
position inside a wheel assembly, and the part of a material no view sees from geometry alone
(inside a wheel -> rim, under the floor -> other, else interior; ``classify``'s
``'never-visible'``).

Determinism: NumPy reductions in a fixed order, tie rules stated at each argmax; the ONNX tree
model is evaluated exactly (thresholds compare float32 features).

Why one module of over 800 lines: the feature columns (``FEATURE_NAMES``), the code that
computes them, the model that reads them and the rules that read them after it change together
(a column renamed or moved breaks all four, and the shipped model's record is checked against
these names), so they live in one file; the training recipe is ``labeller_train``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .artifacts import PART_NAMES, CameraRing, Mesh, ViewSet
from .cameras import make_ring
from .names import name_prior
from .render import render_views
from .runtime import Runtime

MODEL_DIR = Path(__file__).resolve().parent / "models"
MODEL_PATH = MODEL_DIR / "labeller.onnx"
BEHIND_VIEWS = 6           # at most this many views of the layer behind glass
BEHIND_SIZE = 96           # at most this many pixels on its longer side
TB_ELEVATION = 89.0        # the views from above and below (``top_bottom_counts``), degrees
ADJ_VIEWS = 12             # views used for image adjacency (every k-th view)
ADJ_SIZE = 128             # ... sampled at every s-th pixel so the longer side is <= this
SPLIT_MIN_SHARE = 0.05     # a component group must hold this share of the material's area
WHEEL_ZONE = 0.5           # share of area within a wheel's radius: the material is in a wheel
RIM_GAP = 0.15             # mean rho this far inside a wheel's outermost material: the rim
WELD = 2.0 ** -17          # vertex welding grid (canonical units) for components


def _feature_names() -> tuple[str, ...]:
    geo = ["h_mean", "h_std", "h_min", "h_max", "u_mean", "u_max", "u_std", "w_mean", "w_max",
           "ext_h", "ext_u", "ext_w", "z_wheel", "z_end", "z_upper", "z_belt", "z_cabin",
           "z_roof", "z_plate", "z_under", "centre_w",
           "log_area", "log_faces", "n_u", "n_h", "n_w", "n_up", "flat", "log_tri_size",
           "log_comps", "comp_largest", "comp_wheel", "ring_r", "ring_spread",
           "rho_hub", "rho_rim", "rho_tyre", "rho_arch", "rho_mean",
           "mirror", "off_centre"]
    app = ["lab_l", "lab_a", "lab_b", "chroma", "metallic", "roughness", "alpha",
           "transmission", "blend", "mask", "emission", "textured", "gltf_default",
           "see_through", "d_paint", "dl_paint", "same_paint"]
    vis = ["pix_share", "log_expo", "view_frac", "end_view", "top_view", "adj_bg", "adj_clear",
           "adj_paint", "through_glass", "behind_share", "unseen", "area_rank", "pix_rank"]
    names = [f"name_{p}" for p in PART_NAMES] + [f"node_{p}" for p in PART_NAMES]
    ctx = ["ctx_lh", "ctx_wh", "ctx_log_mats", "ctx_wheels", "ctx_clear"]
    return tuple(geo + app + vis + names + ctx)


#: relative (context) columns, appended after the base ones: each material against the other
#: materials of the same vehicle (``relative_features``)
RELATIVE_NAMES: tuple[str, ...] = (
    "rel_area", "rel_pix", "dark_frac", "chroma_frac", "same_colour", "rel_emission",
    "h_rel_paint", "u_rel_paint", "h_rel_glass", "u_rel_glass", "d_glass", "glass_rel_pix")
#: the issue-24 cue columns, appended last (``cue_features``), by cue: ``CUE_GROUPS``
CUE_GROUPS: dict[str, tuple[str, ...]] = {
    "glaze": ("glaze_band", "lamp_zone"),
    "under": ("top_pix", "bottom_pix", "bottom_rel"),
    "trim": ("comp_elong", "comp_narrow"),
}
CUE_NAMES: tuple[str, ...] = tuple(n for g in CUE_GROUPS.values() for n in g)
FEATURE_NAMES: tuple[str, ...] = _feature_names() + RELATIVE_NAMES + CUE_NAMES


@dataclass
class MaterialTable:
    """Per-material features and the facts the labeller reports beside its labels.

    X: (M, D) float32, columns ``FEATURE_NAMES``. pixels: (M,) first-layer pixels (all views);
    behind_pixels: (M,) pixels seen only through glass in the second layer (its view subset);
    comp: (F,) component index of every face (-1 none); comp_* describe components;
    wheels: (K, 5) detected wheels (u, h, w centre in canonical units along the length, up and
    width axes, radius, half thickness)."""

    X: np.ndarray
    pixels: np.ndarray
    behind_pixels: np.ndarray
    face_comp: np.ndarray
    comp_material: np.ndarray
    comp_area: np.ndarray
    comp_box: np.ndarray
    comp_rho: np.ndarray
    wheels: np.ndarray


@dataclass
class MaterialLabels:
    """The labeller's answer. prob: (M, P) float32 over ``PART_NAMES`` (rows sum to 1);
    part: (M,) int index of the chosen part (argmax, ties -> PART_NAMES order); behind_pixels:
    (M,) pixels seen only through glass; splits: {material: [{part, area_share, faces, boxes}]}
    for shared materials that the geometry separates; hidden_part: (M,) the part a material
    takes when no view sees it (``never_visible_part``; None: the argmax ``part``)."""

    prob: np.ndarray
    part: np.ndarray
    behind_pixels: np.ndarray
    splits: dict = field(default_factory=dict)
    hidden_part: np.ndarray | None = None     # (M,) part index if no view sees it (geometry)

    def probability(self, m: int) -> float:
        return float(self.prob[m, self.part[m]])


def label_materials(mesh: Mesh, views: ViewSet, *, use_names: bool = True,
                    model: "LabellerModel | str | Path | None" = None,
                    runtime: Runtime | None = None) -> MaterialLabels:
    """Part probabilities for every material of ``mesh`` (canonical frame) from its ``views``.
    ``model``: a loaded ``LabellerModel`` (keep one to label many meshes) or a path (loaded
    for this call; default the shipped model); the layer behind glass renders on ``runtime``."""
    table = material_table(mesh, views, use_names=use_names, runtime=runtime)
    if not isinstance(model, LabellerModel):
        model = LabellerModel(model or MODEL_PATH)
    prob = wheel_assembly(model.predict(table.X), table.X)
    part = np.argmax(prob, axis=1)                                 # ties -> PART_NAMES order
    return MaterialLabels(prob=prob, part=part, behind_pixels=table.behind_pixels,
                          splits=split_shared(mesh, table, part),
                          hidden_part=never_visible_part(table.X))


def wheel_assembly(prob: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Tyre against rim by radial position in a wheel assembly: when two or more materials with
    ``WHEEL_ZONE`` of their area inside a wheel's radius (rho < 1.1, ``rho_hub`` + ``rho_rim``
    + ``rho_tyre``) are labelled wheel, the outermost (largest mean rho; ties -> the lower
    material index) stays wheel and each one whose mean rho lies ``RIM_GAP`` or more inside
    it becomes rim (its wheel and rim probabilities swapped). Returns a new array."""
    col = {n: i for i, n in enumerate(FEATURE_NAMES)}
    w, r = PART_NAMES.index("wheel"), PART_NAMES.index("rim")
    zone = X[:, col["rho_hub"]] + X[:, col["rho_rim"]] + X[:, col["rho_tyre"]]
    cand = np.flatnonzero((np.argmax(prob, axis=1) == w) & (zone >= WHEEL_ZONE))
    out = np.array(prob, copy=True)
    if cand.size < 2:
        return out
    rho = X[cand, col["rho_mean"]]
    outer = rho.max()                                 # argmax: the first (lower index) on ties
    for m in cand[rho <= outer - RIM_GAP]:
        out[m, [w, r]] = out[m, [r, w]]
    return out


def never_visible_part(X: np.ndarray) -> np.ndarray:
    """(M,) part index for materials that no view sees, from geometry alone: ``rim`` inside a
    wheel (``WHEEL_ZONE``), ``other`` under the floor (more than half its area facing down in
    the lowest 0.3 of the height, ``z_under``, or its mean height under 0.2: axles, tanks,
    exhausts, frame rails), else ``interior`` (inside the body or the cabin)."""
    col = {n: i for i, n in enumerate(FEATURE_NAMES)}
    zone = X[:, col["rho_hub"]] + X[:, col["rho_rim"]] + X[:, col["rho_tyre"]]
    under = (X[:, col["z_under"]] > 0.5) | (X[:, col["h_mean"]] < 0.2)
    return np.where(zone >= WHEEL_ZONE, PART_NAMES.index("rim"),
                    np.where(under, PART_NAMES.index("other"), PART_NAMES.index("interior")))


# ---------------------------------------------------------------------------------------------
# the model
# ---------------------------------------------------------------------------------------------
def onnx_spec(spec: str) -> tuple[str, str]:
    """(MODEL, CONFIG) of an ``onnx:MODEL:CONFIG.json`` option (a user's ONNX model and its
    JSON config); ValueError for another spelling."""
    kind, _, arg = str(spec).partition(":")
    model, _, config = arg.partition(":")
    if kind != "onnx" or not model or not config:
        raise ValueError("expected onnx:MODEL:CONFIG.json (the model and its JSON config)")
    return model, config


def onnx_config(config: str | Path | dict) -> tuple[dict, str]:
    """(the JSON config of a user's ONNX model, how errors name it): ``config`` a path (read
    as UTF-8, a BOM dropped) or a dict already read ('config'). FileNotFoundError when the file
    is missing, ValueError naming it when it is not JSON or not a JSON object."""
    if isinstance(config, dict):
        return config, "config"
    path = Path(config)
    if not path.is_file():
        raise FileNotFoundError(f"ONNX config {path} does not exist")
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not JSON ({exc.msg}, line {exc.lineno})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot be read ({exc})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: not a JSON object")
    return data, str(path)


def onnx_run(session, path: Path, outputs, feeds: dict, what: str = "the model") -> list:
    """``session.run(outputs, feeds)``; ValueError naming the file, on one line, when
    onnxruntime fails (its own exception types, with multi-line messages: e.g. a graph whose
    fixed input size is not the one fed)."""
    try:
        return session.run(outputs, feeds)
    except Exception as exc:  # noqa: BLE001 - onnxruntime's exception types are its own
        why = " ".join(str(exc).split())[:200]
        shapes = ", ".join(str(tuple(v.shape)) for v in feeds.values())
        raise ValueError(f"{path}: {what} fails on a {shapes} input: {type(exc).__name__}: "
                         f"{why}") from None


def open_onnx(model_path: str | Path) -> tuple[Path, Any, str]:
    """(path, CPU session, input name) of a user's ONNX model: FileNotFoundError when the file
    is missing, ValueError naming it when onnxruntime cannot load it (``onnx_session``)."""
    path = Path(model_path)
    if not path.exists():
        raise FileNotFoundError(f"ONNX model {path} does not exist")
    session = onnx_session(path)
    return path, session, session.get_inputs()[0].name


def onnx_session(path: Path, options=None):
    """An onnxruntime CPU session of the model at ``path``; ValueError naming the file when
    onnxruntime cannot load it (its own errors, e.g. ``InvalidProtobuf`` for a file that is no
    ONNX model, are none of ValueError / OSError)."""
    import onnxruntime as ort

    try:
        return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # noqa: BLE001 - onnxruntime's exception types are its own
        raise ValueError(f"{path}: onnxruntime cannot load this model ({type(exc).__name__}: "
                         f"{str(exc)[:300]})") from None


class LabellerModel:
    """The ONNX tree ensemble and its JSON record (feature names must match this code's)."""

    def __init__(self, path: str | Path):
        import onnxruntime as ort

        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"labeller model {self.path} does not exist")
        meta = self.path.with_suffix(".json")
        self.record = json.loads(meta.read_text(encoding="utf-8")) if meta.exists() else {}
        names = tuple(self.record.get("features", FEATURE_NAMES))
        if names != FEATURE_NAMES:
            raise ValueError(f"{self.path}: trained on other features than this code computes "
                             f"({len(names)} vs {len(FEATURE_NAMES)}); retrain it with "
                             "scripts/train_labeller.py")
        classes = self.record.get("classes", list(PART_NAMES))
        if list(classes) != list(PART_NAMES):
            raise ValueError(f"{self.path}: classes {classes} are not {list(PART_NAMES)}")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1
        opts.inter_op_num_threads = 1
        self.session = onnx_session(self.path, opts)
        self.input_name = self.session.get_inputs()[0].name
        outs = [o.name for o in self.session.get_outputs()]
        self.prob_name = next((o for o in outs if "prob" in o), outs[-1])

    def predict(self, X: np.ndarray) -> np.ndarray:
        """(M, P) float32 probabilities for (M, D) features."""
        X = np.ascontiguousarray(X, np.float32)
        if X.shape[0] == 0:
            return np.zeros((0, len(PART_NAMES)), np.float32)
        p = np.asarray(self.session.run([self.prob_name], {self.input_name: X})[0], np.float32)
        p = np.clip(p, 0.0, 1.0)
        return p / np.maximum(p.sum(axis=1, keepdims=True), 1e-12)


# ---------------------------------------------------------------------------------------------
# see-through materials and the layer behind them
# ---------------------------------------------------------------------------------------------
def see_through(mesh: Mesh) -> np.ndarray:
    """(M,) bool: materials a viewer sees through (rule in the module docstring)."""
    out = np.zeros(len(mesh.materials), bool)
    for m, mat in enumerate(mesh.materials):
        a = float(mat.base_color[3])
        out[m] = (mat.transmission > 0.05 or (a < 0.95 and mat.alpha_mode == "BLEND")
                  or a < 0.9)
    return out


def behind_glass(mesh: Mesh, views: ViewSet, runtime: Runtime | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The second visibility layer: (view indices (S,), (S, H', W') uint16 material ids rendered
    without the visible see-through faces, 0 where the first layer is not see-through, and the
    first layer resampled to (S, H', W')). None when no see-through material is visible.
    Views: every k-th of the ring, at most ``BEHIND_VIEWS``; size: the ring's, scaled down to
    at most ``BEHIND_SIZE`` px (nearest pixel centre)."""

    clear = see_through(mesh)
    # a see-through material nobody sees in the first layer (a lamp's inner glass behind its
    # cover) stays in the second layer: it is what lies behind the outer glass
    seen = views.material_counts(len(mesh.materials) + 1)[:, 1:].sum(axis=0) > 0
    clear &= seen
    if not clear.any() or mesh.n_faces == 0:
        return None
    fm = np.asarray(mesh.face_material)
    keep = ~clear[fm]
    if not keep.any():
        return None
    V = views.n_views
    idx = np.arange(0, V, max(1, -(-V // BEHIND_VIEWS)))
    c = views.cameras
    s = min(1.0, BEHIND_SIZE / max(c.width, c.height))
    w, h = max(1, int(round(c.width * s))), max(1, int(round(c.height * s)))
    K = np.array(c.K, np.float64)
    K[0] *= w / c.width
    K[1] *= h / c.height
    ring = CameraRing(K=K, w2c=c.w2c[idx], width=w, height=h, azimuth=c.azimuth[idx],
                      elevation=c.elevation[idx], distance=c.distance, near=c.near)
    sub = Mesh(path=mesh.path, sha256=mesh.sha256, vertices=mesh.vertices,
               faces=np.asarray(mesh.faces)[keep], face_material=fm[keep],
               materials=mesh.materials)
    layer2 = render_views(sub, ring, runtime=runtime).mat_id
    first = _resize_ids(views.mat_id[idx], h, w)
    clear_id = np.zeros(len(mesh.materials) + 1, bool)
    clear_id[1:] = clear
    return idx, np.where(clear_id[first], layer2, 0).astype(np.uint16), first


def top_bottom_counts(mesh: Mesh, runtime: Runtime | None = None) -> np.ndarray:
    """(2, M) pixels of every material in a view from straight above and one from straight
    below (elevations +/- ``TB_ELEVATION``, azimuth 0, ``BEHIND_SIZE`` px square): what the
    ring (elevations 10-45) never shows, the underside (frame rails, axles, tanks, a ground
    sheet) and the roof."""
    M = len(mesh.materials)
    if mesh.n_faces == 0 or M == 0:
        return np.zeros((2, M))
    ring = make_ring(azimuths=(0.0,), elevations=(TB_ELEVATION, -TB_ELEVATION),
                     size=BEHIND_SIZE)
    return render_views(mesh, ring, runtime=runtime).material_counts(M + 1)[:, 1:].astype(
        np.float64)


def _resize_ids(ids: np.ndarray, h: int, w: int) -> np.ndarray:
    """Nearest-pixel resampling of (V, H, W) id maps to (V, h, w) (pixel centres)."""
    V, H, W = ids.shape
    if (H, W) == (h, w):
        return ids
    rows = np.minimum(((np.arange(h) + 0.5) * H / h).astype(np.int64), H - 1)
    cols = np.minimum(((np.arange(w) + 0.5) * W / w).astype(np.int64), W - 1)
    return ids[:, rows][:, :, cols]


# ---------------------------------------------------------------------------------------------
# features
# ---------------------------------------------------------------------------------------------
def material_table(mesh: Mesh, views: ViewSet, *, use_names: bool = True,
                   runtime: Runtime | None = None) -> MaterialTable:
    """Feature rows of every material (see the module docstring); the layer behind glass renders
    on ``runtime`` (default ``get_runtime()``)."""

    M, P = len(mesh.materials), len(PART_NAMES)
    D = len(FEATURE_NAMES)
    col = {n: i for i, n in enumerate(FEATURE_NAMES)}
    X = np.zeros((M, D), np.float64)
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces, np.int64)
    fm = np.asarray(mesh.face_material, np.int64)
    F = f.shape[0]

    def put(name, values):
        X[:, col[name]] = values

    # ---- per-face geometry in the vehicle frame; coordinates as contiguous rows (3, F): the
    # (F, 3) names below (tmin, tmax, unit, c) are transposed views whose columns are rows
    vT = np.ascontiguousarray(v.T)
    P0, P1, P2 = (vT.take(f[:, k], axis=1) for k in range(3))        # (3, F) corners
    tmin = np.minimum(np.minimum(P0, P1), P2).T                       # (F, 3) face boxes
    tmax = np.maximum(np.maximum(P0, P1), P2).T
    lo, hi = (tmin.T.min(axis=1), tmax.T.max(axis=1)) if F else (np.zeros(3), np.ones(3))
    ext = np.maximum(hi - lo, 1e-12)
    la, wa = (0, 2) if ext[0] >= ext[2] else (2, 0)
    mid = 0.5 * (lo + hi)
    e1, e2 = P1 - P0, P2 - P0
    nT = np.stack([e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
                   e1[0] * e2[1] - e1[1] * e2[0]])                     # (3, F) 2 area * normal
    norm = np.sqrt(nT[0] * nT[0] + nT[1] * nT[1] + nT[2] * nT[2])
    area = 0.5 * norm
    unit = (nT / np.maximum(norm, 1e-30)).T
    c = ((P0 + P1 + P2) / 3).T
    h = (c[:, 1] - lo[1]) / ext[1]
    u = (c[:, la] - mid[la]) / (0.5 * ext[la])
    w = (c[:, wa] - mid[wa]) / (0.5 * ext[wa])
    au, aw = np.abs(u), np.abs(w)
    tot = np.bincount(fm, weights=area, minlength=M)
    safe = np.maximum(tot, 1e-30)
    # area-weighted means per material: sparse (M, F) x (F,) products, one per column (each
    # column contiguous: an (F, k) block would be copied to row order first, 5x slower)
    from scipy.sparse import csr_matrix
    order = np.argsort(fm, kind="stable")          # faces by material, then face index
    nf = np.bincount(fm, minlength=M)              # faces per material
    indptr = np.zeros(M + 1, np.int64)             # material m's faces: order[indptr[m]:indptr[m+1]]
    np.cumsum(nf, out=indptr[1:])
    # built as CSR directly (what the COO (fm, face) form converts to, without the conversion)
    S = csr_matrix(((area / safe[fm])[order], order, indptr), shape=(M, F))

    def means(cols: dict) -> None:
        """put() the area-weighted mean of every per-face column of ``cols``."""
        for name, x in cols.items():
            put(name, mean(x))

    def mean(x):
        return S @ np.ascontiguousarray(x, np.float64) if F else np.zeros(M)

    starts = indptr[:-1]
    present = nf > 0

    def reduce(ufunc, rows):
        """(k, M) per-material ``ufunc`` reduction of k per-face rows (0 for no faces)."""
        out = np.zeros((len(rows), M), np.float64)
        if F:
            r = ufunc.reduceat(np.stack(rows).take(order, axis=1), np.minimum(starts, F - 1),
                               axis=1)
            out[:, present] = r[:, present]
        return out

    ny = unit[:, 1]
    means({"h_mean": h, "h_std": h * h, "u_mean": au, "u_std": au * au, "w_mean": aw,
           "z_wheel": (h < 0.42) & (au > 0.35) & (au < 0.92) & (aw > 0.5),
           "z_end": (au > 0.82) & (h > 0.1) & (h < 0.85), "z_upper": h > 0.55,
           "z_belt": (h > 0.35) & (h < 0.6),
           "z_cabin": (au < 0.5) & (aw < 0.55) & (h > 0.15) & (h < 0.7),
           "z_roof": (np.abs(ny) > 0.85) & (h > 0.8), "z_plate": (au > 0.9) & (aw < 0.4) & (h < 0.6),
           "z_under": (ny < -0.7) & (h < 0.3), "centre_w": aw < 0.35,
           "n_u": np.abs(unit[:, la]), "n_h": np.abs(ny), "n_w": np.abs(unit[:, wa]),
           "n_up": ny})
    hm, um = X[:, col["h_mean"]].copy(), X[:, col["u_mean"]].copy()
    put("h_std", np.sqrt(np.maximum(X[:, col["h_std"]] - hm * hm, 0)))
    put("u_std", np.sqrt(np.maximum(X[:, col["u_std"]] - um * um, 0)))
    hmin, umin, wmin = reduce(np.minimum, [(tmin[:, 1] - lo[1]) / ext[1], u, w])
    hmax, umax, wmax, aumax, awmax, hcmax, hcmin = reduce(
        np.maximum, [(tmax[:, 1] - lo[1]) / ext[1], u, w, au, aw, h, -h])
    put("h_min", hmin)
    put("h_max", hmax)
    put("u_max", aumax)
    put("w_max", awmax)
    put("ext_h", hcmax + hcmin)                       # max h - min h of the face centroids
    put("ext_u", umax - umin)
    put("ext_w", wmax - wmin)
    put("log_area", np.log10(np.maximum(tot / max(tot.sum(), 1e-30), 1e-7)))
    put("log_faces", np.log10(np.maximum(nf / max(F, 1), 1e-7)))
    # per-material mean of u u^T (area-weighted), its largest eigenvalue: 1 for a plane
    uT = unit.T
    uu = (uT[:, None, :] * uT[None, :, :]).reshape(9, F)
    outer = (np.stack([S @ r for r in uu], axis=1) if F else np.zeros((M, 9))).reshape(M, 3, 3)
    put("flat", np.linalg.eigvalsh(outer)[:, -1])
    put("log_tri_size", np.log10(np.maximum(tot / np.maximum(nf, 1), 1e-12)))

    # ---- connected components, wheels, rho
    comp, comp_mat = _components(v, f, fm, M)
    C = comp_mat.size
    carea = np.bincount(comp, weights=area, minlength=C) if F else np.zeros(0)
    cbox = _comp_boxes(tmin, tmax, comp, C)                              # (C, 6)
    ncomp = np.bincount(comp_mat, minlength=M)
    put("log_comps", np.log10(np.maximum(ncomp, 1)))
    largest = np.zeros(M)
    if C:                                        # components are ordered by material
        cstart = np.searchsorted(comp_mat, np.arange(M))
        has = np.bincount(comp_mat, minlength=M) > 0
        largest[has] = np.maximum.reduceat(carea, np.minimum(cstart, C - 1))[has]
    put("comp_largest", largest / safe)
    wheel_like, wc = _wheel_like(cbox, lo, ext, la, wa)                  # (C,), (C, 5)
    put("comp_wheel", np.bincount(comp_mat, weights=carea * wheel_like, minlength=M) / safe)
    # radial spread inside wheel-like components: r / R from the component's own axle
    fr = np.zeros(F)
    inwc = wheel_like[comp] if F else np.zeros(0, bool)
    if F and wheel_like.any():                  # r / R of the faces in wheel-like components
        sel = np.flatnonzero(inwc)
        fc = wc[comp[sel]]
        fr[sel] = (np.hypot(c[sel, la] - fc[:, 0], c[sel, 1] - fc[:, 1])
                   / np.maximum(fc[:, 3], 1e-12))
    wsum = np.bincount(fm, weights=area * inwc, minlength=M)
    rr = np.bincount(fm, weights=area * inwc * fr, minlength=M) / np.maximum(wsum, 1e-30)
    rr2 = np.bincount(fm, weights=area * inwc * fr * fr, minlength=M) / np.maximum(wsum, 1e-30)
    put("ring_r", rr)
    put("ring_spread", np.sqrt(np.maximum(rr2 - rr * rr, 0)))
    wheels = _merge_wheels(wc[wheel_like])
    rho = _rho(c, la, wa, wheels) if F else np.zeros(0)
    means({"rho_hub": rho < 0.55, "rho_rim": (rho >= 0.55) & (rho < 0.8),
           "rho_tyre": (rho >= 0.8) & (rho < 1.1), "rho_arch": (rho >= 1.1) & (rho < 1.6),
           "rho_mean": np.minimum(rho, 3.0)})
    crho = (np.bincount(comp, weights=area * np.minimum(rho, 3.0), minlength=C)
            / np.maximum(carea, 1e-30)) if F else np.zeros(0)

    # ---- mirror pairs: centroid mirrored across w = 0, similar area
    cu, ch, cw = mean(u), hm, mean(w)
    rel = tot / max(tot.max(initial=0), 1e-30)
    dist = (np.abs(cu[:, None] - cu[None]) + np.abs(ch[:, None] - ch[None])
            + np.abs(cw[:, None] + cw[None]))
    ratio = np.minimum(rel[:, None], rel[None]) / np.maximum(np.maximum(rel[:, None], rel[None]),
                                                             1e-30)
    pair = (dist < 0.04) & (ratio > 0.7)
    np.fill_diagonal(pair, False)
    put("mirror", (pair.any(axis=1) & (np.abs(cw) > 0.1)).astype(float))
    put("off_centre", np.abs(cw))

    # ---- appearance
    clear = see_through(mesh)
    lab = _lab(np.array([mat.base_color[:3] for mat in mesh.materials],
                        np.float64).reshape(M, 3))
    for m, mat in enumerate(mesh.materials):
        X[m, col["metallic"]] = mat.metallic
        X[m, col["roughness"]] = mat.roughness
        X[m, col["alpha"]] = mat.base_color[3]
        X[m, col["transmission"]] = mat.transmission
        X[m, col["blend"]] = mat.alpha_mode == "BLEND"
        X[m, col["mask"]] = mat.alpha_mode == "MASK"
        X[m, col["emission"]] = max(mat.emissive) if len(mat.emissive) else 0.0
        X[m, col["textured"]] = mat.has_texture
        X[m, col["gltf_default"]] = (tuple(mat.base_color) == (1.0, 1.0, 1.0, 1.0)
                                     and mat.metallic == 1.0 and mat.roughness == 1.0)
    put("lab_l", lab[:, 0])
    put("lab_a", lab[:, 1])
    put("lab_b", lab[:, 2])
    put("chroma", np.hypot(lab[:, 1], lab[:, 2]))
    put("see_through", clear)

    # ---- visibility (first layer: all views; behind glass: a subset)
    cnt = views.material_counts(M + 1)[:, 1:].astype(np.float64)           # (V, M)
    pix = cnt.sum(axis=0)
    obj = max(pix.sum(), 1.0)
    share = pix / obj
    put("pix_share", share)
    put("log_expo", np.log10((share + 1e-6) / (tot / max(tot.sum(), 1e-30) + 1e-6)))
    put("view_frac", (cnt > 0).mean(axis=0) if cnt.shape[0] else 0.0)
    az = np.radians(np.asarray(views.cameras.azimuth, np.float64))
    el = np.asarray(views.cameras.elevation, np.float64)
    put("end_view", (np.abs(np.cos(az)) @ cnt) / np.maximum(pix, 1))
    hi_v = el > 30
    put("top_view", (hi_v @ cnt) / np.maximum(pix, 1) - float(hi_v @ cnt.sum(axis=1)) / obj)
    paint = int(np.argmax(pix)) if M else 0                   # ties -> lower material index
    d_paint = np.linalg.norm(lab - lab[paint], axis=1)
    put("d_paint", d_paint)
    put("dl_paint", lab[:, 0] - lab[paint, 0])
    look = _look(mesh.materials[paint]) if M else None
    same = np.array([_look(mat) == look for mat in mesh.materials], bool)
    put("same_paint", same & (d_paint < 5))
    st = max(1, -(-max(views.mat_id.shape[1:], default=1) // ADJ_SIZE))
    adj = _adjacency(views.mat_id[::max(1, -(-views.n_views // ADJ_VIEWS)), ::st, ::st], M + 1)
    bsum = np.maximum(adj[1:].sum(axis=1) - adj[np.arange(1, M + 1), np.arange(1, M + 1)], 1)
    put("adj_bg", adj[1:, 0] / bsum)
    put("adj_clear", adj[1:, 1:] @ clear.astype(float) / bsum)
    put("adj_paint", adj[1:, 1 + paint] / bsum)
    behind_px = np.zeros(M)
    layer = behind_glass(mesh, views, runtime)
    if layer is not None:
        idx, l2, first = layer
        n_ids = M + 1
        g = np.bincount(l2.ravel(), minlength=n_ids)[1:n_ids].astype(np.float64)
        f1 = np.bincount(first.ravel(), minlength=n_ids)[1:n_ids].astype(np.float64)
        put("through_glass", g / np.maximum(g + f1, 1))
        put("behind_share", g / max(f1.sum(), 1.0))
        behind_px = g
    put("unseen", (pix == 0).astype(float))
    put("area_rank", _rank(tot) / max(M, 1))
    put("pix_rank", _rank(pix) / max(M, 1))

    # ---- names (material and node names)
    if use_names:
        said: dict[str, str | None] = {}            # name -> part; material and node names repeat
        for nm in [mat.name for mat in mesh.materials] + list(mesh.node_names):
            if nm not in said:
                said[nm] = name_prior(nm)
        for m, mat in enumerate(mesh.materials):
            p = said[mat.name]
            if p is not None:
                X[m, col[f"name_{p}"]] = 1.0
        fn = mesh.face_node
        if fn is not None and len(mesh.node_names) and F:
            npart = np.array([PART_NAMES.index(p) if (p := said[nm]) else -1
                              for nm in mesh.node_names] + [-1])
            fp = npart[np.asarray(fn, np.int64)]                      # -1 node -> last entry
            named = fp >= 0
            share = np.bincount(fm[named] * P + fp[named], weights=area[named],
                                minlength=M * P).reshape(M, P) / safe[:, None]
            for k, p in enumerate(PART_NAMES):
                put(f"node_{p}", share[:, k])

    # ---- context
    put("ctx_lh", ext[la] / ext[1])
    put("ctx_wh", ext[wa] / ext[1])
    put("ctx_log_mats", np.log10(max(M, 1)))
    put("ctx_wheels", float(len(wheels)))
    put("ctx_clear", float(clear.any()))
    relative_features(X, col)
    put("glaze_band", mean((h > 0.5) & (h < 0.95) & (au < 0.85)))
    put("lamp_zone", mean((au > 0.75) & (h > 0.15) & (h < 0.65) & (np.abs(unit[:, la]) > 0.5)))
    e = np.sort(cbox[:, 3:] - cbox[:, :3], axis=1) if C else np.zeros((0, 3))    # ascending
    tiny = 1e-6 * float(np.linalg.norm(ext))
    elong = np.clip(np.log10(np.maximum(e[:, 2], tiny) / np.maximum(e[:, 1], tiny)), 0.0, 3.0)
    put("comp_elong", np.bincount(comp_mat, weights=carea * elong, minlength=M) / safe)
    put("comp_narrow", np.bincount(comp_mat, weights=carea * e[:, 1], minlength=M) / safe / ext[1])
    tb = top_bottom_counts(mesh, runtime)                                  # (2, M)
    tshare = tb / np.maximum(tb.sum(axis=1, keepdims=True), 1.0)
    put("top_pix", tshare[0])
    put("bottom_pix", tshare[1])
    put("bottom_rel", np.log10((tshare[1] + 1e-4) / (X[:, col["pix_share"]] + 1e-4)))
    return MaterialTable(X=X.astype(np.float32), pixels=pix.astype(np.int64),
                         behind_pixels=behind_px.astype(np.int64), face_comp=comp,
                         comp_material=comp_mat, comp_area=carea, comp_box=cbox,
                         comp_rho=crho, wheels=wheels)


def relative_features(X: np.ndarray, col: dict[str, int]) -> None:
    """Fill the ``RELATIVE_NAMES`` columns of (M, D) ``X`` in place from its base columns: each
    material against the others of the same vehicle.

    rel_area, rel_pix: log10 area share / pixel share minus the largest material's (0 = the
    largest); dark_frac, chroma_frac: share of the other materials darker (CIELAB L) / more
    chromatic than this one (0 = the darkest / the most colourful; tie-free); same_colour:
    share of the other materials within CIELAB distance 5 (swatches, paint panels);
    rel_emission: emission / the vehicle's largest (0 when nothing glows); h_rel_paint,
    u_rel_paint: mean height / |length position| minus those of the paint (the material with
    the most pixels, ties -> lower index); h_rel_glass, u_rel_glass, d_glass: the same and the
    CIELAB distance against the main glass (the see-through material with the most pixels;
    0, 0, 100 when there is none); glass_rel_pix: a see-through material's pixels / the main
    glass's (0 for opaque materials). Order-free: permuting the materials permutes the rows."""
    M = X.shape[0]
    if M == 0:
        return

    def c(name):
        return X[:, col[name]]

    X[:, col["rel_area"]] = c("log_area") - c("log_area").max()
    lp = np.log10(c("pix_share") + 1e-4)
    X[:, col["rel_pix"]] = lp - lp.max()
    from scipy.spatial import cKDTree

    lab = np.stack([c("lab_l"), c("lab_a"), c("lab_b")], axis=1).astype(np.float64)
    others = max(M - 1, 1)
    # sorted counts and a k-d tree: O(M log M), a 2000-material file stays cheap
    light, chroma = np.sort(c("lab_l")), np.sort(c("chroma"))
    X[:, col["dark_frac"]] = np.searchsorted(light, c("lab_l"), side="left") / others
    X[:, col["chroma_frac"]] = (M - np.searchsorted(chroma, c("chroma"), side="right")) / others
    near = cKDTree(lab).query_ball_point(lab, r=np.nextafter(5.0, 0.0), return_length=True)
    X[:, col["same_colour"]] = (np.asarray(near) - 1) / others
    em = c("emission")
    X[:, col["rel_emission"]] = em / em.max() if em.max() > 0 else 0.0
    pix = c("pix_share")
    paint = int(np.argmax(pix))                                   # ties -> lower index
    X[:, col["h_rel_paint"]] = c("h_mean") - c("h_mean")[paint]
    X[:, col["u_rel_paint"]] = c("u_mean") - c("u_mean")[paint]
    clear = (c("see_through") > 0) & (pix > 0)
    if clear.any():
        g = int(np.flatnonzero(clear)[np.argmax(pix[clear])])      # ties -> lower index
        X[:, col["h_rel_glass"]] = c("h_mean") - c("h_mean")[g]
        X[:, col["u_rel_glass"]] = c("u_mean") - c("u_mean")[g]
        X[:, col["d_glass"]] = np.linalg.norm(lab - lab[g], axis=1)
        X[:, col["glass_rel_pix"]] = np.where(c("see_through") > 0, pix / pix[g], 0.0)
    else:
        X[:, col["h_rel_glass"]] = 0.0
        X[:, col["u_rel_glass"]] = 0.0
        X[:, col["d_glass"]] = 100.0
        X[:, col["glass_rel_pix"]] = 0.0


def _rank(x: np.ndarray) -> np.ndarray:
    """Rank of each entry, 0 = largest (ties -> lower index first)."""
    r = np.empty(x.size)
    r[np.lexsort((np.arange(x.size), -x))] = np.arange(x.size)
    return r


def _look(mat) -> tuple:
    """Appearance key beside the colour: metal/rough buckets, texture, alpha mode."""
    return (round(mat.metallic / 0.1), round(mat.roughness / 0.1), mat.has_texture,
            mat.alpha_mode)


def _lab(rgb) -> np.ndarray:
    """CIELAB (D65) of linear RGB colours in [0, 1]: (..., 3) -> (..., 3)."""
    x = np.clip(np.asarray(rgb, np.float64), 0, 1)
    M = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722],
                  [0.0193, 0.1192, 0.9505]])
    xyz = x @ M.T / np.array([0.95047, 1.0, 1.08883])
    fx = np.where(xyz > 0.008856, np.cbrt(xyz), 7.787 * xyz + 16 / 116)
    return np.stack([116 * fx[..., 1] - 16, 500 * (fx[..., 0] - fx[..., 1]),
                     200 * (fx[..., 1] - fx[..., 2])], axis=-1)


def _components(v, f, fm, M):
    """(F,) component id of every face and (C,) its material: faces of one material joined
    through vertices welded on a ``WELD`` grid. Component ids ordered by (material, first face)."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    F = f.shape[0]
    if F == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    q = np.round(np.ascontiguousarray(v.T) / WELD).astype(np.int64)      # (3, N) rows
    q -= q.min(axis=1, keepdims=True)
    span = int(q.max()) + 1
    key = (q[0] * span + q[1]) * span + q[2] if span ** 3 < 2 ** 62 else None
    if key is None:
        _, weld = np.unique(q.T, axis=0, return_inverse=True)
    else:
        _, weld = np.unique(key, return_inverse=True)
    weld = weld.ravel()
    nw = int(weld.max()) + 1
    wf = weld[f]                                                        # (F, 3) welded corners
    # a welded vertex used by several materials is split: it stays one node for one of them
    # (whichever: the partition into components is the same) and the other materials' corners
    # get nodes of their own
    owner = np.full(nw, -1, np.int64)
    owner[wf.ravel()] = np.repeat(fm, 3)
    mixed = owner[wf] != fm[:, None]
    nid = wf.copy()
    if mixed.any():                                     # few corners: keys of those only
        sel = np.flatnonzero(mixed)                     # flat corner indices, row-major
        _, extra = np.unique(fm[sel // 3] * nw + wf.reshape(-1)[sel], return_inverse=True)
        nid.reshape(-1)[sel] = nw + extra.ravel()
    N = int(nid.max()) + 1
    # the face-corner graph as CSR directly: node f < F is face f with edges to its three
    # corner nodes F + nid (rows already in order: no sort, no COO conversion); the corner
    # nodes have no rows of their own (undirected components follow edges both ways)
    it = np.int32 if 3 * F + N < 2 ** 31 else np.int64      # scipy's own types: no conversion
    indptr = np.full(F + N + 1, 3 * F, it)
    indptr[:F + 1] = np.arange(0, 3 * F + 1, 3, dtype=it)
    corner = nid.astype(it).ravel()
    corner += F
    g = csr_matrix((np.ones(3 * F), corner, indptr), shape=(F + N, F + N))
    _, lab = connected_components(g, directed=False)
    fl = lab[:F]
    # renumber by (material, first face) so ids do not depend on scipy's numbering
    order = np.argsort(fl, kind="stable")                 # faces by label, then face index
    labels, start = np.unique(fl[order], return_index=True)
    first = order[start]                                   # lowest face of each label
    srt = np.lexsort((first, fm[first]))
    new = np.empty(int(labels.max()) + 1, np.int64)
    new[labels[srt]] = np.arange(srt.size)
    return new[fl], fm[first[srt]]


def _comp_boxes(tmin, tmax, comp, C) -> np.ndarray:
    """(C, 6) min xyz, max xyz of each component's faces (from the faces' boxes)."""
    box = np.empty((C, 6))
    if C:
        order = np.argsort(comp, kind="stable")
        starts = np.searchsorted(comp[order], np.arange(C))
        box[:, :3] = np.minimum.reduceat(tmin.T.take(order, axis=1), starts, axis=1).T
        box[:, 3:] = np.maximum.reduceat(tmax.T.take(order, axis=1), starts, axis=1).T
    return box


def _wheel_like(box, lo, ext, la, wa):
    """(C,) bool wheel-like components and (C, 5) their (u, h, w) centre, radius, half width.

    A tyre: circular in the side view (length x height extents within 25 %), thinner across
    than its diameter, diameter 12-65 % of the vehicle height, centre within ~0.65 diameters of
    the ground. A rim, hub or brake disc: the same shape test with any diameter >= 4 % of the
    height, centred (within 30 % of the radius, same side) on such a tyre."""
    C = box.shape[0]
    cen = 0.5 * (box[:, :3] + box[:, 3:])
    size = box[:, 3:] - box[:, :3]
    d = np.maximum(size[:, la], size[:, 1])
    circ = np.minimum(size[:, la], size[:, 1]) / np.maximum(d, 1e-12)
    H = ext[1]
    above = cen[:, 1] - lo[1]
    shape = (circ > 0.75) & (size[:, wa] < 0.9 * d) & (d < 0.65 * H)
    tyre = shape & (d > 0.12 * H) & (above < 0.65 * d + 0.05 * H)
    wc = np.zeros((C, 5))
    wc[:, 0], wc[:, 1], wc[:, 2] = cen[:, la], cen[:, 1], cen[:, wa]
    wc[:, 3], wc[:, 4] = 0.5 * d, 0.5 * size[:, wa]
    ok = tyre.copy()
    inner = np.flatnonzero(shape & ~tyre & (d > 0.04 * H))
    for t in np.flatnonzero(tyre):
        near = ((np.hypot(wc[inner, 0] - wc[t, 0], wc[inner, 1] - wc[t, 1]) < 0.3 * wc[t, 3])
                & (np.abs(wc[inner, 2] - wc[t, 2]) < wc[t, 4] + wc[inner, 4] + 0.3 * wc[t, 3]))
        ok[inner[near]] = True
    return ok, wc


def _merge_wheels(wc: np.ndarray) -> np.ndarray:
    """Wheel-like components sharing an axle (centres within 0.3 radius) -> one wheel with the
    largest radius and the union of widths. Greedy in decreasing radius (ties -> input order)."""
    order = np.lexsort((np.arange(len(wc)), -wc[:, 3]))
    out: list[np.ndarray] = []
    for i in order:
        x = wc[i]
        for k, y in enumerate(out):
            if (np.hypot(x[0] - y[0], x[1] - y[1]) < 0.3 * y[3]
                    and abs(x[2] - y[2]) < y[4] + x[4] + 0.3 * y[3]):
                lo_w = min(y[2] - y[4], x[2] - x[4])
                hi_w = max(y[2] + y[4], x[2] + x[4])
                out[k] = np.array([y[0], y[1], 0.5 * (lo_w + hi_w), y[3], 0.5 * (hi_w - lo_w)])
                break
        else:
            out.append(x.copy())
    return np.array(out).reshape(-1, 5)


def _rho(c, la, wa, wheels) -> np.ndarray:
    """(F,) distance of each face centroid to the nearest wheel axle (side view) / its radius,
    counting only wheels whose width span (grown by half a radius) holds the face; inf if none."""
    rho2 = np.full(c.shape[0], np.inf)
    cu, ch, cw = (np.ascontiguousarray(c[:, k]) for k in (la, 1, wa))
    for u0, h0, w0, R, hw in wheels:
        sel = np.flatnonzero(np.abs(cw - w0) < hw + 0.5 * R)    # the faces on its side
        r2 = ((cu[sel] - u0) ** 2 + (ch[sel] - h0) ** 2) / (R * R)
        rho2[sel] = np.minimum(rho2[sel], r2)
    return np.sqrt(rho2)


def _adjacency(mat_id: np.ndarray, n: int) -> np.ndarray:
    """(n, n) counts of 4-neighbour pixel pairs with different ids, summed over views."""
    adj = np.zeros(n * n, np.int64)
    mat_id = np.ascontiguousarray(mat_id)
    for a, b in ((mat_id[:, :, 1:], mat_id[:, :, :-1]), (mat_id[:, 1:, :], mat_id[:, :-1, :])):
        d = a != b
        x, y = a[d].astype(np.int64), b[d].astype(np.int64)
        adj += np.bincount(x * n + y, minlength=n * n)
    adj = adj.reshape(n, n)
    return adj + adj.T                              # pairs counted both ways


# ---------------------------------------------------------------------------------------------
# shared materials: split by connected component
# ---------------------------------------------------------------------------------------------
def split_shared(mesh: Mesh, table: MaterialTable, part: np.ndarray, *,
                 max_boxes: int = 16) -> dict[int, list[dict]]:
    """{material: groups} for materials whose components lie both inside and outside wheels (see
    the module docstring). Each group: part, area_share, faces, components, boxes (canonical
    min xyz + max xyz of up to ``max_boxes`` largest components, larger first)."""
    out: dict[int, list[dict]] = {}
    if table.comp_material.size == 0 or table.wheels.size == 0:
        return out
    fcount = np.bincount(table.face_comp, minlength=table.comp_material.size)
    for m in range(len(mesh.materials)):
        cs = np.flatnonzero(table.comp_material == m)
        if cs.size < 2:
            continue
        rho = table.comp_rho[cs]
        own = PART_NAMES[int(part[m])]
        groups = np.where(rho < 0.8, "rim", np.where(rho < 1.1, "wheel", own))
        a = table.comp_area[cs]
        total = max(a.sum(), 1e-30)
        names = [g for g in dict.fromkeys(groups.tolist())]
        shares = {g: float(a[groups == g].sum() / total) for g in names}
        big = [g for g in names if shares[g] >= SPLIT_MIN_SHARE]
        if len(big) < 2:
            continue
        rows = []
        for g in sorted(big, key=lambda g: (-shares[g], PART_NAMES.index(g))):
            sel = cs[groups == g]
            top = sel[np.lexsort((sel, -table.comp_area[sel]))][:max_boxes]
            rows.append({"part": g, "area_share": round(shares[g], 4),
                         "faces": int(fcount[sel].sum()), "components": int(sel.size),
                         "boxes": [[round(float(x), 5) for x in table.comp_box[k]] for k in top]})
        out[m] = rows
    return out
