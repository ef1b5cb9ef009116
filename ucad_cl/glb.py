"""Write-back: a catalogued mesh as a GLB (glTF 2.0 binary) with each material's part.

``write_glb(path, mesh, parts)`` writes the ingested geometry (the same faces, materials and
material order as the catalogue's part table) as one glTF mesh with one primitive per material:

* **Frame.** ``frame="file"``: the file frame (the source's coordinates after its scene graph is
  flattened), recovered from the canonical vertices with ``inv(file_to_norm)``. Positions are
  float32 relative to the bounding-box centre, which goes into the node's ``translation``
  (float64 in JSON), so the float32 rounding is relative to the model's size (<= ~6e-8 of the
  bounding-box diagonal), not to its distance from the origin. ``frame="canonical"``: the
  catalogue's canonical frame (+Y up, centred, diagonal 1; docs/CONVENTIONS.md).
* **Parts.** Every glTF material keeps the source name and carries ``extras.ucad`` =
  ``{"part", "score", "iou", "decision", "index", "material_id"}`` (the catalogue's decision for
  it); every primitive carries ``extras.ucad.part`` too; the scene's ``extras.ucad`` names the
  mesh id, the frame and ``file_to_norm``.
* **Materials.** By default the source's factors as ingest recorded them (base colour, metallic,
  roughness, emission, alpha mode, transmission); textures and UVs are not carried (ingest keeps
  neither). ``part_materials=True``: UrbanCAD's part-level prior (``ucad_catalog.parts.
  PART_MATERIALS``: car paint, glass with KHR_materials_transmission, tyre rubber, alloy, chrome,
  lamp lens with emission, plate, interior) replaces each labelled material; 'other' and
  'unseen' keep the source's. ``donor``: {part: props} of another model (``donor_materials``):
  each part present there takes that material (the paper's material transfer); parts the donor
  lacks fall back to the prior (with ``part_materials``) or the source.

No normals are written (glTF viewers then use flat normals), so the geometry is exactly the
ingested triangles. Output bytes are deterministic for the same input.
"""
from __future__ import annotations

import json
import os
import struct
from pathlib import Path

import numpy as np

from ucad_catalog.parts import PART_MATERIALS

from .artifacts import Mesh

FRAMES = ("file", "canonical")
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_FLOAT, _UNSIGNED_INT = 5126, 5125
_TRIANGLES = 4


def write_glb(path: str | os.PathLike, mesh: Mesh, parts, *, frame: str = "file",
              part_materials: bool = False, donor: dict | None = None,
              mesh_id: str = "", fitted: dict | None = None) -> Path:
    """Write ``mesh`` with the part decisions ``parts`` (rows with ``index``, ``name``, ``part``,
    ``score``, ``iou``, ``decision``, ``props``: ``CatalogReader.parts``) to ``path`` (GLB).
    ``fitted``: {part: {"color_linear": [r, g, b], ...}} from ``ucad-index fit``: each material
    of such a part takes its part's prior with that base colour, and the fit's fields in
    ``extras.ucad.fit`` (implies ``part_materials``). ValueError when the table does not
    describe the mesh's materials."""
    if frame not in FRAMES:
        raise ValueError(f"frame must be one of {FRAMES}, got {frame!r}")
    rows = {int(r.index): r for r in parts}
    if sorted(rows) != list(range(len(mesh.materials))) or any(
            rows[k].name != m.name for k, m in enumerate(mesh.materials)):
        raise ValueError(f"{mesh.path}: the part table ({len(rows)} materials) does not match "
                         f"the mesh's {len(mesh.materials)} materials (names or order differ)")
    verts = np.asarray(mesh.vertices, np.float64)
    origin = np.zeros(3)
    if frame == "file":
        h = np.c_[verts, np.ones(len(verts))] @ np.linalg.inv(mesh.file_to_norm).T
        verts = h[:, :3] / h[:, 3:4]
        origin = (verts.min(axis=0) + verts.max(axis=0)) / 2.0
    local = (verts - origin).astype(np.float32)

    blob = bytearray()
    views, accessors, primitives, materials = [], [], [], []
    used_ext: set[str] = set()
    for k, src in enumerate(mesh.materials):
        row = rows[k]
        mat = _material(src.name, row, part_materials or bool(fitted), donor, fitted)
        used_ext |= set(mat.get("extensions", {}))
        materials.append(mat)
        faces = np.asarray(mesh.faces)[np.asarray(mesh.face_material) == k]
        if len(faces) == 0:
            continue
        uniq, inv = np.unique(faces.ravel(), return_inverse=True)
        pos = np.ascontiguousarray(local[uniq])
        idx = np.ascontiguousarray(inv.astype(np.uint32))
        a_pos = _add(blob, views, accessors, pos, _ARRAY_BUFFER, _FLOAT, "VEC3",
                     minmax=(pos.min(axis=0).tolist(), pos.max(axis=0).tolist()))
        a_idx = _add(blob, views, accessors, idx, _ELEMENT_ARRAY_BUFFER, _UNSIGNED_INT, "SCALAR")
        primitives.append({"attributes": {"POSITION": a_pos}, "indices": a_idx, "material": k,
                           "mode": _TRIANGLES, "extras": {"ucad": {"part": row.part}}})
    name = Path(mesh.path).name
    node = {"name": name, "mesh": 0}
    if np.any(origin != 0):
        node["translation"] = [float(x) for x in origin]
    gltf = {
        "asset": {"version": "2.0", "generator": "ucad-cl export-glb"},
        "scene": 0,
        "scenes": [{"name": name, "nodes": [0], "extras": {"ucad": {
            "mesh_id": mesh_id or mesh.sha256, "frame": frame,
            "file_to_norm": np.asarray(mesh.file_to_norm, np.float64).tolist(),
            "part_materials": bool(part_materials or fitted), "transfer": bool(donor),
            "fit": bool(fitted)}}}],
        "nodes": [node],
        "meshes": [{"name": name, "primitives": primitives}],
        "materials": materials,
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": len(blob)}],
    }
    if used_ext:
        gltf["extensionsUsed"] = sorted(used_ext)
    data = _glb_bytes(gltf, bytes(blob))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def donor_materials(parts) -> dict[str, dict]:
    """{part: props} of a model's part table: per part, the material with the most visible
    pixels (ties: the lower material index), for ``write_glb(donor=...)``."""
    best: dict[str, tuple] = {}
    for r in parts:
        key = (-int(r.pixels), int(r.index))
        if r.part not in best or key < best[r.part][0]:
            best[r.part] = (key, dict(r.props), r.name)
    return {p: {**props, "_name": name} for p, (_, props, name) in best.items()}


# ----------------------------------------------------------------------------- materials

def _material(name: str, row, part_materials: bool, donor: dict | None,
              fitted: dict | None = None) -> dict:
    """glTF material for one catalogued material (see the module docstring for the rules)."""
    extras = {"part": row.part, "score": float(row.score), "iou": float(row.iou),
              "decision": row.decision, "index": int(row.index),
              "material_id": int(row.index) + 1}
    props = dict(row.props)
    if fitted and row.part in fitted:
        fit = fitted[row.part]
        color = [min(max(float(c), 0.0), 1.0) for c in fit["color_linear"]] + [1.0]
        if row.part in PART_MATERIALS:
            mat = _prior(name, row.part, {**props, "base_color": color})
            mat["pbrMetallicRoughness"]["baseColorFactor"] = color
            extras["prior"] = PART_MATERIALS[row.part]["label"]
        else:
            mat = _from_props(name, {**props, "base_color": color})
        extras["fit"] = {k: v for k, v in fit.items() if k != "color_srgb"}
    elif donor and row.part in donor:
        props = dict(donor[row.part])
        extras["transferred_from"] = props.pop("_name", "")
        mat = _from_props(name, props)
    elif part_materials and row.part in PART_MATERIALS:
        mat = _prior(name, row.part, props)
        extras["prior"] = PART_MATERIALS[row.part]["label"]
    else:
        mat = _from_props(name, props)
    mat["extras"] = {"ucad": extras}
    return mat


def _from_props(name: str, props: dict) -> dict:
    """The source material's factors (``ucad_cl.artifacts.Material`` fields) as glTF."""
    base = _vec(props.get("base_color"), 4, (0.8, 0.8, 0.8, 1.0))
    mat = {"name": name, "pbrMetallicRoughness": {
        "baseColorFactor": base, "metallicFactor": _unit(props.get("metallic"), 0.0),
        "roughnessFactor": _unit(props.get("roughness"), 1.0)}}
    emissive = _vec(props.get("emissive"), 3, (0.0, 0.0, 0.0))
    if any(emissive):
        mat["emissiveFactor"] = emissive
    alpha = props.get("alpha_mode", "OPAQUE")
    if alpha in ("MASK", "BLEND"):
        mat["alphaMode"] = alpha
    t = _unit(props.get("transmission"), 0.0)
    if t > 0:
        mat["extensions"] = {"KHR_materials_transmission": {"transmissionFactor": t}}
    return mat


def _prior(name: str, part: str, props: dict) -> dict:
    """``PART_MATERIALS[part]`` as a glTF material, with its source-colour rules applied."""
    prior = PART_MATERIALS[part]
    mat = {"name": name, "pbrMetallicRoughness": dict(prior["pbrMetallicRoughness"])}
    source = _vec(props.get("base_color"), 4, (0.8, 0.8, 0.8, 1.0))
    if prior.get("keep_source_color"):
        mat["pbrMetallicRoughness"]["baseColorFactor"] = source[:3] + [1.0]
    if prior.get("emissive_from_source"):
        top = max(source[:3])
        mat["emissiveFactor"] = ([round(c / top, 6) for c in source[:3]] if top > 0.05
                                 else [1.0, 1.0, 1.0])
    if "extensions" in prior:
        mat["extensions"] = json.loads(json.dumps(prior["extensions"]))
    return mat


def _vec(v, n: int, default) -> list[float]:
    if isinstance(v, (list, tuple)) and len(v) >= n and all(
            isinstance(x, (int, float)) for x in v[:n]):
        return [min(max(float(x), 0.0), 1.0) for x in v[:n]]
    return [float(x) for x in default]


def _unit(v, default: float) -> float:
    return min(max(float(v), 0.0), 1.0) if isinstance(v, (int, float)) else float(default)


# ----------------------------------------------------------------------------- binary layout

def _add(blob: bytearray, views: list, accessors: list, arr: np.ndarray, target: int,
         component: int, kind: str, minmax=None) -> int:
    """Append ``arr`` to the binary chunk (4-byte aligned) with a buffer view and an accessor;
    returns the accessor index."""
    while len(blob) % 4:
        blob.append(0)
    offset = len(blob)
    blob += arr.tobytes()
    views.append({"buffer": 0, "byteOffset": offset, "byteLength": arr.nbytes,
                  "target": target})
    acc = {"bufferView": len(views) - 1, "componentType": component,
           "count": int(arr.shape[0]), "type": kind}
    if minmax is not None:
        acc["min"], acc["max"] = minmax
    accessors.append(acc)
    return len(accessors) - 1


def _glb_bytes(gltf: dict, blob: bytes) -> bytes:
    """GLB container: header, JSON chunk (space-padded), BIN chunk (zero-padded)."""
    js = json.dumps(gltf, separators=(",", ":"), ensure_ascii=False).encode("utf-8")
    js += b" " * (-len(js) % 4)
    blob += b"\0" * (-len(blob) % 4)
    gltf["buffers"][0]["byteLength"] = len(blob)
    js = json.dumps(gltf, separators=(",", ":"), ensure_ascii=False).encode("utf-8")
    js += b" " * (-len(js) % 4)
    total = 12 + 8 + len(js) + 8 + len(blob)
    return (struct.pack("<III", 0x46546C67, 2, total) + struct.pack("<II", len(js), 0x4E4F534A)
            + js + struct.pack("<II", len(blob), 0x004E4942) + blob)
