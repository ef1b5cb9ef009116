"""The artifacts that flow from stage to stage.

Conventions (written once, used everywhere; see docs/CONVENTIONS.md):

* Canonical vehicle frame: right-handed, +Y up, the vehicle's front toward +X, its right side
  toward +Z; bounding box centred in x and y (ground contact at y = -height / 2), centred in z
  on the left/right mirror plane when the model is symmetric (on the box otherwise), scaled so
  that the bounding-box diagonal is 1. ``Mesh.file_to_norm`` maps homogeneous file coordinates
  (after the scene graph is flattened) to it, rotation included; ``Mesh.orientation`` says how
  the rotation was found (``ucad_cl.orient``).
* Camera: OpenCV style, x right, y down, z forward. Pixel (i, j) = (row, column) has its centre
  at image coordinates (j + 0.5, i + 0.5). ``K`` is the 3x3 intrinsic matrix, ``w2c`` the 4x4
  world(canonical)-to-camera matrix of each view.
* Azimuth 0 looks from +X toward the origin (the front view); azimuth grows counter-clockwise
  seen from +Y (from +X toward -Z). Elevation > 0 puts the camera above the model. Degrees.
* View order: elevation-major, ``view = elevation_index * n_azimuths + azimuth_index``.
* Ids: material id = material index + 1, 0 = background; triangle id = face index,
  0xFFFFFFFF = background. Depth is linear camera-space z (same unit as the canonical frame),
  +inf for background.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any

import numpy as np

# the camera / view-stack types and the part vocabulary live in ucad_catalog (numpy only), so
# the catalogue reader installs without OpenCL; they are re-exported here for the pipeline
from ucad_catalog.parts import PART_NAMES
from ucad_catalog.views import (BACKGROUND_MAT, BACKGROUND_TRI, CameraRing, ViewSet,
                                nonzero_box)

__all__ = ["BACKGROUND_MAT", "BACKGROUND_TRI", "PART_NAMES", "VEHICLE_KINDS", "CameraRing",
           "EdgeSet", "Features", "IngestReport", "Material", "MaterialPart", "Mesh", "PartMasks",
           "PartTable", "Verdict", "ViewSet", "nonzero_box", "pack_masks"]

#: the vehicle kinds the generator (``ucad_cl.synth``) builds; here so that the CLI lists them
#: without importing the generator (and trimesh)
VEHICLE_KINDS: tuple[str, ...] = ("sedan", "suv", "van", "truck", "bus", "hatchback", "pickup")



def node_stem(name) -> str:
    """A node name without the random ``_xxxxxx`` hex suffix trimesh gives repeated names
    (``4_77af3b`` -> ``4``): a new suffix on every load, so ``Mesh.node_names`` hold stems."""
    return re.sub(r"_[0-9a-f]{6}$", "", str(name))

@dataclass
class Material:
    """One material as the file describes it. Colours are linear RGBA / RGB in [0, 1]."""

    name: str
    base_color: tuple[float, float, float, float] = (0.8, 0.8, 0.8, 1.0)
    alpha_mode: str = "OPAQUE"          # OPAQUE | MASK | BLEND (glTF); OBJ: BLEND when d < 1
    metallic: float = 0.0
    roughness: float = 1.0
    emissive: tuple[float, float, float] = (0.0, 0.0, 0.0)
    transmission: float = 0.0
    has_texture: bool = False


@dataclass
class IngestReport:
    """What ingest changed: counts of removed elements and notes (e.g. 'draco decoded')."""

    faces_in: int = 0
    faces_out: int = 0
    duplicate_faces: int = 0
    zero_area_faces: int = 0
    unreferenced_vertices: int = 0
    notes: list[str] = field(default_factory=list)


@dataclass
class Orientation:
    """How a mesh was turned into the canonical vehicle frame (``ucad_cl.orient``).

    rotation: (3, 3) float64, file-frame directions -> canonical directions (its rows are the
    file-frame front, up and right directions); it is part of ``Mesh.file_to_norm``.
    up_confidence / front_confidence: in [0, 1] (1 for an override, 0 for ``file``).
    source: ``auto`` (estimated), ``file`` (the file's frame trusted, no rotation) or
    ``override`` (given by the user). cues: ``{"up.NAME" | "front.NAME": score}``, each score
    in [-1, 1], positive = the cue agrees with the decision. flags: from ``orient.FLAGS``
    (``multiple_vehicles``, ``no_wheels``, ``front_ambiguous``, ``up_ambiguous``,
    ``asymmetric``). symmetry: share of surface samples whose mirror image across the x-y
    plane lands on the surface, in [0, 1]. mirror_z: z of that mirror plane in the canonical
    frame (0 when the model was centred on it).
    """

    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    up_confidence: float = 0.0
    front_confidence: float = 0.0
    source: str = "file"
    cues: dict = field(default_factory=dict)
    flags: tuple = ()
    symmetry: float = 0.0
    mirror_z: float = 0.0

    UNCERTAIN_BELOW = 0.5

    @property
    def uncertain(self) -> bool:
        """An estimated orientation with a confidence under UNCERTAIN_BELOW."""
        return self.source == "auto" and min(self.up_confidence,
                                             self.front_confidence) < self.UNCERTAIN_BELOW

    def as_dict(self) -> dict:
        """Plain JSON-ready record (what the catalogue stores)."""
        return {"rotation": np.asarray(self.rotation, np.float64).tolist(),
                "up_confidence": float(self.up_confidence),
                "front_confidence": float(self.front_confidence), "source": self.source,
                "cues": {k: float(v) for k, v in sorted(self.cues.items())},
                "flags": list(self.flags), "symmetry": float(self.symmetry),
                "mirror_z": float(self.mirror_z), "uncertain": bool(self.uncertain)}


@dataclass
class Mesh:
    """A triangle mesh in the canonical frame with one material index per face.

    vertices: (N, 3) float64, canonical frame. faces: (F, 3) uint32. face_material: (F,) uint16
    index into ``materials``. face_node: (F,) int32 index into ``node_names`` (-1 unknown);
    node names are ``node_stem``s (trimesh's random suffix of repeated names dropped).
    file_to_norm: (4, 4) float64 homogeneous transform, file frame -> canonical frame.
    orientation: how the canonical vehicle frame was found (None: not oriented yet).
    """

    path: str
    sha256: str
    vertices: np.ndarray
    faces: np.ndarray
    face_material: np.ndarray
    materials: list[Material]
    file_to_norm: np.ndarray = field(default_factory=lambda: np.eye(4))
    face_node: np.ndarray | None = None
    node_names: list[str] = field(default_factory=list)
    report: IngestReport = field(default_factory=IngestReport)
    orientation: Orientation | None = None

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])


@dataclass
class Verdict:
    """Filter decision. ``reason`` is a short machine-readable code, ``detail`` a sentence."""

    accepted: bool
    reason: str = ""
    detail: str = ""


@dataclass
class EdgeSet:
    """Canny edges of material-index maps: (V, H, W) uint8, 255 = edge, 0 = none."""

    edges: np.ndarray


def pack_masks(masks: np.ndarray) -> np.ndarray:
    """(V, P, H, W) bool masks, P <= 16 -> (V, H, W) uint16, bit p set = pixel in mask p."""
    m = np.asarray(masks)
    if m.ndim != 4 or m.dtype != np.bool_ or m.shape[1] > PartMasks.MAX_PARTS:
        raise ValueError(f"masks must be (V, P <= {PartMasks.MAX_PARTS}, H, W) bool to pack, "
                         f"got {m.dtype} {m.shape}")
    # a sum of distinct powers of two is their bitwise or
    return np.einsum("vphw,p->vhw", m.view(np.uint8),
                     (1 << np.arange(m.shape[1])).astype(np.uint16), dtype=np.uint16)


class PartMasks:
    """Segmenter output: for every view, a pixel mask and a confidence per part of ``parts``.

    The masks have two interchangeable forms; a PartMasks is built from either one
    (``PartMasks(parts, masks, confidence)`` or ``PartMasks.from_bits(parts, bits, confidence)``)
    and the other is derived on first access and cached (assigning one drops the other):

    * ``masks``: (V, P, H, W) bool, ``masks[v, p]`` = the pixels of view v inside part p's mask.
    * ``bits``: (V, H, W) uint16 packed masks, bit p set = the pixel is inside part p's mask
      (P <= 16; the form the classifier's histogram kernel reads, 1/8 of the bytes).

    ``parts``: P names from ``PART_NAMES``; ``confidence``: (V, P) float32 in [0, 1]. A part with
    no mask in a view has an all-False mask and confidence 0. ``source`` names the segmenter.
    ``labels``: the per-material answer of a segmenter that labels materials (the learned
    labeller's ``MaterialLabels``: probabilities, the layer behind glass, shared-material
    splits), which ``classify_parts`` reports beside its decisions; None for image segmenters.
    """

    MAX_PARTS = 16                      # bits of the packed form
    _masks: Any                         # (V, P, H, W) bool ndarray, or None until unpacked
    _bits: Any                          # (V, H, W) uint16 ndarray, or None until packed

    def __init__(self, parts: list[str], masks: np.ndarray, confidence: np.ndarray,
                 source: str = ""):
        self.parts = parts
        self.confidence = confidence
        self.source = source
        self.masks = masks
        self.labels = None

    @classmethod
    def from_bits(cls, parts: list[str], bits: np.ndarray, confidence: np.ndarray,
                  source: str = "") -> "PartMasks":
        """A PartMasks from packed (V, H, W) uint16 masks (bit p = part ``parts[p]``)."""
        self = cls.__new__(cls)
        self.parts = parts
        self.confidence = confidence
        self.source = source
        self.bits = bits
        self.labels = None
        return self

    @property
    def masks(self) -> np.ndarray:
        if self._masks is None:
            b = self._bits
            out = np.empty((b.shape[0], len(self.parts)) + b.shape[1:], bool)
            for p in range(len(self.parts)):
                np.not_equal(b & np.uint16(1 << p), 0, out=out[:, p])
            self._masks = out
        return self._masks

    @masks.setter
    def masks(self, value: np.ndarray) -> None:
        self._masks, self._bits = value, None

    @property
    def bits(self) -> np.ndarray:
        if self._bits is None:
            self._bits = pack_masks(self._masks)
        return self._bits

    @bits.setter
    def bits(self, value: np.ndarray) -> None:
        self._bits, self._masks = value, None

    @property
    def packed(self) -> bool:
        """True while only the packed form exists (``masks`` not given, not yet unpacked)."""
        return self._masks is None

    @property
    def shape(self) -> tuple[int, ...]:
        """(V, P, H, W) of the masks, without building them (P from the masks when given)."""
        if self._masks is not None:
            return tuple(np.shape(self._masks))
        b = np.shape(self._bits)
        return b[:1] + (len(self.parts),) + b[1:]

    def nonempty(self) -> np.ndarray:
        """(V, P) bool: part p has at least one pixel in view v."""
        if self._masks is not None:
            return np.asarray(np.asarray(self._masks).any(axis=(2, 3)))
        seen = np.bitwise_or.reduce(self._bits, axis=(1, 2))                 # (V,) uint16
        return (seen[:, None] >> np.arange(len(self.parts), dtype=np.uint16)) & 1 == 1

    def __repr__(self) -> str:
        form = "masks" if self._masks is not None else "bits"
        return (f"PartMasks(parts={self.parts}, shape={self.shape}, from {form}, "
                f"source={self.source!r})")


@dataclass
class MaterialPart:
    """Decision for one material: part label with the evidence behind it."""

    material: int                 # material index (id - 1)
    name: str
    part: str                     # one of PART_NAMES, or 'unseen'
    score: float                  # |material ∩ part| / |material| in the deciding view
    iou: float                    # plain IoU in the deciding view
    view: int                     # deciding view (-1 when none)
    decision: str                 # 'best-view' | 'vote' | 'merged-body' | 'symmetric' | 'unseen' |
    #                               'override' (a curator's, ucad_cl.curation) | ...
    pixels: int = 0               # visible pixels over all views
    prob: float | None = None     # the labeller's probability of ``part`` (None: no labeller)
    split: list | None = None     # shared material: parts per group of connected components
    was: dict | None = None       # a curator's override: what was decided before (ucad_cl.curation)


@dataclass
class PartTable:
    rows: list[MaterialPart]

    def labels(self) -> dict[str, str]:
        return {r.name: r.part for r in self.rows}


@dataclass
class Features:
    """Per-view pose features: (V, D) float32, L2-normalised rows unless stated."""

    feats: np.ndarray
    kind: str = "hog"
