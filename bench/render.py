"""Rendering throughput and error: ucad-cl's OpenCL rasterizer vs Open3D's RaycastingScene (Embree).

Both produce the same material-id / triangle-id / depth maps of the same mesh through the same
pixel centres, in the same run. ucad-cl is measured on both kernel paths: 'serial' (one work-item
per view, explicit 16-lane vectors; the default on CPU devices) and 'parallel' (one work-item per
face and view, atomic min; the default on GPUs); speed-up is against Open3D. Each (implementation, mesh, size) is measured in a fresh
subprocess so that the peak resident memory (ru_maxrss) belongs to it alone; times are medians
of --repeats runs after one warm-up. Open3D's rays are generated once per ring outside the timed
region (in its favour). Compile time is reported apart: 'cold' with every kernel cache disabled,
'cached' for the first call of a new process with the caches on (the normal case).

    python bench/render.py                    # 10k/100k/500k triangles x 128/256/512 px, 72 views
    python bench/render.py --quick            # smaller, for a smoke run
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def bench_mesh(n_tris: int):
    """A synthetic vehicle of about ``n_tris`` triangles (ucad_cl.synth)."""
    from ucad_cl.synth import make_vehicle
    return make_vehicle(7, "sedan", target_triangles=n_tris).mesh()


def open3d_maps(mesh, ring, rays):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    V, H, W = ring.n_views, ring.height, ring.width
    ans = scene.cast_rays(rays)
    prim = ans["primitive_ids"].numpy().astype(np.int64)
    prim[prim == 4294967295] = -1
    tri = prim.reshape(V, H, W)
    mat = np.where(tri >= 0, mesh.face_material[np.maximum(tri, 0)].astype(np.int64) + 1, 0)
    return tri, mat.astype(np.uint16)


def make_rays(ring):
    import open3d as o3d

    from ucad_cl.cameras import pixel_rays

    rays = []
    for v in range(ring.n_views):
        o, d = pixel_rays(ring.K, ring.w2c[v], ring.width, ring.height)
        d = d.reshape(-1, 3)
        rays.append(np.concatenate([np.broadcast_to(o, d.shape), d], 1))
    return o3d.core.Tensor(np.concatenate(rays).astype(np.float32))


def child(impl: str, n_tris: int, size: int, views: int, repeats: int) -> dict:
    import resource

    from ucad_cl.cameras import make_ring

    mesh = bench_mesh(n_tris)
    ring = make_ring(azimuth_step=360.0 / views, elevations=(15.0,), size=size)
    out = {"impl": impl, "tris": mesh.n_faces, "size": size, "views": ring.n_views}
    times = []
    if impl.startswith("ucad-"):
        from ucad_cl.render import render_views
        path = impl.split("-", 1)[1]
        t0 = time.perf_counter()
        res = render_views(mesh, ring, path=path)
        out["first_call_s"] = time.perf_counter() - t0
        for _ in range(repeats):
            t0 = time.perf_counter()
            res = render_views(mesh, ring, path=path)
            times.append(time.perf_counter() - t0)
        mat = res.mat_id
    else:
        rays = make_rays(ring)
        tri, mat = open3d_maps(mesh, ring, rays)
        for _ in range(repeats):
            t0 = time.perf_counter()
            tri, mat = open3d_maps(mesh, ring, rays)
            times.append(time.perf_counter() - t0)
    np.save(os.environ["UCAD_BENCH_OUT"], mat)
    out["seconds"] = float(np.median(times))
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return out


def run_child(impl, n_tris, size, views, repeats, tmp, env_extra=None) -> tuple[dict, np.ndarray]:
    path = os.path.join(tmp, f"{impl}-{n_tris}-{size}.npy")
    env = dict(os.environ, UCAD_BENCH_OUT=path, **(env_extra or {}))
    cmd = [sys.executable, __file__, "--child", impl, str(n_tris), str(size), str(views), str(repeats)]
    res = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if res.returncode:
        raise RuntimeError(f"{impl} {n_tris} {size} failed:\n{res.stderr[-3000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1]), np.load(path)


def compile_times(tmp) -> dict:
    """First-call time with all caches disabled (cold compile) and with caches (new process)."""
    out = {}
    for label, extra in (("cold", {"POCL_KERNEL_CACHE": "0", "PYOPENCL_NO_CACHE": "1"}), ("cached", {})):
        r, _ = run_child("ucad-serial", 10_000, 128, 8, 1, tmp, extra)
        out[label] = r["first_call_s"] - r["seconds"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--child", nargs=5, help=argparse.SUPPRESS)
    ap.add_argument("--tris", type=int, nargs="+", default=[10_000, 100_000, 500_000])
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512])
    ap.add_argument("--views", type=int, default=72)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--paths", nargs="+", default=["serial", "parallel"],
                    choices=["serial", "parallel"], help="ucad-cl kernel paths to measure")
    ap.add_argument("--quick", action="store_true", help="10k/100k tris, 128/256 px, 3 repeats")
    args = ap.parse_args()
    if args.child:
        impl, n, s, v, r = args.child
        print(json.dumps(child(impl, int(n), int(s), int(v), int(r))))
        return
    if args.quick:
        args.tris, args.sizes, args.repeats = [10_000, 100_000], [128, 256], 3
    import tempfile

    from ucad_cl.runtime import get_runtime

    print(f"device: {get_runtime().describe()}")
    with tempfile.TemporaryDirectory() as tmp:
        ct = compile_times(tmp)
        print(f"kernel compile (first call minus steady call): cold {ct['cold']:.2f} s, "
              f"cached {ct['cached']:.3f} s\n")
        hdr = (f"{'tris':>8} {'px':>4} {'impl':>13} {'views/s':>9} {'Mpix/s':>8} {'Mtri/s':>8} "
               f"{'peakMB':>7} {'speedup':>8} {'disagree%':>10}")
        print(hdr)
        print("-" * len(hdr))
        for n in args.tris:
            for s in args.sizes:
                ours = [run_child(f"ucad-{p}", n, s, args.views, args.repeats, tmp)
                        for p in args.paths]
                peer, m2 = run_child("open3d", n, s, args.views, args.repeats, tmp)
                for r, m in ours + [(peer, m2)]:
                    vps = r["views"] / r["seconds"]
                    sp = peer["seconds"] / r["seconds"]
                    dis = 100.0 * float((m != m2).mean())
                    print(f"{r['tris']:>8} {s:>4} {r['impl']:>13} {vps:>9.1f} "
                          f"{vps * s * s / 1e6:>8.1f} {vps * r['tris'] / 1e6:>8.1f} "
                          f"{r['peak_rss_mb']:>7.0f} {sp:>7.2f}x {dis:>10.3f}")
                sys.stdout.flush()


if __name__ == "__main__":
    main()
