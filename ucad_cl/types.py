"""The artifacts that flow from stage to stage.

Conventions (written once, used everywhere; see docs/CONVENTIONS.md):

* Canonical frame: right-handed, +Y up (glTF), model centred at its bounding-box centre and
  scaled so that the bounding-box diagonal is 1. ``Mesh.file_to_norm`` maps homogeneous file
  coordinates (after the scene graph is flattened) to it.
* Camera: OpenCV style, x right, y down, z forward. Pixel (i, j) = (row, column) has its centre
  at image coordinates (j + 0.5, i + 0.5). ``K`` is the 3x3 intrinsic matrix, ``w2c`` the 4x4
  world(canonical)-to-camera matrix of each view.
* Azimuth 0 looks from +X toward the origin; azimuth grows counter-clockwise seen from +Y
  (from +X toward -Z). Elevation > 0 puts the camera above the model. Degrees.
* View order: elevation-major, ``view = elevation_index * n_azimuths + azimuth_index``.
* Ids: material id = material index + 1, 0 = background; triangle id = face index,
  0xFFFFFFFF = background. Depth is linear camera-space z (same unit as the canonical frame),
  +inf for background.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

BACKGROUND_TRI = np.uint32(0xFFFFFFFF)
BACKGROUND_MAT = np.uint16(0)

PART_NAMES: tuple[str, ...] = (
    "body", "window", "wheel", "rim", "light", "chrome", "plate", "interior", "other",
)


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
class Mesh:
    """A triangle mesh in the canonical frame with one material index per face.

    vertices: (N, 3) float64, canonical frame. faces: (F, 3) uint32. face_material: (F,) uint16
    index into ``materials``. face_node: (F,) int32 index into ``node_names`` (-1 unknown).
    file_to_norm: (4, 4) float64 homogeneous transform, file frame -> canonical frame.
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
class CameraRing:
    """Cameras of one mesh. K: (3,3) float64; w2c: (V,4,4) float64; azimuth/elevation: (V,) deg."""

    K: np.ndarray
    w2c: np.ndarray
    width: int
    height: int
    azimuth: np.ndarray
    elevation: np.ndarray
    distance: float
    near: float

    @property
    def n_views(self) -> int:
        return int(self.w2c.shape[0])


@dataclass
class ViewSet:
    """Rendered maps, all (V, H, W): tri_id uint32, mat_id uint16, depth float32."""

    cameras: CameraRing
    tri_id: np.ndarray
    mat_id: np.ndarray
    depth: np.ndarray

    @property
    def n_views(self) -> int:
        return int(self.tri_id.shape[0])

    def select(self, idx) -> "ViewSet":
        """The views ``idx`` (indices or a slice), maps and cameras alike."""
        c = self.cameras
        ring = CameraRing(K=c.K, w2c=c.w2c[idx], width=c.width, height=c.height,
                          azimuth=c.azimuth[idx], elevation=c.elevation[idx],
                          distance=c.distance, near=c.near)
        return ViewSet(cameras=ring, tri_id=self.tri_id[idx], mat_id=self.mat_id[idx],
                       depth=self.depth[idx])


@dataclass
class EdgeSet:
    """Canny edges of material-index maps: (V, H, W) uint8, 255 = edge, 0 = none."""

    edges: np.ndarray


@dataclass
class PartMasks:
    """Segmenter output. masks: (V, P, H, W) bool; confidence: (V, P) float32 in [0, 1].

    A part with no mask in a view has an all-False mask and confidence 0.
    """

    parts: list[str]
    masks: np.ndarray
    confidence: np.ndarray
    source: str = ""


@dataclass
class MaterialPart:
    """Decision for one material: part label with the evidence behind it."""

    material: int                 # material index (id - 1)
    name: str
    part: str                     # one of PART_NAMES, or 'unseen'
    score: float                  # |material ∩ part| / |material| in the deciding view
    iou: float                    # plain IoU in the deciding view
    view: int                     # deciding view (-1 when none)
    decision: str                 # 'best-view' | 'vote' | 'merged-body' | 'symmetric' | 'unseen' | ...
    pixels: int = 0               # visible pixels over all views


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
