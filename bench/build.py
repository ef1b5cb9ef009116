"""Catalogue build throughput: meshes/s, time per stage, peak memory, disk per mesh.

Generates (once, cached in --library) a library of procedural vehicles of about --triangles
triangles with the usual messy share, then builds it with the local engine at each --workers
count into a fresh catalogue, sampling the resident memory of the whole process tree (driver +
workers) every 0.5 s to show it stays flat. Defaults are the acceptance configuration:
1,000 vehicles, 50k triangles, the build's rings (default: 15 and 5 deg, 144 views x 256 px;
``--elevations 15`` is issue 24's 72-view configuration), the default (learned labeller) segmenter.

Orientation row (issue 10's "orientation per 50k-triangle mesh"): ``ucad_cl.orient.
estimate_orientation`` alone, process CPU ms per mesh (median of 3 runs each) on the same
--label-meshes meshes of the library, loaded with ``orientation=None``, in one process with one
BLAS thread (as a build worker has); median, p90 and how many the cascade's cheap pass decides.
The build's own orientation row (wall ms in the loader thread) is contended by the workers.

Labelling row: the learned labeller's own cost per mesh (``LabellerSegmenter.segment``:
features, the layer behind glass, ONNX trees, painting the masks) on --label-meshes meshes of
the library, medians of 3 runs each, beside the hand-written prior segmenter's, in one process
with one PoCL thread per worker as in the build (``POCL_MAX_PTHREAD_COUNT``).

    python bench/build.py                              # the full run (long)
    python bench/build.py --count 40 --workers 1 2     # quick look
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def tree_rss_mb(pid: int) -> float:
    import psutil
    try:
        p = psutil.Process(pid)
        procs = [p] + p.children(recursive=True)
    except psutil.Error:
        return 0.0
    total = 0
    for q in procs:
        try:
            total += q.memory_info().rss
        except psutil.Error:
            pass
    return total / 2**20


def per_mesh_ms(catalog: Path, stage: str) -> tuple[float, float, int]:
    """(median, 90th percentile, count) of a stage's recorded seconds per mesh, in ms."""
    import numpy as np

    from ucad_catalog.reader import CatalogReader

    with CatalogReader(catalog) as r:
        t = [m.timings[stage] for m in r.meshes(state=None) if stage in (m.timings or {})]
    if not t:
        return float("nan"), float("nan"), 0
    return 1000 * float(np.median(t)), 1000 * float(np.quantile(t, 0.9)), len(t)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--count", type=int, default=1000)
    ap.add_argument("--triangles", type=int, default=50_000)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--library", type=Path, default=Path("/tmp/ucad-bench-library"))
    ap.add_argument("--catalog", type=Path, default=Path("/tmp/ucad-bench-catalog"))
    ap.add_argument("--azimuth-step", type=float, default=5.0)
    ap.add_argument("--elevations", type=float, nargs="+", default=None, metavar="DEG",
                    help="the stored rings' elevations (build --elevations; default the build's, "
                         "15 5; 15 alone is issue 24's 72-view configuration)")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--label-meshes", type=int, default=20,
                    help="meshes for the orientation and labelling rows (0: skip)")
    ap.add_argument("--segmenter", default="labeller")
    args = ap.parse_args()

    from ucad_cl.build import BuildOptions, build
    from ucad_cl.synth import write_library

    lib = args.library / f"n{args.count}_t{args.triangles}"
    if not (lib / ".complete").exists():
        shutil.rmtree(lib, ignore_errors=True)
        t0 = time.perf_counter()
        write_library(lib, args.count, seed=2026, target_triangles=args.triangles)
        (lib / ".complete").write_text("ok")
        print(f"generated {args.count} vehicles in {time.perf_counter() - t0:.0f} s -> {lib}")
    if args.label_meshes:
        orient_row(lib, args)
        label_row(lib, args)
    opts = BuildOptions(azimuth_step=args.azimuth_step, size=args.size,
                        elevations=tuple(args.elevations or BuildOptions.elevations),
                        segmenter=args.segmenter)
    print(f"rings: elevations {' '.join(f'{e:g}' for e in opts.elevations)} deg, "
          f"{int(round(360 / opts.azimuth_step)) * len(opts.elevations)} views of {opts.size} px "
          "a mesh")
    rows, orient_ms = [], []
    for w in args.workers:
        cat = args.catalog / f"w{w}"
        shutil.rmtree(cat, ignore_errors=True)
        samples: list[tuple[float, float]] = []
        stop = threading.Event()

        def sample(samples=samples, stop=stop):
            t0 = time.perf_counter()
            while not stop.is_set():
                samples.append((time.perf_counter() - t0, tree_rss_mb(os.getpid())))
                stop.wait(0.5)

        th = threading.Thread(target=sample, daemon=True)
        th.start()
        s = build(lib, cat, opts, workers=w, progress=True, log=lambda *a: None)
        stop.set()
        th.join()
        disk = sum(f.stat().st_size for f in cat.rglob("*") if f.is_file())
        n = max(s.processed, 1)
        rss = [r for _, r in samples]
        q = lambda f, rss=rss: rss[min(len(rss) - 1, int(f * len(rss)))] if rss else 0.0
        rows.append((w, s, disk / n, max(rss) if rss else 0.0, q(0.25), q(0.5), q(0.95)))
        print(f"workers {w}: {s.processed} meshes ({s.accepted} accepted, {s.rejected} rejected: "
              f"{s.reasons}) in {s.seconds:.0f} s")
        stage = {k: v / n for k, v in sorted(s.stage_seconds.items(), key=lambda kv: -kv[1])}
        print("  seconds per mesh by stage (summed over workers): "
              + ", ".join(f"{k} {v:.3f}" for k, v in stage.items()))
        orient_ms.append(per_mesh_ms(cat, "orient"))
    print()
    print(f"{'workers':>7} {'meshes':>6} {'meshes/s':>9} {'peak tree MB':>12} "
          f"{'RSS@25%':>8} {'RSS@50%':>8} {'RSS@95%':>8} {'disk/mesh MB':>12}")
    for w, s, dpm, peak, r25, r50, r95 in rows:
        print(f"{w:>7} {s.processed:>6} {s.meshes_per_s:>9.2f} {peak:>12.0f} {r25:>8.0f} {r50:>8.0f} "
              f"{r95:>8.0f} {dpm / 2**20:>12.2f}")
    print()
    print("in-build orientation stage (ucad_cl.orient in each worker's loader thread; wall ms per "
          "mesh as the catalogue's timings record them, contended by the other workers and "
          "stages: not the issue's row, see 'orientation per 50k-triangle mesh' above)")
    print(f"{'workers':>7} {'meshes':>6} {'median ms':>10} {'p90 ms':>8} {'triangles':>10}")
    for (w, *_), (med, p90, k) in zip(rows, orient_ms):
        print(f"{w:>7} {k:>6} {med:>10.1f} {p90:>8.1f} {args.triangles:>10}")


def library_meshes(lib: Path, count: int, **load_kw):
    """The first ``count`` meshes of the library (file-name order) that load and pass the
    build's filter (``load_kw``: ``load_mesh`` options): the orientation and labelling rows'
    meshes."""
    from ucad_cl.filter import filter_mesh
    from ucad_cl.ingest import IngestError, load_mesh

    n = 0
    for path in sorted(lib.glob("*.glb")):
        if n >= count:
            return
        try:
            mesh = load_mesh(path, **load_kw)
        except IngestError:
            continue
        if filter_mesh(mesh).accepted:
            n += 1
            yield mesh


def median_seconds(fn, *args, clock=time.perf_counter, runs: int = 3, **kw) -> float:
    """Median over ``runs`` calls of ``fn(*args, **kw)`` of the seconds ``clock`` counts."""
    import numpy as np

    times = []
    for _ in range(runs):
        t0 = clock()
        fn(*args, **kw)
        times.append(clock() - t0)
    return float(np.median(times))


def orient_row(lib: Path, args) -> None:
    """The issue's orientation row: process CPU ms of ``estimate_orientation`` per mesh (median
    of 3 runs each, after one warm-up run) on the first --label-meshes meshes of the library
    that load and pass the filter (the labelling row's), loaded without orientation."""
    from contextlib import nullcontext

    import numpy as np

    from ucad_cl.orient import estimate_orientation, takes_fast_path

    try:                                         # one BLAS thread, as in a build worker
        from threadpoolctl import threadpool_limits
        limit = threadpool_limits(1)
    except ImportError:
        limit = nullcontext()
    ms, tris, fast = [], [], 0
    with limit:
        for mesh in library_meshes(lib, args.label_meshes, orientation=None):
            estimate_orientation(mesh)
            ms.append(1000 * median_seconds(estimate_orientation, mesh, clock=time.process_time))
            tris.append(mesh.n_faces)
            fast += takes_fast_path(mesh)
    if not ms:
        return
    print(f"\norientation per 50k-triangle mesh (issue 10: estimate_orientation alone, process "
          f"CPU ms, median of 3 runs per mesh; {len(ms)} meshes of the library, median "
          f"{int(np.median(tris))} triangles, one process, one BLAS thread)")
    print(f"{'meshes':>7} {'median ms':>10} {'p90 ms':>8} {'cheap path':>11}")
    print(f"{len(ms):>7} {np.median(ms):>10.1f} {np.percentile(ms, 90):>8.1f} "
          f"{fast:>7} / {len(ms)}")


def label_row(lib: Path, args) -> None:
    """Median seconds per mesh of the labeller and of the prior segmenter (same meshes, views)."""
    import numpy as np

    # one PoCL thread, as each build worker has (engines/local.py); set before PoCL starts
    # in this process (the build's workers set their own)
    os.environ["POCL_MAX_PTHREAD_COUNT"] = os.environ["POCL_CPU_MAX_CU_NUM"] = "1"
    from ucad_cl.cameras import make_ring
    from ucad_cl.render import render_views
    from ucad_cl.labeller import label_materials
    from ucad_cl.segment import LabellerSegmenter, PriorSegmenter

    ring = make_ring(azimuth_step=args.azimuth_step, elevations=(15.0,), size=args.size)
    segs = {"labeller": LabellerSegmenter(), "prior": PriorSegmenter()}
    t = {k: [] for k in segs}
    t["label only"] = []          # label_materials: features, layer behind glass, ONNX trees
    tris = []
    for mesh in library_meshes(lib, args.label_meshes):
        views = render_views(mesh, ring)
        views.material_counts()                  # cached by the build's filter before segment
        tris.append(mesh.n_faces)
        for k, seg in segs.items():
            t[k].append(median_seconds(seg.segment, mesh, views))
        t["label only"].append(median_seconds(label_materials, mesh, views,
                                               model=segs["labeller"].model))
    if not tris:
        return
    print(f"\nlabelling per mesh ({len(tris)} meshes, median {int(np.median(tris))} triangles, "
          f"{ring.n_views} views x {args.size} px; medians of 3 runs per mesh)")
    print(f"{'segmenter':>10} {'median ms':>10} {'p90 ms':>8}")
    for k, v in t.items():
        print(f"{k:>10} {1000 * np.median(v):>10.1f} {1000 * np.percentile(v, 90):>8.1f}")
    print("  (labeller, prior: the whole segment() call, painting the masks included; "
          "label only: label_materials, the learned labeller's own cost)")
    print(f"{'added':>10} {1000 * (np.median(t['labeller']) - np.median(t['prior'])):>10.1f}"
          "   (labeller - prior, medians)")


if __name__ == "__main__":
    main()
