"""``ucad-index build LIBRARY --catalog PATH``: the main job."""
from __future__ import annotations

import sys
from pathlib import Path

from .render import add_camera_args, add_orientation_args, orientation_from_args


def register(sub) -> None:
    p = sub.add_parser(
        "build", help="build or update the part-labelled catalogue from a mesh library",
        description="Discover meshes in LIBRARY (a folder tree of GLB/glTF/OBJ/PLY/OFF/STL files, an "
                    "Objaverse-style glbs/<shard>/<uid>.glb tree, or a manifest .txt/.json of paths), "
                    "filter them, render 360-degree material-index views, Canny edges, segment parts, "
                    "label every material with a part, compute pose features, and commit each mesh "
                    "atomically to the catalogue. Safe to interrupt (even kill -9): run it again to "
                    "continue. Unchanged meshes are skipped; changed files and changed options are "
                    "re-processed. A bad mesh is a recorded rejection, not a failure: the exit status "
                    "is non-zero only when the run itself fails.")
    p.add_argument("library", type=Path, help="library folder or manifest file")
    p.add_argument("--catalog", required=True, type=Path, metavar="PATH", help="catalogue folder")
    p.add_argument("--workers", type=int, default=1,
                   help="pipeline worker processes (each gets cores/workers OpenCL threads; default 1)")
    p.add_argument("--engine", choices=["local", "ray"], default="local",
                   help="local worker processes (default) or Ray tasks on a cluster (extra 'ray')")
    p.add_argument("--address", default=None, help="Ray cluster address for --engine ray")
    p.add_argument("--segmenter", default="prior", metavar="SPEC",
                   help="prior (default, offline), masks:DIR or onnx:MODEL:CONFIG.json")
    p.add_argument("--threshold", type=float, default=0.5, help="part score threshold (default 0.5)")
    p.add_argument("--triangle-budget", type=int, default=0, metavar="N",
                   help="decimate meshes above N triangles, keeping material boundaries (0 = never)")
    p.add_argument("--max-triangles", type=int, default=2_000_000, metavar="N",
                   help="reject meshes above N triangles after decimation (default 2,000,000)")
    p.add_argument("--min-materials", type=int, default=2,
                   help="reject meshes with fewer materials (default 2)")
    p.add_argument("--dominant-fraction", type=float, default=0.97,
                   help="reject when one material covers this share of visible pixels (default 0.97)")
    p.add_argument("--no-features", action="store_true", help="skip pose features")
    p.add_argument("--no-edges", action="store_true", help="skip Canny edge maps")
    p.add_argument("--uids", type=Path, default=None, metavar="FILE",
                   help="keep only meshes whose file stem is listed (text, or annotations JSON keys)")
    p.add_argument("--categories", nargs="+", default=None, metavar="NAME",
                   help="with an annotations JSON as --uids: keep uids with one of these "
                        "category or tag names (e.g. car vehicle truck)")
    p.add_argument("--limit", type=int, default=None, help="process at most N discovered meshes")
    p.add_argument("--timeout", type=float, default=600.0,
                   help="seconds without progress on one mesh before it is rejected (default 600)")
    add_camera_args(p)
    add_orientation_args(p)
    p.add_argument("--reject-uncertain-orientation", action="store_true",
                   help="reject meshes whose estimated orientation has a confidence under 0.5 "
                        "(reason uncertain_orientation); by default they are accepted and "
                        "counted as flagged in `status`")
    p.set_defaults(func=run)


def options_from_args(args):
    from ..build import BuildOptions
    mode, overrides = orientation_from_args(args)
    return BuildOptions(orientation=args.orientation,
                        orientation_overrides=overrides.as_items() if overrides else (),
                        reject_uncertain_orientation=args.reject_uncertain_orientation,
                        azimuth_step=args.azimuth_step, elevations=tuple(args.elevations),
                        fov_deg=args.fov, size=args.size, segmenter=args.segmenter,
                        threshold=args.threshold, min_materials=args.min_materials,
                        max_triangles=args.max_triangles, triangle_budget=args.triangle_budget,
                        dominant_fraction=args.dominant_fraction,
                        features=not args.no_features, edges=not args.no_edges)


def run(args) -> int:
    from ..build import build, read_uid_list

    try:
        opts = options_from_args(args)
        if args.categories and not args.uids:
            raise ValueError("--categories needs --uids ANNOTATIONS.json")
        uids = read_uid_list(args.uids, args.categories) if args.uids else None
        summary = build(args.library, args.catalog, opts, workers=args.workers,
                        engine=args.engine, ray_address=args.address, uids=uids,
                        limit=args.limit, timeout=args.timeout)
    except (FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print_summary(summary, args.catalog)
    return 0


def print_summary(s, catalog) -> None:
    print()
    print(f"{'discovered':>12} {'skipped':>8} {'accepted':>9} {'rejected':>9} {'seconds':>8} "
          f"{'meshes/s':>9} {'peak MB':>8}")
    print(f"{s.discovered:>12} {s.skipped:>8} {s.accepted:>9} {s.rejected:>9} {s.seconds:>8.1f} "
          f"{s.meshes_per_s:>9.2f} {s.peak_rss_mb:>8.0f}")
    if s.reasons:
        print("rejections: " + ", ".join(f"{k} {v}" for k, v in sorted(s.reasons.items())))
    if s.stage_seconds:
        tot = sum(s.stage_seconds.values()) or 1.0
        print("time per stage: " + ", ".join(f"{k} {v:.1f}s ({100 * v / tot:.0f}%)"
                                             for k, v in sorted(s.stage_seconds.items(),
                                                                key=lambda kv: -kv[1])))
    print(f"catalogue: {catalog}   (ucad-index status --catalog {catalog}; "
          f"ucad-index show ID --catalog {catalog})")
