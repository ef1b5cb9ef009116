"""``ucad-index synth OUT``: write a procedural vehicle library (GLB + truth JSON per vehicle)."""
from __future__ import annotations

import sys


def register(sub) -> None:
    from ..artifacts import VEHICLE_KINDS as KINDS
    p = sub.add_parser(
        "synth", help="write a procedural vehicle library with ground truth",
        description="Write COUNT procedural vehicles as OUT/NAME.glb + OUT/NAME.json (the truth: "
                    "material -> part, symmetric pairs, messy traits, expected rejection, "
                    "file -> canonical transform). Deterministic for a seed.")
    p.add_argument("out", metavar="OUT", help="output folder (created)")
    p.add_argument("--count", type=int, default=100, help="number of vehicles (default 100)")
    p.add_argument("--seed", type=int, default=0, help="library seed (default 0)")
    p.add_argument("--messy-fraction", type=float, default=0.3,
                   help="share of vehicles with a messy trait (default 0.3)")
    p.add_argument("--kinds", nargs="+", choices=KINDS, default=None, metavar="KIND",
                   help=f"vehicle kinds to draw from (default all: {' '.join(KINDS)})")
    p.add_argument("--detail", type=int, default=1,
                   help="tessellation factor, triangles grow ~detail^2 (default 1: ~20-35k)")
    p.add_argument("--triangles", type=int, default=None, metavar="N",
                   help="size every vehicle to about N triangles (overrides --detail)")
    p.add_argument("--huge-triangles", type=int, default=None, metavar="N",
                   help="also use the 'huge' trait, with about N triangles (off by default)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..synth import write_library
    try:
        paths = write_library(args.out, args.count, args.seed,
                              messy_fraction=args.messy_fraction, progress=not args.no_progress,
                              kinds=args.kinds, huge_triangles=args.huge_triangles,
                              detail=args.detail, target_triangles=args.triangles)
    except ValueError as exc:
        print(f"ucad-index synth: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {len(paths)} vehicles to {args.out}")
    return 0
