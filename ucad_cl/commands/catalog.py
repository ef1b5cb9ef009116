"""Catalogue commands: ``status``, ``show ID``, ``export``."""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from ucad_catalog.reader import RECENT_RUNS

from .common import format_low_confidence, format_rows, match_meshes, open_reader


def register(sub) -> None:
    p = sub.add_parser("status", help=f"counts by state and reason, and the last {RECENT_RUNS} "
                                      f"runs' throughput",
                       description=f"Summarise a catalogue: meshes by state and rejection "
                                   f"reason, flagged meshes, stored objects, and the last "
                                   f"{RECENT_RUNS} runs (newest first), all read in one snapshot. "
                                   f"Reads without locking: safe while a build runs.")
    p.add_argument("--catalog", required=True, type=Path, metavar="PATH")
    p.add_argument("--json", action="store_true",
                   help="machine-readable output (keys: ucad_catalog/SCHEMA.md, 'Command output')")
    p.set_defaults(func=run_status)

    p = sub.add_parser("show", help="one mesh: verdict, materials with parts and evidence",
                       description="Show one catalogued mesh. ID is its id (the sha256 of the "
                                   "source content, as in exports) or a prefix of at least 8 "
                                   "hex digits, or its source path in any spelling (absolute, "
                                   "relative to here or to the library folder), or its file "
                                   "name. Several matches are listed, not guessed between.")
    p.add_argument("id", metavar="ID", help="mesh id or id prefix (>= 8 hex digits), path or "
                                            "file name")
    p.add_argument("--catalog", required=True, type=Path, metavar="PATH")
    p.add_argument("--low-confidence", type=int, nargs="?", const=10, default=None, metavar="N",
                   help="also list the N (default 10) materials with the lowest label "
                        "confidence first (unseen ones, then by the labeller's probability of "
                        "the part: never-visible materials usually come first), with a "
                        "--labels-file line to fix each (docs/LABELS.md)")
    p.set_defaults(func=run_show)

    p = sub.add_parser("export", help="export the catalogue as Parquet or JSON lines",
                       description="Two tables with an explicit, versioned schema "
                                   "(ucad_catalog/SCHEMA.md, 'Export'): FILE has one row per "
                                   "mesh (id, paths, state, cameras, artifacts, orientation), "
                                   "FILE with '.materials' before the suffix one row per material "
                                   "(part, evidence, PBR properties). The format follows FILE's "
                                   "suffix (.parquet / .jsonl) unless --format says otherwise. "
                                   "Parquet files carry the export version and conventions in "
                                   "their metadata (JSON lines: FILE.meta.json) and concatenate "
                                   "across catalogues. Parquet needs pyarrow. Reads without "
                                   "locking: safe while a build runs.")
    p.add_argument("--catalog", required=True, type=Path, metavar="PATH")
    p.add_argument("--format", choices=["jsonl", "parquet"], default=None,
                   help="override the format the suffix of --out implies")
    p.add_argument("--out", required=True, type=Path, metavar="FILE",
                   help="e.g. cat.parquet or cat.jsonl (its folder must exist)")
    p.set_defaults(func=run_export)


def run_status(args) -> int:
    r = open_reader(args.catalog)                   # read-only: works while a build runs
    if r is None:
        return 2
    with r:
        st = r.status(RECENT_RUNS)                  # one snapshot: counts and runs agree
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
    print(f"  search index: {st['search_index']}" + ("" if st["search_index"] == "fresh" else
          "  (retrieval reads every stored row; `ucad-index build` writes it anew)"))
    print("  recent runs:")
    print(f"    {'run':>4} {'started':>19} {'engine':>6} {'processed':>9} {'skipped':>7} {'meshes/s':>8}")
    for run in st["runs"]:
        c = run["counts"]
        n = c.get("accepted", 0) + c.get("rejected", 0)
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(run["started"]))
        state = (f" stopped: {c['stopped']}" if c.get("stopped") else
                 f"{run['meshes_per_s']:8.2f}" if run["finished"] else " running/killed")
        print(f"    {run['id']:>4} {when:>19} {run['engine']:>6} {n:>9} {c.get('skipped', 0):>7} "
              f"{state}")
    return 0


def run_show(args) -> int:
    from ucad_catalog._db import CatalogError

    r = open_reader(args.catalog)
    if r is None:
        return 2
    with r:
        hits = match_meshes(r, args.id)
        if len(hits) != 1:
            print(f"error: {len(hits)} meshes match {args.id!r}"
                  + "".join(f"\n  {m.sha256[:12]}  {m.state:<8}  {m.path}" for m in hits[:20])
                  + ("" if hits else "; give an id (prefix of >= 8 hex digits), a path or a "
                     "file name (ucad-index export lists them)"), file=sys.stderr)
            return 2
        m = hits[0]
        print(f"mesh {m.sha256[:12]}  {m.path}\n  id (sha256) {m.sha256}\n"
              f"  library {m.library_root or '(not recorded)'}\n  state {m.state}"
              + (f" ({m.reason}: {m.detail})" if m.state == "rejected" else ""))
        print(f"  triangles {m.n_triangles}  materials {m.n_materials}  run {m.run_id}")
        if m.orientation:
            from .render import describe_orientation
            print(f"  {describe_orientation(m.orientation)}")
            cues = m.orientation.get("cues")
            if cues:
                print("    cues (+ agrees with the decision): " + ", ".join(
                    f"{k} {v:+.2f}" for k, v in sorted(cues.items(), key=lambda kv: -abs(kv[1]))))
        if m.timings:
            print("  seconds: " + ", ".join(f"{k} {v:.3f}" for k, v in m.timings.items()))
        parts = r.parts(m.sha256)
        if parts:
            print(format_rows(parts, indent="  "))
        for kind in ("views.exr", "parts.png", "features.npy", "edges.npy.gz"):
            try:
                print(f"  {kind:<13} {r.artifact_path(m.sha256, kind)}")
            except (CatalogError, KeyError):
                pass
        if args.low_confidence is not None:
            print(format_low_confidence(m.sha256, parts, args.low_confidence, indent="  "))
    return 0


def run_export(args) -> int:
    from ucad_catalog._db import CatalogError

    r = open_reader(args.catalog)                   # read-only: works while a build runs
    if r is None:
        return 2
    with r:
        try:
            n = r.export(args.out, format=args.format)
        except (CatalogError, OSError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    from ucad_catalog.export import materials_path
    print(f"exported {n} meshes to {args.out} and their materials to "
          f"{materials_path(args.out)}")
    return 0
