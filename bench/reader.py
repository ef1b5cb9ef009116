"""Bench: reading one view from the catalogue (the OpenCL-free reader) vs decoding the stack.

Builds (once, cached under --work) a catalogue of --meshes generated vehicles at the build's
defaults (72 views x 256 px), then times, as medians over --reads reads spread over every mesh
and view:

* ``view(id, i)`` with a fresh reader each time (cold: SQLite open, EXR headers parsed, one part
  decoded) and with one reader (headers of the last stacks kept), by index and by angle;
* ``material_map`` only, ``part_masks``, ``edges`` of one view;
* the baseline: the whole view stack through OpenEXR (``read_viewset_exr``, what reading one view
  cost before) and ``OpenEXR.File`` alone.

Every read is checked against the whole-stack decode (0 differing pixels). Usage:
    .venv/bin/python bench/reader.py [--meshes 3] [--reads 200] [--work /tmp/ucad-bench-reader]
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def median_ms(fn, calls) -> float:
    ts = []
    for c in calls:
        t = time.perf_counter()
        fn(*c)
        ts.append(time.perf_counter() - t)
    return 1e3 * float(np.median(ts))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--meshes", type=int, default=3)
    ap.add_argument("--reads", type=int, default=200)
    ap.add_argument("--work", type=Path, default=Path("/tmp/ucad-bench-reader"))
    args = ap.parse_args()

    import OpenEXR

    import ucad_catalog
    from ucad_catalog.exr import read_viewset_exr

    cat = args.work / "catalog"
    if not (cat / "catalog.sqlite").exists():
        from ucad_cl.build import BuildOptions, build
        from ucad_cl.synth import write_library
        write_library(args.work / "lib", args.meshes, seed=5, messy_fraction=0.0, progress=False)
        build(args.work / "lib", cat, BuildOptions(), progress=False, log=lambda *a: None)
    r = ucad_catalog.open(cat)
    metas = r.meshes()
    n_views = len(r.views(metas[0].id))
    rng = np.random.default_rng(0)
    calls = [(metas[rng.integers(len(metas))].id, int(rng.integers(n_views)))
             for _ in range(args.reads)]
    size = r.view(*calls[0]).mat_id.shape
    print(f"{len(metas)} meshes x {n_views} views x {size[1]} x {size[0]} px; {args.reads} reads "
          f"spread over them; load average {os.getloadavg()[0]:.2f} (2 shared cores)")

    # correctness: every read equals the whole-stack decode
    stacks = {m.id: read_viewset_exr(r.artifact_path(m.id, "views.exr"))[0] for m in metas}
    diff = sum(int((r.view(s, v).mat_id != stacks[s].mat_id[v]).sum()
                   + (r.view(s, v).depth != stacks[s].depth[v]).sum()) for s, v in calls[:50])

    def cold(sha, v):
        with ucad_catalog.open(cat) as fresh:
            fresh.view(sha, v)

    one = calls[: max(10, args.reads // 10)]
    rows = [
        ("view(id, i), fresh reader (cold)", median_ms(cold, calls)),
        ("view(id, i), one reader", median_ms(lambda s, v: r.view(s, v), calls)),
        ("view(id, azimuth=, elevation=)",
         median_ms(lambda s, v: r.view(s, azimuth=5.0 * v + 1.0, elevation=14.0), calls)),
        ("material_map(id, i)", median_ms(lambda s, v: r.material_map(s, v), calls)),
        ("part_masks(id, i)", median_ms(lambda s, v: r.part_masks(s, v), calls)),
        ("edges(id, i)", median_ms(lambda s, v: r.edges(s, v), calls)),
        ("baseline: read_viewset_exr (whole stack)",
         median_ms(lambda s, v: read_viewset_exr(r.artifact_path(s, "views.exr")), one)),
        ("baseline: OpenEXR.File (whole stack)",
         median_ms(lambda s, v: OpenEXR.File(str(r.artifact_path(s, "views.exr")),
                                             separate_channels=True), one)),
    ]
    base = rows[-2][1]
    print(f"\n{'read':44s} {'median ms':>10s} {'vs whole stack':>15s}")
    for name, ms in rows:
        print(f"{name:44s} {ms:10.2f} {base / ms:14.1f}x")
    print(f"\npixels differing from the whole-stack decode (50 reads): {diff}")


if __name__ == "__main__":
    main()
