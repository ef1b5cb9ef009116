"""Mesh ingest: one CAD file -> one :class:`~ucad_cl.artifacts.Mesh` in the canonical frame.

Formats: GLB, glTF (+ external .bin), OBJ+MTL, PLY, OFF, STL, read with trimesh (``process=False``,
so vertices are never merged or reordered by the reader).

Conventions and decisions (see also ``ucad_cl/artifacts.py``):

* **Untrusted files.** Every file is read by ``_read_file``: it must be a regular file (a FIFO,
  device, socket, directory or symlink loop is refused from ``stat`` alone, never opened, reason
  ``not_a_file``), opened non-blocking and read up to ``Budgets.max_file_bytes``. trimesh never
  opens a path itself: it gets the bytes we read and a resolver (``_Resolver``) that serves only
  files inside the model's folder. A file the geometry needs (a glTF buffer) that is absolute, a
  URL, outside the model's folder (after resolving symlinks) or not a regular file is refused
  (``unsafe_reference``); one that does not exist gives ``missing_reference``; ``data:`` URIs
  are size-checked before decoding. OBJ ``mtllib`` files and textures the same way, except that a
  refused or missing one is a note (``IngestReport.notes``, stored in the catalogue's detail), not
  a rejection: the model loads without it. glTF images are never read (materials come from the
  JSON). All referenced bytes together are capped by ``Budgets.max_buffer_bytes``.
* **Budgets before allocation** (``Budgets``, reason ``too_large``): counts read from the glTF
  JSON (triangles and vertices of every primitive times its instances, declared materials,
  instances, buffer bytes, node depth; every index and type checked, a node with two parents or
  a cycle is ``unreadable``), from PLY / OFF / binary STL headers and from OBJ line counts, before
  trimesh allocates anything; flattening checks the running totals again.
* **Identity** (``Mesh.sha256``, the catalogue key): sha256 over a format tag (the decoder used:
  the suffix, ``glb``, ``gltf``, ``obj``, ``ply``, ``off``, ``stl``) and the length-prefixed
  bytes of the file, then of every file its geometry or materials are read from (glTF external
  buffers in ``buffers`` order, OBJ ``mtllib`` files in line order), so the same bytes seen as
  ``copy.stl`` and ``real.glb`` are two meshes. ``mesh_identity`` computes it without parsing.
* **Scene graph.** Every (node, geometry) pair of ``scene.graph.nodes_geometry`` is drawn with the
  node's world transform (float64), in that order (trimesh's traversal order: deterministic, the
  same in every process, not necessarily the file's node order); a geometry instanced on several
  nodes is drawn at each.
  Faces of a node whose transform mirrors (det < 0) get their winding flipped so that faces keep
  facing outward. ``face_node`` indexes ``node_names`` (node names without the random suffix trimesh
  gives repeated names, ``artifacts.node_stem``, so they are the same on every load; a PLY, OFF or
  STL file has one node, ``geometry_0``: names never depend on the file's name).
* **Up axis / units.** glTF is +Y up (spec); OBJ, PLY, OFF and STL carry no convention. The file
  frame is the flattened scene frame (file units); which way is up and front is found by the
  orientation stage (below), not assumed.
* **Canonical frame.** ``c`` = centre of the axis-aligned bounding box of the returned vertices,
  ``d`` = its diagonal length; ``(file - c) / d`` in float64, then the orientation stage
  (``ucad_cl.orient``, ``orientation=``: ``"auto"`` by default) turns it into the canonical
  vehicle frame and folds its rotation and placement into ``file_to_norm``;
  ``orientation="file"`` keeps ``file_to_norm = [[I/d, -c/d], [0, 1]]``. A mesh whose extent is
  zero is rejected (``empty``); one whose extent or ``file_to_norm`` overflows float64
  (coordinates near 1e308, or a tiny model far from the origin) is ``non_finite``. ``d`` is the
  square root of the extent's squares summed smallest first (so a re-posed file, its axes
  permuted or negated, gives the same bits); only when that under- or overflows (scales beyond
  1e+-150) is it computed with the extent divided by its largest component first.
* **Materials.** One material index per face, built per geometry (never via trimesh
  concatenate). Material identity = the file's material: for glTF the material index of the
  primitive (two glTF materials with the same name stay two materials), otherwise the material
  object trimesh shares between geometries. Table order: glTF material index order; other formats
  first use in draw order. Only materials used by at least one drawn face are kept. glTF
  properties come from the raw glTF JSON (glTF defaults: base colour 1, metallic 1, roughness 1;
  a value of the wrong type or length takes the default), including
  ``KHR_materials_transmission``; primitives without a material get the glTF default
  material named ``"default"``. OBJ: ``Kd`` -> RGB, ``d`` (or ``1 - Tr``) -> alpha, ``Ke`` ->
  emissive; alpha < 1 gives alpha mode ``BLEND``. PLY/OFF/STL: one ``"default"`` material.
  Names and alpha modes are made valid UTF-8 (lone surrogates written as ``\\udcXX``) and cut
  to ``MAX_NAME_CHARS`` characters.
* **Cleaning** (``clean=True``), done in NumPy on the flattened float64 file-frame mesh, in this
  order: (1) zero-area faces: a repeated vertex index or a cross product that is exactly 0
  (computed on the vertices times the power of two that brings the largest coordinate into
  [0.5, 1): exact, so it only changes the outcome where the unscaled product would under- or
  overflow); (2) duplicate faces: same vertex-index set (any order or winding) AND same
  material, the lowest face index is kept; faces with different materials are never duplicates
  (coplanar duplicates are a renderer hard case, not ours to hide); (3) unreferenced vertices
  (including those orphaned by (1) and (2)); (4) ground plates (``ucad_cl.ground``: a material
  that is one flat plate spanning the whole model, a baked shadow or ground sheet) with a note
  each, and the vertices only they used. Kept faces and vertices keep their relative order, so
  ``face_material`` / ``face_node`` stay aligned. pymeshlab (``meshing_remove_null_faces``,
  ``_duplicate_faces``, ``_unreferenced_vertices``) gives the same counts (tested) but cannot
  tell materials apart when removing duplicates and needs the material carried as face quality
  through its own buffers. Measured on ferrari_458 (358,788 faces, 2 cores, median of 5): NumPy
  0.09 s; pymeshlab 0.15 s including the copy in and out (0.05 s for the filters themselves),
  same kept faces/vertices. So pymeshlab is only the test reference.
* **Draco.** ``KHR_draco_mesh_compression`` is detected in the GLB/glTF JSON. It is decoded by
  trimesh through DracoPy; without DracoPy the file is rejected (``unsupported_compression``)
  before trimesh can hand back placeholder zeros, and a decode that still yields an all-zero
  primitive is rejected the same way. ``EXT_meshopt_compression`` is rejected.
* **Isolation.** ``load_mesh_isolated`` runs the loader in a fresh ``python -c`` child; it costs
  about 0.6-0.9 s per file (interpreter, NumPy and trimesh imports) on top of the load, unless
  the child was started earlier to import the reader's modules (``system.reader_child``, as
  the fit does: then ~0.02 s and the pickled mesh's transfer).
* **Errors** are :class:`IngestError` (a ``ValueError``) with ``.path``, ``.reason`` (a code of
  ``ucad_cl.reasons``) and a message naming the file. ``MemoryError`` is not turned into an
  ``IngestError``: the caller decides (the build records ``too_large`` only for a mesh that
  overruns the worker's memory limit on its own).

Why one module of over 800 lines: every reader path (the untrusted-file checks, the budgets from
headers, identity, flattening, cleaning) shares one ``_Resolver`` and one ``Budgets`` contract,
and the security argument above is read top to bottom; the public surface is small
(``load_mesh``, ``mesh_identity``, ``Budgets``, ``IngestError``).
"""
from __future__ import annotations

import hashlib
import io
import json
import os
import re
import stat
import struct
import traceback
from dataclasses import dataclass, field, replace
from pathlib import Path
from urllib.parse import unquote

import numpy as np

from . import reasons
from .artifacts import IngestReport, Material, Mesh, node_stem
from .ground import ground_plates
from .orient import orient_mesh
from .system import (IsolatedCallFailed, IsolatedChild, call_isolated, reader_child,
                     reader_modules_loaded)

SUPPORTED_SUFFIXES = (".glb", ".gltf", ".obj", ".ply", ".off", ".stl")
DRACO = "KHR_draco_mesh_compression"
MESHOPT = ("EXT_meshopt_compression", "KHR_meshopt_compression")
MAX_MATERIALS = 65534          # material id = index + 1 must fit uint16 (0 = background)
MAX_NAME_CHARS = 1024          # material names and alpha modes are cut to this many characters
GLTF_DEFAULT = Material("default", (1.0, 1.0, 1.0, 1.0), "OPAQUE", 1.0, 1.0)
IDENTITY_TAG = b"ucad-mesh/1"  # first bytes hashed into every mesh identity (see module doc)
_GL_TRIANGLES = 4
_TRIMESH_PRIMITIVE_MODES = (0, 1, 4, 5)   # modes trimesh turns into a geometry (points, lines, tris)
_READ_CHUNK = 1 << 20


@dataclass(frozen=True)
class Budgets:
    """Limits checked before anything is allocated for a file's geometry (reason ``too_large``).

    Bytes per file (the model and each file it references) and in all; drawn triangles and
    vertices (every instance of every primitive, as flattening allocates them; vertices also as
    loaded, once per primitive); declared materials; drawn (node, mesh) instances; glTF node
    depth. The defaults suit the build's defaults (``BuildOptions.max_input_triangles``).
    """

    max_file_bytes: int = 1 << 30
    max_buffer_bytes: int = 1 << 30
    max_triangles: int = 4_000_000
    max_vertices: int = 12_000_000
    max_materials: int = MAX_MATERIALS
    max_instances: int = 100_000
    max_node_depth: int = 256


class IngestError(ValueError):
    """A file that cannot become a Mesh. ``str`` names the file, the problem and the reason code."""

    def __init__(self, path: str | os.PathLike, reason: str, message: str):
        if reason not in reasons.CODES:
            raise ValueError(f"unknown ingest reason code {reason!r}")
        self.path, self.reason, self.message = str(path), reason, message
        super().__init__(f"{self.path}: {message} [{reason}]")

    def __reduce__(self):
        return (IngestError, (self.path, self.reason, self.message))


def load_mesh(path: str | os.PathLike, *, clean: bool = True,
              budgets: Budgets | None = None, orientation="auto", overrides=None) -> Mesh:
    """Load a CAD file into a canonical-frame Mesh with one material index per face.

    orientation: ``"auto"`` (estimate the vehicle frame), ``"file"`` (trust the file's +Y up)
    or ``"UP,FRONT"`` / ``(up, front)`` signed file axes (see ``ucad_cl.orient``); None skips
    the stage (the bounding-box normalisation only; ``mesh.orientation`` stays None, for a
    caller that orients it itself). overrides: an ``orient.OrientationOverrides`` whose entry
    for this file (by path or sha256) replaces ``orientation``."""
    path = Path(path)
    budgets = budgets or Budgets()
    source = _read_source(path, budgets)
    report = IngestReport()
    gltf = source.gltf
    draco = _check_compression(path, gltf, report) if gltf is not None else False
    sha = source.identity()

    scene = _trimesh_scene(path, source, budgets)
    report.notes.extend(source.notes)
    vertices, faces, face_material, face_node, node_names, materials = _flatten(
        path, scene, gltf, draco, budgets, report.notes)
    del scene
    if faces.shape[0] == 0:
        raise IngestError(path, "empty", "no triangles in the file" + _notes(report))
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise IngestError(path, "non_finite",
                          f"{int(bad.sum())} vertices have NaN/inf coordinates "
                          f"(first: vertex {int(np.argmax(bad))})")

    report.faces_in = int(faces.shape[0])
    if clean:
        vertices, faces, face_material, face_node = _clean(vertices, faces, face_material,
                                                           face_node, report)
        vertices, faces, face_material, face_node = _drop_ground_plates(
            vertices, faces, face_material, face_node, materials, report)
    report.faces_out = int(faces.shape[0])
    if faces.shape[0] == 0:
        raise IngestError(path, "empty", "no triangles left after removing degenerate faces")
    # keep only the materials used by the kept faces, in table order
    used = np.unique(face_material)
    if used.size > MAX_MATERIALS:
        raise IngestError(path, "unsupported_format", f"{used.size} materials used; material ids "
                                                      f"are uint16, at most {MAX_MATERIALS}")
    remap = np.zeros(len(materials), np.int64)
    remap[used] = np.arange(used.size)
    face_material = remap[face_material]
    materials = [materials[i] for i in used]

    centre, diag = _extent(path, vertices)
    file_to_norm = np.eye(4)
    file_to_norm[:3, :3] /= diag
    file_to_norm[:3, 3] = -centre / diag
    if not np.isfinite(file_to_norm).all():
        raise IngestError(path, "non_finite",
                          f"the canonical transform overflows float64 (extent {diag:.3g} at "
                          f"{np.abs(centre).max():.3g} from the origin)")
    mesh = Mesh(path=str(path), sha256=sha, vertices=(vertices - centre) / diag,
                faces=faces.astype(np.uint32), face_material=face_material.astype(np.uint16),
                materials=materials, file_to_norm=file_to_norm,
                face_node=face_node.astype(np.int32), node_names=node_names, report=report)
    if orientation is None:
        return mesh
    if overrides is not None:
        orientation = overrides.mode_for(path, sha, orientation)
    return orient_mesh(mesh, orientation)


def mesh_identity(path: str | os.PathLike, budgets: Budgets | None = None) -> str:
    """The content key ``load_mesh`` stores in ``Mesh.sha256`` (format tag + the bytes of the
    file and of the files it references, see the module doc), without parsing the geometry.
    Raises ``IngestError`` when the file itself cannot be read safely."""
    return _read_source(Path(path), budgets or Budgets(), check=False).identity()


def unreadable_identity(path: str | os.PathLike) -> str:
    """Key of a file whose bytes cannot be read (``not_a_file``, permissions...): the format tag
    and the path, so its rejection is recorded once and skipped while the path is unchanged."""
    fmt = Path(path).suffix.lower().lstrip(".")
    h = hashlib.sha256(IDENTITY_TAG + b"\0unreadable\0" + fmt.encode() + b"\0")
    h.update(os.fsencode(str(path)))
    return h.hexdigest()


def file_sha256(path: str | os.PathLike) -> str:
    """Alias of ``mesh_identity`` (the name older callers use)."""
    return mesh_identity(path)


class MeshLoader:
    """Reads meshes in the file's own frame (``load_mesh(path, orientation=None)``: the frame
    the catalogue records ``file_to_norm`` from) for a caller that reads several, or wants a
    read started ahead. ``isolated`` (the default unless this process has imported
    ``READER_MODULES`` already): in a child interpreter (``system.IsolatedChild``) started at
    construction, which imports the reader's modules meanwhile (trimesh, without the SciPy it
    would import: ``system.READER_HIDDEN``; ~0.5 s of a core, beside the caller's own work); a
    reader that crashes or hangs then costs one load (``IngestError``), not the process, and the
    next load starts a new child. ``prefetch(path)`` starts that read in the child at once; the
    ``load(path)`` that follows collects it (the fit's CLI so reads a given mesh while it
    imports its own modules, reads the photo and finds the object: ``ucad_cl.commands.fit``).
    Not isolated: in this process (where the modules are loaded already, or when nothing would
    run beside the child's start); ``prefetch`` then does nothing. ``child``: such a child
    started earlier (``system.reader_child()``; the CLI starts one before its own imports),
    used instead of a new one. ``close`` ends the child (also on leaving a ``with``
    block)."""

    def __init__(self, isolated: bool | None = None, child: IsolatedChild | None = None) -> None:
        if child is None:
            if isolated is None:
                isolated = not reader_modules_loaded()
            child = reader_child() if isolated else None
        self._child = child
        self._ahead: str | None = None          # the path a prefetch is reading

    @property
    def isolated(self) -> bool:
        return self._child is not None

    def prefetch(self, path: str | os.PathLike) -> None:
        """Start reading ``path`` in the child now (isolated only)."""
        if self._child is None:
            return
        if self._ahead is not None or not self._child.alive:   # an unwanted read, or dead
            self._renew()
        assert self._child is not None
        self._child.submit(load_mesh, str(path), clean=True, orientation=None)
        self._ahead = str(path)

    def load(self, path: str | os.PathLike) -> Mesh:
        if self._child is None:
            return load_mesh(path, orientation=None)
        if self._ahead is not None and self._ahead != str(path):
            self._renew()                       # the read ahead is of another file
        elif self._ahead is None and not self._child.alive:
            self._renew()
        self._ahead = None
        assert self._child is not None
        return load_mesh_isolated(path, orientation=None, child=self._child)

    def _renew(self) -> None:
        assert self._child is not None
        self._child.close()
        self._child = reader_child()
        self._ahead = None

    def close(self) -> None:
        if self._child is not None:
            self._child.close()

    def __enter__(self) -> "MeshLoader":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def load_mesh_isolated(path: str | os.PathLike, *, timeout: float = 120.0, clean: bool = True,
                       loader=None, child: IsolatedChild | None = None, **kwargs) -> Mesh:
    """``load_mesh(path, clean=clean, **kwargs)`` in a fresh child interpreter
    (``system.call_isolated``), so a native crash or hang cannot kill us (the CLI's ``render``,
    ``parts`` and ``pose`` load user files this way; ``build`` isolates loading in its workers
    instead).

    A child that dies without answering raises ``IngestError`` reason ``loader_crashed`` (the
    message names the signal or exit code); one still running after ``timeout`` seconds is killed
    and raises reason ``timeout``; any other exception than ``IngestError`` raises reason
    ``unreadable`` naming it. ``loader`` (a picklable module-level function
    ``loader(path, clean=..., **kwargs) -> Mesh``) replaces ``load_mesh``, for tests; ``kwargs``
    (budgets, orientation, overrides) must pickle. ``child``: a child started earlier
    (``system.reader_child``: ``MeshLoader``) instead of a new one; it stays open.
    """
    try:
        if child is not None:
            return child.call(loader or load_mesh, str(path), timeout=timeout, clean=clean,
                              **kwargs)
        return call_isolated(loader or load_mesh, str(path), timeout=timeout, clean=clean,
                             **kwargs)
    except IsolatedCallFailed as exc:
        if exc.kind == "timeout":
            raise IngestError(path, "timeout",
                              f"loader did not finish within {timeout:g} s (killed)") from None
        raise IngestError(path, "loader_crashed", f"loader process {exc.how}") from None
    except IngestError:
        raise
    except Exception as exc:  # noqa: BLE001 - whatever the loader raised names the file
        raise IngestError(path, "unreadable", f"loader raised {describe_exception(exc)}") from None


def describe_exception(exc: BaseException) -> str:
    """``Type: message``; for an exception without a message, where it was raised instead."""
    text = str(exc).strip()
    if text:
        return f"{type(exc).__name__}: {text[:500]}"
    frames = traceback.extract_tb(exc.__traceback__)
    where = f" at {Path(frames[-1].filename).name}:{frames[-1].lineno}" if frames else ""
    return f"{type(exc).__name__} (no message){where}"


# ----------------------------------------------------------------------------- file level

@dataclass
class _Source:
    """What was read from disk for one model: its bytes, the referenced files' bytes (by the
    name the file uses), the glTF JSON, notes."""

    path: Path
    fmt: str
    raw: bytes
    refs: list[tuple[str, bytes]] = field(default_factory=list)   # hashed, in order
    gltf: dict | None = None
    notes: list[str] = field(default_factory=list)
    ref_budget: int = 0            # bytes the resolver may still read (textures)
    stand_ins: dict[str, bytes] = field(default_factory=dict)     # served, not hashed

    def identity(self) -> str:
        h = hashlib.sha256(IDENTITY_TAG + b"\0" + self.fmt.encode() + b"\0")
        for data in [self.raw] + [d for _, d in self.refs]:
            h.update(len(data).to_bytes(8, "little"))
            h.update(data)
        return h.hexdigest()


def _read_source(path: Path, budgets: Budgets, check: bool = True) -> _Source:
    """Read a model and the files it references, safely (see the module doc). ``check``: also
    apply the budgets (identity alone only needs the bytes)."""
    suffix = path.suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES:
        raise IngestError(path, "unsupported_format",
                          f"unsupported file extension {path.suffix!r} "
                          f"(supported: {', '.join(SUPPORTED_SUFFIXES)})")
    raw = _read_file(path, budgets.max_file_bytes, path, main=True)
    src = _Source(path, suffix[1:], raw, ref_budget=budgets.max_buffer_bytes)
    if len(raw) == 0:
        raise IngestError(path, "empty", "file is empty (0 bytes)")
    if src.fmt in ("glb", "gltf"):
        src.gltf = _gltf_json(path, raw)
        _gltf_check(src, budgets, check)
    elif src.fmt == "obj":
        _obj_check(src, budgets, check)
    elif check:
        _header_check(src, budgets)
    return src


_KIND_NAMES = ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
               (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"),
               (stat.S_ISDIR, "a directory"))


def _file_kind(mode: int) -> str:
    return next((name for test, name in _KIND_NAMES if test(mode)), "not a regular file")


def _read_file(path: Path, cap: int, owner: Path, main: bool = False, what: str = "") -> bytes:
    """The bytes of a regular file of at most ``cap`` bytes, never blocking on a FIFO or device.

    ``main``: the model itself (reasons ``unreadable`` / ``not_a_file``), else a file the model
    references (``missing_reference`` / ``unsafe_reference``), reported against ``owner``."""
    label = "file" if main else (what or f"referenced file {path.name!r}")
    bad_kind = "not_a_file" if main else "unsafe_reference"
    try:
        st = os.stat(path)
    except FileNotFoundError:
        if os.path.islink(path):
            raise IngestError(owner, bad_kind, f"{label} is a dangling symlink") from None
        raise IngestError(owner, "unreadable" if main else "missing_reference",
                          f"{label} not found" if main else f"{label} does not exist") from None
    except OSError as e:
        if e.errno == 40:                                   # ELOOP
            raise IngestError(owner, bad_kind, f"{label} is a symlink loop") from None
        raise IngestError(owner, "unreadable", f"cannot stat {label}: {e.strerror}") from None
    if not stat.S_ISREG(st.st_mode):
        raise IngestError(owner, bad_kind, f"{label} is {_file_kind(st.st_mode)}, not a regular "
                                           "file (not opened)")
    if st.st_size > cap:
        raise IngestError(owner, "too_large", f"{label} has {st.st_size} bytes, more than the "
                                              f"limit of {cap}")
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except OSError as e:
        raise IngestError(owner, "unreadable", f"cannot open {label}: {e.strerror}") from None
    try:
        st = os.fstat(fd)                                   # the file we opened, not a swapped one
        if not stat.S_ISREG(st.st_mode):
            raise IngestError(owner, bad_kind, f"{label} is {_file_kind(st.st_mode)}")
        chunks, n = [], 0
        while True:
            chunk = os.read(fd, min(_READ_CHUNK, cap + 1 - n))
            if not chunk:
                break
            chunks.append(chunk)
            n += len(chunk)
            if n > cap:
                raise IngestError(owner, "too_large", f"{label} grew past the limit of {cap} "
                                                      "bytes while being read")
        return b"".join(chunks)
    except OSError as e:
        raise IngestError(owner, "unreadable", f"cannot read {label}: {e.strerror}") from None
    finally:
        os.close(fd)


def _resolve_inside(model: Path, name: str) -> tuple[Path | None, str]:
    """(path, '') for a relative reference that stays inside the model's folder after resolving
    ``..`` and symlinks, else (None, why it is refused)."""
    if not isinstance(name, str) or not name.strip():
        return None, f"reference {name!r} is not a file name"
    rel = unquote(name.strip())
    if "\0" in rel:
        return None, f"reference {name[:80]!r} contains a NUL byte"
    if re.match(r"^[A-Za-z][A-Za-z0-9+.-]*:", rel):
        return None, f"reference {name[:80]!r} is a URL or a drive path"
    if rel.startswith(("/", "\\")) or os.path.isabs(rel):
        return None, f"reference {name[:80]!r} is an absolute path"
    try:
        folder = model.parent.resolve()
        target = (folder / rel).resolve()
    except (OSError, RuntimeError):                          # RuntimeError: a symlink loop
        return None, f"reference {name[:80]!r} is a symlink loop"
    if not target.is_relative_to(folder):
        return None, f"reference {name[:80]!r} leaves the model's folder"
    return target, ""


def _read_reference(src: _Source, name: str, what: str, budgets: Budgets) -> bytes:
    """Bytes of a file the geometry needs (a glTF buffer): refused unless safe (see module doc)."""
    target, why = _resolve_inside(src.path, name)
    if target is None:
        raise IngestError(src.path, "unsafe_reference", f"{what}: {why}")
    data = _read_file(target, min(budgets.max_file_bytes, src.ref_budget), src.path, what=what)
    src.ref_budget -= len(data)
    return data


def _notes(report: IngestReport) -> str:
    return f" ({'; '.join(report.notes)})" if report.notes else ""


def _gltf_json(path: Path, raw: bytes) -> dict:
    """The glTF JSON of a .gltf file or of a GLB's JSON chunk, validating the GLB container."""
    if path.suffix.lower() == ".gltf":
        text = raw
    else:
        if len(raw) < 20 or raw[:4] != b"glTF":
            raise IngestError(path, "unreadable", "not a GLB file (bad magic or shorter than 20 bytes)")
        _, total = struct.unpack_from("<II", raw, 4)
        if total != len(raw):
            raise IngestError(path, "unreadable",
                              f"truncated or padded GLB: header says {total} bytes, file has {len(raw)}")
        chunk_len, chunk_type = struct.unpack_from("<II", raw, 12)
        if chunk_type != 0x4E4F534A or 20 + chunk_len > len(raw):
            raise IngestError(path, "unreadable", "GLB JSON chunk missing or longer than the file")
        text = raw[20:20 + chunk_len]
    try:
        gltf = json.loads(text.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise IngestError(path, "unreadable", f"invalid glTF JSON: {e}") from None
    except RecursionError:
        raise IngestError(path, "unreadable", "invalid glTF JSON: nested too deeply") from None
    if not isinstance(gltf, dict):
        raise IngestError(path, "unreadable", "glTF JSON is not an object")
    return gltf


def _gltf_check(src: _Source, budgets: Budgets, check: bool) -> None:  # noqa: C901  a flat list of structural checks
    """Validate the parts of the glTF JSON that size or locate data, read external buffers, and
    check the budgets (see module doc). Types are checked before use, so a hostile JSON gives an
    ``unreadable`` naming the field, never a TypeError."""
    path, gltf = src.path, src.gltf

    def fail(msg, reason="unreadable"):
        raise IngestError(path, reason, msg)

    def items(key):
        v = gltf.get(key, [])
        if not isinstance(v, list):
            fail(f"glTF '{key}' must be a list, got {type(v).__name__}")
        for i, item in enumerate(v):
            if not isinstance(item, dict):
                fail(f"glTF {key}[{i}] must be an object, got {type(item).__name__}")
        return v

    def index(v, n, where):
        if not isinstance(v, int) or isinstance(v, bool) or not 0 <= v < n:
            fail(f"glTF {where} = {str(v)[:40]!r} is not an index below {n}")
        return v

    def count(v, where):
        if not isinstance(v, int) or isinstance(v, bool) or v < 0:
            fail(f"glTF {where} = {str(v)[:40]!r} is not a non-negative integer")
        return v

    buffers = items("buffers")
    total = 0
    for b, buf in enumerate(buffers):
        total += count(buf.get("byteLength", 0), f"buffers[{b}].byteLength")
        uri = buf.get("uri")
        if uri is None:
            continue
        if not isinstance(uri, str):
            fail(f"glTF buffers[{b}].uri must be a string, got {type(uri).__name__}")
        if "base64," in uri:
            size = (len(uri) - uri.index("base64,") - 7) * 3 // 4
            if check and size > budgets.max_buffer_bytes:
                fail(f"buffers[{b}] data: URI decodes to ~{size} bytes, more than the limit of "
                     f"{budgets.max_buffer_bytes}", "too_large")
        elif uri.startswith("data:"):
            fail(f"buffers[{b}] is a data: URI without base64 encoding (not supported)")
        else:
            src.refs.append((uri, _read_reference(src, uri, f"buffers[{b}] {uri[:80]!r}",
                                                  budgets)))
    if check and total > budgets.max_buffer_bytes:
        fail(f"buffers declare {total} bytes, more than the limit of {budgets.max_buffer_bytes}",
             "too_large")
    if not check:
        return
    views = items("bufferViews")
    for v, view in enumerate(views):
        index(view.get("buffer"), len(buffers), f"bufferViews[{v}].buffer")
    accessors = items("accessors")
    for a, acc in enumerate(accessors):
        count(acc.get("count"), f"accessors[{a}].count")
        if "bufferView" in acc:
            index(acc["bufferView"], len(views), f"accessors[{a}].bufferView")
    materials = items("materials")
    if len(materials) > budgets.max_materials:
        fail(f"{len(materials)} materials declared, more than the limit of "
             f"{budgets.max_materials}", "too_large")
    meshes = items("meshes")
    mesh_tris, mesh_verts, loaded_verts = [], [], 0
    for m, mesh in enumerate(meshes):
        prims = mesh.get("primitives", [])
        if not isinstance(prims, list):
            fail(f"glTF meshes[{m}].primitives must be a list")
        tris = verts = 0
        for p, prim in enumerate(prims):
            where = f"meshes[{m}].primitives[{p}]"
            if not isinstance(prim, dict) or not isinstance(prim.get("attributes", {}), dict):
                fail(f"glTF {where} must be an object with an 'attributes' object")
            for name, acc in prim.get("attributes", {}).items():
                index(acc, len(accessors), f"{where}.attributes.{name}")
            if "material" in prim:
                index(prim["material"], len(materials), f"{where}.material")
            mode = prim.get("mode", _GL_TRIANGLES)
            if not isinstance(mode, int) or isinstance(mode, bool) or not 0 <= mode <= 6:
                fail(f"glTF {where}.mode = {str(mode)[:40]!r} is not a primitive mode (0-6)")
            pos = prim.get("attributes", {}).get("POSITION")
            n_pos = accessors[pos]["count"] if pos is not None else 0
            n = n_pos
            if "indices" in prim:
                n = accessors[index(prim["indices"], len(accessors), f"{where}.indices")]["count"]
            tris += n // 3 if mode == _GL_TRIANGLES else max(n - 2, 0) if mode in (5, 6) else 0
            verts += n_pos
        mesh_tris.append(tris)
        mesh_verts.append(verts)
        loaded_verts += verts
    instances = _gltf_instances(path, gltf, items("nodes"), len(meshes), budgets, index, fail)
    n_inst = sum(instances)
    drawn_tris = sum(k * t for k, t in zip(instances, mesh_tris))
    drawn_verts = sum(k * v for k, v in zip(instances, mesh_verts))
    for what, value, limit in (("instances of meshes", n_inst, budgets.max_instances),
                               ("triangles drawn", drawn_tris, budgets.max_triangles),
                               ("vertices drawn", max(drawn_verts, loaded_verts),
                                budgets.max_vertices)):
        if value > limit:
            fail(f"{value} {what}, more than the limit of {limit}", "too_large")


def _gltf_instances(path, gltf, nodes, n_meshes, budgets, index, fail) -> list[int]:
    """How many times each mesh is drawn: nodes reachable from the scene (``scene``, else scene
    0; without scenes every root node), each node at most one parent, no cycles, depth limited."""
    parent = {}
    for n, node in enumerate(nodes):
        children = node.get("children", [])
        if not isinstance(children, list):
            fail(f"glTF nodes[{n}].children must be a list")
        for c in children:
            index(c, len(nodes), f"nodes[{n}].children")
            if c in parent or c == n:
                fail(f"glTF node {c} has two parents or is its own child (the node graph must be "
                     "a forest)")
            parent[c] = n
        if "mesh" in node:
            index(node["mesh"], n_meshes, f"nodes[{n}].mesh")
    scenes = gltf.get("scenes", [])
    if not isinstance(scenes, list) or not all(isinstance(s, dict) for s in scenes):
        fail("glTF 'scenes' must be a list of objects")
    if scenes:
        s = gltf.get("scene", 0)
        scene = scenes[index(s, len(scenes), "scene")]
        roots = scene.get("nodes", [])
        if not isinstance(roots, list):
            fail("glTF scene nodes must be a list")
        for r in roots:
            index(r, len(nodes), "scene nodes")
    else:
        roots = [n for n in range(len(nodes)) if n not in parent]
    state: dict[int, int] = {}              # cycle check: 1 = on the current walk up, 2 = done
    for n in range(len(nodes)):
        walk, x = [], n
        while x is not None and x not in state:
            state[x] = 1
            walk.append(x)
            x = parent.get(x)
        if x is not None and state[x] == 1:
            fail(f"glTF node {x} is its own ancestor (a cycle in the node graph)")
        for y in walk:
            state[y] = 2
    if not nodes:
        return [1] * n_meshes
    counts = [0] * n_meshes
    seen = set()
    stack = [(r, 1) for r in dict.fromkeys(roots)]
    while stack:
        n, depth = stack.pop()
        if n in seen:                       # a root listed again below another root
            continue
        seen.add(n)
        if depth > budgets.max_node_depth:
            fail(f"glTF node hierarchy deeper than {budgets.max_node_depth} levels", "too_large")
        node = nodes[n]
        if "mesh" in node:
            counts[node["mesh"]] += 1
        stack.extend((c, depth + 1) for c in node.get("children", []))
    return counts


def _obj_check(src: _Source, budgets: Budgets, check: bool) -> None:
    """OBJ: ``mtllib`` files (read if safe, else a note), line-count budgets."""
    raw = src.raw
    for m in re.finditer(rb"(?m)^[ \t]*mtllib[ \t]+([^\r\n]+)", raw):
        name = m.group(1).decode("utf-8", "replace").strip()
        target, why = _resolve_inside(src.path, name)
        if target is None:
            src.notes.append(f"mtllib not read: {why}; materials named after 'usemtl' with "
                             "default properties")
            src.stand_ins[name] = _usemtl_stand_in(raw)
            continue
        if not target.exists():
            src.notes.append(f"mtllib {name[:80]!r} not found: materials named after 'usemtl' "
                             "with default properties")
            src.stand_ins[name] = _usemtl_stand_in(raw)
            continue
        try:
            data = _read_file(target, min(budgets.max_file_bytes, src.ref_budget), src.path,
                              what=f"mtllib {name[:80]!r}")
        except IngestError as e:
            if e.reason == "too_large":
                raise
            src.notes.append(f"mtllib not read: {e.message}; materials named after 'usemtl' "
                             "with default properties")
            src.stand_ins[name] = _usemtl_stand_in(raw)
            continue
        src.ref_budget -= len(data)
        src.refs.append((name, data))
    if check:
        n_v = len(re.findall(rb"(?m)^[ \t]*v[ \t]", raw))
        n_f = len(re.findall(rb"(?m)^[ \t]*f[ \t]", raw))
        for what, value, limit in (("vertex lines", n_v, budgets.max_vertices),
                                   ("face lines", n_f, budgets.max_triangles)):
            if value > limit:
                raise IngestError(src.path, "too_large",
                                  f"{value} {what}, more than the limit of {limit}")


def _usemtl_stand_in(raw: bytes) -> bytes:
    """An MTL naming every ``usemtl`` material of the OBJ (first use order), default properties:
    served instead of a missing or refused ``mtllib`` so material identity survives."""
    names = re.findall(rb"(?m)^[ \t]*usemtl[ \t]+([^\r\n]+)", raw)
    return b"".join(b"newmtl " + n.strip() + b"\n" for n in dict.fromkeys(names))


def _header_check(src: _Source, budgets: Budgets) -> None:
    """PLY / OFF / STL: counts from the header checked against the budgets and the file size."""
    path, raw = src.path, src.raw

    def over(what, value, limit):
        if value > limit:
            raise IngestError(path, "too_large", f"header declares {value} {what}, more than "
                                                 f"the limit of {limit}")

    if src.fmt == "stl":
        if len(raw) >= 84:
            n = struct.unpack_from("<I", raw, 80)[0]
            if 84 + 50 * n == len(raw):                     # binary STL (may start with 'solid')
                over("triangles", n, budgets.max_triangles)
                return
        if raw.lstrip()[:5].lower() == b"solid":
            over("triangles ('facet' lines)", raw.count(b"facet normal"), budgets.max_triangles)
            return
        n = struct.unpack_from("<I", raw, 80)[0] if len(raw) >= 84 else None
        raise IngestError(path, "unreadable",
                          "not an STL file: no ASCII 'solid' header, and as binary STL the "
                          + (f"header's {n} triangles need {84 + 50 * n} bytes but the file has "
                             f"{len(raw)}" if n is not None else f"file is {len(raw)} bytes, "
                                                                 "shorter than its 84-byte header"))
    if src.fmt == "ply":
        end = raw.find(b"end_header", 0, 1 << 16)
        if not raw.startswith(b"ply") or end < 0:
            raise IngestError(path, "unreadable", "not a PLY file (no 'ply' magic or no "
                                                  "'end_header' in the first 64 KiB)")
        for line in raw[:end].decode("ascii", "replace").splitlines():
            parts = line.split()
            if len(parts) == 3 and parts[0] == "element":
                try:
                    n = int(parts[2])
                except ValueError:
                    raise IngestError(path, "unreadable", f"PLY header line {line!r} has no "
                                                          "integer count") from None
                if parts[1] == "vertex":
                    over("vertices", n, budgets.max_vertices)
                elif parts[1] == "face":
                    over("faces", n, budgets.max_triangles)
                elif n > budgets.max_vertices:
                    over(f"'{parts[1][:40]}' elements", n, budgets.max_vertices)
        return
    if src.fmt == "off":
        text = raw[:4096].decode("ascii", "replace")
        tokens = [t for ln in text.splitlines() for t in ln.split("#", 1)[0].split()]
        if not tokens or not tokens[0].endswith("OFF"):
            raise IngestError(path, "unreadable", "not an OFF file (no 'OFF' header)")
        counts = tokens[1:3] if tokens[0] == "OFF" else []
        try:
            nv, nf = (int(t) for t in counts)
        except ValueError:
            raise IngestError(path, "unreadable", "OFF header has no vertex and face counts"
                              ) from None
        over("vertices", nv, budgets.max_vertices)
        over("faces", nf, budgets.max_triangles)


class _Resolver:
    """What trimesh may read besides the model: the referenced files we already read (by the
    name the model uses), else (textures) a guarded read inside the model's folder, within what
    is left of ``Budgets.max_buffer_bytes``. Anything else is ``FileNotFoundError``."""

    def __init__(self, src: _Source, budgets: Budgets):
        self._src, self._budgets = src, budgets
        self._served: dict[str, bytes] = {}
        for name, data in src.refs + list(src.stand_ins.items()):
            self._served[name] = self._served[name.strip()] = data

    def get(self, name):
        if isinstance(name, str) and name in self._served:
            return self._served[name]
        name = str(name)
        # trimesh's own candidates, all inside the folder: as written, without leading '/', base name
        for cand in (name.strip(), name.strip().lstrip("/"), os.path.split(name)[-1]):
            target, _ = _resolve_inside(self._src.path, cand)
            if target is None or not target.exists():
                continue
            try:
                data = _read_file(target, min(self._budgets.max_file_bytes, self._src.ref_budget),
                                  self._src.path, what="texture")
            except IngestError as e:
                self._src.notes.append(f"{name[:80]!r} not read: {e.message}")
                raise FileNotFoundError(name) from None
            self._src.ref_budget -= len(data)
            self._served[name] = data
            return data
        raise FileNotFoundError(name)

    __getitem__ = get

    def namespaced(self, namespace):
        return self

    def keys(self):
        return iter(())

    def write(self, name, data):
        raise PermissionError("ingest never writes")


def _check_compression(path: Path, gltf: dict, report: IngestReport) -> bool:
    """Reject compression we cannot decode; return whether the file uses Draco."""
    used = set()
    for key in ("extensionsUsed", "extensionsRequired"):
        v = gltf.get(key, [])
        used |= {x for x in v if isinstance(x, str)} if isinstance(v, list) else set()
    for mesh in gltf.get("meshes", []):
        for prim in mesh.get("primitives", []):
            ext = prim.get("extensions", {})
            used |= set(ext) if isinstance(ext, dict) else set()
    for name in MESHOPT:
        if name in used:
            raise IngestError(path, "unsupported_compression", f"{name} is not supported")
    if DRACO in used:
        try:
            import DracoPy  # noqa: F401
        except ImportError:
            raise IngestError(path, "unsupported_compression",
                              f"{DRACO} needs DracoPy, which is not installed") from None
        report.notes.append("draco decoded")
        return True
    return False


def _trimesh_scene(path: Path, src: _Source, budgets: Budgets):
    """trimesh's scene of the bytes we read; it reads nothing itself (see ``_Resolver``)."""
    import trimesh
    kwargs = {"skip_materials": True} if src.fmt in ("glb", "gltf") else {}
    try:
        with np.errstate(all="ignore"):         # extreme scales: checked after flattening
            scene = trimesh.load(io.BytesIO(src.raw), file_type=src.fmt, force="scene",
                                 process=False, resolver=_Resolver(src, budgets), **kwargs)
    except MemoryError:
        raise
    except RecursionError:
        raise IngestError(path, "unreadable", "trimesh could not read it: nesting too deep"
                          ) from None
    except Exception as e:  # noqa: BLE001 - any reader failure is an unreadable file
        raise IngestError(path, "unreadable",
                          f"trimesh could not read it: {describe_exception(e)}" +
                          (f" ({'; '.join(src.notes)})" if src.notes else "")) from None
    return scene


# ----------------------------------------------------------------------------- flattening

def _flatten(path: Path, scene, gltf: dict | None, draco: bool = False,
             budgets: Budgets = Budgets(), notes: list[str] | None = None):
    """Draw every (node, geometry) pair: float64 vertices, faces, face material/node, materials.
    The running triangle / vertex / instance totals are checked against ``budgets`` before each
    draw (the header checks cannot see everything, e.g. OBJ polygons or trimesh's instancing).
    Geometries without triangles (glTF POINTS, LINES, LINE_LOOP, LINE_STRIP primitives, OBJ
    lines: wireframe helpers) are skipped; one line in ``notes`` counts them by kind."""
    import trimesh
    geometries = scene.geometry
    if notes is not None:
        skipped = _skipped_primitives(gltf, geometries)
        if skipped:
            notes.append(skipped)
    n_tris = n_verts = 0
    prim_material = _gltf_primitive_materials(gltf, geometries) if gltf is not None else None

    keys: dict = {}          # material identity -> provisional index
    provisional: list[Material] = []
    sort_keys: list = []
    verts, tris, fmat, fnode, node_names = [], [], [], [], []
    offset = 0
    for node in scene.graph.nodes_geometry:
        with np.errstate(all="ignore"):
            transform, geom_name = scene.graph[node]
        geom = geometries[geom_name]
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            continue
        n_tris += len(geom.faces)
        n_verts += len(geom.vertices)
        for what, value, limit in (("triangles drawn", n_tris, budgets.max_triangles),
                                   ("vertices drawn", n_verts, budgets.max_vertices),
                                   ("instances drawn", len(node_names) + 1, budgets.max_instances)):
            if value > limit:
                raise IngestError(path, "too_large", f"more than {limit} {what} (limit)")
        v = np.asarray(geom.vertices, dtype=np.float64)
        f = np.asarray(geom.faces, dtype=np.int64)
        if draco and v.size and not v.any():
            raise IngestError(path, "unsupported_compression",
                              f"Draco primitive {geom_name!r} decoded to placeholder zeros")
        if f.min() < 0 or f.max() >= len(v):
            raise IngestError(path, "unreadable", f"geometry {geom_name!r} has out-of-range face indices")
        transform = np.asarray(transform, dtype=np.float64)
        with np.errstate(all="ignore"):                       # non-finite input is rejected later
            finite_in = np.isfinite(v).all()
            v = v @ transform[:3, :3].T + transform[:3, 3]
            if finite_in and np.isfinite(transform).all() and not np.isfinite(v).all():
                raise IngestError(path, "non_finite",
                                  f"node {str(node)[:80]!r}'s transform (scale up to "
                                  f"{np.abs(transform[:3, :3]).max():.3g}) takes coordinates past "
                                  "the float64 range")
        if np.linalg.slogdet(transform[:3, :3])[0] < 0:     # the sign survives 1e+-200 scales
            f = f[:, ::-1]
        if prim_material is not None:
            raw_index = prim_material[geom_name]
            key = ("gltf", raw_index)
            sort_key = (0, raw_index) if raw_index >= 0 else (1, 0)
        else:
            mat = getattr(geom.visual, "material", None)
            key = ("object", id(mat)) if mat is not None else ("default",)
            sort_key = (0, len(keys))
        if key not in keys:
            keys[key] = len(provisional)
            provisional.append(_material_for(key, gltf, geom))
            sort_keys.append(sort_key)
        verts.append(v)
        tris.append(f + offset)
        fmat.append(np.full(len(f), keys[key], np.int64))
        fnode.append(np.full(len(f), len(node_names), np.int64))
        node_names.append(node_stem(node))          # trimesh's random suffix dropped
        offset += len(v)
    if not tris:
        return (np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int64),
                np.zeros(0, np.int64), [], [])
    order = sorted(range(len(provisional)), key=lambda i: sort_keys[i])
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    materials = [provisional[i] for i in order]
    return (np.concatenate(verts), np.concatenate(tris), rank[np.concatenate(fmat)],
            np.concatenate(fnode), node_names, materials)


_PRIMITIVE_KINDS = {0: "points", 1: "lines", 2: "line loop", 3: "line strip", 6: "triangle fan"}


def _skipped_primitives(gltf: dict | None, geometries) -> str:
    """A note counting the primitives (glTF: by mode, as declared) or geometries (other formats:
    by trimesh class) that give no triangles and are skipped; '' when there are none. Kinds are
    listed in glTF mode order."""
    import trimesh
    counts: dict[str, int] = {}
    if gltf is not None:
        meshes = gltf.get("meshes", [])
        for m in meshes if isinstance(meshes, list) else []:
            prims = m.get("primitives", []) if isinstance(m, dict) else []
            for p in prims if isinstance(prims, list) else []:
                mode = p.get("mode", _GL_TRIANGLES) if isinstance(p, dict) else _GL_TRIANGLES
                if mode in _PRIMITIVE_KINDS:
                    counts[_PRIMITIVE_KINDS[mode]] = counts.get(_PRIMITIVE_KINDS[mode], 0) + 1
        order = list(_PRIMITIVE_KINDS.values())
    else:
        for geom in geometries.values():
            if not isinstance(geom, trimesh.Trimesh):
                kind = "points" if isinstance(geom, trimesh.PointCloud) else "lines"
                counts[kind] = counts.get(kind, 0) + 1
        order = ["points", "lines"]
    if not counts:
        return ""
    what = ", ".join(f"{counts[k]} {k}" for k in order if k in counts)
    return f"skipped non-triangle primitives ({what}): not drawn, not labelled"


def _gltf_primitive_materials(gltf: dict, geometries) -> dict | None:
    """Map trimesh geometry name -> glTF material index (-1 = none), or None if unmatched.

    trimesh creates one geometry per primitive it understands (points, lines, triangles,
    strips), in mesh then primitive order; the match is verified by count and material name.
    """
    prims = [p for m in gltf.get("meshes", []) for p in m.get("primitives", [])
             if p.get("mode", _GL_TRIANGLES) in _TRIMESH_PRIMITIVE_MODES]
    names = list(geometries.keys())
    if len(prims) != len(names):
        return None
    table = gltf.get("materials", [])
    result = {}
    for prim, name in zip(prims, names):
        index = prim.get("material", -1)
        if not isinstance(index, int) or index >= len(table):
            return None
        # points and lines (trimesh's PointCloud / Path3D) may have no visual at all
        mat = getattr(getattr(geometries[name], "visual", None), "material", None)
        expected = table[index].get("name") if index >= 0 else None
        if index >= 0 and mat is not None and expected is not None and mat.name != expected:
            return None
        result[name] = index
    return result


def _material_for(key: tuple, gltf: dict | None, geom) -> Material:
    if key[0] == "gltf":
        return replace(GLTF_DEFAULT) if key[1] < 0 else _gltf_material(gltf["materials"][key[1]], key[1])
    mat = getattr(geom.visual, "material", None)
    if mat is None:
        return Material("default")
    kwargs = getattr(mat, "kwargs", None)
    if kwargs is not None:                       # trimesh SimpleMaterial (OBJ MTL)
        return _mtl_material(mat, kwargs)
    return _pbr_material(mat)


def _gltf_material(m: dict, index: int) -> Material:
    """Material fields from the glTF JSON; a value of the wrong type or length takes the glTF
    default (hostile files must not stop the load over a colour)."""
    def obj(d, key):
        v = d.get(key, {}) if isinstance(d, dict) else {}
        return v if isinstance(v, dict) else {}

    pbr, ext = obj(m, "pbrMetallicRoughness"), obj(m, "extensions")
    textured = "baseColorTexture" in pbr or "diffuseTexture" in obj(
        ext, "KHR_materials_pbrSpecularGlossiness")
    return Material(
        name=_text(m.get("name", f"material_{index}")),
        base_color=_floats(pbr.get("baseColorFactor"), 4, (1.0, 1.0, 1.0, 1.0), exact=True),
        alpha_mode=_text(m.get("alphaMode", "OPAQUE")),
        metallic=_floats(pbr.get("metallicFactor"), 1, (1.0,), exact=True)[0],
        roughness=_floats(pbr.get("roughnessFactor"), 1, (1.0,), exact=True)[0],
        emissive=_floats(m.get("emissiveFactor"), 3, (0.0, 0.0, 0.0), exact=True),
        transmission=_floats(obj(ext, "KHR_materials_transmission").get("transmissionFactor"),
                             1, (0.0,), exact=True)[0],
        has_texture=bool(textured),
    )


def _text(value) -> str:
    """``str(value)`` as valid UTF-8 (lone surrogates -> ``\\udcXX``), at most MAX_NAME_CHARS."""
    text = value if isinstance(value, str) else str(value)
    return text.encode("utf-8", "backslashreplace").decode("utf-8")[:MAX_NAME_CHARS]


def _floats(value, n: int, default: tuple, exact: bool = False) -> tuple:
    """``n`` floats from a number or a list (one value repeats), else ``default``. ``exact``: the
    list must have exactly ``n`` finite numbers (glTF); otherwise extra values are cut (MTL)."""
    if value is None or isinstance(value, (bool, bytes)):
        return default
    try:
        vals = [float(x) for x in (value if isinstance(value, (list, tuple, np.ndarray)) else [value])]
    except (TypeError, ValueError, OverflowError):
        return default
    if exact:
        return tuple(vals) if len(vals) == n and all(np.isfinite(vals)) else default
    if len(vals) == 1:
        vals = vals * n
    return tuple(vals[:n]) if len(vals) >= n else default


def _mtl_material(mat, kwargs: dict) -> Material:
    rgb = _floats(kwargs.get("kd"), 3, (0.8, 0.8, 0.8))
    alpha = 1.0
    if "d" in kwargs:
        alpha = _floats(kwargs["d"], 1, (1.0,))[0]
    elif "tr" in kwargs:
        alpha = 1.0 - _floats(kwargs["tr"], 1, (0.0,))[0]
    return Material(
        name=_text(mat.name), base_color=(*rgb, alpha), alpha_mode="BLEND" if alpha < 1.0 else "OPAQUE",
        metallic=0.0, roughness=1.0, emissive=_floats(kwargs.get("ke"), 3, (0.0, 0.0, 0.0)),
        transmission=0.0, has_texture=getattr(mat, "image", None) is not None)


def _pbr_material(mat) -> Material:
    color = getattr(mat, "baseColorFactor", None)
    if color is None:
        rgba = (1.0, 1.0, 1.0, 1.0)
    else:
        color = np.asarray(color)
        rgba = tuple(float(x) for x in (color / 255.0 if color.dtype.kind in "ui" else color))
    emissive = getattr(mat, "emissiveFactor", None)
    return Material(
        name=_text(mat.name), base_color=rgba, alpha_mode=_text(getattr(mat, "alphaMode", None) or "OPAQUE"),
        metallic=float(_or(getattr(mat, "metallicFactor", None), 1.0)),
        roughness=float(_or(getattr(mat, "roughnessFactor", None), 1.0)),
        emissive=tuple(float(x) for x in emissive) if emissive is not None else (0.0, 0.0, 0.0),
        has_texture=getattr(mat, "baseColorTexture", None) is not None)


def _or(value, default):
    return default if value is None else value


def _extent(path: Path, vertices: np.ndarray) -> tuple[np.ndarray, float]:
    """(bounding-box centre, diagonal) in float64, robust to extreme scales (see module doc)."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    with np.errstate(over="ignore", invalid="ignore", under="ignore"):
        extent = hi - lo
        centre = (lo + hi) / 2.0
        if not np.isfinite(centre).all():
            centre = lo / 2.0 + hi / 2.0
        diag = _fixed_norm(extent)
        top = float(np.max(extent))
        if np.isfinite(top) and top > 0.0 and not (np.isfinite(diag) and diag > 0.0):
            diag = top * _fixed_norm(extent / top)
    if not np.isfinite(extent).all() or not np.isfinite(diag):
        raise IngestError(path, "non_finite",
                          f"the model's extent overflows float64 (coordinates from "
                          f"{lo.min():.3g} to {hi.max():.3g})")
    if diag <= 0.0:
        raise IngestError(path, "empty", f"mesh has zero extent (bbox diagonal {diag})")
    return centre, diag


def _fixed_norm(v: np.ndarray) -> float:
    """Euclidean length with the squares summed smallest first: the same bits for any order
    or signs of the components (a re-posed file gives the same diagonal)."""
    return float(np.sqrt(np.sort(v * v).sum()))


# ----------------------------------------------------------------------------- cleaning

def _first_of_each(corners: np.ndarray, material: np.ndarray) -> np.ndarray:
    """Row indices of the first row of each distinct (corner 0, 1, 2, material) key, as
    ``np.unique(key, axis=0, return_index=True)[1]`` gives them (in key order). Keys of values
    below 2^32 are packed into two uint64 words and sorted by a stable lexsort (~6x faster on
    a 50k-face mesh); larger ones go through np.unique."""
    if len(corners) == 0 or max(int(corners.max()), int(material.max())) >= 2**32 \
            or min(int(corners.min()), int(material.min())) < 0:
        key = np.concatenate([corners, material[:, None]], axis=1)
        return np.unique(key, axis=0, return_index=True)[1]
    c = corners.astype(np.uint64)
    hi = (c[:, 0] << np.uint64(32)) | c[:, 1]
    lo = (c[:, 2] << np.uint64(32)) | material.astype(np.uint64)
    order = np.lexsort((lo, hi))            # stable: equal keys keep their row order
    hi, lo = hi[order], lo[order]
    start = np.ones(len(order), bool)
    start[1:] = (hi[1:] != hi[:-1]) | (lo[1:] != lo[:-1])
    return order[start]


def _drop_ground_plates(vertices: np.ndarray, faces: np.ndarray, face_material: np.ndarray,
                        face_node: np.ndarray, materials: list[Material], report: IngestReport):
    """Cleaning step (4): the faces of ground plates (``ground.ground_plates``: a baked shadow or
    ground sheet spanning the model) left out, with a note naming each, then the vertices only
    they used (not counted as unreferenced: the file used them). Order-preserving, as
    ``_clean``."""
    plates = ground_plates(vertices, faces, face_material)
    if not plates:
        return vertices, faces, face_material, face_node
    drop = np.isin(face_material, plates)
    for m in plates:
        report.notes.append(f"material {materials[m].name!r} left out: a flat plate spanning the "
                            f"whole model ({int((face_material == m).sum())} faces; a baked "
                            "shadow or ground sheet, not part of the vehicle)")
    vertices, faces, _ = _referenced_only(vertices, faces[~drop])
    return vertices, faces, face_material[~drop], face_node[~drop]


def _referenced_only(vertices: np.ndarray, faces: np.ndarray):
    """(the vertices ``faces`` use, in order; ``faces`` renumbered onto them; how many were
    dropped)."""
    referenced = np.zeros(len(vertices), bool)
    referenced[faces.ravel()] = True
    new_index = np.cumsum(referenced) - 1
    return vertices[referenced], new_index[faces], int(len(vertices) - referenced.sum())


def _clean(vertices: np.ndarray, faces: np.ndarray, face_material: np.ndarray,
           face_node: np.ndarray, report: IngestReport):
    """Remove zero-area faces, then same-material duplicate faces, then unreferenced vertices.

    Order-preserving: kept faces and vertices keep their relative order. Counts go to ``report``.
    """
    top = float(np.abs(vertices).max()) if vertices.size else 0.0
    scale = float(np.ldexp(1.0, -np.frexp(top)[1])) if 0.0 < top < np.inf else 1.0
    scaled = vertices * scale                 # exact: a power of two (see module doc)
    a, b, c = scaled[faces[:, 0]], scaled[faces[:, 1]], scaled[faces[:, 2]]
    repeated = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])
    zero = repeated | ~np.cross(b - a, c - a).any(axis=1)
    keep = ~zero
    report.zero_area_faces = int(zero.sum())

    idx = np.flatnonzero(keep)
    first = _first_of_each(np.sort(faces[idx], axis=1), face_material[idx])
    unique_mask = np.zeros(idx.size, bool)
    unique_mask[first] = True
    report.duplicate_faces = int(idx.size - first.size)
    keep[idx[~unique_mask]] = False

    vertices, faces, report.unreferenced_vertices = _referenced_only(vertices, faces[keep])
    return vertices, faces, face_material[keep], face_node[keep]
