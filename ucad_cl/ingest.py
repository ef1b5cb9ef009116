"""Mesh ingest: one CAD file -> one :class:`~ucad_cl.artifacts.Mesh` in the canonical frame.

Formats: GLB, glTF (+ external .bin), OBJ+MTL, PLY, OFF, STL, read with trimesh (``process=False``,
so vertices are never merged or reordered by the reader).

Conventions and decisions (see also ``ucad_cl/artifacts.py``):

* **Scene graph.** Every (node, geometry) pair of ``scene.graph.nodes_geometry`` is drawn with the
  node's world transform (float64), in that order (trimesh's traversal order: deterministic, the
  same in every process, not necessarily the file's node order); a geometry instanced on several
  nodes is drawn at each.
  Faces of a node whose transform mirrors (det < 0) get their winding flipped so that faces keep
  facing outward. ``face_node`` indexes ``node_names`` (trimesh's unique node names).
* **Up axis / units.** glTF is +Y up (spec); OBJ, PLY, OFF and STL carry no convention. The file
  frame is the flattened scene frame (file units); which way is up and front is found by the
  orientation stage (below), not assumed.
* **Canonical frame.** ``c`` = centre of the axis-aligned bounding box of the returned vertices,
  ``d`` = its diagonal length (squares summed smallest first, so a re-posed file gives the same
  bits); ``(file - c) / d`` in float64, then the orientation stage (``ucad_cl.orient``,
  ``orientation=``: ``"auto"`` by default) turns it into the canonical vehicle frame and
  folds its rotation and placement into ``file_to_norm``; ``orientation="file"`` keeps
  ``file_to_norm = [[I/d, -c/d], [0, 1]]``. A mesh whose extent is zero is rejected (``empty``).
* **Materials.** One material index per face, built per geometry (never via trimesh
  concatenate). Material identity = the file's material: for glTF the material index of the
  primitive (two glTF materials with the same name stay two materials), otherwise the material
  object trimesh shares between geometries. Table order: glTF material index order; other formats
  first use in draw order. Only materials used by at least one drawn face are kept. glTF
  properties come from the raw glTF JSON (glTF defaults: base colour 1, metallic 1, roughness 1),
  including ``KHR_materials_transmission``; primitives without a material get the glTF default
  material named ``"default"``. OBJ: ``Kd`` -> RGB, ``d`` (or ``1 - Tr``) -> alpha, ``Ke`` ->
  emissive; alpha < 1 gives alpha mode ``BLEND``. PLY/OFF/STL: one ``"default"`` material.
* **Cleaning** (``clean=True``), done in NumPy on the flattened float64 file-frame mesh, in this
  order: (1) zero-area faces: a repeated vertex index or a cross product that is exactly 0;
  (2) duplicate faces: same vertex-index set (any order or winding) AND same material, the
  lowest face index is kept; faces with different materials are never duplicates (coplanar
  duplicates are a renderer hard case, not ours to hide); (3) unreferenced vertices (including
  those orphaned by (1) and (2)). Kept faces and vertices keep their relative order, so
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
* **sha256** of the file bytes; for .gltf the .gltf bytes followed by every external buffer in
  ``buffers`` order; for .obj the .obj bytes followed by its ``mtllib`` files (materials live
  there).
* **Isolation.** ``load_mesh_isolated`` runs the loader in a fresh ``python -c`` child; it costs
  about 0.7-1 s per file (interpreter, NumPy and trimesh imports) on top of the load.
* **Errors** are :class:`IngestError` (a ``ValueError``) with ``.path``, ``.reason`` (one of
  :data:`REASONS`) and a message naming the file.
"""
from __future__ import annotations

import hashlib
import json
import os
import pickle
import signal
import struct
import subprocess
import sys
from dataclasses import replace
from multiprocessing.connection import Connection
from pathlib import Path
from urllib.parse import unquote

import numpy as np

from .artifacts import IngestReport, Material, Mesh

SUPPORTED_SUFFIXES = (".glb", ".gltf", ".obj", ".ply", ".off", ".stl")
REASONS = ("unreadable", "empty", "non_finite", "unsupported_compression", "unsupported_format",
           "loader_crashed", "loader_timeout")
DRACO = "KHR_draco_mesh_compression"
MESHOPT = ("EXT_meshopt_compression", "KHR_meshopt_compression")
MAX_MATERIALS = 65534          # material id = index + 1 must fit uint16 (0 = background)
GLTF_DEFAULT = Material("default", (1.0, 1.0, 1.0, 1.0), "OPAQUE", 1.0, 1.0)
_GL_TRIANGLES = 4
_TRIMESH_PRIMITIVE_MODES = (0, 1, 4, 5)   # modes trimesh turns into a geometry (points, lines, tris)


class IngestError(ValueError):
    """A file that cannot become a Mesh. ``str`` names the file, the problem and the reason code."""

    def __init__(self, path: str | os.PathLike, reason: str, message: str):
        if reason not in REASONS:
            raise ValueError(f"unknown ingest reason code {reason!r}")
        self.path, self.reason, self.message = str(path), reason, message
        super().__init__(f"{self.path}: {message} [{reason}]")

    def __reduce__(self):
        return (IngestError, (self.path, self.reason, self.message))


def load_mesh(path: str | os.PathLike, *, clean: bool = True, orientation="auto",
              overrides=None) -> Mesh:
    """Load a CAD file into a canonical-frame Mesh with one material index per face.

    orientation: ``"auto"`` (estimate the vehicle frame), ``"file"`` (trust the file's +Y up)
    or ``"UP,FRONT"`` / ``(up, front)`` signed file axes (see ``ucad_cl.orient``); None skips
    the stage (the bounding-box normalisation only; ``mesh.orientation`` stays None, for a
    caller that orients it itself). overrides: an ``orient.OrientationOverrides`` whose entry
    for this file (by path or sha256) replaces ``orientation``."""
    path = Path(path)
    raw = _read_bytes(path)
    suffix = path.suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES:
        raise IngestError(path, "unsupported_format",
                          f"unsupported file extension {path.suffix!r} "
                          f"(supported: {', '.join(SUPPORTED_SUFFIXES)})")
    if len(raw) == 0:
        raise IngestError(path, "empty", "file is empty (0 bytes)")
    report = IngestReport()
    gltf = _gltf_json(path, raw) if suffix in (".glb", ".gltf") else None
    draco = _check_compression(path, gltf, report) if gltf is not None else False
    sha = _sha256(path, raw, gltf)

    scene = _trimesh_scene(path)
    vertices, faces, face_material, face_node, node_names, materials = _flatten(path, scene, gltf,
                                                                                draco)
    if faces.shape[0] == 0:
        raise IngestError(path, "empty", "no triangles in the file")
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise IngestError(path, "non_finite",
                          f"{int(bad.sum())} vertices have NaN/inf coordinates "
                          f"(first: vertex {int(np.argmax(bad))})")

    report.faces_in = int(faces.shape[0])
    if clean:
        vertices, faces, face_material, face_node = _clean(vertices, faces, face_material,
                                                           face_node, report)
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

    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    centre = (lo + hi) / 2.0
    diag = float(np.sqrt(np.sort((hi - lo) ** 2).sum()))       # same bits for any axis order
    if not np.isfinite(diag) or diag <= 0.0:
        raise IngestError(path, "empty", f"mesh has zero extent (bbox diagonal {diag})")
    file_to_norm = np.eye(4)
    file_to_norm[:3, :3] /= diag
    file_to_norm[:3, 3] = -centre / diag
    mesh = Mesh(path=str(path), sha256=sha, vertices=(vertices - centre) / diag,
                faces=faces.astype(np.uint32), face_material=face_material.astype(np.uint16),
                materials=materials, file_to_norm=file_to_norm,
                face_node=face_node.astype(np.int32), node_names=node_names, report=report)
    if orientation is None:
        return mesh
    from .orient import orient_mesh

    if overrides is not None:
        orientation = overrides.mode_for(path, sha, orientation)
    return orient_mesh(mesh, orientation)


def file_sha256(path: str | os.PathLike) -> str:
    """The content key ``load_mesh`` stores in ``Mesh.sha256``, without loading the geometry."""
    path = Path(path)
    raw = _read_bytes(path)
    return _sha256(path, raw, _gltf_json(path, raw) if path.suffix.lower() == ".gltf" else None)


def load_mesh_isolated(path: str | os.PathLike, *, timeout: float = 120.0, clean: bool = True,
                       loader=None) -> Mesh:
    """``load_mesh`` in a fresh child interpreter, so a native crash or hang cannot kill us.

    The child is ``python -c`` (not multiprocessing 'spawn', which re-runs the caller's
    ``__main__`` and breaks scripts without a main guard); arguments go in on stdin, the pickled
    result comes back on a dedicated pipe (native libraries may write to stdout). A child that
    dies without answering raises ``IngestError`` reason ``loader_crashed`` (the message names
    the signal or exit code); one still running after ``timeout`` seconds is killed and raises
    reason ``loader_timeout``. ``loader`` (a picklable module-level function
    ``loader(path, clean=...) -> Mesh``) replaces ``load_mesh``, for tests.
    """
    if not timeout > 0:
        raise ValueError(f"timeout must be > 0 seconds, got {timeout}")
    read_fd, write_fd = os.pipe()
    code = ("import pickle, sys; sys.path[:0] = pickle.load(sys.stdin.buffer); "
            "from ucad_cl.ingest import _isolated_child; _isolated_child(int(sys.argv[1]))")
    try:
        proc = subprocess.Popen([sys.executable, "-c", code, str(write_fd)], pass_fds=(write_fd,),
                                stdin=subprocess.PIPE, stdout=subprocess.DEVNULL)
    finally:
        os.close(write_fd)
    conn = Connection(read_fd, writable=False)
    try:
        try:
            proc.stdin.write(pickle.dumps([p for p in sys.path if isinstance(p, str)]))
            proc.stdin.write(pickle.dumps((str(path), clean, loader or load_mesh)))
            proc.stdin.close()
        except BrokenPipeError:
            pass                                    # the child died early: reported below
        if not conn.poll(timeout):
            proc.kill()
            proc.wait()
            raise IngestError(path, "loader_timeout",
                              f"loader did not finish within {timeout:g} s (killed)")
        try:
            kind, payload = conn.recv()
        except (EOFError, OSError):
            code = proc.wait()
            how = (f"killed by signal {signal.Signals(-code).name}" if code < 0
                   else f"exit code {code}")
            raise IngestError(path, "loader_crashed", f"loader process died ({how})") from None
    finally:
        conn.close()
        if proc.poll() is None:
            try:
                proc.wait(5.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    if kind == "ok":
        return payload
    if kind == "ingest_error":
        raise IngestError(*payload)
    raise IngestError(path, "unreadable", f"loader raised {payload}")


def _isolated_child(fd: int) -> None:
    """Child side of ``load_mesh_isolated``: read (path, clean, loader) on stdin, answer on fd."""
    conn = Connection(fd, readable=False)
    try:
        path, clean, loader = pickle.load(sys.stdin.buffer)
        result = ("ok", loader(path, clean=clean))
    except IngestError as e:
        result = ("ingest_error", (e.path, e.reason, e.message))
    except BaseException as e:  # noqa: BLE001 - everything goes back to the parent as text
        result = ("error", f"{type(e).__name__}: {e}")
    conn.send(result)
    conn.close()


# ----------------------------------------------------------------------------- file level

def _read_bytes(path: Path) -> bytes:
    if not path.exists():
        raise IngestError(path, "unreadable", "file not found")
    if not path.is_file():
        raise IngestError(path, "unreadable", "not a regular file")
    try:
        return path.read_bytes()
    except OSError as e:
        raise IngestError(path, "unreadable", f"cannot read file: {e}") from None


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
    if not isinstance(gltf, dict):
        raise IngestError(path, "unreadable", "glTF JSON is not an object")
    return gltf


def _check_compression(path: Path, gltf: dict, report: IngestReport) -> bool:
    """Reject compression we cannot decode; return whether the file uses Draco."""
    used = set(gltf.get("extensionsUsed", [])) | set(gltf.get("extensionsRequired", []))
    for mesh in gltf.get("meshes", []):
        for prim in mesh.get("primitives", []):
            used |= set(prim.get("extensions", {}))
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


def _sha256(path: Path, raw: bytes, gltf: dict | None) -> str:
    h = hashlib.sha256(raw)
    suffix = path.suffix.lower()
    extra: list[Path] = []
    if suffix == ".gltf":
        for buf in gltf.get("buffers", []):
            uri = buf.get("uri")
            if uri and not uri.startswith("data:"):
                extra.append(path.parent / unquote(uri))
    elif suffix == ".obj":
        for line in raw.decode("utf-8", "replace").splitlines():
            parts = line.strip().split(None, 1)
            if len(parts) == 2 and parts[0] == "mtllib" and (path.parent / parts[1]).is_file():
                extra.append(path.parent / parts[1])
    for p in extra:
        try:
            h.update(p.read_bytes())
        except OSError as e:
            raise IngestError(path, "unreadable", f"cannot read referenced file {p.name}: {e}") from None
    return h.hexdigest()


def _trimesh_scene(path: Path):
    import trimesh
    try:
        scene = trimesh.load(str(path), force="scene", process=False)
    except Exception as e:  # noqa: BLE001 - any reader failure is an unreadable file
        raise IngestError(path, "unreadable", f"trimesh could not read it: {type(e).__name__}: {e}") from None
    return scene


# ----------------------------------------------------------------------------- flattening

def _flatten(path: Path, scene, gltf: dict | None, draco: bool = False):
    """Draw every (node, geometry) pair: float64 vertices, faces, face material/node, materials."""
    import trimesh
    geometries = scene.geometry
    prim_material = _gltf_primitive_materials(gltf, geometries) if gltf is not None else None

    keys: dict = {}          # material identity -> provisional index
    provisional: list[Material] = []
    sort_keys: list = []
    verts, tris, fmat, fnode, node_names = [], [], [], [], []
    offset = 0
    for node in scene.graph.nodes_geometry:
        transform, geom_name = scene.graph[node]
        geom = geometries[geom_name]
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            continue
        v = np.asarray(geom.vertices, dtype=np.float64)
        f = np.asarray(geom.faces, dtype=np.int64)
        if draco and v.size and not v.any():
            raise IngestError(path, "unsupported_compression",
                              f"Draco primitive {geom_name!r} decoded to placeholder zeros")
        if f.min() < 0 or f.max() >= len(v):
            raise IngestError(path, "unreadable", f"geometry {geom_name!r} has out-of-range face indices")
        transform = np.asarray(transform, dtype=np.float64)
        with np.errstate(invalid="ignore", over="ignore"):     # non-finite input is rejected later
            v = v @ transform[:3, :3].T + transform[:3, 3]
        if np.linalg.det(transform[:3, :3]) < 0:
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
        node_names.append(str(node))
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
        mat = getattr(geometries[name].visual, "material", None)
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
    pbr = m.get("pbrMetallicRoughness", {})
    ext = m.get("extensions", {})
    textured = "baseColorTexture" in pbr or "diffuseTexture" in ext.get(
        "KHR_materials_pbrSpecularGlossiness", {})
    return Material(
        name=str(m.get("name", f"material_{index}")),
        base_color=tuple(float(x) for x in pbr.get("baseColorFactor", (1.0, 1.0, 1.0, 1.0))),
        alpha_mode=str(m.get("alphaMode", "OPAQUE")),
        metallic=float(pbr.get("metallicFactor", 1.0)),
        roughness=float(pbr.get("roughnessFactor", 1.0)),
        emissive=tuple(float(x) for x in m.get("emissiveFactor", (0.0, 0.0, 0.0))),
        transmission=float(ext.get("KHR_materials_transmission", {}).get("transmissionFactor", 0.0)),
        has_texture=bool(textured),
    )


def _floats(value, n: int, default: tuple) -> tuple:
    try:
        vals = [float(x) for x in (value if isinstance(value, (list, tuple, np.ndarray)) else [value])]
    except (TypeError, ValueError):
        return default
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
        name=str(mat.name), base_color=(*rgb, alpha), alpha_mode="BLEND" if alpha < 1.0 else "OPAQUE",
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
        name=str(mat.name), base_color=rgba, alpha_mode=str(getattr(mat, "alphaMode", None) or "OPAQUE"),
        metallic=float(_or(getattr(mat, "metallicFactor", None), 1.0)),
        roughness=float(_or(getattr(mat, "roughnessFactor", None), 1.0)),
        emissive=tuple(float(x) for x in emissive) if emissive is not None else (0.0, 0.0, 0.0),
        has_texture=getattr(mat, "baseColorTexture", None) is not None)


def _or(value, default):
    return default if value is None else value


# ----------------------------------------------------------------------------- cleaning

def _clean(vertices: np.ndarray, faces: np.ndarray, face_material: np.ndarray,
           face_node: np.ndarray, report: IngestReport):
    """Remove zero-area faces, then same-material duplicate faces, then unreferenced vertices.

    Order-preserving: kept faces and vertices keep their relative order. Counts go to ``report``.
    """
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    repeated = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])
    zero = repeated | ~np.cross(b - a, c - a).any(axis=1)
    keep = ~zero
    report.zero_area_faces = int(zero.sum())

    idx = np.flatnonzero(keep)
    key = np.concatenate([np.sort(faces[idx], axis=1), face_material[idx, None]], axis=1)
    _, first = np.unique(key, axis=0, return_index=True)   # first = lowest face index per key
    unique_mask = np.zeros(idx.size, bool)
    unique_mask[first] = True
    report.duplicate_faces = int(idx.size - first.size)
    keep[idx[~unique_mask]] = False

    faces, face_material, face_node = faces[keep], face_material[keep], face_node[keep]
    referenced = np.zeros(len(vertices), bool)
    referenced[faces.ravel()] = True
    report.unreferenced_vertices = int(len(vertices) - referenced.sum())
    new_index = np.cumsum(referenced) - 1
    return vertices[referenced], new_index[faces], face_material, face_node
