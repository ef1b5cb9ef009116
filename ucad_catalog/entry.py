"""``CatalogEntry``: everything the catalogue stores about one mesh, as plain data.

The build driver fills one entry per mesh and hands it to ``Catalog.commit_mesh``. Artifacts are
``{kind: bytes | Path}``; a ``Path`` is copied into the object store. The kinds the build
writes are ``ucad_catalog._db.ARTIFACT_KINDS`` (``views.exr``, ``edges.npy.gz``,
``features.npy``, ``parts.png``; SCHEMA.md). Angles in degrees, K / w2c as in ``ucad_cl.artifacts`` (OpenCV camera,
canonical frame). ``CatalogEntry.from_results`` builds an entry from the pipeline dataclasses
(duck-typed: this module does not import ``ucad_cl``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ._db import CatalogError, is_sha256

STATES = ("accepted", "rejected")


@dataclass
class MaterialRow:
    """Decision for one material (mirrors ``ucad_cl.artifacts.MaterialPart``); props: free JSON."""

    index: int
    name: str
    part: str
    score: float = 0.0
    iou: float = 0.0
    view: int = -1
    decision: str = ""
    pixels: int = 0
    props: dict = field(default_factory=dict)


@dataclass
class ViewRow:
    """One camera: K (3, 3) and w2c (4, 4) float64, angles in degrees; stats: free JSON."""

    index: int
    azimuth: float
    elevation: float
    K: np.ndarray
    w2c: np.ndarray
    stats: dict = field(default_factory=dict)


@dataclass
class CatalogEntry:
    """One mesh. ``options_hash=None`` means the hash of the run it is committed in."""

    sha256: str
    path: str
    size: int
    mtime: float
    state: str = "accepted"                       # 'accepted' | 'rejected'
    reason: str = ""                              # machine-readable code (required if rejected)
    detail: str = ""
    n_triangles: int = 0
    n_materials: int = 0
    file_to_norm: np.ndarray = field(default_factory=lambda: np.eye(4))
    materials: list[MaterialRow] = field(default_factory=list)
    views: list[ViewRow] = field(default_factory=list)
    artifacts: dict[str, bytes | Path] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    options_hash: str | None = None
    library_root: str = ""                        # absolute library folder; path is relative to it
    orientation: dict | None = None               # the orientation stage's record (JSON), if any
    meta: dict = field(default_factory=dict)      # free per-mesh metadata (JSON, namespaced keys)

    @classmethod
    def from_results(cls, *, sha256: str, path: str, size: int, mtime: float, verdict: Any,
                     mesh: Any = None, table: Any = None, ring: Any = None,
                     artifacts: dict | None = None, timings: dict | None = None,
                     view_stats: list[dict] | None = None) -> "CatalogEntry":
        """Entry from ``Verdict``, ``Mesh``, ``PartTable`` and ``CameraRing`` (any may be None
        except the verdict). Material props record the ``Material`` fields of the mesh."""
        mats: list[MaterialRow] = []
        if table is not None:
            by_index = {m: mesh.materials[m] for m in range(len(mesh.materials))} if mesh else {}
            for r in table.rows:
                mat = by_index.get(int(r.material))
                props = {k: v for k, v in vars(mat).items() if k != "name"} if mat else {}
                for k in ("prob", "split", "was"):     # the labeller's, a curator's override
                    if getattr(r, k, None) is not None:
                        props[k] = getattr(r, k)
                mats.append(MaterialRow(int(r.material), r.name, r.part, float(r.score),
                                        float(r.iou), int(r.view), r.decision, int(r.pixels),
                                        props))
        views: list[ViewRow] = []
        if ring is not None:
            for v in range(int(ring.w2c.shape[0])):
                views.append(ViewRow(v, float(ring.azimuth[v]), float(ring.elevation[v]),
                                     np.asarray(ring.K, np.float64),
                                     np.asarray(ring.w2c[v], np.float64),
                                     dict(view_stats[v]) if view_stats else {}))
        orientation = getattr(mesh, "orientation", None) if mesh is not None else None
        return cls(sha256=sha256, path=str(path), size=int(size), mtime=float(mtime),
                   state="accepted" if verdict.accepted else "rejected",
                   reason=verdict.reason, detail=verdict.detail,
                   n_triangles=int(mesh.n_faces) if mesh is not None else 0,
                   n_materials=len(mesh.materials) if mesh is not None else 0,
                   file_to_norm=(np.asarray(mesh.file_to_norm, np.float64) if mesh is not None
                                 else np.eye(4)),
                   materials=mats, views=views, artifacts=dict(artifacts or {}),
                   timings=dict(timings or {}),
                   orientation=None if orientation is None else _plain(
                       orientation.as_dict() if hasattr(orientation, "as_dict") else orientation))

    def validate(self) -> None:
        """Raise CatalogError naming the first problem (the entry's path is in the message)."""
        where = f"entry for {self.path!r}"
        if not is_sha256(self.sha256):
            raise CatalogError(f"{where}: sha256 must be 64 lowercase hex digits, got "
                               f"{self.sha256!r}")
        if not isinstance(self.path, str) or not self.path:
            raise CatalogError(f"{where}: path must be a non-empty string")
        if self.state not in STATES:
            raise CatalogError(f"{where}: state must be one of {STATES}, got {self.state!r}")
        if self.state == "rejected" and not self.reason:
            raise CatalogError(f"{where}: a rejected entry needs a reason code")
        if int(self.size) < 0 or not math.isfinite(float(self.mtime)):
            raise CatalogError(f"{where}: size must be >= 0 and mtime finite")
        if not isinstance(self.library_root, str):
            raise CatalogError(f"{where}: library_root must be a string")
        if self.orientation is not None and not isinstance(self.orientation, dict):
            raise CatalogError(f"{where}: orientation must be a dict or None")
        if not isinstance(self.meta, dict):
            raise CatalogError(f"{where}: meta must be a dict")
        if self.options_hash is not None and not is_sha256(self.options_hash):
            raise CatalogError(f"{where}: options_hash must be a sha256 hex digest")
        _check_matrix(self.file_to_norm, (4, 4), f"{where}: file_to_norm")
        seen: set[int] = set()
        for m in self.materials:
            if m.index in seen:
                raise CatalogError(f"{where}: material index {m.index} appears twice")
            seen.add(m.index)
            if not (math.isfinite(m.score) and math.isfinite(m.iou)):
                raise CatalogError(f"{where}: material {m.name!r} has a non-finite score/iou")
        seen = set()
        for v in self.views:
            if v.index in seen:
                raise CatalogError(f"{where}: view index {v.index} appears twice")
            seen.add(v.index)
            _check_matrix(v.K, (3, 3), f"{where}: view {v.index} K")
            _check_matrix(v.w2c, (4, 4), f"{where}: view {v.index} w2c")
            if not (math.isfinite(v.azimuth) and math.isfinite(v.elevation)):
                raise CatalogError(f"{where}: view {v.index} has a non-finite angle")
        for kind, data in self.artifacts.items():
            if not isinstance(kind, str) or not kind or "/" in kind or kind != kind.strip():
                raise CatalogError(f"{where}: bad artifact kind {kind!r}")
            if isinstance(data, (str, Path)):
                if not Path(data).is_file():
                    raise CatalogError(f"{where}: artifact {kind!r}: file {data} does not exist")
            elif not isinstance(data, (bytes, bytearray, memoryview)):
                raise CatalogError(f"{where}: artifact {kind!r} must be bytes or a Path, got "
                                   f"{type(data).__name__}")


def _plain(obj: Any) -> Any:
    """A dataclass / object record as plain JSON-able data (NumPy arrays as lists)."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if hasattr(obj, "__dict__"):
        return _plain(vars(obj))
    return obj


def _check_matrix(a: Any, shape: tuple[int, int], what: str) -> None:
    arr = np.asarray(a)
    if arr.shape != shape or not np.issubdtype(arr.dtype, np.number):
        raise CatalogError(f"{what} must be a numeric {shape} array, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise CatalogError(f"{what} has non-finite values")
