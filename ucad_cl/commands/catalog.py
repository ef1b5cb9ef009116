"""Catalogue commands: ``status``, ``show ID``, ``export``."""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("status", help="counts by state and reason, and the last runs' throughput",
                       description="Summarise a catalogue: meshes by state and rejection reason, "
                                   "stored objects, and the last run that processed meshes.")
    p.add_argument("--catalog", required=True, type=Path, metavar="PATH")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=run_status)

    p = sub.add_parser("show", help="one mesh: verdict, materials with parts and evidence",
                       description="Show one catalogued mesh by id (the number in `status`/export), "
                                   "sha256 (or a unique prefix) or path.")
    p.add_argument("id", help="mesh id, sha256 prefix or path")
    p.add_argument("--catalog", required=True, type=Path, metavar="PATH")
    p.set_defaults(func=run_show)

    p = sub.add_parser("export", help="export the catalogue as JSON lines or Parquet",
                       description="One record per mesh with materials, parts, views and artifact "
                                   "paths. Parquet needs pyarrow.")
    p.add_argument("--catalog", required=True, type=Path, metavar="PATH")
    p.add_argument("--format", choices=["jsonl", "parquet"], default="jsonl")
    p.add_argument("--out", required=True, type=Path, metavar="FILE")
    p.set_defaults(func=run_export)


def open_reader(path):
    """A CatalogReader for ``path``, or None after printing why it cannot be opened."""
    from ucad_catalog._db import CatalogError
    from ucad_catalog.reader import CatalogReader
    try:
        return CatalogReader(path)
    except CatalogError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return None


def match_meshes(metas, key: str) -> list:
    """Catalogued meshes that ``key`` names, first rule that matches wins: mesh id, path or file
    name, then sha256 prefix (at least 6 hex digits)."""
    k = key.lower()
    for rule in (lambda m: str(m.id) == key,
                 lambda m: m.path == key or Path(m.path).name.lower() == k,
                 lambda m: len(k) >= 6 and m.sha256.startswith(k)):
        hits = [m for m in metas if rule(m)]
        if hits:
            return hits
    return []


def _open(path):
    from ucad_catalog._db import CatalogError
    from ucad_catalog.store import Catalog
    try:
        return Catalog.open(path, create=False)
    except CatalogError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return None


def run_status(args) -> int:
    cat = _open(args.catalog)
    if cat is None:
        return 2
    with cat:
        st = cat.status()
        runs = cat._db.execute("SELECT id, started, finished, engine, counts, meshes_per_s FROM runs "
                               "ORDER BY id DESC LIMIT 5").fetchall()
    if args.json:
        print(json.dumps(st, indent=1))
        return 0
    print(f"catalogue {st['root']} (schema {st['schema_version']})")
    print(f"  meshes: {st['meshes']}  accepted: {st['by_state'].get('accepted', 0)}  "
          f"rejected: {st['by_state'].get('rejected', 0)}")
    for reason, n in st["by_reason"].items():
        print(f"    rejected {reason:<24} {n}")
    for reason, n in st.get("flagged", {}).items():
        if n:
            print(f"    flagged  {reason:<24} {n}  (accepted; ucad-index show ID prints why)")
    print(f"  objects: {st['objects']} ({st['object_bytes'] / 2**20:.1f} MiB)")
    print("  recent runs:")
    print(f"    {'run':>4} {'started':>19} {'engine':>6} {'processed':>9} {'skipped':>7} {'meshes/s':>8}")
    for rid, started, finished, engine, counts, rate in runs:
        c = json.loads(counts) if counts else {}
        n = c.get("accepted", 0) + c.get("rejected", 0)
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(started))
        state = f"{rate:8.2f}" if finished else " running/killed"
        print(f"    {rid:>4} {when:>19} {engine:>6} {n:>9} {c.get('skipped', 0):>7} {state}")
    return 0


def run_show(args) -> int:
    from ucad_catalog._db import CatalogError

    r = open_reader(args.catalog)
    if r is None:
        return 2
    with r:
        hits = match_meshes(r.meshes(state=None), args.id)
        if len(hits) != 1:
            print(f"error: {len(hits)} meshes match {args.id!r}", file=sys.stderr)
            return 2
        m = hits[0]
        print(f"mesh {m.id}  {m.path}\n  sha256 {m.sha256}\n  state {m.state}"
              + (f" ({m.reason}: {m.detail})" if m.state == "rejected" else ""))
        print(f"  triangles {m.n_triangles}  materials {m.n_materials}  run {m.run_id}")
        from .render import describe_orientation
        print(f"  {describe_orientation(m.orientation)}")
        cues = m.orientation.get("cues") if m.orientation else None
        if cues:
            print("    cues (+ agrees with the decision): " + ", ".join(
                f"{k} {v:+.2f}" for k, v in sorted(cues.items(), key=lambda kv: -abs(kv[1]))))
        if m.timings:
            print("  seconds: " + ", ".join(f"{k} {v:.3f}" for k, v in m.timings.items()))
        parts = r.parts(m.sha256)
        if parts:
            from .parts import format_rows
            print(format_rows(parts, indent="  "))
        for kind in ("views.exr", "parts.png", "features.npy", "edges.npy.gz"):
            try:
                print(f"  {kind:<13} {r.artifact_path(m.sha256, kind)}")
            except (CatalogError, KeyError):
                pass
    return 0


def run_export(args) -> int:
    from ucad_catalog._db import CatalogError

    cat = _open(args.catalog)
    if cat is None:
        return 2
    with cat:
        try:
            n = cat.export(args.out, format=args.format)
        except CatalogError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    print(f"exported {n} meshes to {args.out}")
    return 0
