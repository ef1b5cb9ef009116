"""Decimation speed against error: ucad_cl.decimate (exact material boundaries) vs plain QEM.

For synth vehicles of about 200k and 1M triangles and budgets (full, 100k, 50k, 20k, 10k, 5k)
prints, per variant: decimation time, peak extra RSS during decimation, render time of 72 views
x 256 px, and the pixel disagreement of the material maps and of the silhouette against the full
mesh (on the union of both foregrounds). Times and errors are medians over ``--runs`` runs
(errors are deterministic; they are identical across runs). The peer is plain pymeshlab QEM on
the mesh as stored (``decimate(..., preserve_boundaries=False)``).

    .venv/bin/python bench/decimate.py --sizes 200000 1000000 --runs 3
"""
from __future__ import annotations

import argparse
import os
import statistics
import threading
import time

import numpy as np

from ucad_cl.cameras import make_ring
from ucad_cl.decimate import decimate
from ucad_cl.render import render_views
from ucad_cl.synth import make_vehicle

BUDGETS = (0, 100_000, 50_000, 20_000, 10_000, 5_000)     # 0 = full mesh
VARIANTS = {"exact": dict(preserve_boundaries=True), "plain": dict(preserve_boundaries=False)}


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


class PeakRSS:
    """Samples RSS every 5 ms in a thread; ``peak`` is the largest value above the start."""

    def __enter__(self):
        self.base = self.peak = rss_mb()
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()
        return self

    def _run(self):
        while not self._stop.wait(0.005):
            self.peak = max(self.peak, rss_mb())

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, rss_mb())

    @property
    def extra(self) -> float:
        return self.peak - self.base


def _peak_child(mesh, budget, kw, conn):
    with PeakRSS() as p:
        decimate(mesh, budget, **kw)
    conn.send(p.extra)


def peak_extra_mb(mesh, budget, kw) -> float:
    """Peak RSS above the baseline of one decimation in a fresh (spawned) process."""
    import multiprocessing as mp
    ctx = mp.get_context("spawn")
    a, b = ctx.Pipe()
    proc = ctx.Process(target=_peak_child, args=(mesh, budget, kw, b))
    proc.start()
    extra = a.recv()
    proc.join()
    return extra


def timed(fn, runs):
    out, times = None, []
    for _ in range(runs):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return out, statistics.median(times)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[200_000, 1_000_000])
    ap.add_argument("--budgets", type=int, nargs="+", default=list(BUDGETS))
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--seed", type=int, default=3)
    args = ap.parse_args()

    ring = make_ring(azimuth_step=5.0, elevations=(15.0,), size=256)       # 72 views x 256 px
    t = time.perf_counter()
    render_views(make_vehicle(0).mesh(), ring)
    print(f"render warm-up (kernel compile + first launch): {time.perf_counter() - t:.1f} s")
    print("+RSS MB: peak resident memory above the baseline of a fresh process, one decimation")
    print(f"{'mesh':>9} {'budget':>7} {'variant':>7} {'faces':>8} {'decim s':>8} "
          f"{'+RSS MB':>8} {'render s':>8} {'mat dis %':>9} {'sil dis %':>9}")
    for size in args.sizes:
        mesh = make_vehicle(args.seed, target_triangles=size).mesh()
        full, t_full = timed(lambda m=mesh: render_views(m, ring), args.runs)
        fg = full.mat_id > 0
        print(f"{mesh.n_faces:>9} {'full':>7} {'-':>7} {mesh.n_faces:>8} {0.0:>8.2f} "
              f"{0.0:>8.0f} {t_full:>8.2f} {0.0:>9.3f} {0.0:>9.3f}")
        for budget in args.budgets:
            if budget <= 0 or budget >= mesh.n_faces:
                continue
            for name, kw in VARIANTS.items():
                out, t_dec = timed(lambda m=mesh, b=budget, k=kw: decimate(m, b, **k), args.runs)
                peak = peak_extra_mb(mesh, budget, kw)
                views, t_render = timed(lambda o=out: render_views(o, ring), args.runs)
                union = fg | (views.mat_id > 0)
                mat_dis = 100.0 * np.mean(views.mat_id[union] != full.mat_id[union])
                sil_dis = 100.0 * np.mean((views.mat_id > 0)[union] != fg[union])
                print(f"{mesh.n_faces:>9} {budget:>7} {name:>7} {out.n_faces:>8} "
                      f"{t_dec:>8.2f} {peak:>8.0f} "
                      f"{t_render:>8.2f} {mat_dis:>9.3f} {sil_dis:>9.3f}", flush=True)


if __name__ == "__main__":
    main()
