"""Pose-search acceptance benchmark (synthetic references, made by us).

Vehicles (``ucad_cl.synth`` when present, else the shared real models) are rendered at random
azimuths OFF the catalogue grid and random elevations in [2, 28] deg, at a random distance
(1.0-1.6x the fitted one), with random part colours (one per part: body, window, ...), random light, ambient and specular, Gaussian
pixel noise and a cluttered background (gradient + random shapes). Each reference is cropped with
its ground-truth box (from the depth mask). For each method the table prints the median and
90th-percentile azimuth error of the best candidate, the share within 15 deg (a front/back flip
counts as an error) and the elevation error, and queries/s (median of --repeats timed runs of
the whole query set; the coarse ring features of each vehicle are precomputed, as a catalogue
stores them, and timed separately as "ring s"); "peak MiB" is the process's peak resident
memory so far (methods run in order, so it only grows).

Methods: the built-in OpenCL HOG at coarse steps 30/10/5 deg, and 10 deg + on-demand refinement
(estimate_pose); the peer is OpenCV's ``cv2.HOGDescriptor`` (same crop, same 64 px resolution,
8x8 cells, 9 bins, 2x2 blocks: the same family of descriptor on the CPU) at 10 deg + refinement.

    .venv/bin/python bench/pose.py --vehicles 10 --queries 8 --repeats 3 --kernels

Descriptor tuning (10 synth vehicles x 8 references, box references, one run each; hog10 = coarse
10 deg ring, +r = with refinement; median az error / share within 15 deg):

    variant                          hog10            hog10+r
    size 64, cell 8, 9 unsigned      3.07 / 95.0 %    1.56 / 95.0 %   <- default
    12 signed bins                   6.18 / 67.5 %    4.92 / 66.2 %   (paint colour flips sign)
    18 unsigned bins                 3.26 / 95.0 %    1.45 / 95.0 %   (2x longer, no gain)
    min_grad 0.03 / 0.06 / 0.1       3.2 / 92.5-93.8  1.56-1.62 / 92.5-93.8
    eps 4 (default 1)                3.26 / 93.8 %    1.82 / 93.8 %
    silhouette 8x8 (mask refs)       3.16 / 96.2 %    1.61 / 95.0 %   (vs 3.17 / 93.8, 1.74 / 95.0)

Differences of one reference (1.25 %) are noise at this size. The silhouette channel needs a
real mask on the reference side and did not change the refined result, so it is off by default.
A render-support-masked distance and re-ranking hypotheses by coarse score were also tried; the
latter lost (93.8 % vs 95.0 %), so refined hypotheses are re-ranked by their refined score.
"""
from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ucad_cl.cameras import make_ring                          # noqa: E402
from ucad_cl.features import HogExtractor, crop_square, l2_rows  # noqa: E402
from ucad_cl.pose import estimate_pose, pose_ring, _az_diff     # noqa: E402
from ucad_cl.render import render_views                         # noqa: E402
from ucad_cl.shade import shade_views                           # noqa: E402
from ucad_cl.artifacts import Features                              # noqa: E402

REAL = ["o3dv_car.glb", "ferrari_348_lowpoly.glb", "cesium_milk_truck.glb", "a_frame_car/car.obj",
        "openmaterial_vehicle/vehicle_example.gltf", "godot_truck_town_vehicles.glb"]


class CvHog:
    """Peer: OpenCV's HOGDescriptor on the same square crop (grey conversion by OpenCV)."""

    kind = "cv-hog"

    def __init__(self, size=64):
        self.size = size
        self.hog = cv2.HOGDescriptor((size, size), (16, 16), (8, 8), (8, 8), 9)

    def extract(self, images, masks):
        crops, _ = crop_square(images, masks, self.size, 0.1)
        f = np.stack([self.hog.compute(c).ravel() for c in crops])
        return Features(feats=l2_rows(f), kind=self.kind)


def load_vehicles(n: int, seed: int):
    try:
        from ucad_cl.synth import make_vehicle
    except ImportError:
        make_vehicle = None
    if make_vehicle is not None:
        vs = [make_vehicle(seed + i) for i in range(n)]
        return "synth", [v.mesh() for v in vs], [v.truth["materials"] for v in vs]
    from ucad_cl.ingest import load_mesh
    base = ROOT.parent / "shared" / "data" / "vehicles"
    meshes = [load_mesh(base / p) for p in REAL[:n]]
    return "real", meshes, [{} for _ in meshes]


def clutter(rng, H, W):
    """A random linear gradient with random filled shapes and lines."""
    c0, c1 = rng.integers(0, 256, 3), rng.integers(0, 256, 3)
    ang = rng.uniform(0, 2 * np.pi)
    yy, xx = np.mgrid[0:H, 0:W]
    t = (np.cos(ang) * xx / W + np.sin(ang) * yy / H + 1) / 2
    img = np.ascontiguousarray((c0 + (c1 - c0) * t[..., None]).astype(np.uint8))
    for _ in range(rng.integers(6, 16)):
        col = tuple(int(x) for x in rng.integers(0, 256, 3))
        kind = rng.integers(3)
        p = (int(rng.integers(0, W)), int(rng.integers(0, H)))
        if kind == 0:
            cv2.circle(img, p, int(rng.integers(4, H // 4)), col, -1)
        elif kind == 1:
            q = (int(rng.integers(0, W)), int(rng.integers(0, H)))
            cv2.rectangle(img, p, q, col, -1)
        else:
            q = (int(rng.integers(0, W)), int(rng.integers(0, H)))
            cv2.line(img, p, q, col, int(rng.integers(1, 5)))
    return img


def make_queries(mesh, parts, n, rng, size=(256, 192)):
    """n references of mesh: (image, gt box, azimuth, elevation). One random colour per part
    (``parts``: material name -> part; a material without a part gets its own colour)."""
    out = []
    for _ in range(n):
        az = rng.uniform(0, 360)
        el = rng.uniform(2, 28)
        fitted = make_ring(azimuths=[0.0], elevations=[0.0], size=size).distance
        ring = make_ring(azimuths=[az], elevations=[el], size=size,
                         distance=fitted * rng.uniform(1.0, 1.6))
        views = render_views(mesh, ring)
        keys = [parts.get(m.name, m.name) for m in mesh.materials]
        palette = {k: rng.uniform(0.02, 0.95, 3) for k in sorted(set(keys))}
        colors = np.array([palette[k] for k in keys])
        light = (rng.uniform(-1, 1), rng.uniform(-1, 0.2), -rng.uniform(0.3, 1.0))
        img = shade_views(mesh, views, colors=colors, light_dir=light,
                          ambient=rng.uniform(0.15, 0.45), specular=rng.uniform(0.0, 0.5),
                          background=clutter(rng, size[1], size[0]))[0]
        img = np.clip(img + rng.normal(0, 4, img.shape), 0, 255).astype(np.uint8)
        m = np.isfinite(views.depth[0])
        rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
        box = (cols[0], rows[0], cols[-1] + 1, rows[-1] + 1)
        out.append((img, box, az, el, m))
    return out


def run_method(meshes, queries, extractor, step, refine, size, use_mask=False):
    t0 = time.perf_counter()
    rings = [pose_ring(m, extractor, azimuth_step=step, size=size) for m in meshes]
    t_ring = time.perf_counter() - t0
    errs, el_errs = [], []
    t0 = time.perf_counter()
    for mesh, ring, qs in zip(meshes, rings, queries):
        for img, box, az, el, mask in qs:
            where = dict(mask=mask) if use_mask else dict(box=box)
            best = estimate_pose(img, mesh, coarse=ring, refine=refine, top=2, **where)[0]
            errs.append(_az_diff(best.azimuth, az))
            el_errs.append(abs(best.elevation - el))
    t_query = time.perf_counter() - t0
    return np.array(errs), np.array(el_errs), t_ring, t_query


def kernel_table(repeats: int):
    """HOG throughput per work-group size (pixel kernel / cell kernel) vs cv2.HOGDescriptor.

    "first call" includes PoCL's per-local-size work-group compile (run with an empty
    POCL_CACHE_DIR to see it cold)."""
    from ucad_cl.runtime import get_runtime

    rng = np.random.default_rng(0)
    crops = rng.integers(0, 256, (512, 64, 64, 3), dtype=np.uint8)
    rt = get_runtime()
    t0 = time.perf_counter()
    rt.program("features")
    print(f"features.cl build {time.perf_counter() - t0:.2f} s (0 when cached); {rt.describe()}")
    print(f"{'descriptor':22s} {'first call s':>12s} {'crops/s':>9s}")
    for lp, lc in ((64, None), (64, 8), (64, 16), (64, 64), (16, None), (256, None)):
        ex = HogExtractor(local_pixels=lp, local_cells=lc)
        t0 = time.perf_counter()
        ex.describe(crops[:1])
        first = time.perf_counter() - t0
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            ex.describe(crops)
            ts.append(time.perf_counter() - t0)
        print(f"{f'hog local {lp}/{lc}':22s} {first:12.3f} {len(crops) / np.median(ts):9.0f}")
    peer = cv2.HOGDescriptor((64, 64), (16, 16), (8, 8), (8, 8), 9)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for c in crops:
            peer.compute(c)
        ts.append(time.perf_counter() - t0)
    print(f"{'cv2.HOGDescriptor':22s} {'':12s} {len(crops) / np.median(ts):9.0f}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vehicles", type=int, default=6)
    ap.add_argument("--queries", type=int, default=8, help="references per vehicle")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--size", type=int, default=128, help="render size of the rings")
    ap.add_argument("--methods", default="hog30,hog10,hog5,hog10+r,cv10+r")
    ap.add_argument("--hog", default="", help="HogExtractor overrides, e.g. bins=12,signed=1")
    ap.add_argument("--kernels", action="store_true", help="also print the kernel table")
    ap.add_argument("--mask", action="store_true",
                    help="give the references' ground-truth mask instead of the box (needed for "
                         "the silhouette channel to mean anything)")
    args = ap.parse_args()
    if args.kernels:
        kernel_table(args.repeats)
    source, meshes, parts = load_vehicles(args.vehicles, args.seed)
    rng = np.random.default_rng(args.seed)
    queries = [make_queries(m, p, args.queries, rng) for m, p in zip(meshes, parts)]
    kw = {k: type(getattr(HogExtractor(), k))(float(v)) if k != "signed" else bool(int(v))
          for k, v in (p.split("=") for p in args.hog.split(",") if p)}
    hog = HogExtractor(**kw)
    hog.describe(np.zeros((1, hog.size, hog.size, 3), np.uint8),
                 np.ones((1, hog.size, hog.size), np.float32))        # compile + first launch
    n_q = sum(len(q) for q in queries)
    print(f"source={source} vehicles={len(meshes)} queries={n_q} hog={hog} render={args.size}px "
          f"reference={'mask' if args.mask else 'box'}")
    print(f"{'method':10s} {'med az':>7s} {'p90 az':>7s} {'<=15deg':>8s} {'med el':>7s} "
          f"{'ring s':>7s} {'q/s':>7s} {'peak MiB':>9s}")
    for name in args.methods.split(","):
        ex = CvHog() if name.startswith("cv") else hog
        step = float(name[2:].split("+")[0]) if name.startswith("cv") else \
            float(name[3:].split("+")[0])
        refine = name.endswith("+r")
        runs = [run_method(meshes, queries, ex, step, refine, args.size, args.mask)
                for _ in range(args.repeats)]
        errs, el_errs = runs[0][0], runs[0][1]
        assert all(np.array_equal(errs, r[0]) for r in runs), "non-deterministic result"
        t_ring = float(np.median([r[2] for r in runs]))
        qps = n_q / float(np.median([r[3] for r in runs]))
        print(f"{name:10s} {np.median(errs):7.2f} {np.percentile(errs, 90):7.2f} "
              f"{np.mean(errs <= 15) * 100:7.1f}% {np.median(el_errs):7.2f} {t_ring:7.2f} "
              f"{qps:7.1f} {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:9.0f}")


if __name__ == "__main__":
    main()
