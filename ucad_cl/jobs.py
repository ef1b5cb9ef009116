"""What the build's driver and its engines exchange: options (and the code version that enters
their hash), mesh references, a worker's "already catalogued" answer, rejections, environment
faults. No stage is imported here, so the driver (``ucad_cl.build``), which never opens a mesh
or a device, stays small; the stages themselves are ``ucad_cl.pipeline``, loaded by workers.
"""
from __future__ import annotations

import errno
import hashlib
import json
import os
import sqlite3
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Iterable

from ucad_catalog.entry import CatalogEntry

from . import reasons
from .artifacts import Verdict
from .cameras import BUILD_ELEVATIONS
from .ingest import Budgets, IngestError, mesh_identity, unreadable_identity
from .curation import LabelOverrides, mesh_options_hash
from .orient import parse_mode

if TYPE_CHECKING:
    from .build import BuildSummary


CODE_VERSION = "19"       # bump when a change alters results: it enters the options hash


@dataclass(frozen=True)
class BuildOptions:
    """Everything that affects what is stored. Angles in degrees, sizes in pixels."""

    azimuth_step: float = 5.0
    elevations: tuple[float, ...] = BUILD_ELEVATIONS   # the first: the label ring
    fov_deg: float = 40.0
    size: int = 256
    segmenter: str = "labeller"         # 'labeller[:MODEL]' | 'prior' | 'masks:DIR' | 'onnx:MODEL:CONFIG'
    threshold: float = 0.5              # part score threshold (UrbanCAD: 0.5)
    min_materials: int = 2
    max_triangles: int = 2_000_000      # reject above this (after decimation, if any)
    triangle_budget: int = 0            # decimate above this many triangles (0 = never)
    dominant_fraction: float = 0.97     # reject when one material covers this share of pixels
    min_visible_materials: int = 2
    features: bool = True
    edges: bool = True
    max_input_triangles: int = Budgets.max_triangles   # ingest budget, before allocation
    orientation: str = "auto"           # 'auto' | 'file' | 'UP,FRONT' (ucad_cl.orient)
    orientation_overrides: tuple = ()   # ((path or sha256, 'UP,FRONT' | 'auto' | 'file'), ...)
    reject_uncertain_orientation: bool = False   # reject instead of flag (uncertain_orientation)
    # curators' fixes ((path or sha256, material, part), ...): per-mesh, outside the run's hash
    label_overrides: tuple = ()

    def __post_init__(self):
        parse_mode(self.orientation)                      # a bad mode fails here
        object.__setattr__(self, "orientation_overrides",
                           tuple((str(k), str(v)) for k, v in self.orientation_overrides))
        object.__setattr__(self, "label_overrides",
                           LabelOverrides.from_items(self.label_overrides).as_items())

    def to_dict(self) -> dict:
        d = asdict(self)
        d["elevations"] = list(self.elevations)
        d["orientation_overrides"] = [list(kv) for kv in self.orientation_overrides]
        d["label_overrides"] = [list(kv) for kv in self.label_overrides]
        return d

    def run_record(self) -> dict:
        """What a run records and hashes (``Catalog.begin_run``): ``to_dict`` and the code
        version, the label overrides left out of the hash (a mesh's own fixes enter its own
        options hash, ``curation.mesh_options_hash``: editing the file re-processes only the
        meshes whose fixes changed); their count is kept under the unhashed ``runtime`` key."""
        d = {**self.to_dict(), "code": CODE_VERSION}
        d.pop("label_overrides")
        d["runtime"] = {"label_overrides": len(self.label_overrides)}
        return d

    def hash(self) -> str:
        blob = json.dumps({"code": CODE_VERSION, **self.to_dict()}, sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()

    def budgets(self) -> Budgets:
        """Ingest budgets: triangles as given, vertices three per triangle (at least the
        default vertex budget: files often carry unreferenced vertices)."""
        return Budgets(max_triangles=self.max_input_triangles,
                       max_vertices=max(Budgets.max_vertices, 3 * self.max_input_triangles))


@dataclass
class MeshRef:
    """A library file: path, size in bytes, mtime (s); size -1 when it cannot be stat-ed."""

    path: str
    size: int
    mtime: float


class BuildStopped(RuntimeError):
    """An environment fault stopped the build (nothing recorded for the meshes in flight).
    ``code`` is an environment reason code, ``str`` says what to free or fix; ``summary`` holds
    what the run did before it stopped."""

    def __init__(self, code: str, message: str, summary: "BuildSummary | None" = None):
        self.code = reasons.check(code, reasons.ENVIRONMENT)
        self.summary = summary
        super().__init__(message)


def environment_code(exc: BaseException) -> str | None:
    """The environment reason code of an error raised while writing the catalogue or staging
    files (``disk_full``, ``io_error``), or None when it is not an environment fault."""
    if isinstance(exc, OSError):
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return "disk_full"
        if exc.errno in (errno.EIO, errno.EROFS, errno.ENXIO, errno.ENODEV, errno.ESTALE):
            return "io_error"
        return None
    if isinstance(exc, sqlite3.Error):
        code = getattr(exc, "sqlite_errorcode", None)
        text = str(exc).lower()
        if code == 13 or "disk is full" in text:                 # SQLITE_FULL
            return "disk_full"
        if (code is not None and code & 0xFF in (8, 10, 14)) or "disk i/o error" in text:
            return "io_error"                                   # READONLY, IOERR, CANTOPEN
    return None


def content_sha256(path: str | os.PathLike) -> str:
    """The mesh key (``ingest.mesh_identity``: format tag + the bytes of the file and of the
    files it references); for a file that cannot be read, ``ingest.unreadable_identity``."""
    try:
        return mesh_identity(path)
    except IngestError:
        return unreadable_identity(path)


@dataclass
class Skipped:
    """A worker's answer for a path whose content is already catalogued with these options."""

    sha256: str


class KnownContent:
    """Read-only question to the catalogue, asked by workers: is content ``sha`` (at ``path``)
    already catalogued with its options hash (the run's ``ohash``, or with the mesh's label
    fixes from ``label_overrides`` triples, ``curation.mesh_options_hash``) and not with a
    reason being retried? No lock; any error answers "no" (the mesh is then simply processed)."""

    def __init__(self, catalog: str | os.PathLike | None, ohash: str | None,
                 retry: Iterable[str] = (), label_overrides: tuple = ()):
        self._db = Path(catalog) / "catalog.sqlite" if catalog else None
        self._ohash, self._retry = ohash, set(retry)
        self._labels = LabelOverrides.from_items(label_overrides)
        self._conn = None

    def __call__(self, sha: str, path: str | os.PathLike | None = None) -> bool:
        if self._db is None or not self._ohash:
            return False
        ohash = mesh_options_hash(self._ohash, self._labels.for_mesh(path, sha))
        try:
            if self._conn is None:
                self._conn = sqlite3.connect(f"{self._db.resolve().as_uri()}?mode=ro", uri=True,
                                             timeout=5.0, check_same_thread=False)
            row = self._conn.execute("SELECT state, reason FROM meshes WHERE sha256=? AND "
                                     "options_hash=?", (sha, ohash)).fetchone()
        except sqlite3.Error:
            return False
        return row is not None and not (row[0] == "rejected" and row[1] in self._retry)


def rejected_entry(ref: MeshRef, sha: str, reason: str, detail: str):
    reasons.check(reason, reasons.REJECTION)
    return CatalogEntry.from_results(sha256=sha, path=ref.path, size=max(ref.size, 0),
                                     mtime=ref.mtime, verdict=Verdict(False, reason, detail))
