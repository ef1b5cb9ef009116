"""The fit: one photo of a vehicle -> the catalogued model's part materials (UrbanCAD's optimiser).

``fit_photo(photo, box=... | mask=..., catalog=CAT, mesh=None)`` runs, on a CPU:

1. **Object**: the vehicle's pixels (the given mask, or GrabCut inside the box:
   ``ucad_cl.foreground``). With a box, GrabCut is rerun with a prior (``_refined_object``):
   the best stored views of the first ``REFINE_MESHES`` meshes by the HOG of GrabCut's object
   (``_first_views``; with ``mesh`` given, its stored view nearest by HOG), stretched onto the
   box; their majority is probable foreground, its core (eroded by ``REFINE_CORE`` of the box
   side) foreground; retrieval, the pose search (``_pose_given``) and the fit then run with
   the new mask. When GrabCut keeps too little of the box both times (clutter of the
   vehicle's colours), the box goes to the pose search and the render's silhouette at the
   pose, inside the box, is the outline (a note says so); a box of uniform pixels (standard
   deviation under ``UNIFORM_STD`` levels) is
   refused as holding no vehicle.
2. **Retrieval** (no ``mesh``): the photo's HOG feature against every stored view of every
   accepted mesh (``CatalogReader.feature_table``: stacked once per reader, so a batch of
   photos reads the catalogue's features once; meshes without readable features are left out
   with a note): the ``PRESELECT_ROWS`` rows of largest float32 dot product with the query
   (the stored rows are unit vectors), then ``search.search_catalog``'s exact float64 ranking of
   those; of the first ``PREFILTER_MESHES`` distinct meshes, the ``FINE_MESHES`` of least HOG
   distance + ``EDGE_WEIGHT`` x ``cues.edge_distance`` (below) at their best view, read from
   the stored material map (``_prefiltered``), are re-ranked by a finer HOG (``FINE_HOG``:
   128 px crop, 8 px cells) of their best view and its neighbours, the stored views shaded
   from their depth, material and triangle maps (``shade.shade_stored_view``; no mesh is
   read): a view's score = HOG distance + ``FINE_WEIGHT`` x the finer HOG's distance +
   ``EDGE_WEIGHT`` x how far the view's material boundaries lie from the photo's edges
   (``cues.edge_distance``); a mesh's = its best view's + ``RECALL_WEIGHT`` x how far the
   photo's edges inside the object lie from that view's boundaries (``cues.edge_recall``) +
   ``REGION_WEIGHT`` x the colour variance that view's material regions leave
   (``cues.region_residual``; ``_fine_rerank``);
   the first ``RERANK_POSE`` distinct meshes are posed (step 3) and the best pose score wins;
   the first ``CANDIDATES`` distinct meshes are reported as ``candidates`` (mesh, view pose,
   feature score; lower is better).
3. **Pose**: ``pose.estimate_pose`` with the mesh re-read from the recorded library (as
   ``export-glb`` does: refused when the file moved or changed; with retrieval to run and the
   reader not imported yet, read in a child interpreter started with the fit,
   ``ingest.MeshLoader``, so that the reader's import runs beside retrieval and a reader that
   crashes or hangs costs the pose, not the process; the CLI reads a given mesh there ahead),
   its coarse ring taken from the catalogue's stored features
   (``catalog_ring``, refinement renders at most ``RING_SIDE`` pixels), the photo's camera
   assumed of ``pose.FOV_PRIOR`` unless ``fov`` is given; when the file is gone
   or unreadable, the nearest stored view of that mesh is used as is, scaled and shifted onto
   the object's box (``pose.source = "stored view"``, and a note says so). Then azimuth and elevation are touched up by ``ROT_STEPS``
   (at most ``ROT_RANGE``) for the best silhouette IoU, the render's silhouette is shifted by
   whole pixels (at most ``SHIFT`` of the working side) to best overlap the photo's object
   (IoU; ties: the smaller shift, then row-major order), and the shift is folded into ``K``.
4. **Part masks**: the render's part map (the catalogue's material -> part table) inside the
   photo's object, each part eroded by ``margin = max(1, round(MARGIN * d))`` pixels (``d`` the
   diagonal of the object's box in the working frame) so that a slightly wrong pose or outline
   does not mix neighbouring parts; a ``segmenter`` (``PhotoSegmenter``) replaces the part map
   with its own masks (still inside the render's silhouette, which gives the normals).
5. **Light and colours**: ``ucad_cl.light.fit_light`` (sky, sun, clear-coat Fresnel; closed-form
   base colours; the paper's ``l_rgb + 0.1 l_stat``; trimmed residuals; the scale convention
   E_up = 1 is documented there), then white-balanced on the tyres (``NEUTRAL_PARTS``: the
   light takes half, ``light.BALANCE_SHARE``, of the colour cast that would make them neutral
   grey). Each part keeps its prior (``ucad_catalog.parts``) metallic, roughness, clear coat
   and transmission; only the base colour is fitted. With ``vgg`` (a user's ONNX feature
   extractor, ``ucad_cl.vgg``) the paper's l_vgg joins the objective: the colours are moved
   from the closed form by a few Levenberg-Marquardt steps on l_rgb + 0.1 l_stat + w l_vgg,
   the light kept (``vgg.refine_colours``).
6. **Status per part**: ``fitted``; ``prior`` when the render shows none of it inside the
   object (the prior's colour is kept: the source colour for car paint and 'other'); ``flagged``
   with a reason when fewer than ``MIN_PIXELS`` pixels are left after erosion (prior colour), or
   when its materials, each fitted alone under the light, form two groups ``TWO_COLOUR_CHROMA``
   apart in chromaticity and ``TWO_COLOUR_DE`` in CIEDE2000, each holding at least
   ``TWO_COLOUR_SHARE`` of its pixels (``_two_colours``; the colour reported is the fit of all
   its pixels).

The working frame is the photo cropped to the object's box grown by ``CROP_GROW`` and scaled so
its longer side is at most ``WORK_SIDE`` pixels (never enlarged); poses are reported for the
full photo (``K``, ``w2c``: docs/CONVENTIONS.md). A large photo is analysed by steps 1-6 in a
window around its box (``foreground.PhotoWindow``), pose search told the whole photo's assumed
camera; the pose and the object come back in the photo's pixels (a 12-megapixel photo cost ~3 s
more than a small one, docs/FIT.md). Deterministic: GrabCut is reseeded, grids and
tie rules are fixed, so the same inputs give the same numbers.

Why one module of over 800 lines: the six steps above share the working frame, the photo's
object and the pose, and each is a few short functions; the light model and its solver, the
largest separable part, live in ``ucad_cl/light.py``.
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Protocol

import numpy as np

from ucad_catalog import CatalogError
from ucad_catalog.parts import PART_MATERIALS, PART_NAMES
from ucad_catalog.reader import CatalogReader, FeatureTable, MeshInfo, ViewAngles
from ucad_catalog.searchindex import SearchIndex

from .artifacts import CameraRing, Mesh
from .cameras import NEAR_FRACTION, camera_distance, pixel_rays, single_camera
from .colorimetry import delta_e2000, linear_to_lab, linear_to_srgb8, srgb8_to_linear, srgb_hex
from .cues import boundary_points, edge_distance, edge_recall, photo_edges, region_residual
from .decimate import render_proxy
from .features import HogExtractor, unit_rows
from .foreground import (GrownPhoto, ObjectMask, PhotoWindow, box_stretch, check_image,
                         mask_box, object_mask, past_the_edge, refine_with_silhouette)
from .ingest import IngestError, MeshLoader
from .jobs import content_sha256
from .labeller import onnx_run, onnx_spec
from .light import (LUMA, Lighting, Samples, balance, fit_light, neutral_gains,
                    plausible_cast, predict, shading)
from .orient import in_frame
from .pose import (FOV_PRIOR, PoseRing, check_fov, estimate_pose, nearest_ring_view,
                   past_edge_choice, query_features)
from .render import render_views
from .runtime import Runtime
from .search import CatalogMatch, search_catalog
from .segment import OnnxSegmenter
from .shade import face_normals, shade_stored_view
from .vgg import OnnxFeatures, VggFit, refine_colours

RING_SIDE = 192             # pose refinement render size, pixels
WORK_SIDE = 384             # longer side of the working frame, pixels
CROP_GROW = 0.1             # the object's box grown by this share of its size on every side
MARGIN = 0.006              # part-boundary erosion, share of the object box's diagonal
SHIFT = 0.03                # silhouette alignment search, share of the working frame's side
ROT_STEPS = (2.0, 1.0, 0.5)   # pose touch-up steps (degrees of azimuth / elevation)
ROT_RANGE = 6.0             # at most this far from the pose search's answer, degrees
UNIFORM_STD = 4.0           # a box whose pixels vary less (8-bit levels) holds no vehicle
MIN_PIXELS = 30             # fewer eroded pixels: the part is flagged ("too few pixels")
SATURATED = 250             # sRGB level at or above which a photo pixel is not used
TWO_COLOUR_CHROMA = 0.08    # material groups at least this far apart in (r, g) chromaticity
TWO_COLOUR_DE = 12.0        # ... and this far apart in CIEDE2000 ...
TWO_COLOUR_SHARE = 0.2      # ... each holding at least this share: flagged "two colours"
NOT_ONE_COLOUR = ("light", "window")   # parts not tested for two colours (red and white
#                                        lamps; glass shows what is behind it)
NEUTRAL_PARTS = ("wheel",)  # white balance: tyres are taken as neutral grey ...
TYRE_LUMA = 0.2             # ... when their fitted luminance is at most this (tyres are dark;
#                             a light "tyre" means its mask landed on something else)
RERANK_POSE = 1             # retrieval: the first meshes posed; the best pose score wins
POSE_PROXY_FROM = 150_000   # meshes over this many triangles are posed on a render proxy ...
POSE_PROXY_CELLS = 256      # ... clustered on diagonal / 256 (decimate.render_proxy; docs/FIT.md)
CANDIDATES = 5              # distinct meshes listed by retrieval
UNCERTAIN_MARGIN = 0.02     # retrieval is "uncertain" when the next listed mesh scores within this
#                             share of the answer's score (retrieval_margin; docs/FIT.md: chosen on
#                             tuning draws, checked on a held-out one)
INDEX_FROM = 32768          # retrieval reads the search index (if fresh) over this many rows ...
INDEX_ROWS = 4096           # ... and keeps the rows nearest in its projections (docs/FIT.md)
PRESELECT_ROWS = 2048       # ... then by float32 dot products of the full rows, for the exact rank
REFINE_MESHES = 3           # object: stored silhouettes of the first meshes seed GrabCut again
PREFILTER_MESHES = 20       # retrieval: of this many first meshes by HOG, the FINE_MESHES of
                            # least HOG + edge distance at their best view ...
FINE_MESHES = 10            # ... are re-ranked by the finer HOG ...
FINE_VIEWS = 1              # ... at their best view and this many neighbours on each side ...
FINE_WEIGHT = 2.0           # ... by HOG distance + this x the finer HOG's distance
FINE_HOG = dict(size=128, cell=8)   # the finer HOG: 15 x 15 blocks of the 128 px crop
EDGE_WEIGHT = 2.0           # ... + this x the stored view's edges' distance to the photo's
RECALL_WEIGHT = 0.25        # ... + this x the photo's inside edges' distance to the view's
REGION_WEIGHT = 0.5         # ... + this x the colour variance its material regions leave
REFINE_CORE = 0.04          # ... their core (eroded by this share of the box side) is foreground
MIN_REFINED = 0.3           # ... kept when GrabCut keeps at least this share of the prior
SEED_MASK_STEP = 10.0       # ... and each seed alone too, over stored rings of at most this
#                             azimuth step (degrees; docs/FIT.md) ...
SURE_MARGIN = 0.15          # ... unless the voted mask's answer leads by this retrieval_margin
SHADE_THREADS = 2           # threads shading the re-rank's stored views (_describe_fine)


class PhotoSegmenter(Protocol):
    """Part masks of a photo: ``segment_photo(image (H, W, 3) uint8 RGB) -> {part: (H, W)
    bool}`` (parts of ``PART_NAMES``), e.g. an ONNX model (``OnnxPhotoSegmenter``)."""

    def segment_photo(self, image: np.ndarray) -> dict[str, np.ndarray]: ...


class OnnxPhotoSegmenter:
    """A user ONNX segmenter run on the photo (the paper's Grounded SAM step): the model, config
    (``classes`` {index: part}, ``input_size`` [H, W]) and output contract of
    ``ucad_cl.segment.OnnxSegmenter`` (an (N, H, W) integer class map or (N, C, H, W) logits),
    fed the working-frame photo as float RGB in [0, 1], NCHW."""

    def __init__(self, model: OnnxSegmenter):
        self.model = model

    @classmethod
    def from_spec(cls, spec: str) -> "OnnxPhotoSegmenter":
        """From ``onnx:MODEL:CONFIG.json`` (``labeller.onnx_spec``)."""
        return cls(OnnxSegmenter(*onnx_spec(spec)))

    def segment_photo(self, image: np.ndarray) -> dict[str, np.ndarray]:
        import cv2

        m = self.model
        H, W = image.shape[:2]
        h, w = m.input_size
        x = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)
        x = np.ascontiguousarray(x.transpose(2, 0, 1)[None], np.float32) / np.float32(255)
        y = np.asarray(onnx_run(m.session, m.model_path, None, {m.input_name: x},
                                f"the segmenter (input_size {list(m.input_size)})")[0])
        if y.ndim == 4 and np.issubdtype(y.dtype, np.floating):
            cls = y[0].argmax(axis=0)
        elif y.ndim == 3 and np.issubdtype(y.dtype, np.integer):
            cls = y[0]
        else:
            raise ValueError(f"{m.model_path}: output must be (N, H, W) classes or (N, C, H, W) "
                             f"logits, got {y.dtype} {y.shape}")
        full = cv2.resize(cls.astype(np.int32), (W, H), interpolation=cv2.INTER_NEAREST)
        return {part: full == k for k, part in sorted(m.classes.items()) if part in PART_NAMES}


@dataclass
class FitPose:
    """The photo's camera: azimuth / elevation (degrees, canonical frame), K (3, 3) and w2c
    (4, 4) of the full photo; source 'refined' (pose search with the mesh) or 'stored view'."""

    azimuth: float
    elevation: float
    K: np.ndarray
    w2c: np.ndarray
    source: str = "refined"


@dataclass
class PartFit:
    """One part's fitted material. color_linear (3,) linear RGB (relative to the photo's
    exposure, ``ucad_cl.light``); pixels: eroded mask pixels used; residual: RMS luminance
    residual (linear) of the kept pixels; status 'fitted' | 'prior' | 'flagged' (+ reason)."""

    part: str
    color_linear: np.ndarray
    metallic: float
    roughness: float
    pixels: int
    residual: float
    status: str
    reason: str = ""
    reflection: str = ""        # coated fitted parts: 'modelled' or 'folded' (ucad_cl.light)


@dataclass
class Candidate:
    """A retrieved mesh: its best stored view (pose of the view) and feature distance."""

    mesh_id: str
    mesh_path: str
    view: int
    azimuth: float
    elevation: float
    score: float


@dataclass
class FitImages:
    """Working-frame images for the overview PNG (all (h, w, ...)): photo uint8 RGB, render
    uint8 RGB (fitted model under the estimated light, grey outside the silhouette), part_map
    int (index into PART_NAMES, -1 none) of the eroded masks, object mask bool."""

    photo: np.ndarray
    render: np.ndarray
    part_map: np.ndarray
    object: np.ndarray


@dataclass
class FitResult:
    """What ``fit_photo`` found; ``to_json`` gives the interface of docs/FIT.md."""

    mesh_id: str
    mesh_path: str
    pose: FitPose
    lighting: Lighting
    parts: dict[str, PartFit]
    materials: list[dict]
    candidates: list[Candidate]
    seconds: dict[str, float]
    notes: list[str] = field(default_factory=list)
    images: FitImages | None = field(default=None, repr=False)
    mesh: Mesh | None = field(default=None, repr=False)
    part_rows: list = field(default_factory=list, repr=False)
    object_source: str = ""
    loss: float = 0.0
    object: ObjectMask | None = field(default=None, repr=False)   # the photo's object (full
    #                                                               frame), as the fit used it
    retrieval_margin: float | None = None   # retrieval_margin(candidates); None: mesh given
    vgg: VggFit | None = None             # the l_vgg refinement (``vgg=``); None: not run

    def to_json(self) -> dict:
        """JSON-ready dict; floats rounded (6 digits, seconds 3), keys in a fixed order."""
        return {
            "mesh_id": self.mesh_id, "mesh_path": self.mesh_path,
            "pose": {"azimuth": round(self.pose.azimuth, 4),
                     "elevation": round(self.pose.elevation, 4),
                     "K": _rl(self.pose.K), "w2c": _rl(self.pose.w2c),
                     "source": self.pose.source},
            "lighting": self.lighting.to_json(),
            "parts": {p: {"color_linear": _rl(f.color_linear),
                          "color_srgb": srgb_hex(np.clip(f.color_linear, 0.0, 1.0)),
                          "metallic": f.metallic, "roughness": f.roughness,
                          "pixels": f.pixels, "residual": round(f.residual, 6),
                          "status": f.status, **({"reason": f.reason} if f.reason else {}),
                          **({"reflection": f.reflection} if f.reflection else {})}
                      for p, f in self.parts.items()},
            "materials": self.materials,
            "candidates": [{"mesh_id": c.mesh_id, "mesh_path": c.mesh_path, "view": c.view,
                            "azimuth": round(c.azimuth, 4), "elevation": round(c.elevation, 4),
                            "score": round(c.score, 6)} for c in self.candidates],
            "retrieval_margin": (None if self.retrieval_margin is None
                                 else round(self.retrieval_margin, 6)),
            "object": self.object_source,
            "loss": round(self.loss, 8),
            "vgg": self.vgg.to_json() if self.vgg is not None else None,
            "notes": self.notes,
            "seconds": {k: round(v, 3) for k, v in self.seconds.items()},
        }


def fit_photo(photo: np.ndarray, *, box=None, mask: np.ndarray | None = None,
              catalog: str | Path | CatalogReader, mesh: str | None = None,
              segmenter: PhotoSegmenter | None = None, runtime: Runtime | None = None,
              mesh_loader: MeshLoader | None = None, fov: float | None = None,
              vgg: OnnxFeatures | None = None) -> FitResult:
    """Fit the part materials of the catalogued vehicle in ``photo`` ((H, W, 3) uint8 RGB),
    given by ``box`` (x0, y0, x1, y1 pixels, x1/y1 exclusive) or ``mask`` ((H, W) bool), against
    ``catalog`` (a path or an open reader); ``mesh`` (id, id prefix, path or file name) skips
    retrieval; ``mesh_loader``: a ``MeshLoader`` to reuse over a batch of photos (default: one
    started for this photo); ``fov``: the photo's field of view over its narrower side in
    degrees, when known (a lens's focal length: ``pose.FOV_RANGE``; default: the pose search
    assumes ``pose.FOV_PRIOR``); ``vgg``: a user's ONNX feature extractor
    (``ucad_cl.vgg.OnnxFeatures``) whose masked Gram matrices join the objective (the paper's
    l_vgg; step 5). ValueError with a one-line message for bad input (see the
    module docstring), a damaged catalogue included (an object unreadable or gone: "the
    catalogue ...")."""
    check_fov(fov)
    if isinstance(catalog, CatalogReader):
        return _run(catalog, runtime, mesh_loader, photo, box, mask, mesh, segmenter, fov, vgg)
    try:
        reader = CatalogReader(catalog)
    except CatalogError as exc:
        raise ValueError(str(exc)) from None
    with reader:
        return _run(reader, runtime, mesh_loader, photo, box, mask, mesh, segmenter, fov, vgg)


def _run(reader: CatalogReader, runtime, mesh_loader, photo, box, mask, mesh,
         segmenter, fov, vgg=None) -> FitResult:
    """``_Fit.run`` with the catalogue's read errors (and any file read error) met anywhere in
    the fit turned into the one-line ValueError (the CLI prints it, never a traceback); a
    ``MeshLoader`` started for the photo when none is given (with retrieval to run, its
    child imports the mesh reader meanwhile)."""
    if mesh_loader is None:
        try:                                    # the mesh given: no retrieval to hide behind
            own = MeshLoader(isolated=False) if mesh is not None else MeshLoader()
        except OSError as exc:                  # no process to be had (limits, memory)
            raise ValueError(f"cannot start the mesh reader's process: {exc}") from None
        with own:
            return _run(reader, runtime, own, photo, box, mask, mesh, segmenter, fov, vgg)
    try:
        return _Fit(reader, runtime, mesh_loader).run(photo, box, mask, mesh, segmenter, fov,
                                                      vgg)
    except CatalogError as exc:
        raise ValueError(f"the catalogue is damaged: {exc}") from None
    except OSError as exc:                     # a file the fit reads that the reader did not wrap
        where = f" {exc.filename}" if exc.filename else ""
        raise ValueError(f"cannot read{where}: {exc.strerror or exc}") from None


def catalog_ring(reader: CatalogReader, key: str) -> PoseRing:
    """A ``PoseRing`` of a catalogued mesh from its stored views and HOG features (coarse
    stage of ``estimate_pose`` without rendering), its cameras scaled to at most RING_SIDE
    pixels (the size the refinement renders at; HOG crops are resized, so the stored features
    stay comparable); ValueError when it has no features."""
    try:
        feats = reader.features(key)
    except (CatalogError, KeyError, OSError):
        raise ValueError(f"mesh {key[:12]} has no stored features (built with --no-features)"
                         ) from None
    views = reader.record(key)["views"]
    K = np.asarray(views[0]["K"], np.float64)
    w2c = np.stack([np.asarray(v["w2c"], np.float64) for v in views])
    az = np.array([v["azimuth"] for v in views], np.float64)
    el = np.array([v["elevation"] for v in views], np.float64)
    dist = camera_distance(w2c[0])
    W, H = int(round(2 * K[0, 2])), int(round(2 * K[1, 2]))
    f = min(1.0, RING_SIDE / max(W, H))            # pose refinement renders at this size
    K = np.diag([f, f, 1.0]) @ K
    W, H = max(1, int(round(W * f))), max(1, int(round(H * f)))
    ring = CameraRing(K=K, w2c=w2c, width=W, height=H, azimuth=az, elevation=el,
                      distance=dist, near=NEAR_FRACTION * dist)
    sides = f * np.array([float(v["stats"].get("box_side", 0.0)) for v in views])
    return PoseRing(ring=ring, feats=np.asarray(feats, np.float32), sides=sides,
                    extractor=HogExtractor(), azimuth_step=azimuth_step(el))


def catalog_rows(reader: CatalogReader, query: np.ndarray
                 ) -> tuple[list[MeshInfo], np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """The stored rows retrieval ranks a photo's features ``query`` (D,) against, read as the
    fit reads them: (meshes, rows (n, D) float32, each row's mesh index into meshes and view,
    notes). With the catalogue's search index (fresh, at least ``INDEX_FROM`` rows) its
    ``INDEX_ROWS`` rows nearest to the query in projection; else every stored row
    (``CatalogReader.feature_table``). ValueError naming the problem when the catalogue has no
    usable features."""
    notes: list[str] = []
    rows = _StoredRows(reader, notes).rows(query)
    return rows.meshes, rows.take(), rows.mesh_of, rows.view_of, notes


def retrieval_margin(candidates: list[Candidate]) -> float | None:
    """How far retrieval's answer (``candidates[0]``) is ahead of the next listed mesh: (the
    least score of the others - the answer's) / the answer's score. A listed mesh that scores
    exactly the answer's score has the answer's stored views (a copy of the model in the
    library: the same fit) and is not counted. None when no other mesh is listed or the answer
    scores 0. Below ``UNCERTAIN_MARGIN`` the fit says retrieval is uncertain (such answers on
    the bench's real photos: 13 of 15 wrong on tuning draws, 2 of 2 on a held-out one;
    docs/FIT.md, "How sure retrieval is")."""
    if not candidates or not candidates[0].score > 0:
        return None
    s0 = candidates[0].score
    others = [c.score for c in candidates[1:] if c.score != s0]
    return (min(others) - s0) / s0 if others else None


def retrieval_uncertain(margin: float | None) -> bool:
    """Whether a ``retrieval_margin`` says retrieval is uncertain: known and below
    ``UNCERTAIN_MARGIN`` (the fit's note, the batch's mark and the overview's band)."""
    return margin is not None and margin < UNCERTAIN_MARGIN


def azimuth_step(elevations) -> float:
    """Azimuth step (degrees) of a stored ring from its views' elevations: 360 over the number
    of views at the first elevation (rings are elevation-major, ``cameras.make_ring``)."""
    el = np.asarray(elevations, np.float64)
    return 360.0 / max(int(np.sum(el == el[0])), 1)


# ----------------------------------------------------------------------------- the steps

@dataclass
class _Frame:
    """Geometry of the matched pose in the working frame: part_map (h, w) int (index into
    PART_NAMES, -1 background or unseen), normal / view (h, w, 3) canonical unit vectors
    (normals face the camera), K (3, 3) and w2c (4, 4) of the working frame."""

    part_map: np.ndarray
    normal: np.ndarray
    view: np.ndarray
    K: np.ndarray
    w2c: np.ndarray
    mat_map: np.ndarray


@dataclass
class _Described:
    """A stored view the retrieval re-rank has read, kept for the photo (other object masks
    meet it again): its material-id map (0 = background), ``cues.boundary_points`` of it, and
    its unit finer-HOG row (``FINE_HOG``; set by the batch that describes new views, None
    while only ``_prefiltered`` has read the view)."""

    mat: np.ndarray
    boundary: tuple
    fine: np.ndarray | None = None


class _StoredRows:
    """The stored rows retrieval ranks a photo against (``rows``), read once per photo; what
    it finds worth saying (an index missing or not used, meshes left out) is appended to
    ``notes``."""

    def __init__(self, reader: CatalogReader, notes: list[str]):
        self.r, self.notes = reader, notes
        self.db: FeatureTable | SearchIndex | None = None
        self.read: np.ndarray | None = None    # (>= n_read, D) float32: the index rows read ...
        self.n_read = 0
        self.at: np.ndarray | None = None      # ... and where each index row is in it (-1: not)

    def database(self) -> FeatureTable | SearchIndex:
        """Where retrieval's stored rows come from: the catalogue's search index when it is
        fresh (``CatalogReader.search_index``) and holds at least ``INDEX_FROM`` rows, else its
        stacked features (``_table``: below that size reading them all costs less than the
        index's row reads, 0.25 s over 123 meshes); the reader keeps both, so a batch of
        photos reads them once."""
        if self.db is None:
            try:
                index, why = self.r.search_index()
            except CatalogError as exc:
                raise ValueError(str(exc)) from None
            if index is None or len(index.mesh) < INDEX_FROM:
                self.db = self._table()
                if index is None and len(self.db.mesh) >= INDEX_FROM:
                    self.notes.append(f"{why}: every stored row read (`ucad-index build` on "
                                      "the same library writes the index)")
            else:
                self.db = index
                self._note_skipped(index.skipped)
        return self.db

    def _table(self) -> FeatureTable:
        """The catalogue's stacked features (``CatalogReader.feature_table``)."""
        try:
            table = self.r.feature_table()
        except CatalogError as exc:
            raise ValueError(str(exc)) from None
        if not len(table.feats):
            raise ValueError("the catalogue has no accepted mesh with stored features")
        self._note_skipped(table.skipped)
        return table

    def _note_skipped(self, skipped) -> None:
        """A note naming the accepted meshes left out of retrieval (no or unreadable features)."""
        if skipped:
            sha, why = skipped[0]
            self.notes.append(f"{len(skipped)} accepted mesh(es) left out of retrieval, "
                              f"e.g. {sha[:12]}: {why}")

    def rows(self, query) -> "_RowSet":
        """The stored rows a query is ranked against. With the search index, its
        ``INDEX_ROWS`` rows nearest to the query in projection, read in full (an object that
        no longer reads as the index says: a note, and every stored row from then on); else
        every stored row."""
        src = self.database()
        if isinstance(src, SearchIndex):
            near = src.preselect(query, INDEX_ROWS)
            try:
                where = self._read_rows(src, near)
                assert self.read is not None
                return _RowSet(src.meshes, src.mesh[near], src.view[near],
                               self.read[:self.n_read], where)
            except CatalogError as exc:
                self.notes.append(f"search index not used ({exc}): every stored row read")
                src = self.db = self._table()
        return _RowSet(src.meshes, src.mesh, src.view, src.feats, None)

    def _read_rows(self, index: SearchIndex, near: np.ndarray) -> np.ndarray:
        """Where the index's rows ``near`` are in ``read``, each read once per photo (the
        queries of one photo ask for mostly the same rows) straight into ``read``, which holds
        ``4 x INDEX_ROWS`` rows before it first grows (its pages taken as they are written)."""
        if self.at is None:
            self.at = np.full(len(index.mesh), -1, np.int64)
            self.read = np.empty((min(4 * INDEX_ROWS, len(index.mesh)), index.mean.shape[0]),
                                 np.float32)
        assert self.read is not None
        new = near[self.at[near] < 0]
        if len(new):
            n = self.n_read
            if n + len(new) > len(self.read):
                grown = np.empty((max(2 * len(self.read), n + len(new)), self.read.shape[1]),
                                 np.float32)
                grown[:n] = self.read[:n]
                self.read = grown
            index.rows(new, out=self.read[n:n + len(new)])
            self.at[new] = np.arange(n, n + len(new))
            self.n_read = n + len(new)
        return self.at[near]


@dataclass
class _RowSet:
    """The stored rows one query is ranked against (``_StoredRows.rows``): ``meshes``, and per
    row its mesh (index into ``meshes``) and view; ``store[where]`` (``where`` None: all of
    ``store``) are its (n, D) float32 rows, gathered only as ``take`` asks (a photo's queries
    share the rows they read)."""

    meshes: list[MeshInfo]
    mesh_of: np.ndarray
    view_of: np.ndarray
    store: np.ndarray
    where: np.ndarray | None

    def __len__(self) -> int:
        return len(self.mesh_of)

    def scores(self, query: np.ndarray) -> np.ndarray:
        """(n,) float32 dot products of the rows with ``query`` made unit: the order in which
        retrieval preselects rows and picks the refinement's seeds."""
        q = (query / max(float(np.linalg.norm(query)), 1e-30)).astype(np.float32)
        return self.store @ q if self.where is None else (self.store @ q)[self.where]

    def take(self, sel: np.ndarray | None = None) -> np.ndarray:
        """(len(sel), D) float32: the rows ``sel`` (None: every row)."""
        if self.where is None:
            return self.store if sel is None else self.store[sel]
        return self.store[self.where if sel is None else self.where[sel]]


class _Fit:
    def __init__(self, reader: CatalogReader, runtime: Runtime | None,
                 mesh_loader: MeshLoader | None = None):
        """``mesh_loader``: what reads the retrieved mesh (None: this process)."""
        self.r, self.runtime = reader, runtime
        self.mesh_loader = mesh_loader or MeshLoader(isolated=False)
        self.seconds: dict[str, float] = {}
        self.notes: list[str] = []
        self.described: dict[tuple[str, int], _Described] = {}   # (sha, view) -> re-rank's
        self.angles: dict[str, list[ViewAngles]] = {}             # sha -> its views' angles
        self.albedo: dict[str, np.ndarray] = {}   # sha -> base colour a material id (+1), re-rank
        self.rings: dict[str, PoseRing] = {}                       # sha -> its catalog_ring
        self.stored_rows = _StoredRows(reader, self.notes)          # retrieval's rows
        self.intrinsics: np.ndarray | None = None   # the photo's assumed K in a window's pixels
        self.fov: float | None = None               # the photo's field of view, when given
        self._t = time.perf_counter()

    def _lap(self, stage: str) -> None:
        now = time.perf_counter()
        self.seconds[stage] = self.seconds.get(stage, 0.0) + now - self._t
        self._t = now

    def run(self, photo, box, mask, mesh_key, segmenter, fov=None, vgg=None) -> FitResult:
        photo = check_image(photo)
        window = PhotoWindow.around(photo.shape[:2], box, mask)
        if window is not None:                  # a large photo: steps 1-6 run on a window of it
            full_shape = photo.shape[:2]
            photo, box, mask = window.cut(photo, box, mask)
            self.intrinsics = window.intrinsics(full_shape, fov or FOV_PRIOR)
        self.fov = fov                          # else the pose search makes K of it
        obj = object_mask(photo, box=box, mask=mask, follow_edges=True)   # foreground.py
        if obj.source == "box":
            x0, y0, x1, y1 = obj.box
            spread = float(photo[y0:y1, x0:x1].reshape(-1, 3).std(axis=0).max())
            if spread < UNIFORM_STD:
                shown = obj.box if window is None else window.photo_box(obj.box)
                raise ValueError(f"no vehicle found inside the box {shown}: it is uniform "
                                 f"(standard deviation {spread:.1f} levels; all background?)")
        self._lap("object")
        obj, meta, candidates, best_view, canvas = self._object_and_mesh(photo, obj, mesh_key)
        self._lap("retrieval")
        if obj.source == "box":
            self.notes.append(f"GrabCut kept {obj.kept:.0%} of the box: the vehicle's outline "
                              "is the render's silhouette at the pose, inside the box")
        given = _pose_given(box, obj, canvas)
        mesh, note = self._load(meta)
        self._lap("load")
        crop, scale = _work_crop(photo.shape[:2], obj)
        pose = None
        if mesh is not None:
            pose, score = self._refined_pose(photo, mesh, meta.sha256, given, canvas)
            if canvas is not None:
                self.notes.append("the pose was searched on the photo grown past its edge, "
                                  "ignoring what the photo does not show; the colours use "
                                  "what it shows")
            for c in candidates[1:RERANK_POSE]:     # the next meshes, posed alike
                other = self.r.mesh(c.mesh_id)
                m2, _ = self._load(other)
                if m2 is None:
                    continue
                p2, s2 = self._refined_pose(photo, m2, other.sha256, given, canvas)
                if s2 < score:
                    meta, mesh, pose, score = other, m2, p2, s2
            if candidates and candidates[0].mesh_id != meta.sha256:
                candidates = ([c for c in candidates if c.mesh_id == meta.sha256]
                              + [c for c in candidates if c.mesh_id != meta.sha256])
        if note:
            self.notes.append(note)
        if pose is None:
            pose = self._stored_pose(meta.sha256, best_view, obj, photo)
        rows = self.r.parts(meta.sha256)
        self._lap("pose")
        work = _to_work(photo, crop, scale)
        obj_w = _to_work(obj.mask.astype(np.uint8), crop, scale, nearest=True) > 0
        K_work = _work_K(pose.K, crop, scale)
        lut = _part_lut(rows)
        if mesh is not None:
            if obj.source != "box":
                pose = _refine_rotation(mesh, pose, K_work, obj_w, self.runtime)
            frame = _render_frame(mesh, K_work, pose.w2c, work.shape[1], work.shape[0], lut,
                                  self.runtime)
        else:
            frame = self._stored_frame(meta.sha256, pose, K_work, work.shape, lut)
        if obj.source == "box":                 # the silhouette is the outline (see notes)
            shift = (0, 0)
            obj_w = obj_w & (frame.part_map >= 0)
        else:
            frame, shift = _align(frame, obj_w)
        pose.K = pose.K.copy()
        pose.K[:2, 2] += np.array(shift, np.float64) / scale
        self._lap("render")
        seg = segmenter.segment_photo(work) if segmenter is not None else None
        parts, light, loss, images, materials, vgg_fit = _fit_parts(work, obj_w, frame, rows,
                                                                    seg, vgg)
        if window is not None:                  # the pose and the object in the photo's pixels
            pose.K = window.photo_K(pose.K)
            obj = window.photo_object(obj, full_shape)
        self._lap("fit")
        margin = retrieval_margin(candidates) if mesh_key is None else None
        if mesh_key is None:
            self._say_how_sure(candidates, margin)
        return FitResult(mesh_id=meta.sha256, mesh_path=str(meta.source), pose=pose,
                         lighting=light, parts=parts, materials=materials,
                         candidates=candidates, seconds=dict(self.seconds), notes=self.notes,
                         images=images, mesh=mesh, part_rows=rows, object_source=obj.source,
                         loss=loss, object=obj, retrieval_margin=margin, vgg=vgg_fit)

    def _say_how_sure(self, candidates: list[Candidate], margin: float | None) -> None:
        """Notes on retrieval's answer: listed meshes that score exactly as it does (copies of
        the model), and, when ``margin`` is below ``UNCERTAIN_MARGIN``, the next mesh."""
        if not candidates:
            return
        s0 = candidates[0].score
        copies = [Path(c.mesh_path).name for c in candidates[1:] if c.score == s0]
        if copies:
            verb, what = ("scores", "a copy") if len(copies) == 1 else ("score", "copies")
            self.notes.append(f"{', '.join(copies)} {verb} exactly as this mesh (the same stored "
                              f"views: {what} of the model in the library?)")
        if retrieval_uncertain(margin):
            nxt = min((c for c in candidates[1:] if c.score != s0), key=lambda c: c.score)
            self.notes.append(
                f"retrieval is uncertain: the next mesh ({Path(nxt.mesh_path).name}) scores "
                f"within {margin:.1%} of this one (below {UNCERTAIN_MARGIN:.0%}, most answers "
                "on the bench's real photos were wrong): check the candidates, or give --mesh")

    # -- the object and the mesh
    def _object_and_mesh(self, photo, obj: ObjectMask, mesh_key):
        """(object, mesh record, candidates, best stored view, canvas): steps 1-2 of
        docs/FIT.md. ``canvas``: the ``past_the_edge`` hypothesis whose retrieval won (with
        ``mesh_key``: whose HOG is nearest to one of the mesh's stored views, when nearer than
        the photo as it is; ties: the photo, then ``PAST_EDGE`` order), else None; the pose
        search runs there (``_refined_pose``). With
        a box, GrabCut's object is refined by the stored silhouettes of the first meshes
        (``_refined_object``: a pixel at least half of them cover), and, without ``--mesh``,
        once by each of those silhouettes alone: retrieval runs on every such mask and keeps
        the answer that scores best (ties: the voted mask's, then the seeds' order); the
        object returned, which the pose touch-up and the part masks use, stays the voted mask
        (the colours were worse from the winning mask: docs/FIT.md). The single-seed masks
        only over stored rings of azimuth step (``azimuth_step``) at most ``SEED_MASK_STEP``:
        a coarser ring's silhouettes are too far from the photo's pose, and a mask shaped by
        one of them favours its own mesh (docs/FIT.md). The single-seed masks are not tried
        when the voted mask's answer is sure, ``retrieval_margin`` of its candidates at least
        ``SURE_MARGIN`` (on the bench's tuning draws no such answer was changed by them)."""
        hypotheses: list[ObjectMask] = []       # other object masks retrieval tries
        first, placed, seeds = obj, [], []
        if obj.source != "mask":                # GrabCut again, seeded by stored silhouettes
            if mesh_key is None:
                seeds = self._first_views(photo, obj)
            else:
                sha = self._given(mesh_key).sha256
                seeds = [(sha, self._nearest_view(sha, photo, obj))]
            self._lap("retrieval")
            placed = self._placed_silhouettes(photo, first, seeds)
            refined = self._refined_object(photo, first, placed)
            if refined is not None:
                obj = refined
            self._lap("object")
        meta, candidates, best_view = self._pick_mesh(photo, obj, mesh_key)
        margin = retrieval_margin(candidates)
        if (len(seeds) > 1 and (margin is None or margin < SURE_MARGIN)
                and azimuth_step([v.elevation for v in self._views(seeds[0][0])])
                <= SEED_MASK_STEP):
            self._lap("retrieval")
            for one in placed:                  # one mask per seed too (docstring)
                alone = self._refined_object(photo, first, [one])
                if alone is not None:
                    hypotheses.append(alone)
            self._lap("object")
        tried = [obj.mask]
        for alt in hypotheses:                  # (ties: the mask voted by every seed)
            if any(np.array_equal(alt.mask, m) for m in tried):
                continue                        # a mask already tried: the same answer
            tried.append(alt.mask)
            m2, c2, v2 = self._pick_mesh(photo, alt, None)
            if c2[0].score < candidates[0].score:
                meta, candidates, best_view = m2, c2, v2
        cut = past_the_edge(photo, obj)
        canvas = None
        if mesh_key is None:
            for hyp in cut:                     # a vehicle cut by the photo's edge (ties: as
                m2, c2, v2 = self._pick_mesh(hyp.image, hyp.obj, None)   # seen, then in
                if c2[0].score < candidates[0].score:                    # PAST_EDGE order)
                    meta, candidates, best_view, canvas = m2, c2, v2, hyp
        elif cut:                               # the given mesh's own stored views decide
            canvas = past_edge_choice(photo, cut, self._ring(meta.sha256),
                                      HogExtractor(runtime=self.runtime))
        if cut and mesh_key is None:
            self.notes.append("the vehicle touches the photo's edge: retrieval also tried it "
                              "going on past the edge")
        elif cut:
            self.notes.append("the vehicle touches the photo's edge")
        return obj, meta, candidates, best_view, canvas

    # -- which mesh
    def _given(self, key):
        """The catalogue's record of the mesh the caller named (ValueError if not accepted)."""
        try:
            meta = self.r.mesh(str(key))
        except CatalogError as exc:
            raise ValueError(f"{exc}") from None
        if meta.state != "accepted":
            raise ValueError(f"mesh {key} is {meta.state} in the catalogue ({meta.reason});"
                             " it has no part table to fit")
        return meta

    def _first_views(self, photo, obj: ObjectMask) -> list[tuple[str, int]]:
        """[(sha, view)] of the first ``REFINE_MESHES`` distinct meshes by float32 dot product
        of the object's HOG with the stored rows retrieval searches (``_StoredRows.rows``: the
        order the exact search refines; ties: the lower row), each with its best row: the seeds
        of ``_refined_object``."""
        q, _ = query_features(photo, HogExtractor(runtime=self.runtime), mask=obj.mask,
                              runtime=self.runtime)
        rows = self.stored_rows.rows(q)
        out: dict[int, int] = {}
        for row in np.argsort(-rows.scores(q), kind="stable"):
            out.setdefault(int(rows.mesh_of[row]), int(rows.view_of[row]))
            if len(out) >= REFINE_MESHES:
                break
        return [(rows.meshes[k].sha256, v) for k, v in out.items()]

    def _pick_mesh(self, photo, obj: ObjectMask, key):
        if key is not None:
            return self._given(key), [], None
        query, _ = query_features(photo, HogExtractor(runtime=self.runtime), mask=obj.mask,
                                  runtime=self.runtime)
        rows = self.stored_rows.rows(query)
        metas, mesh_of, view_of = rows.meshes, rows.mesh_of, rows.view_of
        near = None
        if len(rows) > PRESELECT_ROWS:             # float32 dot products pick the rows that
            near = np.sort(np.argpartition(-rows.scores(query), PRESELECT_ROWS)  # the exact
                           [:PRESELECT_ROWS])                        # search ranks
            mesh_of, view_of = mesh_of[near], view_of[near]
        db = rows.take(near)
        zeros = np.zeros(len(db))                  # angles are read for the matches only
        matches = search_catalog(query, db, mesh_of, view_of, zeros, zeros,
                                 top=len(db))
        first: dict[int, CatalogMatch] = {}       # mesh -> its best row
        for mt in matches:
            first.setdefault(mt.mesh, mt)
        ranked = self._fine_rerank(photo, obj, query, metas, list(first.values()))
        cands = []
        for k, view, score in ranked[:CANDIDATES]:
            m = metas[k]
            v = self._views(m.sha256)[view]
            cands.append(Candidate(m.sha256, str(m.source), view, v.azimuth, v.elevation,
                                   score))
        return metas[ranked[0][0]], cands, ranked[0][1]

    def _fine_rerank(self, photo, obj: ObjectMask, query, metas,
                     best: list[CatalogMatch]) -> list[tuple[int, int, float]]:
        """[(mesh index, view, score)] in retrieval order: ``FINE_MESHES`` meshes of ``best``
        (each mesh's best row, in HOG order), chosen among its first ``PREFILTER_MESHES`` by
        ``_prefiltered``, each at its best view and its
        ``FINE_VIEWS`` neighbours on each side in azimuth (same elevation), its view chosen by
        ``d + FINE_WEIGHT * d_fine + EDGE_WEIGHT * d_edge`` (ties: the first in azimuth order,
        from ``-FINE_VIEWS``): ``d`` the squared distance of the unit HOG rows, ``d_fine``
        that of the finer HOG (``FINE_HOG``) of the photo's object and of the stored view
        shaded from its maps (``shade.shade_stored_view``: no mesh read), ``d_edge`` how far
        the stored view's material boundaries lie from the photo's edges around the object
        (``cues.edge_distance``); the mesh scored by that view's sum + ``RECALL_WEIGHT *
        d_recall + REGION_WEIGHT * d_region`` (``cues.edge_recall``: how far the photo's
        edges inside the object lie from the view's boundaries; ``cues.region_residual``: the
        colour variance its material regions leave), re-ranked by it (ties: the HOG order);
        the other meshes follow with their HOG distance."""
        ex = HogExtractor(runtime=self.runtime, **FINE_HOG)
        q_fine, _ = query_features(photo, ex, mask=obj.mask, runtime=self.runtime)
        edges = photo_edges(photo, obj.mask)
        qf = unit_rows(q_fine[None])[0][0]
        q = unit_rows(np.asarray(query)[None])[0][0]
        table = self.stored_rows.database()        # mt.mesh indexes its meshes (= metas)
        todo: dict[tuple[str, int], int] = {}      # (sha, view) to describe -> its materials
        rows = []
        kept = self._prefiltered(edges, metas, best)
        for mt in kept:
            sha = metas[mt.mesh].sha256
            views = self._views(sha)
            ring = sorted((v.azimuth, v.index) for v in views
                          if v.elevation == views[mt.view].elevation)
            at = [i for _, i in ring].index(mt.view)
            sel = [ring[(at + d) % len(ring)][1] for d in range(-FINE_VIEWS, FINE_VIEWS + 1)]
            first = int(np.searchsorted(table.mesh, mt.mesh))    # its rows, in view order
            d = 2.0 - 2.0 * unit_rows(table.rows(first + np.asarray(sel)))[0] @ q
            for v, dv in zip(sel, d):
                rows.append((mt.mesh, v, float(dv)))
                have = self.described.get((sha, v))
                if have is None or have.fine is None:
                    todo.setdefault((sha, v), metas[mt.mesh].n_materials)
        if todo:
            self._describe_fine(ex, todo)
        scored: list[tuple[float, int, int, int]] = []
        if rows:
            seen = [self.described[metas[k].sha256, v] for k, v, _ in rows]
            f = np.stack([sv.fine for sv in seen])
            total = (np.array([dv for _, _, dv in rows]) + FINE_WEIGHT * (2.0 - 2.0 * f @ qf)
                     + EDGE_WEIGHT * np.array([edge_distance(edges, *sv.boundary)
                                               for sv in seen]))
            for rank, mt in enumerate(kept):
                own = [i for i, (k, _, _) in enumerate(rows) if k == mt.mesh]
                i = own[int(np.argmin(total[own]))]     # the view; then the mesh's score:
                sv = seen[i]
                score = (float(total[i]) + RECALL_WEIGHT * edge_recall(edges, *sv.boundary)
                         + REGION_WEIGHT * region_residual(edges, sv.mat))
                scored.append((score, rank, mt.mesh, rows[i][1]))
        scored.sort()
        ranked = {mt.mesh for mt in kept}
        return ([(k, v, s) for s, _, k, v in scored]
                + [(mt.mesh, mt.view, mt.score) for mt in best if mt.mesh not in ranked])

    def _describe_fine(self, ex: HogExtractor, todo: dict[tuple[str, int], int]) -> None:
        """The finer HOG of each stored view (sha, view) of ``todo`` (-> its materials) into
        ``described`` (and its boundaries, where ``_prefiltered`` did not read it): the views
        read in turn, each shaded (``shade_stored_view``, the catalogue's base colours) on
        ``SHADE_THREADS`` threads while the next is read, then one HOG launch for all."""
        albedo = self.albedo
        shaded, masks = [], []
        with ThreadPoolExecutor(SHADE_THREADS) as pool:
            for (sha, v), n_materials in todo.items():
                if sha not in albedo:           # (once per photo: the part rows' JSON)
                    albedo[sha] = np.full((n_materials + 1, 3), 0.8)
                    for row in self.r.parts(sha):
                        albedo[sha][row.index + 1] = row.props.get("base_color", [0.8] * 3)[:3]
                rec = self.r.view(sha, v, part_masks=False)   # maps and K only
                shaded.append(pool.submit(shade_stored_view, rec.depth, rec.mat_id, rec.tri_id,
                                          rec.K, albedo[sha]))
                masks.append(np.isfinite(rec.depth))
                if (sha, v) not in self.described:
                    self.described[sha, v] = _Described(rec.mat_id, boundary_points(rec.mat_id))
        images = np.stack([f.result() for f in shaded])
        new = unit_rows(ex.extract(images, np.stack(masks)).feats)[0]
        for (sha, v), row in zip(todo, new):
            self.described[sha, v].fine = row

    def _prefiltered(self, edges, metas, best: list[CatalogMatch]) -> list[CatalogMatch]:
        """The meshes of ``best`` (HOG order) that ``_fine_rerank`` describes: of the first
        ``PREFILTER_MESHES``, the ``FINE_MESHES`` of least ``d + EDGE_WEIGHT * d_edge`` at
        their best HOG view (``d`` = the match's score; the stored material map alone: nothing
        shaded; ties: the HOG order), kept in HOG order; all of them when there are no more
        than ``FINE_MESHES``."""
        pool = best[:PREFILTER_MESHES]
        if len(pool) <= FINE_MESHES:
            return pool
        pre = []
        for rank, mt in enumerate(pool):
            sha = metas[mt.mesh].sha256
            if (sha, mt.view) not in self.described:
                mat = np.asarray(self.r.material_map(sha, int(mt.view)))
                self.described[sha, mt.view] = _Described(mat, boundary_points(mat))
            d_edge = edge_distance(edges, *self.described[sha, mt.view].boundary)
            pre.append((mt.score + EDGE_WEIGHT * d_edge, rank))
        keep = sorted(rank for _, rank in sorted(pre)[:FINE_MESHES])
        return [pool[r] for r in keep]

    def _views(self, sha: str) -> list[ViewAngles]:
        """The angles of a mesh's stored views (``CatalogReader.view_angles``), read once per
        photo."""
        if sha not in self.angles:
            self.angles[sha] = self.r.view_angles(sha)
        return self.angles[sha]

    def _load(self, meta) -> tuple[Mesh | None, str]:
        """(the mesh in the catalogue's frame, ''), or (None, why) when its file is gone,
        changed or unreadable."""
        src = meta.source
        if not src.is_file():
            return None, (f"the mesh file is not at {src} (it moved or was deleted): fitted on "
                          "the nearest stored view, no GLB")
        try:
            if content_sha256(src) != meta.sha256:
                return None, (f"{src} changed since it was catalogued: fitted on the nearest "
                              "stored view, no GLB")
            mesh = in_frame(self.mesh_loader.load(src), meta.file_to_norm)
        except (IngestError, ValueError, OSError) as exc:
            return None, f"{src} cannot be read ({exc}): fitted on the nearest stored view"
        if len(mesh.materials) != meta.n_materials:
            return None, (f"{src}: {len(mesh.materials)} materials, the catalogue has "
                          f"{meta.n_materials}: fitted on the nearest stored view")
        return mesh, ""

    # -- the object
    def _placed_silhouettes(self, photo, obj: ObjectMask, seeds) -> list[np.ndarray | None]:
        """The stored silhouettes of ``seeds`` ([(sha, view)]), each placed onto the object's
        box (its silhouette's box stretched onto it): (H, W) bool, None for an empty one."""
        import cv2

        H, W = photo.shape[:2]
        placed: list[np.ndarray | None] = []
        for sha, view in seeds:
            sil = np.asarray(self.r.material_map(sha, int(view))) > 0
            if not sil.any():
                placed.append(None)
                continue
            M = box_stretch(mask_box(sil), obj.box)
            placed.append(cv2.warpAffine(sil.astype(np.uint8), M, (W, H),
                                         flags=cv2.INTER_NEAREST) > 0)
        return placed

    def _refined_object(self, photo, obj: ObjectMask,
                        placed: list[np.ndarray | None]) -> ObjectMask | None:
        """GrabCut rerun with placed stored silhouettes (``_placed_silhouettes``) as its prior
        (``foreground.refine_with_silhouette``, core ``REFINE_CORE``): a pixel is "probably
        foreground" when at least half of them cover it. None when GrabCut keeps under
        ``MIN_REFINED`` of that prior (it lost the vehicle)."""
        X0, Y0, X1, Y1 = obj.box
        votes = sum((m for m in placed if m is not None), np.zeros(photo.shape[:2], np.float64))
        prior = votes >= len(placed) / 2.0
        if not prior.any():
            return None
        fg = refine_with_silhouette(photo, prior, core=REFINE_CORE, follow_edges=True)
        if np.count_nonzero(fg) < max(MIN_REFINED * np.count_nonzero(prior), 8):
            return None
        return ObjectMask(mask=fg, source="grabcut", box=obj.box,
                          kept=float(fg[Y0:Y1, X0:X1].mean()))

    def _nearest_view(self, sha: str, photo, obj: ObjectMask) -> int:
        """The stored view of mesh ``sha`` nearest to the photo's object by HOG."""
        return nearest_ring_view(photo, obj.mask, self._ring(sha),
                                 HogExtractor(runtime=self.runtime)).view

    def _ring(self, sha: str) -> PoseRing:
        """``catalog_ring`` of mesh ``sha``, read once per photo."""
        if sha not in self.rings:
            self.rings[sha] = catalog_ring(self.r, sha)
        return self.rings[sha]

    # -- pose
    def _refined_pose(self, photo, mesh, sha, given: dict,
                      canvas: GrownPhoto | None = None) -> tuple[FitPose, float]:
        """The pose search's best pose and its score (lower is better); ``given``: the box
        or the object's mask. A mesh over ``POSE_PROXY_FROM`` triangles is searched on its
        ``render_proxy`` (the caller renders the fit with the mesh itself). ``canvas``: the
        photo grown past its edge (``past_the_edge``) that retrieval chose: the search runs
        there (``estimate_pose(grown=...)``: framed by the grown box or mask, the camera moved
        with it, the cues told what the photo shows); the pose's K is in the photo's pixels."""
        ring = self._ring(sha)
        if mesh.n_faces > POSE_PROXY_FROM:        # silhouettes at RING_SIDE px: a proxy will do
            mesh = render_proxy(mesh, POSE_PROXY_CELLS)
        est = estimate_pose(photo, mesh, coarse=ring, top=1, runtime=self.runtime,
                            intrinsics=self.intrinsics, fov=self.fov, grown=canvas, **given)
        c = est.best
        assert c.K is not None and c.w2c is not None
        return FitPose(c.azimuth, c.elevation, np.asarray(c.K, np.float64),
                       np.asarray(c.w2c, np.float64), "refined"), float(c.score)

    def _stored_pose(self, sha, view, obj, photo) -> FitPose:
        """The nearest stored view (by HOG) placed onto the object's box."""
        if view is None:
            view = self._nearest_view(sha, photo, obj)
        rec = self.r.view(sha, int(view), part_masks=False)
        sil = rec.mat_id > 0
        if not sil.any():
            raise ValueError(f"stored view {view} of mesh {sha[:12]} shows nothing")
        A = _box_similarity(mask_box(sil), mask_box(obj.mask))
        self.stored = (rec, A)
        return FitPose(rec.azimuth, rec.elevation, A @ np.asarray(rec.K, np.float64),
                       np.asarray(rec.w2c, np.float64), "stored view")

    def _stored_frame(self, sha, pose, K_work, shape, lut) -> _Frame:
        import cv2

        rec, A = self.stored
        h, w = shape[:2]
        normal = _depth_normals(rec.depth, rec.K, rec.w2c)
        M = (K_work @ np.linalg.inv(np.asarray(rec.K, np.float64)))[:2]
        mat = cv2.warpAffine(rec.mat_id.astype(np.float32), M, (w, h), flags=cv2.INTER_NEAREST,
                             borderValue=0.0).astype(np.int64)
        nrm = cv2.warpAffine(normal.astype(np.float32), M, (w, h), flags=cv2.INTER_NEAREST,
                             borderValue=(0.0, 0.0, 0.0)).astype(np.float64)
        _, rays = pixel_rays(K_work, pose.w2c, w, h)
        view = -rays
        return _Frame(part_map=lut[np.minimum(mat, len(lut) - 1)], normal=_facing(nrm, view),
                      view=view, K=K_work, w2c=pose.w2c, mat_map=mat)


def _pose_given(box, obj: ObjectMask, canvas: GrownPhoto | None) -> dict:
    """What the pose search is framed by: the object's mask, or the box when GrabCut lost the
    vehicle (``obj.source == "box"``) or the photo was grown past its edge (``canvas``: its
    grown box; a grown GrabCut mask posed worse there). With ``RERANK_POSE`` = 1 this choice
    sets the pose only, not the mesh (docs/FIT.md, "The pose framed by the object's mask")."""
    if box is not None and (obj.source == "box" or canvas is not None):
        return {"box": box}
    return {"mask": obj.mask}


def _part_lut(rows) -> np.ndarray:
    """material id (index + 1; 0 background) -> index into PART_NAMES (-1: none/unseen)."""
    lut = np.full(max((int(r.index) for r in rows), default=-1) + 2, -1, np.int64)
    for r in rows:
        if r.part in PART_NAMES:
            lut[int(r.index) + 1] = PART_NAMES.index(r.part)
    return lut


def _work_crop(shape, obj: ObjectMask) -> tuple[tuple[int, int, int, int], float]:
    """The working crop (x0, y0, x1, y1) of the photo and its scale (<= 1)."""
    H, W = shape
    x0, y0, x1, y1 = mask_box(obj.mask)
    g = CROP_GROW * max(x1 - x0, y1 - y0)
    c = (max(0, int(np.floor(x0 - g))), max(0, int(np.floor(y0 - g))),
         min(W, int(np.ceil(x1 + g))), min(H, int(np.ceil(y1 + g))))
    side = max(c[2] - c[0], c[3] - c[1])
    return c, min(1.0, WORK_SIDE / side)


def _to_work(img: np.ndarray, crop, scale: float, nearest: bool = False) -> np.ndarray:
    import cv2

    x0, y0, x1, y1 = crop
    sub = np.ascontiguousarray(img[y0:y1, x0:x1])
    if scale == 1.0:
        return sub
    size = (max(1, int(round((x1 - x0) * scale))), max(1, int(round((y1 - y0) * scale))))
    return cv2.resize(sub, size, interpolation=cv2.INTER_NEAREST if nearest
                      else cv2.INTER_AREA)


def _work_K(K: np.ndarray, crop, scale: float) -> np.ndarray:
    """K of the working frame: pixel centres map by x_w + 0.5 = scale (x + 0.5 - x0)."""
    A = np.array([[scale, 0.0, -scale * crop[0]], [0.0, scale, -scale * crop[1]],
                  [0.0, 0.0, 1.0]])
    return A @ np.asarray(K, np.float64)


def _box_similarity(src, dst) -> np.ndarray:
    """3x3 scale + translation taking box ``src`` onto box ``dst`` (centres aligned, longer
    sides equal), image coordinates."""
    s = max(dst[2] - dst[0], dst[3] - dst[1]) / max(src[2] - src[0], src[3] - src[1], 1)
    cs = ((src[0] + src[2]) / 2.0, (src[1] + src[3]) / 2.0)
    cd = ((dst[0] + dst[2]) / 2.0, (dst[1] + dst[3]) / 2.0)
    return np.array([[s, 0.0, cd[0] - s * cs[0]], [0.0, s, cd[1] - s * cs[1]], [0, 0, 1.0]])


def _facing(normal: np.ndarray, view: np.ndarray) -> np.ndarray:
    """Unit normals flipped toward the camera (zero normals: the view direction)."""
    n = np.asarray(normal, np.float64)
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(length > 1e-9, n / np.maximum(length, 1e-12), view)
    flip = np.einsum("...i,...i->...", n, view) < 0
    n[flip] *= -1.0
    return n


def _render_frame(mesh: Mesh, K, w2c, w: int, h: int, lut, runtime) -> _Frame:
    views = render_views(mesh, single_camera(K, w2c, w, h), runtime=runtime)
    tri = views.tri_id[0].astype(np.int64)
    fg = tri != 0xFFFFFFFF
    normals = face_normals(mesh)
    nrm = np.zeros((h, w, 3))
    nrm[fg] = normals[tri[fg]]
    _, rays = pixel_rays(np.asarray(K, np.float64), np.asarray(w2c, np.float64), w, h)
    view = -rays
    mat = views.mat_id[0].astype(np.int64)
    part_map = np.where(mat < len(lut), lut[np.minimum(mat, len(lut) - 1)], -1)
    return _Frame(part_map=part_map, normal=_facing(nrm, view), view=view, K=K, w2c=w2c,
                  mat_map=mat)


def _rotated(w2c: np.ndarray, d_az: float, d_el: float) -> np.ndarray:
    """w2c of the camera moved by d_az degrees of azimuth (about +Y through the vehicle's
    centre) and d_el degrees of elevation (about the camera's right axis through the centre)."""
    def rot(axis, deg):
        a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
        t = np.radians(deg)
        A = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        return np.eye(3) + np.sin(t) * A + (1 - np.cos(t)) * A @ A
    R = rot([0.0, 1.0, 0.0], d_az) @ rot(-w2c[0, :3], d_el)   # moves the camera centre
    out = np.asarray(w2c, np.float64).copy()
    out[:3, :3] = w2c[:3, :3] @ R.T
    return out


def _silhouette_iou(mesh, K, w2c, obj: np.ndarray, runtime) -> float:
    """IoU of the render's silhouette and ``obj`` after the best whole-pixel shift."""
    h, w = obj.shape
    sil = np.isfinite(render_views(mesh, single_camera(K, w2c, w, h), runtime=runtime).depth[0])
    return _best_shift(sil, obj, max(1, int(round(SHIFT * max(h, w)))))[0]


def _best_shift(sil: np.ndarray, obj: np.ndarray, s: int) -> tuple[float, int, int]:
    """(IoU, dx, dy) of the shift of ``sil`` within +-s pixels that best overlaps ``obj``
    (ties: the smaller |dx| + |dy|, then dy, then dx)."""
    best = (-1.0, 0, 0)
    shifts = sorted(((dx, dy) for dy in range(-s, s + 1) for dx in range(-s, s + 1)),
                    key=lambda t: (abs(t[0]) + abs(t[1]), t[1], t[0]))
    n_obj = np.count_nonzero(obj)
    n_sil = np.count_nonzero(sil)
    for dx, dy in shifts:
        inter = np.count_nonzero(_shifted(sil, dx, dy, False) & obj)
        union = n_obj + n_sil - inter
        iou = inter / union if union else 0.0
        if iou > best[0]:
            best = (iou, dx, dy)
    return best


def _refine_rotation(mesh, pose: FitPose, K_work, obj: np.ndarray, runtime) -> FitPose:
    """Coordinate descent on (azimuth, elevation) maximising the silhouette IoU in the half-size
    working frame: steps of ``ROT_STEPS`` degrees, each axis in turn, while it improves."""
    import cv2

    h, w = obj.shape
    half = cv2.resize(obj.astype(np.uint8), (max(1, w // 2), max(1, h // 2)),
                      interpolation=cv2.INTER_NEAREST) > 0
    Kh = np.diag([0.5, 0.5, 1.0]) @ K_work
    best = (_silhouette_iou(mesh, Kh, pose.w2c, half, runtime), 0.0, 0.0)
    for step in ROT_STEPS:
        improved = True
        while improved:
            improved = False
            for da, de in ((-step, 0.0), (step, 0.0), (0.0, -step), (0.0, step)):
                a, e = best[1] + da, best[2] + de
                if abs(a) > ROT_RANGE or abs(e) > ROT_RANGE:
                    continue
                iou = _silhouette_iou(mesh, Kh, _rotated(pose.w2c, a, e), half, runtime)
                if iou > best[0] + 1e-9:
                    best, improved = (iou, a, e), True
                    break
    _, a, e = best
    if a == 0.0 and e == 0.0:
        return pose
    return FitPose((pose.azimuth + a) % 360.0, pose.elevation + e, pose.K,
                   _rotated(pose.w2c, a, e), pose.source)


def _depth_normals(depth: np.ndarray, K, w2c) -> np.ndarray:
    """(H, W, 3) canonical-frame normals of a stored depth map (central differences of the
    back-projected points; zero where a neighbour is background)."""
    H, W = depth.shape
    j, i = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    Kinv = np.linalg.inv(np.asarray(K, np.float64))
    d = np.where(np.isfinite(depth), depth, np.nan).astype(np.float64)
    cam = np.stack([j, i, np.ones_like(j)], -1) @ Kinv.T * d[..., None]
    R, t = np.asarray(w2c)[:3, :3], np.asarray(w2c)[:3, 3]
    P = (cam - t) @ R                                  # R^T (p - t)
    du = np.gradient(P, axis=1)
    dv = np.gradient(P, axis=0)
    n = np.cross(du, dv)
    return np.nan_to_num(n)


def _align(frame: _Frame, obj: np.ndarray) -> tuple[_Frame, tuple[int, int]]:
    """The frame shifted by whole pixels (dx, dy) to best overlap ``obj`` (IoU)."""
    sil = np.isfinite(frame.normal[..., 0]) & (np.abs(frame.normal).sum(-1) > 0) & \
        (frame.part_map >= 0)
    h, w = obj.shape
    _, dx, dy = _best_shift(sil, obj, max(1, int(round(SHIFT * max(h, w)))))
    if dx == 0 and dy == 0:
        return frame, (0, 0)
    K = frame.K.copy()
    K[0, 2] += dx
    K[1, 2] += dy
    return _Frame(part_map=_shifted(frame.part_map, dx, dy, -1),
                  mat_map=_shifted(frame.mat_map, dx, dy, 0),
                  normal=_shifted(frame.normal, dx, dy, 0.0),
                  view=frame.view, K=K, w2c=frame.w2c), (dx, dy)


def _shifted(a: np.ndarray, dx: int, dy: int, fill) -> np.ndarray:
    out = np.full_like(a, fill)
    h, w = a.shape[:2]
    ys, yd = (slice(0, h - dy), slice(dy, h)) if dy >= 0 else (slice(-dy, h), slice(0, h + dy))
    xs, xd = (slice(0, w - dx), slice(dx, w)) if dx >= 0 else (slice(-dx, w), slice(0, w + dx))
    out[yd, xd] = a[ys, xs]
    return out


# ----------------------------------------------------------------------------- fitting

def _prior(part: str, rows) -> tuple[np.ndarray, float, float, float]:
    """(prior base colour, metallic, roughness, clear-coat weight) of a part; car paint and
    'other' take the colour of the part's largest material (most pixels; ties: lower index)."""
    spec = PART_MATERIALS.get(part)
    mine = sorted((r for r in rows if r.part == part), key=lambda r: (-int(r.pixels), r.index))
    src = mine[0].props.get("base_color") if mine else None
    src_rgb = np.asarray(src[:3] if isinstance(src, list) and len(src) >= 3 else (0.8,) * 3,
                         np.float64)
    if spec is None:
        props = mine[0].props if mine else {}
        return (src_rgb, float(props.get("metallic", 0.0) or 0.0),
                float(props.get("roughness", 1.0) or 1.0), 0.0)
    pbr = spec["pbrMetallicRoughness"]
    color = (src_rgb if spec.get("keep_source_color")
             else np.asarray(pbr.get("baseColorFactor", [0.8] * 4)[:3], np.float64))
    ext = spec.get("extensions", {})
    coat = float(ext.get("KHR_materials_clearcoat", {}).get("clearcoatFactor", 0.0))
    if "KHR_materials_transmission" in ext:
        coat = 1.0                                  # glass reflects like a clear coat
    return color, float(pbr["metallicFactor"]), float(pbr["roughnessFactor"]), coat


def _fit_parts(work, obj, frame: _Frame, rows, seg, vgg=None):
    """Per-part fit in the working frame; returns (parts, lighting, loss, images, materials,
    the l_vgg refinement or None); ``vgg``: ``ucad_cl.vgg.OnnxFeatures`` or None."""
    import cv2

    h, w = obj.shape
    present = [p for p in PART_NAMES if any(r.part == p for r in rows)]
    rendered = (frame.part_map >= 0) & obj
    diag = float(np.hypot(*(np.array(mask_box(obj))[2:] - np.array(mask_box(obj))[:2])))
    margin = max(1, int(round(MARGIN * diag)))
    kernel = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
    part_map = np.full((h, w), -1, np.int64)
    visible: dict[str, int] = {}
    for p in present:
        k = PART_NAMES.index(p)
        m = (frame.part_map == k) & obj
        if seg is not None:
            m = np.asarray(seg.get(p, np.zeros((h, w), bool)), bool) & rendered
        visible[p] = int(m.sum())
        er = cv2.erode(m.astype(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT,
                       borderValue=0) > 0
        part_map[er] = k
    lin = srgb8_to_linear(work)
    unsat = work.max(axis=-1) < SATURATED
    priors = {p: _prior(p, rows) for p in present}
    fit_parts = [p for p in present if np.count_nonzero((part_map == PART_NAMES.index(p))
                                                        & unsat) >= MIN_PIXELS]
    if not fit_parts:
        raise ValueError("no part of the vehicle shows enough pixels to fit (the object is "
                         f"too small or the pose misses it: {sum(visible.values())} pixels)")
    index = {PART_NAMES.index(p): i for i, p in enumerate(fit_parts)}
    sel = np.zeros((h, w), bool)
    for k in index:
        sel |= part_map == k
    sel &= unsat
    mats = frame.mat_map[sel]
    samples = _samples(lin[sel], frame.normal[sel], frame.view[sel], part_map[sel], index,
                       fit_parts, priors)
    lf = fit_light(samples, len(fit_parts))
    neutral = {i: float(np.count_nonzero(samples.part == i)) for i, p in enumerate(fit_parts)
               if p in NEUTRAL_PARTS and float(LUMA @ np.nan_to_num(lf.albedo[i])) <= TYRE_LUMA}
    lf, gain = balance(lf, neutral)
    vgg_fit = None
    if vgg is not None:                        # the paper's l_vgg joins (ucad_cl/vgg.py)
        lf, vgg_fit = refine_colours(vgg, work, samples, np.nonzero(sel), lf)
    B, C = shading(samples, lf.lighting)
    res = (samples.rgb - predict(samples, lf.lighting, lf.albedo))
    parts: dict[str, PartFit] = {}
    for p in present:
        color, metal, rough, _ = priors[p]
        npx = int(np.count_nonzero(part_map == PART_NAMES.index(p)))
        if p in fit_parts:
            i = fit_parts.index(p)
            on = (samples.part == i)
            kept = on & lf.kept
            r = float(np.sqrt(np.mean((res[kept] @ LUMA) ** 2)))
            status, fitted = "fitted", lf.albedo[i]
            reason = (_two_colours(samples, B, C, on & lf.kept, mats)
                      if p not in NOT_ONE_COLOUR else "")
            if p in NEUTRAL_PARTS:             # a tyre is dark grey: else its mask is off it
                reason, fitted = _check_tyre(fitted, color, lf.lighting.white_balance)
            if reason:
                status = "flagged"
            refl = ""
            if priors[p][3] > 0:
                scale = lf.lighting.coat_scale
                refl = "folded" if scale is not None and scale[i] == 0 else "modelled"
            parts[p] = PartFit(p, fitted, metal, rough, npx, r, status, reason, refl)
        elif visible[p] == 0:
            parts[p] = PartFit(p, color, metal, rough, 0, 0.0, "prior")
        else:
            parts[p] = PartFit(p, color, metal, rough, npx, 0.0, "flagged",
                               f"too few pixels ({npx} after a {margin}-pixel erosion, "
                               f"fewer than {MIN_PIXELS})")
    render = _render_image(work, frame, parts, lf.lighting, priors)
    materials = [{"name": r.name, "part": r.part,
                  "color_linear": _rl(parts[r.part].color_linear) if r.part in parts
                  else _rl(_prior(r.part, [r])[0])}
                 for r in sorted(rows, key=lambda r: r.index)]
    images = FitImages(photo=work, render=render, part_map=part_map, object=obj)
    return parts, lf.lighting, lf.loss, images, materials, vgg_fit


def _check_tyre(fitted: np.ndarray, prior: np.ndarray, gains: np.ndarray):
    """(reason, colour) of a fitted tyre: ('', fitted), or a reason and the prior colour when
    it is lighter than ``TYRE_LUMA`` or, after the white balance ``gains``, still further from
    grey than a plausible light cast (``light.plausible_cast``): its mask holds something else
    (paint, background)."""
    luma = float(LUMA @ np.nan_to_num(fitted))
    if luma > TYRE_LUMA:
        return (f"fitted luminance {luma:.2f} is too light for a tyre (over {TYRE_LUMA}): its "
                "mask is likely off the tyres; prior colour kept"), prior
    if luma > 0 and not plausible_cast(neutral_gains(np.nan_to_num(fitted))):
        return (f"fitted colour {srgb_hex(np.clip(fitted, 0, 1))} is not grey for a tyre: its "
                "mask is likely off the tyres; prior colour kept"), prior
    return "", fitted


def _samples(rgb, normal, view, pmap, index, fit_parts, priors) -> Samples:
    lut = np.full(len(PART_NAMES) + 1, -1, np.int64)
    for k, i in index.items():
        lut[k] = i
    part = lut[np.asarray(pmap, np.int64)]
    table = np.array([priors[p][1:] for p in fit_parts], np.float64)   # metallic, rough, coat
    return Samples(rgb=rgb, normal=normal, view=view, part=part, coat=table[part, 2],
                   metallic=table[part, 0], roughness=table[part, 1])


def _two_colours(s: Samples, B: np.ndarray, C: np.ndarray, on: np.ndarray,
                 mats: np.ndarray) -> str:
    """A reason when the part's materials show two colours, else ''.

    Each material of the part with at least MIN_PIXELS kept pixels gets its own closed-form
    colour under the fitted light (averaging over a material cancels most per-pixel model
    error); the colours are reduced to chromaticity (r, g) = (R, G) / (R + G + B), which an
    error of the light's strength does not change (two greys, e.g. black and white, are not
    told apart), and split by 2-means (pixel-weighted; from the largest material and the
    material farthest from it). Flagged when each group holds at least TWO_COLOUR_SHARE of the
    pixels and the groups are TWO_COLOUR_CHROMA apart in chromaticity and TWO_COLOUR_DE in
    CIEDE2000 (their pixel-weighted colours)."""
    ids, cols, wts = [], [], []
    for m in np.unique(mats[on]):
        sel = on & (mats == m)
        n = int(np.count_nonzero(sel))
        if n < MIN_PIXELS:
            continue
        b, c, y = B[sel], C[sel], s.rgb[sel]
        a = np.maximum((b * (y - c)).sum(axis=0) / np.maximum((b * b).sum(axis=0), 1e-12), 0)
        if a.sum() <= 1e-6:
            continue
        ids.append(int(m))
        cols.append(a)
        wts.append(n)
    if len(cols) < 2:
        return ""
    col, w = np.array(cols), np.array(wts, np.float64)
    ch = col[:, :2] / col.sum(axis=1, keepdims=True)
    c1 = ch[int(np.argmax(w))]
    c2 = ch[int(np.argmax(np.linalg.norm(ch - c1, axis=1)))]
    a = np.ones(len(ch), bool)
    for _ in range(10):
        a = np.linalg.norm(ch - c1, axis=1) <= np.linalg.norm(ch - c2, axis=1)
        if a.all():
            return ""
        c1 = (ch[a] * w[a, None]).sum(0) / w[a].sum()
        c2 = (ch[~a] * w[~a, None]).sum(0) / w[~a].sum()
    share = float(w[a].sum() / w.sum())
    if min(share, 1 - share) < TWO_COLOUR_SHARE or np.linalg.norm(c1 - c2) < TWO_COLOUR_CHROMA:
        return ""
    g1 = (col[a] * w[a, None]).sum(0) / w[a].sum()
    g2 = (col[~a] * w[~a, None]).sum(0) / w[~a].sum()
    de = float(delta_e2000(linear_to_lab(g1), linear_to_lab(g2)))
    if de < TWO_COLOUR_DE:
        return ""
    return (f"two colours: materials holding {share:.0%} and {1 - share:.0%} of its pixels "
            f"are {srgb_hex(np.clip(g1, 0, 1))} and {srgb_hex(np.clip(g2, 0, 1))} "
            f"(CIEDE2000 {de:.0f})")


def _render_image(work, frame: _Frame, parts, light, priors) -> np.ndarray:
    """uint8 RGB of the fitted model under ``light`` in the working frame (grey background)."""
    h, w = frame.part_map.shape
    out = np.full((h, w, 3), 128, np.uint8)
    sel = frame.part_map >= 0
    if not sel.any():
        return out
    names = [p for p in PART_NAMES if p in parts]
    idx = {PART_NAMES.index(p): i for i, p in enumerate(names)}
    pm = frame.part_map[sel]
    keep = np.isin(pm, list(idx))
    s = _samples(np.zeros((int(keep.sum()), 3)), frame.normal[sel][keep], frame.view[sel][keep],
                 pm[keep], idx, names, priors)
    albedo = np.array([parts[p].color_linear for p in names], np.float64)
    scale = np.array([0.0 if parts[p].reflection == "folded" else 1.0 for p in names])
    light = replace(light, coat_scale=scale)           # indexed by ``names``, not fitted parts
    vals = np.zeros((len(pm), 3))
    vals[keep] = predict(s, light, albedo)
    out[sel] = linear_to_srgb8(vals)
    return out


def _rl(v) -> list:
    a = np.asarray(v, np.float64)
    return np.round(a, 6).tolist()
