"""Catalogue maintenance: ``verify`` (read-only consistency report) and ``gc`` (reclaim space)."""
from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser(
        "verify", help="check a catalogue: database integrity, missing/corrupt/unreferenced objects",
        description="Read-only check of a catalogue (safe while a build runs): SQLite "
                    "integrity_check and foreign_key_check, every referenced object present "
                    "with the right size and sha256 (re-hashed; --quick checks sizes only), and "
                    "the objects nothing references (a killed build's last objects, artifacts "
                    "replaced by a rebuild, .tmp-* files), which `ucad-index gc` deletes. While a "
                    "build runs, the objects it is about to commit also show as unreferenced. "
                    "Exit status 1 when the catalogue is damaged, 0 otherwise.")
    p.add_argument("--catalog", required=True, type=Path, metavar="PATH")
    p.add_argument("--quick", action="store_true", help="compare sizes only, do not re-hash")
    p.add_argument("--json", action="store_true", help="machine-readable report")
    p.set_defaults(func=run_verify)

    p = sub.add_parser(
        "gc", help="delete unreferenced objects and leftovers of killed builds and exports",
        description="Take the catalogue's writer lock (so never during a build: a running build "
                    "makes gc stop with a message) and delete the objects nothing references, "
                    "temporary .tmp-* files and the staging folder a killed build left behind. "
                    "--dry-run only counts them.")
    p.add_argument("--catalog", required=True, type=Path, metavar="PATH")
    p.add_argument("--dry-run", action="store_true", help="report what would be deleted")
    p.set_defaults(func=run_gc)


def run_verify(args) -> int:
    from .common import open_reader

    r = open_reader(args.catalog)
    if r is None:
        return 2
    with r:
        report = r.verify(rehash=not args.quick)
    if args.json:
        print(json.dumps(report, indent=1))
        return 1 if report["problems"] else 0
    unref = sum(n for _, n in report["unreferenced"])
    tmp = sum(n for _, n in report["tmp_files"])
    print(f"catalogue {args.catalog}: {report['objects']} referenced objects "
          f"({report['bytes'] / 2**20:.1f} MiB){' (sizes only)' if args.quick else ''}")
    for line in report["problems"][:50]:
        print(f"  PROBLEM {line}")
    if len(report["problems"]) > 50:
        print(f"  ... {len(report['problems']) - 50} more problems")
    print(f"  {len(report['unreferenced'])} unreferenced objects ({unref / 2**20:.1f} MiB), "
          f"{len(report['tmp_files'])} temporary files ({tmp / 2**20:.1f} MiB)"
          + (f": `ucad-index gc --catalog {args.catalog}` deletes them"
             if report["unreferenced"] or report["tmp_files"] else ""))
    if report["problems"]:
        print(f"{len(report['problems'])} problems: the catalogue is damaged", file=sys.stderr)
        return 1
    print("  ok: database and referenced objects are consistent")
    return 0


def run_gc(args) -> int:
    from ucad_catalog._db import CatalogError
    from ucad_catalog.store import Catalog

    try:
        cat = Catalog.open(args.catalog, create=False)
    except CatalogError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    staging = Path(args.catalog) / "staging"
    staged = sum(f.stat().st_size for f in staging.rglob("*") if f.is_file()) \
        if staging.is_dir() else 0
    with cat:
        if args.dry_run:
            rep = cat.verify_report(rehash=False)
            unref = sum(n for _, n in rep["unreferenced"]) + sum(n for _, n in rep["tmp_files"])
            print(f"would delete {len(rep['unreferenced'])} unreferenced objects and "
                  f"{len(rep['tmp_files'])} temporary files ({unref / 2**20:.1f} MiB), and "
                  f"{staged / 2**20:.1f} MiB of staging leftovers")
            return 0
        stats = cat.gc()
    shutil.rmtree(staging, ignore_errors=True)
    print(f"deleted {stats['objects_removed']} unreferenced objects and {stats['tmp_removed']} "
          f"temporary files ({stats['bytes_freed'] / 2**20:.1f} MiB), and "
          f"{staged / 2**20:.1f} MiB of staging leftovers")
    return 0
