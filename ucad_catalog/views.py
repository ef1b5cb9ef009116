"""View-stack types shared by the pipeline and the reader: cameras and rendered maps.

These live in ``ucad_catalog`` (numpy only) so the reader installs without OpenCL;
``ucad_cl.artifacts`` re-exports them. Conventions (docs/CONVENTIONS.md):

* OpenCV camera (x right, y down, z forward); pixel (i, j) = (row, column) has its centre at
  image coordinates (j + 0.5, i + 0.5). ``K`` 3x3, ``w2c`` 4x4 world(canonical)-to-camera.
* Azimuth 0 looks from +X toward the origin, growing counter-clockwise seen from +Y; elevation
  > 0 is above the model. Degrees. Views are elevation-major.
* Material id = material index + 1 (0 background, uint16); triangle id = face index
  (0xFFFFFFFF background, uint32); depth = linear camera z (+inf background, float32).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

BACKGROUND_TRI = np.uint32(0xFFFFFFFF)
BACKGROUND_MAT = np.uint16(0)


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
    _counts: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)

    @property
    def n_views(self) -> int:
        return int(self.tri_id.shape[0])

    def material_counts(self, n_ids: int | None = None) -> np.ndarray:
        """(V, n_ids) int64: pixels of every material id (0 = background) in each view.

        Counted once and cached (the filter, the segmenter and the build all need it; a ViewSet's
        maps are not modified after rendering). ``n_ids`` defaults to the largest id + 1;
        ValueError when a view holds an id >= ``n_ids``. Counted per view with OpenCV's
        histogram when OpenCV is installed (exact integer bins; 4x faster than np.bincount on
        uint16 maps), with np.bincount otherwise: the same counts."""
        if self._counts is None:
            self._counts = _id_counts(np.asarray(self.mat_id))
        top = self._counts.shape[1]
        n = top if n_ids is None else int(n_ids)
        if n < top:
            raise ValueError(f"material id {top - 1} in the views but only {n} ids expected")
        out = np.zeros((self._counts.shape[0], n), np.int64)
        out[:, :top] = self._counts
        return out

    def select(self, idx) -> "ViewSet":
        """The views ``idx`` (indices or a slice), maps and cameras alike."""
        c = self.cameras
        ring = CameraRing(K=c.K, w2c=c.w2c[idx], width=c.width, height=c.height,
                          azimuth=c.azimuth[idx], elevation=c.elevation[idx],
                          distance=c.distance, near=c.near)
        return ViewSet(cameras=ring, tri_id=self.tri_id[idx], mat_id=self.mat_id[idx],
                       depth=self.depth[idx])


def nonzero_box(img: np.ndarray, margin: int = 0) -> tuple[int, int, int, int] | None:
    """(y0, y1, x0, x1), half-open, of the non-zero pixels of a (H, W) image grown by ``margin``
    pixels and clipped to the image; None when every pixel is zero."""
    rows = np.flatnonzero(img.any(axis=1))
    if rows.size == 0:
        return None
    H, W = img.shape
    y0, y1 = max(int(rows[0]) - margin, 0), min(int(rows[-1]) + 1 + margin, H)
    cols = np.flatnonzero(img[y0:y1].any(axis=0))
    return y0, y1, max(int(cols[0]) - margin, 0), min(int(cols[-1]) + 1 + margin, W)


def _id_counts(mat_id: np.ndarray) -> np.ndarray:
    """(V, max id + 1) int64 pixel counts of each id per view of (V, H, W) uint16 maps."""
    V = mat_id.shape[0]
    if mat_id.size == 0:
        return np.zeros((V, 1), np.int64)
    n = int(mat_id.max()) + 1
    try:
        import cv2
    except ImportError:                 # the reader's install has no OpenCV: same counts
        cv2 = None  # type: ignore[assignment]
    if cv2 is None or mat_id.dtype != np.uint16 or mat_id[0].size >= 2**24:
        # (float32 histogram bins are exact below 2^24 pixels)
        return np.stack([np.bincount(m.ravel(), minlength=n) for m in mat_id]).astype(np.int64)
    return np.stack([cv2.calcHist([np.ascontiguousarray(m)], [0], None, [n], [0, n]).ravel()
                     for m in mat_id]).astype(np.int64)
