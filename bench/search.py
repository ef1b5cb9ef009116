"""Benchmark: feature search over a catalogue-sized database, ours vs NumPy and faiss.

Database: MESHES x 72 views of D-dim HOG-like features (non-negative, L2-normalised, smooth in
azimuth, one cluster per mesh); a batch of Q queries: random meshes at random off-grid azimuths
with fresh noise, as a reference image would be. Every method runs in its own forked process so its peak memory
(VmHWM after the fork minus RSS at the fork) is its own; the OpenCL runtime is never created in
the parent. Times are medians of RUNS warm runs; "first" is the first call (PoCL compiles each
kernel at its first launch) and "build" the index construction (upload, PCA fit, program build).

Reference: float64 exact distances (host, expansion in float64, error ~1e-16 relative).
Usage: python bench/search.py [--meshes 1000] [--dim 512] [--queries 100] [--k 10] [--runs 5]
                              [--device P:D]
Without --device, every PoCL build present is measured in its own subprocess and the ucad rows
are compared side by side (bench/devices.py).
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from devices import per_device, side_by_side  # noqa: E402


def _mesh_params(meshes: int, dim: int, seed: int) -> np.ndarray:
    """(meshes, 3, dim): per mesh a + b cos(az) + c sin(az) feature curve coefficients."""
    rng = np.random.default_rng(seed)
    return (rng.standard_normal((meshes, 3, dim)) * [[0.6], [0.5], [0.5]]).astype(np.float32)


def _features(params: np.ndarray, az: np.ndarray, rng, noise: float) -> np.ndarray:
    """HOG-like rows relu(a + b cos(az) + c sin(az) + noise), L2-normalised; az (M, V) radians."""
    a, b, c = params[:, 0, None], params[:, 1, None], params[:, 2, None]
    f = a + b * np.cos(az)[..., None] + c * np.sin(az)[..., None]
    f += noise * rng.standard_normal(f.shape, dtype=np.float32)
    f = np.maximum(f, 0).reshape(-1, params.shape[2])
    return (f / np.maximum(np.linalg.norm(f, axis=1, keepdims=True), 1e-12)).astype(np.float32)


def make_features(meshes: int, views: int, dim: int, seed: int = 0) -> np.ndarray:
    """Database: every mesh seen at azimuths 0, 360/views, ... (one cluster per mesh)."""
    params = _mesh_params(meshes, dim, seed)
    rng = np.random.default_rng(seed + 1)
    az = np.broadcast_to(np.arange(views) * (2 * np.pi / views), (100, views))
    return np.concatenate([_features(params[m:m + 100], az[:len(params[m:m + 100])], rng, 0.15)
                           for m in range(0, meshes, 100)])


def make_queries(meshes: int, dim: int, n: int, seed: int = 0) -> np.ndarray:
    """Reference images: random meshes at random (off-grid) azimuths, with fresh noise."""
    params = _mesh_params(meshes, dim, seed)
    rng = np.random.default_rng(seed + 2)
    pick = rng.choice(meshes, n, replace=False)
    az = rng.uniform(0, 2 * np.pi, (n, 1))
    return _features(params[pick], az, rng, 0.15)


def _rss(field: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field):
                return int(line.split()[1]) * 1024
    return 0


def _run_numpy(db, q, k):
    n2 = np.einsum("ij,ij->i", db, db)

    def go():
        d = n2[None, :] - 2.0 * (q @ db.T)
        part = np.argpartition(d, k - 1, axis=1)[:, :k]
        pd = np.take_along_axis(d, part, 1)
        o = np.lexsort((part, pd), axis=1)
        return np.take_along_axis(part, o, 1), np.take_along_axis(pd, o, 1)
    return go


def _run_faiss(db, q, k):
    import faiss

    faiss.omp_set_num_threads(2)
    index = faiss.IndexFlatL2(db.shape[1])
    index.add(db)

    def go():
        d, i = index.search(q, k)
        return i, d
    return go


def _run_ours(db, q, k, mode, cold=False, **opts):
    if cold:   # empty PoCL kernel cache and no pyopencl binary cache: real compile times
        import tempfile

        os.environ["POCL_CACHE_DIR"] = tempfile.mkdtemp(prefix="pocl-cold-")
        os.environ["PYOPENCL_NO_CACHE"] = "1"
    from ucad_cl.search import FeatureIndex

    index = FeatureIndex(db, mode=mode, **opts)
    return lambda: index.search(q, k)


def _child(conn, name, maker, db, q, k, runs):
    try:
        with open("/proc/self/clear_refs", "w") as f:   # reset VmHWM to the current RSS
            f.write("5")
    except OSError:
        pass
    rss0 = _rss("VmRSS:")
    t0 = time.perf_counter()
    go = maker(db, q, k)
    build = time.perf_counter() - t0
    t0 = time.perf_counter()
    idx, dist = go()
    first = time.perf_counter() - t0
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        go()
        times.append(time.perf_counter() - t0)
    conn.send((name, build, first, times, _rss("VmHWM:") - rss0,
               np.asarray(idx, np.int64), np.asarray(dist, np.float32)))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--meshes", type=int, default=1000)
    ap.add_argument("--views", type=int, default=72)
    ap.add_argument("--dim", type=int, default=512)
    ap.add_argument("--queries", type=int, default=100)
    ap.add_argument("--k", type=int, default=10)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--pca-dims", default="64,128", help="comma-separated reduced dims")
    ap.add_argument("--rerank", type=int, default=32)
    ap.add_argument("--device", default=None, help="OpenCL device P:D (default: every PoCL build, "
                                                   "side by side)")
    ap.add_argument("--json", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--no-peers", action="store_true", help="skip NumPy and faiss")
    args = ap.parse_args()
    argv = [a for a in sys.argv[1:]]
    runs = per_device(argv, args.device)
    if runs is not None:
        side_by_side(runs, "queries/s")
        return

    db = make_features(args.meshes, args.views, args.dim)
    q = make_queries(args.meshes, args.dim, args.queries)
    n, k = db.shape[0], args.k
    print(f"database {n} x {args.dim} float32 ({db.nbytes / 2**20:.0f} MiB), "
          f"{args.queries} queries, k={k}, medians of {args.runs} runs; "
          f"load average before: {os.getloadavg()[0]:.2f} (2 cores, shared)")

    # float64 reference (exact up to ~1e-16 relative)
    d64 = np.einsum("ij,ij->i", db.astype(np.float64), db.astype(np.float64))[None, :] \
        - 2.0 * (q.astype(np.float64) @ db.T.astype(np.float64)) \
        + np.einsum("ij,ij->i", q.astype(np.float64), q.astype(np.float64))[:, None]
    ref_top = np.argsort(d64, axis=1, kind="stable")[:, :k]
    del d64

    methods = [] if args.no_peers else [
        ("numpy sgemm scan", _run_numpy),
        ("faiss IndexFlatL2", _run_faiss),
    ]
    methods += [
        ("ucad runtime only (N=16)", lambda d, qq, kk: _run_ours(d[:16], qq, kk, "f32")),
        ("ucad f32, cold caches", lambda d, qq, kk: _run_ours(d, qq, kk, "f32", cold=True)),
        ("ucad f32", lambda d, qq, kk: _run_ours(d, qq, kk, "f32")),
        ("ucad f16", lambda d, qq, kk: _run_ours(d, qq, kk, "f16")),
    ]
    for dims in map(int, args.pca_dims.split(",")):
        methods += [
            (f"ucad pca d={dims}",
             lambda d, qq, kk, dims=dims: _run_ours(d, qq, kk, "pca", pca_dims=dims)),
            (f"ucad pca d={dims} rerank {args.rerank}",
             lambda d, qq, kk, dims=dims: _run_ours(d, qq, kk, "pca", pca_dims=dims,
                                                    rerank=args.rerank)),
        ]
    ctx = mp.get_context("fork")
    results = {}
    for name, maker in methods:
        a, b = ctx.Pipe(False)
        p = ctx.Process(target=_child, args=(b, name, maker, db, q, k, args.runs))
        p.start()
        b.close()                      # so that a child that dies gives EOFError, not a hang
        try:
            results[name] = a.recv()
        except EOFError:
            print(f"{name}: failed (is it installed?)")
        p.join()

    exact = results.get("ucad f32")
    print(f"\n{'method':34s} {'build s':>8s} {'first s':>8s} {'median ms':>10s} {'q/s':>8s} "
          f"{'peak MiB':>9s} {'top1=f32':>9s} {'R@1':>6s} {'R@10':>6s}")
    for name, (_, build, first, times, peak, idx, _dist) in results.items():
        med = float(np.median(times))
        row = (f"{name:34s} {build:8.2f} {first:8.3f} {med * 1e3:10.1f} {len(q) / med:8.0f} "
               f"{peak / 2**20:9.0f}")
        if "runtime only" in name:
            print(row)
            continue
        top1_32 = float(np.mean(idx[:, 0] == exact[5][:, 0])) if exact else float("nan")
        r1 = float(np.mean(idx[:, 0] == ref_top[:, 0]))
        r10 = float(np.mean([len(set(a) & set(b)) / k for a, b in zip(idx, ref_top)]))
        print(f"{row} {top1_32:9.3f} {r1:6.3f} {r10:6.3f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({name: len(q) / float(np.median(r[3])) for name, r in results.items()
                       if name.startswith("ucad") and "cold" not in name}, f)
    print("\nR@1 / R@10: overlap with the float64 reference top-1 / top-10 (top1=f32: same top-1 "
          "as ucad f32). 'build': index construction incl. program build; 'first': first search, "
          "incl. PoCL's compile of each kernel at its first launch (cold row: empty caches). Peak: "
          "process RSS high-water mark minus RSS at fork; the 'runtime only' row is the PoCL/LLVM "
          "baseline inside every ucad row.")


if __name__ == "__main__":
    main()
