"""Bench: batched OpenCL Canny (ucad_cl.edges.canny) vs cv2.Canny on the CPU and on OpenCV's own
OpenCL path (cv2.UMat) on the same PoCL device, over the 72 views of a rendered synthetic vehicle.

Inputs are realistic material maps: the 3-channel colouring of the rendered material ids
(``colour_ids``, what ``material_edges`` runs) and its grey version (cv2 BGR2GRAY).
Throughput is images/s, median of --runs runs (each run = the whole batch, upload and download
included). First-launch times (program build + PoCL per-local-size compile) are reported
separately ("1st (s)": the first call, i.e. program build plus PoCL's per-kernel, per-local-size
compile; cold unless --warm-cache: the bench points PoCL's kernel cache at an empty folder and
turns pyopencl's binary cache off). "diff" counts pixels differing from cv2.Canny on the CPU
(must be 0 for ours). "scratch" is our device memory for the batch (input, planes, map, worklist).

    .venv/bin/python bench/edges.py [--sizes 128 256 512] [--views 72] [--runs 7] [--warm-cache]
                                    [--device P:D]

Without --device, every PoCL build present is measured in its own subprocess and our throughput
is compared side by side (bench/devices.py).
"""
from __future__ import annotations

import os
import sys
import tempfile

os.environ.setdefault("OPENCV_OPENCL_DEVICE", "Portable Computing Language:CPU:")
if "--warm-cache" not in sys.argv:
    os.environ["POCL_CACHE_DIR"] = tempfile.mkdtemp(prefix="pocl-cold-")
    os.environ["PYOPENCL_NO_CACHE"] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import time  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from devices import per_device, side_by_side  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

LOW, HIGH = 50.0, 150.0


def material_maps(size: int, views: int) -> np.ndarray:
    from ucad_cl.cameras import make_ring
    from ucad_cl.edges import colour_ids
    from ucad_cl.render import render_views
    from ucad_cl.synth import make_vehicle

    ring = make_ring(azimuth_step=360.0 / views, size=size)
    return colour_ids(render_views(make_vehicle(0).mesh(), ring).mat_id)


def median_time(fn, runs: int) -> float:
    ts = []
    for _ in range(runs):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512])
    ap.add_argument("--views", type=int, default=72)
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--warm-cache", action="store_true", help="keep PoCL's kernel cache")
    ap.add_argument("--device", default=None, help="OpenCL device P:D (default: every PoCL build, "
                                                   "side by side)")
    ap.add_argument("--json", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    runs = per_device(sys.argv[1:], args.device)
    if runs is not None:
        side_by_side(runs, "images/s")
        return
    results = {}

    from ucad_cl.edges import canny
    from ucad_cl.runtime import get_runtime

    rt = get_runtime()
    cv2.ocl.setUseOpenCL(True)
    ocl_dev = cv2.ocl.Device.getDefault().name() if cv2.ocl.haveOpenCL() else "none"
    print(f"ours:   {rt.describe()}")
    print(f"opencv: {cv2.__version__}, threads {cv2.getNumThreads()}, useOpenCL "
          f"{cv2.ocl.useOpenCL()}, OpenCL device {ocl_dev!r}")
    print(f"thresholds {LOW}/{HIGH}, L1, {args.views} views, median of {args.runs} runs\n")
    hdr = (f"{'size':>5} {'input':>5} | {'ours img/s':>10} {'1st (s)':>7} {'diff':>5} | "
           f"{'cv2 CPU img/s':>13} | {'cv2 OCL img/s':>13} {'1st (s)':>7} {'diff':>5} | "
           f"{'ours/CPU':>8} {'ours/OCL':>8} {'scratch MiB':>11}")
    print(hdr)
    print("-" * len(hdr))
    for size in args.sizes:
        colour = material_maps(size, args.views)
        grey = np.stack([cv2.cvtColor(c, cv2.COLOR_BGR2GRAY) for c in colour])
        for name, imgs in (("grey", grey), ("bgr", colour)):
            B = imgs.shape[0]
            ref = np.stack([cv2.Canny(im, LOW, HIGH) for im in imgs])
            t = time.perf_counter()
            ours = canny(imgs, LOW, HIGH)
            first = time.perf_counter() - t
            diff = int(np.count_nonzero(ours != ref))
            t_ours = median_time(lambda x=imgs: canny(x, LOW, HIGH), args.runs)
            t_cpu = median_time(lambda x=imgs: [cv2.Canny(im, LOW, HIGH) for im in x], args.runs)

            def ocl(x=imgs):
                return [cv2.Canny(cv2.UMat(im), LOW, HIGH).get() for im in x]
            t = time.perf_counter()
            out_ocl = np.stack(ocl())
            first_ocl = time.perf_counter() - t
            diff_ocl = int(np.count_nonzero(out_ocl != ref))
            t_ocl = median_time(ocl, max(1, args.runs // 2))
            C = imgs.shape[-1] if imgs.ndim == 4 else 1
            scratch = B * size * size * (C + (C if C > 1 else 0) + 1 + 4) / 2**20
            results[f"canny {size} px {name}, ours"] = B / t_ours
            print(f"{size:>5} {name:>5} | {B / t_ours:>10.0f} {first:>7.2f} {diff:>5} | "
                  f"{B / t_cpu:>13.0f} | {B / t_ocl:>13.0f} {first_ocl:>7.2f} {diff_ocl:>5} | "
                  f"{t_cpu / t_ours:>8.2f} {t_ocl / t_ours:>8.1f} {scratch:>11.1f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f)
    print(f"\nmax RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB; "
          f"program build times: {rt.compile_seconds}")


if __name__ == "__main__":
    main()
