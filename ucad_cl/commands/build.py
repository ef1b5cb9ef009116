"""``ucad-index build LIBRARY --catalog PATH``: the main job."""
from __future__ import annotations

import sys
from pathlib import Path

from ..cameras import BUILD_ELEVATIONS
from ..segment import segmenter_help
from .render import add_camera_args, add_orientation_args, orientation_from_args


def register(sub) -> None:
    p = sub.add_parser(
        "build", help="build or update the part-labelled catalogue from a mesh library",
        description="Discover meshes in LIBRARY (a folder tree of GLB/glTF/OBJ/PLY/OFF/STL files, an "
                    "Objaverse-style glbs/<shard>/<uid>.glb tree, a single mesh file, or a manifest "
                    ".txt/.json of paths; paths are recorded relative to the library folder, whose "
                    "absolute path is recorded too), "
                    "filter them, render 360-degree material-index views, Canny edges, segment parts, "
                    "label every material with a part, compute pose features, and commit each mesh "
                    "atomically to the catalogue. Safe to interrupt (even kill -9): run it again to "
                    "continue. Unchanged meshes are skipped; changed files and changed options are "
                    "re-processed. A bad mesh is a recorded rejection with a reason code (listed in "
                    "docs/CONVENTIONS.md), not a failure: the summary lists rejections by reason "
                    "with example files and the run log's path. Files are untrusted: a worker "
                    "reads, hashes and parses each one under --timeout and --memory-limit-mb, "
                    "with budgets checked before allocation. Exit status: 0 every mesh has a "
                    "verdict; 1 some meshes hit an internal error (reason pipeline_error); 2 the "
                    "build could not run or stopped on an environment fault (disk full, I/O "
                    "error, workers killed from outside, another build holding the catalogue): "
                    "the message says what to fix, nothing was recorded for the meshes in "
                    "flight, and running the same command again continues.")
    p.add_argument("library", type=Path, help="library folder, a mesh file, or a manifest file")
    p.add_argument("--catalog", required=True, type=Path, metavar="PATH", help="catalogue folder")
    p.add_argument("--workers", type=int, default=1,
                   help="pipeline worker processes (each gets cores/workers OpenCL threads; default 1)")
    p.add_argument("--engine", choices=["local", "ray"], default="local",
                   help="local worker processes (default) or Ray tasks on a cluster (extra 'ray')")
    p.add_argument("--address", default=None, help="Ray cluster address for --engine ray")
    p.add_argument("--segmenter", default="labeller", metavar="SPEC",
                   help=f"default labeller. {segmenter_help()}")
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
                   help="keep only meshes whose file stem is listed: a text file (one uid per "
                        "line), a Parquet table (column 'uid'), or an annotations JSON (its keys)")
    p.add_argument("--categories", nargs="+", default=None, metavar="NAME",
                   help="with an annotations JSON as --uids: keep uids with one of these "
                        "category or tag names (e.g. car vehicle truck)")
    p.add_argument("--limit", type=int, default=None, help="process at most N discovered meshes")
    p.add_argument("--timeout", type=float, default=600.0,
                   help="seconds without progress on one mesh before its worker is killed; the "
                        "mesh is retried alone with twice the time, then rejected 'timeout' "
                        "(default 600)")
    p.add_argument("--memory-limit-mb", type=float, default=None, metavar="MB",
                   help="resident memory one worker may use; a mesh that needs more on its own "
                        "is rejected 'too_large' (default: half the machine's memory divided "
                        "by --workers, at least 1024)")
    p.add_argument("--max-input-triangles", type=int, default=None, metavar="N",
                   help="reject files that would draw more than N triangles (counted from the "
                        "file's header/JSON before loading; default 4,000,000)")
    p.add_argument("--retry-failed", nargs="*", default=None, metavar="REASON",
                   help="re-process recorded rejections with these reason codes even though "
                        "file and options are unchanged (no code: timeout, loader_crashed, "
                        "too_large, pipeline_error)")
    p.add_argument("--quiet", "-q", action="store_true",
                   help="no progress bar and no summary: only warnings and errors (stderr); the "
                        "run log still records everything")
    add_camera_args(p, BUILD_ELEVATIONS,
                    ": one ring of M views each, stored in this order. The first is the label "
                    "ring: the view filter, Canny edges, the segmenter and the classifier see its "
                    "views only; every ring is stored with features, and retrieval and pose "
                    "search read them all (the 5 deg ring finds photos taken from low down: "
                    "docs/FIT.md)")
    add_orientation_args(p)
    p.add_argument("--labels-file", type=Path, default=None, metavar="FILE",
                   help="curators' label corrections: JSON {\"PATH or SHA256\": {\"MATERIAL\": "
                        "\"PART\"}} or text lines 'PATH_OR_SHA256 MATERIAL PART' (MATERIAL: "
                        "the name, quoted if it has spaces, or #N for material index N; paths "
                        "relative to FILE). Applied after labelling (decision 'override'); "
                        "editing the file re-processes only the meshes whose fixes changed "
                        "(docs/LABELS.md)")
    p.add_argument("--reject-uncertain-orientation", action="store_true",
                   help="reject meshes whose estimated orientation has a confidence under 0.5 "
                        "(reason uncertain_orientation); by default they are accepted and "
                        "counted as flagged in `status`")
    p.set_defaults(func=run)


def options_from_args(args):
    from ..build import BuildOptions
    from ..curation import LabelOverrides
    mode, overrides = orientation_from_args(args)
    labels = LabelOverrides.read(args.labels_file) if args.labels_file else LabelOverrides()
    return BuildOptions(orientation=args.orientation, label_overrides=labels.as_items(),
                        orientation_overrides=overrides.as_items() if overrides else (),
                        reject_uncertain_orientation=args.reject_uncertain_orientation,
                        azimuth_step=args.azimuth_step, elevations=tuple(args.elevations),
                        fov_deg=args.fov, size=args.size, segmenter=args.segmenter,
                        threshold=args.threshold, min_materials=args.min_materials,
                        max_triangles=args.max_triangles, triangle_budget=args.triangle_budget,
                        dominant_fraction=args.dominant_fraction,
                        features=not args.no_features, edges=not args.no_edges,
                        **({"max_input_triangles": args.max_input_triangles}
                           if args.max_input_triangles else {}))


def run(args) -> int:
    from ucad_catalog import CatalogError

    from .. import reasons
    from ..build import BuildStopped, build, read_uid_list
    from ..system import printable

    say = (lambda *a, **k: None) if args.quiet else print
    try:
        opts = options_from_args(args)
        if args.categories and not args.uids:
            raise ValueError("--categories needs --uids ANNOTATIONS.json")
        retry = args.retry_failed
        if retry is not None:
            retry = retry or list(reasons.default_retry())
            bad = [r for r in retry if reasons.CODES.get(r, (None,))[0] != reasons.REJECTION]
            if bad:
                raise ValueError(f"--retry-failed: {', '.join(bad)} is not a rejection reason "
                                 f"code (codes: {', '.join(reasons.of_kind(reasons.REJECTION))})")
        uids = read_uid_list(args.uids, args.categories) if args.uids else None
        if args.engine == "local":
            report_device(say)
        summary = build(args.library, args.catalog, opts, workers=args.workers,
                        engine=args.engine, ray_address=args.address, uids=uids,
                        limit=args.limit, timeout=args.timeout, progress=not args.quiet,
                        log=say, retry_failed=retry, memory_limit_mb=args.memory_limit_mb)
    except BuildStopped as stop:
        if stop.summary is not None and not args.quiet:
            print_summary(stop.summary, args.catalog)
        print(f"error: {stop}", file=sys.stderr)
        return 2
    except (FileNotFoundError, ValueError, CatalogError) as exc:
        print(f"error: {printable(str(exc))}", file=sys.stderr)
        return 2
    if not args.quiet:
        print_summary(summary, args.catalog)
    if summary.failed:
        print(f"error: {summary.failed} meshes failed with an internal error (pipeline_error): "
              f"see `ucad-index status --catalog {args.catalog}` and the run log; after a fix, "
              "`--retry-failed pipeline_error` re-processes them", file=sys.stderr)
        return 1
    return 0


def report_device(say) -> None:
    """Say which OpenCL device the workers will use; warn (stderr, even with --quiet) when it is
    a PoCL known to be slow, with the measured cost and the fix."""
    from ..runtime import OpenCLUnavailable, pick_device_info, slow_device_warning

    try:
        info, why = pick_device_info()
    except OpenCLUnavailable as exc:
        raise ValueError(str(exc)) from None
    say(f"OpenCL device {info.spec}: {info.summary()} ({why})")
    warning = slow_device_warning(info)
    if warning:
        print(warning, file=sys.stderr)


def print_summary(s, catalog) -> None:
    print()
    print(f"{'discovered':>12} {'skipped':>8} {'accepted':>9} {'rejected':>9} {'seconds':>8} "
          f"{'meshes/s':>9} {'peak MB':>8}")
    print(f"{s.discovered:>12} {s.skipped:>8} {s.accepted:>9} {s.rejected:>9} {s.seconds:>8.1f} "
          f"{s.meshes_per_s:>9.2f} {s.peak_rss_mb:>8.0f}")
    print(f"memory: peak {s.peak_rss_mb:.0f} MB for the process tree (driver + workers), driver "
          f"{s.peak_driver_mb:.0f} MB, largest worker {s.peak_worker_mb:.0f} MB (limit "
          f"{s.memory_limit_mb:.0f} MB per worker)" + (f"; {s.retried} attempts retried after a "
                                                       "worker failure" if s.retried else ""))
    if s.reasons:
        print(f"rejected {s.rejected} mesh(es), by reason (ucad-index status --catalog "
              f"{catalog} lists them all):")
        for reason, n in sorted(s.reasons.items(), key=lambda kv: (-kv[1], kv[0])):
            shown = ", ".join(s.examples.get(reason, []))
            more = f", ... ({n - len(s.examples.get(reason, []))} more)" if n > len(
                s.examples.get(reason, [])) else ""
            print(f"  {reason:<24} {n:>5}  {shown}{more}")
    if s.log_path:
        print(f"run log (every mesh, reasons, timings): {s.log_path}")
    if s.stage_seconds:
        tot = sum(s.stage_seconds.values()) or 1.0
        print("time per stage: " + ", ".join(f"{k} {v:.1f}s ({100 * v / tot:.0f}%)"
                                             for k, v in sorted(s.stage_seconds.items(),
                                                                key=lambda kv: -kv[1])))
    if s.superseded_mb:
        print(f"{s.superseded_mb:.1f} MiB of replaced artifacts are no longer referenced: "
              f"`ucad-index gc --catalog {catalog}` deletes them")
    print(f"catalogue: {catalog}   (ucad-index status --catalog {catalog}; "
          f"ucad-index show ID|PATH|NAME --catalog {catalog})")
