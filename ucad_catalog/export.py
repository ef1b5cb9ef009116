"""Catalogue exports with an explicit, versioned schema: one row per mesh plus a materials table.

``write_export(records, out, format)`` writes two tables next to each other:

* ``OUT`` (e.g. ``cat.parquet`` / ``cat.jsonl``): one row per mesh, columns ``MESH_COLUMNS``;
* ``OUT`` with ``.materials`` before the suffix (``cat.materials.parquet``): one row per material,
  columns ``MATERIAL_COLUMNS``, joined to the meshes on ``mesh_id`` = the mesh's ``id``.

The schema does not depend on the content (an all-rejected catalogue has the same column types as
any other), so exports of different catalogues concatenate (``pyarrow.concat_tables``,
``cat a.jsonl b.jsonl``). Every row carries ``export_version``; Parquet files also carry the
metadata ``EXPORT_METADATA`` (keys ``ucad:*``: export version, catalogue schema version, tool
version, conventions, table name); JSON lines get it as ``OUT.meta.json``. No timestamps or run
ids are exported: the same catalogue content gives the same bytes, whichever build made it.

Column types are written once, in ``MESH_COLUMNS`` / ``MATERIAL_COLUMNS`` (name, Arrow type, what);
``json`` columns are JSON text in Parquet and JSON values in JSON lines. Parquet needs pyarrow.
"""
from __future__ import annotations

import json
import os
import uuid
from pathlib import Path

from . import __version__
from ._db import SCHEMA_VERSION, CatalogError, canonical_json, remove_stale_exports
from .exr import CONVENTIONS
from .parts import PART_NAMES, UNSEEN

EXPORT_VERSION = 1
FORMATS = {".parquet": "parquet", ".pq": "parquet", ".jsonl": "jsonl", ".ndjson": "jsonl"}

# (name, type, meaning); types: string, int32, int64, float64, bool, json, list<float64>,
# views (list of {index, azimuth, elevation, K, w2c}), artifacts (list of {kind, sha256, bytes})
MESH_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("export_version", "int32", "this export schema's version"),
    ("id", "string", "mesh id: sha256 of the source content (a prefix of >= 8 digits names it)"),
    ("library_root", "string", "absolute library folder the mesh was built from"),
    ("path", "string", "source file relative to library_root (absolute when outside it)"),
    ("name", "string", "file name of the source"),
    ("size", "int64", "source file size, bytes"),
    ("mtime", "float64", "source file modification time, Unix seconds"),
    ("state", "string", "accepted or rejected"),
    ("reason", "string", "rejection code ('' when accepted)"),
    ("detail", "string", "rejection detail, a sentence"),
    ("n_triangles", "int64", "triangles after ingest"),
    ("n_materials", "int64", "materials after ingest"),
    ("n_views", "int32", "rendered views"),
    ("file_to_norm", "list<float64>", "4x4 row-major, file frame -> canonical frame"),
    ("orientation", "json", "the orientation stage's record, null when none"),
    ("meta", "json", "free per-mesh metadata (object)"),
    ("options_hash", "string", "sha256 of the build options that produced the row"),
    ("views", "views", "cameras: index, azimuth, elevation (deg), K 3x3 and w2c 4x4 row-major"),
    ("artifacts", "artifacts", "stored objects: kind, sha256 (object name), bytes"),
)
MATERIAL_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("export_version", "int32", "this export schema's version"),
    ("mesh_id", "string", "the mesh's id"),
    ("index", "int32", "material index; its id in the maps is index + 1"),
    ("name", "string", "material name in the source"),
    ("part", "string", f"one of {', '.join(PART_NAMES)} or {UNSEEN}"),
    ("score", "float64", "|material & part| / |material| in the deciding view"),
    ("iou", "float64", "IoU in the deciding view"),
    ("view", "int32", "deciding view (-1 none)"),
    ("decision", "string", "how the part was decided"),
    ("pixels", "int64", "visible pixels over all views"),
    ("base_color", "list<float64>", "linear RGBA, null when unknown"),
    ("metallic", "float64", "metallic factor, null when unknown"),
    ("roughness", "float64", "roughness factor, null when unknown"),
    ("emissive", "list<float64>", "linear RGB emission, null when unknown"),
    ("transmission", "float64", "transmission factor, null when unknown"),
    ("alpha_mode", "string", "OPAQUE, MASK or BLEND; null when unknown"),
    ("has_texture", "bool", "the source material has a base colour texture, null when unknown"),
    ("props", "json", "every recorded material property (object)"),
)


def export_metadata(table: str) -> dict[str, str]:
    """The file-level metadata of an export table (Parquet key-value metadata)."""
    return {"ucad:export_version": str(EXPORT_VERSION), "ucad:table": table,
            "ucad:catalog_schema_version": str(SCHEMA_VERSION),
            "ucad:tool": f"ucad-catalog {__version__}", "ucad:conventions": CONVENTIONS,
            "ucad:parts": ",".join(PART_NAMES + (UNSEEN,)),
            "ucad:columns": canonical_json({n: [t, d] for n, t, d in
                                            (MESH_COLUMNS if table == "meshes"
                                             else MATERIAL_COLUMNS)})}


def format_for(out: str | Path, format: str | None = None) -> str:
    """'jsonl' | 'parquet': ``format`` when given, else from ``out``'s suffix (CatalogError)."""
    if format is not None:
        if format not in ("jsonl", "parquet"):
            raise CatalogError(f"export format must be 'jsonl' or 'parquet', got {format!r}")
        return format
    found = FORMATS.get(Path(out).suffix.lower())
    if found is None:
        raise CatalogError(f"{out}: cannot tell the export format from the suffix "
                           f"{Path(out).suffix!r}; name it .parquet or .jsonl, or give a format")
    return found


def materials_path(out: str | Path) -> Path:
    """``cat.parquet`` -> ``cat.materials.parquet`` (the materials table beside the meshes)."""
    out = Path(out)
    return out.with_name(f"{out.stem}.materials{out.suffix}")


def rows(records: list[dict]) -> tuple[list[dict], list[dict]]:
    """(mesh rows, material rows) of ``CatalogReader.record``-style records, schema order."""
    meshes, materials = [], []
    for rec in records:
        meshes.append({
            "export_version": EXPORT_VERSION, "id": rec["sha256"],
            "library_root": rec["library_root"], "path": rec["path"],
            "name": Path(rec["path"]).name, "size": int(rec["size"]),
            "mtime": float(rec["mtime"]), "state": rec["state"], "reason": rec["reason"],
            "detail": rec["detail"], "n_triangles": int(rec["n_triangles"]),
            "n_materials": int(rec["n_materials"]), "n_views": len(rec["views"]),
            "file_to_norm": [float(x) for row in rec["file_to_norm"] for x in row],
            "orientation": rec["orientation"], "meta": rec["meta"],
            "options_hash": rec["options_hash"],
            "views": [{"index": int(v["index"]), "azimuth": float(v["azimuth"]),
                       "elevation": float(v["elevation"]),
                       "K": [float(x) for r in v["K"] for x in r],
                       "w2c": [float(x) for r in v["w2c"] for x in r]} for v in rec["views"]],
            "artifacts": [{"kind": k, "sha256": a["sha256"], "bytes": int(a["bytes"])}
                          for k, a in sorted(rec["artifacts"].items())],
        })
        for m in rec["materials"]:
            p = m["props"]
            materials.append({
                "export_version": EXPORT_VERSION, "mesh_id": rec["sha256"],
                "index": int(m["index"]), "name": m["name"], "part": m["part"],
                "score": float(m["score"]), "iou": float(m["iou"]), "view": int(m["view"]),
                "decision": m["decision"], "pixels": int(m["pixels"]),
                "base_color": _floats(p.get("base_color")), "metallic": _float(p.get("metallic")),
                "roughness": _float(p.get("roughness")), "emissive": _floats(p.get("emissive")),
                "transmission": _float(p.get("transmission")),
                "alpha_mode": p.get("alpha_mode") if isinstance(p.get("alpha_mode"), str)
                else None,
                "has_texture": bool(p["has_texture"]) if "has_texture" in p else None,
                "props": p,
            })
    return meshes, materials


def write_export(records: list[dict], out: str | Path, format: str | None = None) -> int:
    """Write the meshes table to ``out`` and the materials table beside it (``materials_path``);
    returns the number of meshes. Files appear whole (``.tmp-<name>.<pid>.<random>``, then
    rename); the temporary file is removed on any error, and one a killed export left (its
    process gone) by the next export to the same name."""
    fmt = format_for(out, format)
    out = Path(out)
    if out.parent != Path("") and not out.parent.is_dir():
        raise CatalogError(f"cannot write {out}: folder {out.parent} does not exist")
    if fmt == "parquet":
        try:
            import pyarrow  # noqa: F401
        except ImportError:
            raise CatalogError("Parquet export needs pyarrow, which is not installed (pip install "
                               "pyarrow), or export .jsonl") from None
    mesh_rows, material_rows = rows(records)
    targets = [(out, "meshes", MESH_COLUMNS, mesh_rows),
               (materials_path(out), "materials", MATERIAL_COLUMNS, material_rows)]
    if fmt == "jsonl":
        meta = {k: v for k, v in export_metadata("meshes").items() if k != "ucad:table"}
        targets_meta = out.with_name(out.name + ".meta.json")
    for path, table, columns, data in targets:
        remove_stale_exports(path)                  # left by a killed export (process gone)
        tmp = path.with_name(f".tmp-{path.name}.{os.getpid()}.{uuid.uuid4().hex[:12]}")
        try:
            if fmt == "parquet":
                _write_parquet(tmp, table, columns, data)
            else:
                with open(tmp, "w", encoding="utf-8") as f:
                    for row in data:
                        f.write(canonical_json(row) + "\n")
            os.replace(tmp, path)
        except OSError as exc:
            raise CatalogError(f"cannot write {path}: {exc.strerror or exc}") from None
        finally:
            if tmp.exists():
                tmp.unlink()
    if fmt == "jsonl":
        meta["ucad:tables"] = canonical_json({"meshes": out.name,
                                              "materials": materials_path(out).name})
        targets_meta.write_text(json.dumps(meta, indent=1, sort_keys=True) + "\n",
                                encoding="utf-8")
    return len(mesh_rows)


def arrow_schema(table: str):
    """The pyarrow schema of an export table ('meshes' or 'materials'), with its metadata."""
    import pyarrow as pa

    f64s = pa.list_(pa.float64())
    types = {"string": pa.string(), "int32": pa.int32(), "int64": pa.int64(),
             "float64": pa.float64(), "bool": pa.bool_(), "json": pa.string(),
             "list<float64>": f64s,
             "views": pa.list_(pa.struct([("index", pa.int32()), ("azimuth", pa.float64()),
                                          ("elevation", pa.float64()), ("K", f64s),
                                          ("w2c", f64s)])),
             "artifacts": pa.list_(pa.struct([("kind", pa.string()), ("sha256", pa.string()),
                                              ("bytes", pa.int64())]))}
    columns = MESH_COLUMNS if table == "meshes" else MATERIAL_COLUMNS
    return pa.schema([pa.field(n, types[t]) for n, t, _ in columns],
                     metadata=export_metadata(table))


def _write_parquet(path: Path, table: str, columns, data: list[dict]) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    json_cols = [n for n, t, _ in columns if t == "json"]
    data = [{**row, **{c: None if row[c] is None else canonical_json(row[c]) for c in json_cols}}
            for row in data]
    pq.write_table(pa.Table.from_pylist(data, schema=arrow_schema(table)), str(path))


def _float(v) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def _floats(v) -> list[float] | None:
    if isinstance(v, (list, tuple)) and all(isinstance(x, (int, float)) for x in v):
        return [float(x) for x in v]
    return None
