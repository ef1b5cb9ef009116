"""``ucad-index parts MESH...``: material -> part table of meshes (segment + IoU classification).

Per mesh: render the camera ring, segment the views (``--segmenter labeller`` (default, offline:
the learned per-material labeller), ``prior``, ``masks:DIR`` or ``onnx:MODEL:CONFIG.json``, the
same spelling as ``build``), classify every material, print the table and write
``OUT/NAME.parts.csv``, ``OUT/NAME.parts.json`` and ``OUT/NAME.parts.png`` (the views coloured by
the decided part: a fixed colour per part, legend on the right).
"""
from __future__ import annotations

import csv
import json
import sys
from dataclasses import asdict
from pathlib import Path

from ..segment import segmenter_from_spec, segmenter_help
from .common import format_rows, match_meshes, open_reader
from .render import add_camera_args, add_orientation_args, orientation_from_args, ring_from_args

COLUMNS = ("material", "name", "part", "score", "iou", "view", "decision", "pixels", "prob",
           "split", "was")


def register(sub) -> None:
    p = sub.add_parser(
        "parts", help="label every material with a vehicle part (segment views + IoU vote)",
        description="Render each MESH, segment the views into parts and give every material the "
                    "part whose mask covers it (score = |material ∩ part| / |material| > 0.5; the "
                    "paper's best-view rule and a confidence x area weighted vote). Prints the "
                    "table and writes OUT/NAME.parts.csv, .parts.json and a .parts.png contact "
                    "sheet. Exit status 1 if any mesh failed.")
    p.add_argument("meshes", nargs="*", metavar="MESH",
                   help="mesh files (with --catalog: mesh ids, sha256 prefixes or paths; "
                        "none = every accepted mesh)")
    p.add_argument("--catalog", type=Path, default=None, metavar="PATH",
                   help="print the stored material -> part tables of a catalogue instead")
    p.add_argument("--segmenter", default="labeller", metavar="SPEC",
                   help=f"default labeller. {segmenter_help()}")
    p.add_argument("--out", type=Path, default=Path("out/parts"), metavar="DIR",
                   help="output folder (default out/parts)")
    p.add_argument("--threshold", type=float, default=0.5, help="score threshold (default 0.5)")
    add_camera_args(p)
    add_orientation_args(p)
    p.set_defaults(func=run)


def write_table(table, stem: Path) -> None:
    """``stem.parts.csv`` and ``stem.parts.json`` (one row per material)."""
    rows = [asdict(r) for r in table.rows]
    with open(f"{stem}.parts.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS)
        w.writeheader()
        w.writerows([{**r, **{k: json.dumps(r[k]) if r[k] else "" for k in ("split", "was")}}
                     for r in rows])
    Path(f"{stem}.parts.json").write_text(json.dumps(rows, indent=1, ensure_ascii=False),
                                          encoding="utf-8")


def format_table(table) -> str:
    return format_rows(table.rows)


def run_catalog(args) -> int:
    """Stored tables: one block per mesh, same columns as a fresh run."""

    reader = open_reader(args.catalog)
    if reader is None:
        return 2
    with reader as r:
        metas = r.meshes(state=None)
        if args.meshes:
            hit_ids = {m.id for k in args.meshes for m in match_meshes(r, k)}
            metas = [m for m in metas if m.id in hit_ids]
            if not metas:
                print(f"error: no catalogued mesh matches {args.meshes}", file=sys.stderr)
                return 2
        else:
            metas = [m for m in metas if m.state == "accepted"]
        for m in metas:
            print(f"== {m.id[:12]} {m.path} ({m.state}{': ' + m.reason if m.reason else ''})")
            rows = r.parts(m.sha256)
            if rows:
                print(format_rows(rows))
    return 0


def run(args) -> int:
    if args.catalog is not None:
        return run_catalog(args)
    if not args.meshes:
        print("error: give MESH files, or --catalog PATH", file=sys.stderr)
        return 2
    from ..classify import classify_parts
    from ..system import printable
    from ..ingest import IngestError, describe_exception, load_mesh_isolated
    from ..render import render_views
    from ..names import name_priors
    from ..sheets import part_sheet, write_png

    try:
        segmenter = segmenter_from_spec(args.segmenter)
        mode, overrides = orientation_from_args(args)
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    from .render import output_stems

    try:
        stems = output_stems(args.meshes)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    ring = ring_from_args(args)
    from ..runtime import get_runtime
    get_runtime()           # no usable OpenCL device: one line (cli.main), not one per file
    args.out.mkdir(parents=True, exist_ok=True)
    failed = 0
    for path, name in zip(args.meshes, stems):
        stem = args.out / name
        try:
            mesh = load_mesh_isolated(path, orientation=mode, overrides=overrides)
            views = render_views(mesh, ring)
            masks = segmenter.segment(mesh, views)
            table = classify_parts(mesh, views, masks, threshold=args.threshold,
                                   priors=name_priors(mesh))
            print(f"== {printable(path)} ({masks.source}, {views.n_views} views)")
            print(format_table(table))
            write_table(table, stem)
            write_png(f"{stem}.parts.png", part_sheet(views, table))
        except IngestError as exc:                  # every file gets its line, none stops us
            failed += 1
            print(f"FAIL  {printable(str(exc))}", file=sys.stderr)
        except MemoryError:
            failed += 1
            print(f"FAIL  {printable(path)}: out of memory [too_large]", file=sys.stderr)
        except Exception as exc:                    # noqa: BLE001 - reported per file
            failed += 1
            print(f"FAIL  {printable(path)}: {describe_exception(exc)}", file=sys.stderr)
    print(f"{len(args.meshes) - failed} labelled, {failed} failed; outputs in {args.out}")
    return 1 if failed else 0
