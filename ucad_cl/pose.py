"""Pose search: which camera around a mesh best explains a reference photo of it.

``estimate_pose(image, mesh, box=... | mask=...)`` follows UrbanCAD (pick the rendering whose
features are nearest to the photo's), made robust to what a real photo does to a car:

1. **The object, not the box** (``ucad_cl.foreground``): with a mask, the photo's background is
   replaced by the renders' flat grey; with a box, GrabCut estimates the object inside it first
   (``PoseMethod.refine_mask`` reruns it seeded by the best render's silhouette and searches
   again: measured no gain at twice the time, off). The photo is then turned
   virtually so the object sits on the optical axis (``centre_on_axis``, assuming a field of view
   of ``fov_prior``), as the renders see the vehicle.
2. **Appearance-invariant cues** (``ucad_cl.cues``): HOG of the object, silhouette IoU, edge
   chamfer against the render's geometric and material edges, and how well the render's material
   regions explain the photo's colours, combined with the weights of ``PoseMethod`` (chosen with
   ``bench/pose.py --split tuning`` on the tuning split only).
3. **Coarse to fine**: every view of a coarse ring (``pose_ring``: rendered once, reusable for
   many photos, e.g. from a catalogue) is scored; the ``seeds`` best distinct views and the best
   view's twins are refined on a grid rendered on demand (+-0.6 coarse step in azimuth, +-1/4
   of the elevation spacing, at the camera distance estimated from the object's size); the best
   and its best twin then try the distance (which sets the perspective) x0.8 and x1.25 and two
   finer grids (+-0.15 step and +-1/8 spacing, then +-0.075 and +-1/16). A hypothesis that the
   first grid leaves at its upper reach above the highest ring climbs on (``PoseMethod.climb``):
   a photo from higher up than the ring is posed at its own elevation.
4. **Front/back and left/right as an explicit decision**: the best candidate is compared with its
   twins, refined alike: ``mirror`` (azimuth -a: the other side), ``opposite`` (a + 180) and
   ``front-back`` (180 - a: same side, the other end; the outline is the same, only the lamps,
   glazing and cab tell them apart). The best twin is reported second (``flipped=True``, its
   ``twin`` kind and ``gap`` = its score minus the best score); ``PoseEstimate.ambiguous`` says
   when the gap is below ``AMBIGUOUS_GAP``.
5. **A vehicle cut by the photo's edge** (``past_edge=True``, what ``ucad-index pose`` does):
   posed on the photo grown past that edge (``foreground.past_the_edge``) when that matches the
   coarse ring better (``past_edge_choice``), the cues told which pixels the photo shows.

Conventions (``docs/CONVENTIONS.md``): azimuth/elevation in degrees in the mesh's canonical frame
(azimuth 0 looks from +X, the vehicle's front, and grows counter-clockwise seen from +Y), reported
in [0, 360); distance in canonical units (bbox diagonal 1). Each candidate carries a full camera
for the reference image: ``K`` (3x3: the focal length that makes the render at that distance as
large as the object in the photo; principal point at the image centre) and ``w2c`` (4x4
canonical -> OpenCV camera: the camera at (azimuth, elevation, distance) looking at the
vehicle's centre, turned so that the centre projects onto the centre of the object's box).

* score: the weighted sum of cue distances (``ucad_cl.cues.combine``), lower is better; computed
  in float64.
* Ties: equal scores go to the view rendered first (coarse views by index, then each refinement
  grid in elevation-major order); every stage keeps its seed on ties.

The catalogue-wide variant, one query feature against the stored features of many (mesh, view)
rows, is ``search.search_catalog``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from .artifacts import CameraRing, Mesh
from .cameras import look_at_w2c, make_ring, single_camera
from .cues import Cues, combine, cue_distances, query_cues, query_hog_distance, view_cues
from .features import FeatureExtractor, HogExtractor, box_mask
from .foreground import (RENDER_BACKGROUND, GrownPhoto, ObjectMask, PhotoWindow, axis_turn,
                         centre_on_axis, check_image, composite, mask_box, object_mask,
                         past_the_edge, photo_intrinsics, refine_with_silhouette)
from .render import render_views
from .runtime import Runtime
from .search import CatalogMatch, search_catalog
from .shade import face_normals, shade_views

FOV_PRIOR = 45.0            # assumed field of view of a photo over its narrower side, degrees
FOV_RANGE = (5.0, 120.0)    # a field of view given instead (estimate_pose / fit_photo fov=)
#: score gap below which the best twin is called a close call; tuning split, 360 references per
#: mode: with a box it flags 10 % of the answers, half of the wrong ones (47 % of the flagged are
#: wrong, 10 % of all); with a mask 1.4 % of the answers, none wrong
AMBIGUOUS_GAP = 0.03
TWINS = ("mirror", "opposite", "front-back")
FLIP_MIN_DEG = 135.0        # legacy flip rule (``twins=False``): best candidate this far away
MIN_DISTANCE = 0.55         # renders keep the camera outside the bounding sphere (radius 0.5)
#: elevation climb (``PoseMethod.climb``): a pose at the upper edge of what the coarse ring's first
#: grid reaches steps up by CLIMB_STEP x the elevation spacing (at the first grid's azimuth
#: offsets) while its score falls, never to CLIMB_LIMIT deg or above
CLIMB_STEP = 0.5
CLIMB_LIMIT = 85.0


@dataclass(frozen=True)
class PoseMethod:
    """How ``estimate_pose`` searches. ``ROBUST`` (the default) is this module's method,
    ``LEGACY`` the one before it (``bench/pose.py`` compares them).

    weights / box_weights: cue weights (``ucad_cl.cues``) for a given mask / an object estimated
    inside a box. isolate: replace the photo's background by the renders' (False: the crop of
    the box, background included). fov_prior: centre the object on the optical axis assuming
    this field of view (None: no centring, renders at the ring's distance). twins: decide
    between the best candidate and its twins (False: report the best candidate >=
    FLIP_MIN_DEG away). seeds: coarse views refined besides the twins. stages: refinement grids,
    each (azimuth offsets x the coarse step, elevation offsets x the coarse elevation spacing);
    the first for every hypothesis, the others for the best and its runner-up.
    distance_factors: camera distances tried around the estimate (perspective) last.
    refine_mask: with a box, rerun GrabCut seeded by the best render's silhouette and search
    again (measured: no gain at twice the time, see bench/pose.py; off). box_frame: with a box,
    crop, centre and size the photo by the box rather than by GrabCut's mask (GrabCut then only
    decides which pixels keep their colours) when a side of the mask's box is more than
    ``box_frame`` x the box's size away from the box's side (0: always; None: never).
    climb: every hypothesis that the first grid leaves at the upper edge of its reach above the
    ring's highest elevation walks on upwards while its score falls (``CLIMB_STEP``), then gets
    the first grid again: a photo taken from higher than the ring (a catalogue stores rings at
    5 and 15 deg) is posed at its own elevation, not at ~19 deg (docs/POSE.md).
    """

    weights: tuple = (("hog", 1.0), ("silhouette", 1.0), ("chamfer", 1.0), ("region", 1.0))
    box_weights: tuple = (("hog", 1.0), ("chamfer", 1.0))
    isolate: bool = True
    fov_prior: float | None = FOV_PRIOR
    twins: bool = True
    seeds: int = 2
    stages: tuple = (((-0.6, -0.3, 0.0, 0.3, 0.6), (-0.25, 0.0, 0.25)),
                     ((-0.15, 0.0, 0.15), (-0.125, 0.0, 0.125)),
                     ((-0.075, 0.0, 0.075), (-0.0625, 0.0, 0.0625)))
    distance_factors: tuple = (0.8, 1.25)
    refine_mask: bool = False
    box_frame: float | None = 0.08
    climb: bool = True


ROBUST = PoseMethod()
#: before issue 12: HOG of the box crop (background included); the best coarse view and the best
#: one >= FLIP_MIN_DEG away refined on one grid of +-1 step at 2 deg (10 deg steps) and half the
#: elevation spacing, at the ring's distance (what the old search did with top=2)
LEGACY = PoseMethod(weights=(("hog", 1.0),), box_weights=(("hog", 1.0),), isolate=False,
                    fov_prior=None, twins=False, seeds=1,
                    stages=((tuple(np.round(np.arange(-1.0, 1.0001, 0.2), 6)), (-0.5, 0.0, 0.5)),),
                    distance_factors=(), climb=False)


@dataclass
class PoseCandidate:
    """One pose hypothesis. ``view``: index of the coarse-ring view it grew from."""

    azimuth: float
    elevation: float
    distance: float
    score: float
    view: int
    refined: bool = False       # found on a fine grid around the seed view
    flipped: bool = False       # the best twin of the best candidate (see ``twin``)
    twin: str = ""              # 'mirror' | 'opposite' | 'front-back' relation to the best
    gap: float = 0.0            # score minus the best candidate's score
    cues: dict = field(default_factory=dict)     # cue -> distance (the cues the score weighs)
    K: np.ndarray | None = field(default=None, repr=False, compare=False)
    w2c: np.ndarray | None = field(default=None, repr=False, compare=False)


@dataclass
class PoseEstimate:
    """What ``estimate_pose`` found: ``candidates`` best first (the best twin second), the
    object it matched (``object``: mask source and the share of the box kept), ``ambiguous``
    when the best twin is within AMBIGUOUS_GAP of the best, ``past_edge`` (``estimate_pose``'s)."""

    candidates: list[PoseCandidate]
    object: ObjectMask
    ambiguous: bool = False
    past_edge: tuple[int, int, int, int] = (0, 0, 0, 0)   # px past the left/top/right/bottom

    @property
    def best(self) -> PoseCandidate:
        return self.candidates[0]

    @property
    def runner_up(self) -> PoseCandidate | None:
        """The best twin of the best candidate, when one was reported."""
        return next((c for c in self.candidates if c.flipped), None)


@dataclass
class PoseRing:
    """A coarse ring of one mesh, described once for many queries.

    feats: (V, D) float32 descriptor rows, sides: (V,) longer side of each view's object box in
    pixels; cues: every cue map (``ucad_cl.cues``), None when only features are known (e.g.
    from a catalogue): the coarse stage then ranks by the HOG cue alone.
    """

    ring: CameraRing
    feats: np.ndarray
    sides: np.ndarray
    extractor: FeatureExtractor
    azimuth_step: float
    cues: Cues | None = None


def estimate_pose(image: np.ndarray, mesh: Mesh, *, box: Sequence[float] | None = None,
                  mask: np.ndarray | None = None, extractor: FeatureExtractor | None = None,
                  azimuth_step: float = 10.0, elevations: Sequence[float] = (0.0, 15.0, 30.0),
                  fov_deg: float = 40.0, size: int = 128, top: int = 5, refine: bool = True,
                  coarse: PoseRing | None = None, method: PoseMethod = ROBUST,
                  runtime: Runtime | None = None,
                  intrinsics: np.ndarray | None = None,
                  fov: float | None = None, valid: np.ndarray | None = None,
                  past_edge: bool = False, grown: GrownPhoto | None = None) -> PoseEstimate:
    """Best ``top`` poses of ``mesh`` for the object in ``image`` ((H, W, 3) uint8 RGB), rendered
    on ``runtime`` (default ``get_runtime()``).

    The object is ``box`` (x0, y0, x1, y1 pixels, x1/y1 exclusive) or ``mask`` ((H, W) bool).
    The coarse ring has ``azimuth_step`` and ``elevations`` (or is ``coarse``, from
    ``pose_ring``; its parameters then win). ``refine=False``: coarse views only.
    ``intrinsics``: the photo camera assumed (3x3: focal length and principal point in
    ``image``'s pixels) when ``image`` is a window cut from a larger photo and scaled (the fit
    does so); default: the principal point at the image centre and the focal length of
    ``method.fov_prior`` over the narrower side. Without it a large photo is searched in a
    window around its object (``foreground.PhotoWindow``), and the candidates' ``K`` and the
    object come back in the photo's pixels. ``fov``: the photo's field of view over its
    narrower side in degrees (``FOV_RANGE``), when known (instead of ``method.fov_prior``; ignored with
    ``intrinsics``). ``valid``: (H, W) bool, the pixels the photo shows (None: all; e.g. a
    photo grown past its edge, ``past_the_edge``): the cues compare nothing else
    (``cues.query_cues``). ``past_edge``: an object that touches the photo's edge is posed on
    the photo grown past that edge when ``past_edge_choice`` finds it nearer to the coarse ring
    so (the search framed by the grown object, its cues told which pixels the photo shows, the
    photo's camera moved with it; ``PoseEstimate.past_edge`` says by how much); not with
    ``valid``. ``grown``: a ``past_the_edge`` hypothesis of this photo (pixels, not a
    window's) that the caller chose (the fit's retrieval), searched the same way; the object is
    then its own (``grown.obj``, or GrabCut in its box when the photo's object came from a
    box). ValueError naming the problem for a bad image, an empty or tiny mask or box, a
    ``valid`` of another shape, both ``valid`` and ``grown``.
    """
    check_fov(fov)
    if valid is not None and np.shape(valid) != np.shape(image)[:2]:
        raise ValueError(f"valid has shape {np.shape(valid)}, the image {np.shape(image)[:2]}")
    if valid is not None and grown is not None:
        raise ValueError("give valid or grown, not both: a grown photo says what it shows")
    prior = fov or method.fov_prior or FOV_PRIOR
    window = (PhotoWindow.around(np.shape(image)[:2], box, mask)
              if intrinsics is None and grown is None else None)
    if window is not None:
        full_shape = np.shape(image)[:2]
        image, box, mask = window.cut(check_image(image), box, mask)
        if valid is not None:
            valid = window.cut_mask(valid, image.shape[:2])
        intrinsics = window.intrinsics(full_shape, prior)
    elif intrinsics is None and fov is not None:
        intrinsics = photo_intrinsics(np.shape(image)[:2], fov)
    if grown is None:                       # (a grown photo brings its own object)
        obj = object_mask(image, box=box, mask=mask, grabcut=method.isolate)
    if top < 1:
        raise ValueError(f"top={top} must be >= 1")
    image = np.asarray(image)
    extractor = extractor or HogExtractor(runtime=runtime)
    if coarse is None:
        coarse = pose_ring(mesh, extractor, azimuth_step=azimuth_step, runtime=runtime,
                           elevations=elevations, fov_deg=fov_deg, size=size)
    if grown is None and past_edge and valid is None and method.isolate:
        grown = past_edge_choice(image, past_the_edge(image, obj), coarse, extractor)
    if grown is not None:                   # the search runs on the grown photo
        base = (intrinsics if intrinsics is not None
                else photo_intrinsics(image.shape[:2], method.fov_prior or FOV_PRIOR))
        intrinsics = np.array(base, np.float64)
        intrinsics[:2, 2] += grown.at
        valid, image = grown.shown(), grown.image
        obj = (grown.obj if mask is not None
               else object_mask(image, box=grown.obj.box, grabcut=method.isolate))
    if not method.isolate:                  # the box, background included (before issue 12)
        obj = ObjectMask(mask=box_mask(obj.mask.shape, obj.box), source="box", box=obj.box,
                         kept=1.0)
    weights = dict(method.weights if obj.source == "mask" else method.box_weights)
    search = _Search(mesh, coarse, weights, method, refine, runtime, intrinsics)
    frame = None
    if method.box_frame is not None and obj.source != "mask":
        b, m = np.array(obj.box, float), np.array(mask_box(obj.mask), float)
        size = np.array([b[2] - b[0], b[3] - b[1]] * 2)
        if np.any(np.abs(m - b) > method.box_frame * size):
            frame = box_mask(obj.mask.shape, obj.box)
    search.set_photo(image, obj.mask, frame, valid)
    found = search.run()
    if method.refine_mask and refine and obj.source == "grabcut":
        fg = refine_with_silhouette(image, search.silhouette_in_photo(found[0]))
        if fg.sum() >= 0.5 * obj.mask.sum():
            x0, y0, x1, y1 = obj.box
            obj = ObjectMask(mask=fg, source="grabcut+render", box=obj.box,
                             kept=float(fg[y0:y1, x0:x1].mean()))
            search.set_photo(image, obj.mask, frame, valid)
            found = search.run()
    cands = search.report(found, top)
    moved = (0, 0, 0, 0)
    if grown is not None:                   # back in the photo's (window's) pixels
        (x, y), (h, w) = grown.at, grown.seen.mask.shape
        for c in cands:                     # the principal point moved back
            c.K = None if c.K is None else c.K - np.array([[0, 0, x], [0, 0, y], [0, 0, 0]])
        inside = obj.mask[y:y + h, x:x + w]
        obj = (ObjectMask(mask=inside, source=obj.source, box=grown.seen.box, kept=obj.kept)
               if inside.any() else grown.seen)
        moved = grown.margins()
    if window is not None:                  # back in the photo's pixels
        for c in cands:
            c.K = window.photo_K(c.K) if c.K is not None else None
        obj = window.photo_object(obj, full_shape)
        moved = window.photo_lengths(moved)
    runner = next((c for c in cands if c.flipped), None)
    ambiguous = bool(method.twins) and runner is not None and runner.gap < AMBIGUOUS_GAP
    return PoseEstimate(candidates=cands, object=obj, ambiguous=ambiguous, past_edge=moved)


def past_edge_choice(image: np.ndarray, cut: list[GrownPhoto], ring: PoseRing,
                     extractor: FeatureExtractor) -> GrownPhoto | None:
    """Of the photo grown past its edge (``cut``: ``foreground.past_the_edge``'s hypotheses
    for its object), the one whose object's descriptor (``extractor``, as ``ring``'s) is
    nearest to one of ``ring``'s views, when nearer than the object as the photo shows it
    (ties: the photo, then ``PAST_EDGE`` order); None when ``cut`` is empty or the photo as it
    is is nearest. A vehicle cut by the photo's edge described as it shows compares with views
    of a shorter vehicle; grown, with views of the whole one (docs/FIT.md)."""
    if not cut:
        return None
    best = nearest_ring_view(image, cut[0].seen.mask, ring, extractor).score
    choice = None
    for hyp in cut:
        d = nearest_ring_view(hyp.image, hyp.obj.mask, ring, extractor).score
        if d < best:
            best, choice = d, hyp
    return choice


def nearest_ring_view(image: np.ndarray, mask: np.ndarray, ring: PoseRing,
                      extractor: FeatureExtractor) -> CatalogMatch:
    """The view of ``ring`` nearest to the object ``mask`` of ``image`` by its descriptor
    (``extractor``, as ``ring``'s; ``search_catalog``'s distance and ties)."""
    q, _ = query_features(image, extractor, mask=mask)
    n = len(ring.feats)
    return search_catalog(q, ring.feats, np.zeros(n, int), np.arange(n), ring.ring.azimuth,
                          ring.ring.elevation, top=1)[0]


def check_fov(fov: float | None) -> None:
    """ValueError unless ``fov`` is None or inside ``FOV_RANGE`` (NaN is not)."""
    if fov is not None and not FOV_RANGE[0] <= fov <= FOV_RANGE[1]:
        raise ValueError(f"field of view {fov} deg outside {FOV_RANGE[0]:g}-{FOV_RANGE[1]:g} deg "
                         "(over the photo's narrower side)")


def pose_ring(mesh: Mesh, extractor: FeatureExtractor, *, azimuth_step: float = 10.0,
              elevations: Sequence[float] = (0.0, 15.0, 30.0), fov_deg: float = 40.0,
              size: int = 128, runtime: Runtime | None = None) -> PoseRing:
    """Render, shade and describe the coarse ring of ``mesh`` once (reuse for many queries)."""
    ring = make_ring(azimuth_step, elevations, fov_deg=fov_deg, size=size)
    cues = render_cues(mesh, ring, extractor, runtime=runtime)
    return PoseRing(ring=ring, feats=cues.hog, sides=cues.sides * min(ring.width, ring.height),
                    extractor=extractor, azimuth_step=float(azimuth_step), cues=cues)


def render_cues(mesh: Mesh, ring: CameraRing, extractor: FeatureExtractor,
                normals: np.ndarray | None = None, runtime: Runtime | None = None) -> Cues:
    """Cues (``ucad_cl.cues``) of shaded renders of every view of ``ring`` (``normals``: the
    mesh's ``shade.face_normals`` when the caller has them)."""
    views = render_views(mesh, ring, runtime=runtime)
    empty = np.flatnonzero(~np.isfinite(views.depth).any(axis=(1, 2)))
    if empty.size:
        raise ValueError(f"mesh {mesh.path!r}: nothing visible in view(s) {empty.tolist()}")
    if normals is None:
        normals = face_normals(mesh)
    images = shade_views(mesh, views, background=RENDER_BACKGROUND, normals=normals,
                         runtime=runtime)
    return view_cues(mesh, views, images, extractor, normals=normals)


def query_features(image: np.ndarray, extractor: FeatureExtractor | None = None, *, box=None,
                   mask=None, isolate: bool = True,
                   runtime: Runtime | None = None) -> tuple[np.ndarray, ObjectMask]:
    """(D,) descriptor of the object in a photo, as the renders' features are computed (the
    background replaced unless ``isolate`` is False), and the object it used."""
    obj = object_mask(image, box=box, mask=mask, grabcut=isolate)
    m = obj.mask if isolate else box_mask(obj.mask.shape, obj.box)
    img = composite(image, m) if isolate else np.asarray(image)
    return (extractor or HogExtractor(runtime=runtime)).extract(img[None], m[None]).feats[0], obj


def twin_azimuth(azimuth: float, kind: str) -> float:
    """The azimuth of a twin view in [0, 360): 'mirror' -a, 'opposite' a + 180, 'front-back'
    180 - a (for a left/right symmetric vehicle the front-back twin has the same outline)."""
    a = float(azimuth)
    if kind == "mirror":
        return (-a) % 360.0
    if kind == "opposite":
        return (a + 180.0) % 360.0
    if kind == "front-back":
        return (180.0 - a) % 360.0
    raise ValueError(f"unknown twin kind {kind!r}; expected one of {TWINS}")


def az_diff(a: float, b: float) -> float:
    """Absolute azimuth difference in degrees, in [0, 180]."""
    d = abs(a - b) % 360.0
    return min(d, 360.0 - d)



# ----------------------------------------------------------------------------- the search

@dataclass
class _Pose:
    """A scored pose: rendered at (azimuth, elevation, distance); ``side`` = the object's box
    side in that render over the render's focal length (its angular size), ``offset`` = where
    the box centre is, (x, y) from the principal point over the focal length."""

    azimuth: float
    elevation: float
    distance: float
    score: float
    view: int
    side: float
    offset: tuple
    cues: dict
    refined: bool = False


class _Search:
    """One photo against one mesh: scoring, coarse ranking, refinement, twins."""

    def __init__(self, mesh, coarse: PoseRing, weights: dict, method: PoseMethod, refine: bool,
                 runtime: Runtime | None = None, intrinsics: np.ndarray | None = None):
        self.mesh, self.coarse, self.weights, self.runtime = mesh, coarse, weights, runtime
        self.intrinsics = None if intrinsics is None else np.asarray(intrinsics, np.float64)
        self.method, self.refine = method, refine
        self.twins = method.twins
        ring = coarse.ring
        self.f_render = float(ring.K[0, 0])
        self.size = (ring.width, ring.height)
        self.el_step = _elevation_step(ring.elevation)
        self.step = coarse.azimuth_step
        self.normals = face_normals(mesh)

    # -- the photo
    def set_photo(self, image, mask, frame=None, valid=None):
        """Prepare the photo: background replaced (method.isolate), object centred on the
        optical axis (method.fov_prior), its cues; ``frame`` (a bool mask, e.g. the box) sets
        the crop, the centre and the size instead of ``mask``; ``valid`` (a bool mask): the
        pixels the photo shows (``estimate_pose``)."""
        m = self.method
        self.image_shape = mask.shape
        self.camera0 = (self.intrinsics if self.intrinsics is not None else  # the photo's
                        photo_intrinsics(mask.shape, m.fov_prior or FOV_PRIOR))   # assumed K
        self.box_photo = mask_box(mask if frame is None else frame)
        img = composite(image, mask) if m.isolate else image
        if m.fov_prior is not None:
            c = centre_on_axis(img, mask, m.fov_prior, frame, K=self.camera0, valid=valid)
            img, mask, frame, valid = c.image, c.mask, c.frame, c.valid
        self.query = query_cues(img, mask, self.coarse.extractor, frame=frame, valid=valid)
        x0, y0, x1, y1 = mask_box(mask if frame is None else frame)
        self.photo_side = float(max(x1 - x0, y1 - y0))

    def scores(self, cues: Cues) -> tuple[np.ndarray, dict]:
        d = cue_distances(self.query, cues, [k for k, w in self.weights.items() if w])
        return combine(d, self.weights), d

    # -- stages
    def run(self) -> list[_Pose]:
        """Scored poses: [best, ..., the best's twins when searched]; see report()."""
        c = self.coarse
        if c.cues is not None:
            s, d = self.scores(c.cues)
        else:
            s = query_hog_distance(self.query, c.feats)
            d = {"hog": s}
        ring = c.ring
        sides = np.asarray(c.sides, np.float64) / self.f_render
        offsets = c.cues.offsets if c.cues is not None else np.zeros((ring.n_views, 2))
        coarse = [_Pose(float(ring.azimuth[v] % 360.0), float(ring.elevation[v]), ring.distance,
                        float(s[v]), v, float(sides[v]), tuple(offsets[v]),
                        {k: float(x[v]) for k, x in d.items()})
                  for v in range(ring.n_views)]
        self.ranked = sorted(coarse, key=lambda p: p.score)        # stable: lower view first
        best = self.ranked[0]
        if not self.refine:
            return self.ranked
        self.distance = (self._distance_estimate(best) if self.method.fov_prior is not None
                         else ring.distance)
        hyps = _distinct(self.ranked, self.method.seeds, self.step)
        if self.twins:
            hyps += [self._coarse_near(twin_azimuth(best.azimuth, k), best.elevation)
                     for k in TWINS]
        else:
            flip = next((p for p in self.ranked
                         if az_diff(p.azimuth, best.azimuth) >= FLIP_MIN_DEG), None)
            if flip is not None:
                hyps.append(flip)
        done = self._climb(self._stage(_unique(hyps), 0))
        best = min(done, key=lambda p: p.score)                      # first minimum on ties
        if self.twins:
            more = []
            for k in TWINS:
                az = twin_azimuth(best.azimuth, k)
                if az_diff(az, best.azimuth) >= 2 * self.step and \
                        not any(az_diff(az, p.azimuth) < self.step for p in done + more):
                    more.append(self._coarse_near(az, best.elevation))
            done += self._climb(self._stage(_unique(more), 0)) if more else []
        runner = self._best_twin(best, done)
        finals = self._finals([best] + ([runner] if runner is not None else []))
        finals.sort(key=lambda p: p.score)
        best = finals[0]
        runner = finals[1] if len(finals) > 1 else None      # twins are mutual: a twin's twin
        rest = [p for p in sorted(done, key=lambda p: p.score)
                if all(az_diff(p.azimuth, q.azimuth) >= self.step for q in finals)]
        return [best] + ([runner] if runner is not None else []) + rest + self.ranked

    def _stage(self, seeds: list[_Pose], k: int) -> list[_Pose]:
        """For each seed, the best pose of grid ``k`` of method.stages around it (the seed
        itself included when it was rendered at the grid's distance; it wins ties)."""
        az_off, el_off = self.method.stages[k]
        specs = []
        for s in seeds:
            azs = [s.azimuth + a * self.step for a in az_off]
            els = [e for e in (s.elevation + o * self.el_step for o in el_off) if abs(e) < 89.0]
            specs.append((azs, els, s.distance if s.refined else self.distance, s.view))
        out = []
        for seed, cands in zip(seeds, self._grids(specs)):
            keep = [seed] if seed.distance == cands[0].distance else []
            out.append(min(keep + cands, key=lambda p: p.score))
        return out

    def _climb(self, poses: list[_Pose]) -> list[_Pose]:
        """``method.climb``: each pose the first grid left at the upper edge of its reach from
        the ring's highest elevation steps up by CLIMB_STEP x the elevation spacing (the best of
        the first grid's azimuths kept) while its score falls (a tie stops it); the poses that
        moved then get the first grid around them. The poses step together (one render per
        step); the others are returned unchanged. Upwards only: a ring's lowest elevation is
        near the ground, and a camera below the ground is not a photo of a vehicle on it."""
        if not self.method.climb:
            return poses
        reach = max(abs(o) for o in self.method.stages[0][1]) * self.el_step
        top = float(np.max(self.coarse.ring.elevation)) + reach - 1e-6
        step = CLIMB_STEP * self.el_step
        out = list(poses)
        going = [i for i, p in enumerate(out) if p.elevation >= top]
        moved: set[int] = set()
        while going:
            going = [i for i in going if out[i].elevation + step < CLIMB_LIMIT]
            specs = [([out[i].azimuth + a * self.step for a in self.method.stages[0][0]],
                      [out[i].elevation + step],
                      out[i].distance if out[i].refined else self.distance, out[i].view)
                     for i in going]
            still = []
            for i, cands in zip(going, self._grids(specs) if specs else []):
                c = min(cands, key=lambda p: p.score)          # first minimum on ties
                if c.score < out[i].score:
                    out[i] = c
                    moved.add(i)
                    still.append(i)
            going = still
        order = sorted(moved)
        for i, p in zip(order, self._stage([out[i] for i in order], 0) if order else []):
            out[i] = p
        return out

    def _finals(self, poses: list[_Pose]) -> list[_Pose]:
        """The camera distances (perspective) around each pose, then the later stages."""
        for f in self.method.distance_factors:
            grids = self._grids([([p.azimuth], [p.elevation], p.distance * f, p.view)
                                 for p in poses])
            poses = [min([p] + c, key=lambda q: q.score) for p, c in zip(poses, grids)]
        for k in range(1, len(self.method.stages)):
            poses = self._stage(poses, k)
        return poses

    def _grids(self, specs) -> list[list[_Pose]]:
        """Scored poses of grids (azimuths, elevations, distance, seed view), elevation-major;
        grids at the same distance are rendered together (first-seen distance first)."""
        out: list = [None] * len(specs)
        groups: dict[float, list[int]] = {}
        for i, spec in enumerate(specs):
            groups.setdefault(max(float(spec[2]), MIN_DISTANCE), []).append(i)
        for distance, idx in groups.items():
            if distance == self.coarse.ring.distance:          # the ring's own field of view
                fov = float(np.degrees(2 * np.arctan(0.5 * min(self.size) / self.f_render)))
            else:                                              # the sphere fills it as in a ring
                fov = min(2.0 * np.degrees(np.arcsin(min(1.05 * 0.5 / distance, 1.0))), 120.0)
            rings = [make_ring(azimuths=specs[i][0], elevations=specs[i][1], fov_deg=fov,
                               size=self.size, distance=distance) for i in idx]
            r0 = rings[0]
            ring = CameraRing(K=r0.K, w2c=np.concatenate([r.w2c for r in rings]),
                              width=r0.width, height=r0.height,
                              azimuth=np.concatenate([r.azimuth for r in rings]),
                              elevation=np.concatenate([r.elevation for r in rings]),
                              distance=distance, near=r0.near)
            cues = render_cues(self.mesh, ring, self.coarse.extractor, self.normals,
                               runtime=self.runtime)
            s, d = self.scores(cues)
            side = cues.sides * min(self.size) / float(r0.K[0, 0])
            poses = [_Pose(float(ring.azimuth[v] % 360.0), float(ring.elevation[v]), distance,
                           float(s[v]), 0, float(side[v]), tuple(cues.offsets[v]),
                           {k: float(x[v]) for k, x in d.items()}, refined=True)
                     for v in range(ring.n_views)]
            start = 0
            for i, r in zip(idx, rings):
                out[i] = poses[start:start + r.n_views]
                for p in out[i]:
                    p.view = specs[i][3]
                start += r.n_views
        return out

    def _distance_estimate(self, best: _Pose) -> float:
        """Camera distance at which the best coarse view is as large (in angle) as the object
        in the photo under the assumed field of view."""
        angle = self.photo_side / float(self.camera0[0, 0])
        return max(self.coarse.ring.distance * best.side / angle, MIN_DISTANCE)

    def _coarse_near(self, azimuth: float, elevation: float) -> _Pose:
        return min(self.ranked, key=lambda p: (az_diff(p.azimuth, azimuth),
                                               abs(p.elevation - elevation), p.view))

    def _best_twin(self, best: _Pose, poses: list[_Pose]) -> _Pose | None:
        if not self.twins:
            return next((p for p in sorted(poses, key=lambda p: p.score)
                         if az_diff(p.azimuth, best.azimuth) >= FLIP_MIN_DEG), None)
        near = []
        for p in poses:
            if p is best or az_diff(p.azimuth, best.azimuth) < 2 * self.step:
                continue
            kind = self.twin_kind(best.azimuth, p.azimuth)
            if kind:
                near.append(p)
        return min(near, key=lambda p: p.score) if near else None

    def twin_kind(self, best_az: float, az: float) -> str:
        """The twin relation of ``az`` to ``best_az`` (within 1.5 coarse steps), or ''."""
        diffs = [(az_diff(az, twin_azimuth(best_az, k)), k) for k in TWINS]
        d, k = min(diffs)
        return k if d <= 1.5 * self.step else ""

    # -- output
    def report(self, found: list[_Pose], top: int) -> list[PoseCandidate]:
        best = found[0]
        out = [self._candidate(best, best)]
        runner = self._best_twin(best, found[1:]) if len(found) > 1 else None
        if top > 1 and runner is not None:
            c = self._candidate(runner, best)
            c.flipped = True
            c.twin = self.twin_kind(best.azimuth, runner.azimuth) if self.twins else "flip"
            out.append(c)
        for p in found[1:]:
            if len(out) >= top:
                break
            if all(az_diff(p.azimuth, o.azimuth) >= self.step for o in out):
                out.append(self._candidate(p, best))
        return out

    def _candidate(self, p: _Pose, best: _Pose) -> PoseCandidate:
        K, w2c = self.camera(p)
        return PoseCandidate(azimuth=p.azimuth, elevation=p.elevation, distance=p.distance,
                             score=p.score, view=p.view, refined=p.refined,
                             gap=p.score - best.score, cues=dict(p.cues), K=K, w2c=w2c)

    def camera(self, p: _Pose) -> tuple[np.ndarray, np.ndarray]:
        """(K, w2c) of the photo for pose ``p`` (see the module docstring)."""
        f = self.photo_side / max(p.side, 1e-9)
        K = np.array([[f, 0.0, self.camera0[0, 2]], [0.0, f, self.camera0[1, 2]],
                      [0.0, 0.0, 1.0]])
        x0, y0, x1, y1 = self.box_photo
        # the vehicle's centre projects where the render has it relative to the object's box
        R = axis_turn(K, ((x0 + x1) / 2.0 - f * p.offset[0], (y0 + y1) / 2.0 - f * p.offset[1]))
        turn = np.eye(4)
        turn[:3, :3] = R.T
        return K, turn @ look_at_w2c(p.azimuth, p.elevation, p.distance)

    def silhouette_in_photo(self, p: _Pose) -> np.ndarray | None:
        """(H, W) bool silhouette of pose ``p`` rendered with its photo camera."""
        K, w2c = self.camera(p)
        H, W = self.image_shape
        ring = single_camera(K, w2c, W, H, azimuth=p.azimuth, elevation=p.elevation,
                             distance=p.distance)
        return np.isfinite(render_views(self.mesh, ring, runtime=self.runtime).depth[0])


# ----------------------------------------------------------------------------- helpers

def _distinct(ranked: list[_Pose], n: int, min_sep: float) -> list[_Pose]:
    out: list[_Pose] = []
    for c in ranked:
        if len(out) >= n:
            break
        if all(az_diff(c.azimuth, o.azimuth) >= min_sep for o in out):
            out.append(c)
    return out


def _unique(poses: list[_Pose]) -> list[_Pose]:
    seen, out = set(), []
    for p in poses:
        if p.view not in seen:
            seen.add(p.view)
            out.append(p)
    return out


def _elevation_step(elevations: Sequence[float]) -> float:
    e = np.unique(np.asarray(elevations, np.float64))
    return float(np.min(np.diff(e))) if e.size > 1 else 10.0


def box_side(mask: np.ndarray) -> float:
    """Side of the mask's bounding box in pixels (the longer one); 0 for an empty mask."""
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return 0.0
    return float(max(rows[-1] - rows[0] + 1, cols[-1] - cols[0] + 1))
