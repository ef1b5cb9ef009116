"""Part classification bench: prior-segmenter accuracy on the real vehicles and IoU-pass speed.

    .venv/bin/python bench/parts.py [--size 128] [--azimuth-step 15] [--repeats 5] [--models a,b]

Table 1: per real model of ``../shared/data/vehicles`` (loaded with ``ucad_cl.ingest.load_mesh``,
material names REPLACED by ``Material.000``...), the prior segmenter + ``classify_parts`` against
the manifest's material -> part mapping. Accuracy counts visible materials (not 'unseen'), and
also all materials. The same with the real names, for comparison.

Table 2: the histogram pass (``ucad_cl/kernels/parts.cl``) in views/s for several local sizes and
pixels-per-item, side by side with the NumPy peer (``np.bincount`` per view and part), medians of
``--repeats`` runs (total = host packing + upload + kernel + read back; kernel = enqueue to read
back), plus the first call per configuration and peak host memory. The first call includes
PoCL's per-local-size kernel compile only when its cache is cold: run with
``POCL_CACHE_DIR=$(mktemp -d) PYOPENCL_NO_CACHE=1`` to measure compile times.
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
VEHICLES = ROOT.parent / "shared" / "data" / "vehicles"

from ucad_cl.cameras import make_ring  # noqa: E402
from ucad_cl.classify import classify_parts, last_timing, part_histogram  # noqa: E402
from ucad_cl.render import render_views  # noqa: E402
from ucad_cl.segment import PriorSegmenter  # noqa: E402
from ucad_cl.artifacts import PART_NAMES  # noqa: E402

SKIP = {"ferrari_458.glb"}      # same model as ferrari_458_nodraco.glb


def numpy_histogram(mat_id, masks, n_ids):
    V, P = masks.shape[:2]
    out = np.zeros((V, n_ids, 1 + P), np.int64)
    for v in range(V):
        m = mat_id[v].ravel()
        out[v, :, 0] = np.bincount(m, minlength=n_ids)
        for p in range(P):
            out[v, :, 1 + p] = np.bincount(m[masks[v, p].ravel()], minlength=n_ids)
    return out


def accuracy_table(args):
    from ucad_cl.ingest import load_mesh

    manifest = json.loads((VEHICLES / "manifest.json").read_text())
    ring = make_ring(azimuth_step=args.azimuth_step, elevations=(15.0, 45.0), size=args.size)
    print(f"\n## Prior segmenter on real vehicles ({ring.n_views} views, {args.size} px), "
          "names replaced by Material.NNN")
    print(f"{'model':44s} {'mats':>4s} {'seen':>4s} {'acc seen':>8s} {'acc all':>7s} "
          f"{'acc w/ names':>12s}  wrong (material: got/expected)")
    tot_ok = tot_n = 0
    per_model = []
    for model in manifest["models"]:
        if model["file"] in SKIP or (args.models and model["file"] not in args.models):
            continue
        mesh = load_mesh(VEHICLES / model["file"])
        truth = model["materials"]
        views = render_views(mesh, ring)
        anon = replace(mesh, materials=[replace(m, name=f"Material.{i:03d}")
                                        for i, m in enumerate(mesh.materials)])
        res = {}
        for tag, msh in (("anon", anon), ("named", mesh)):
            masks = PriorSegmenter().segment(msh, views)
            res[tag] = classify_parts(msh, views, masks)
        ok = n = ok_all = ok_named = 0
        wrong = []
        for r_anon, r_named, orig in zip(res["anon"].rows, res["named"].rows, mesh.materials):
            exp = truth.get(orig.name)
            if exp is None:
                continue
            ok_all += r_anon.part == exp
            ok_named += r_named.part == exp
            if r_anon.part != "unseen":
                n += 1
                ok += r_anon.part == exp
                if r_anon.part != exp:
                    wrong.append(f"{orig.name}: {r_anon.part}/{exp}")
        tot_ok += ok
        tot_n += n
        acc = ok / n if n else float("nan")
        per_model.append(acc)
        print(f"{model['file']:44s} {len(truth):4d} {n:4d} {acc:8.1%} {ok_all / len(truth):7.1%} "
              f"{ok_named / len(truth):12.1%}  {'; '.join(wrong[:6])}")
    print(f"{'ALL (pooled over seen materials)':44s} {'':4s} {tot_n:4d} "
          f"{tot_ok / max(tot_n, 1):8.1%}"
          f"   median per model {np.nanmedian(per_model):.1%}")


def speed_table(args):
    from ucad_cl.runtime import get_runtime

    rt = get_runtime()
    rng = np.random.default_rng(0)
    V, S, P, n_ids = 72, args.size, len(PART_NAMES), 18
    # realistic maps: blocks of materials (long runs) and part masks = material's part
    blocks = rng.integers(1, n_ids, (V, S // 8, S // 8)).astype(np.uint16)
    mat = np.kron(blocks, np.ones((8, 8), np.uint16))
    mat[:, : S // 4] = 0
    part_of = rng.integers(0, P, n_ids)
    part_of[0] = -1
    masks = np.stack([part_of[mat] == p for p in range(P)], axis=1)
    ref = numpy_histogram(mat, masks, n_ids)
    print(f"\n## IoU histogram pass: {V} views x {S}x{S} px, {P} parts, {n_ids} ids "
          f"({rt.describe()})")
    print(f"{'impl':34s} {'first call s':>12s} {'median s':>9s} {'views/s':>9s} "
          f"{'kernel s':>9s} {'exact':>6s}")
    t = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        numpy_histogram(mat, masks, n_ids)
        t.append(time.perf_counter() - t0)
    med = float(np.median(t))
    print(f"{'numpy bincount (peer)':34s} {'':>12s} {med:9.4f} {V / med:9.1f} {'':>9s} {'ref':>6s}")
    for use_local in (True, False):
        for local in args.local_sizes:
            for ppi in args.ppi:
                t0 = time.perf_counter()
                h = part_histogram(mat, masks, n_ids=n_ids, local_size=local,
                                   pixels_per_item=ppi, use_local=use_local)
                first = time.perf_counter() - t0
                t, tk = [], []
                for _ in range(args.repeats):
                    t0 = time.perf_counter()
                    part_histogram(mat, masks, n_ids=n_ids, local_size=local,
                                   pixels_per_item=ppi, use_local=use_local)
                    t.append(time.perf_counter() - t0)
                    tk.append(last_timing["histogram"])
                med = float(np.median(t))
                name = f"{'local' if use_local else 'global'} atomics L={local} ppi={ppi}"
                print(f"{name:34s} {first:12.3f} {med:9.4f} {V / med:9.1f} "
                      f"{float(np.median(tk)):9.4f} {str(np.array_equal(h, ref)):>6s}")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak host RSS {peak:.0f} MiB; program build times: "
          + ", ".join(f"{k[0]} {v:.2f}s" for k, v in rt.compile_seconds.items()))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--azimuth-step", type=float, default=15.0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--models", type=lambda s: s.split(","), default=None)
    ap.add_argument("--skip-accuracy", action="store_true")
    ap.add_argument("--local-sizes", type=lambda s: [int(x) for x in s.split(",")],
                    default=[1, 4, 16, 64, 256])
    ap.add_argument("--ppi", type=lambda s: [int(x) for x in s.split(",")],
                    default=[64, 256, 1024])
    ap.add_argument("--skip-speed", action="store_true")
    args = ap.parse_args()
    if not args.skip_accuracy:
        if (VEHICLES / "manifest.json").exists():
            accuracy_table(args)
        else:
            print(f"(no vehicles at {VEHICLES}; accuracy table skipped)")
    if not args.skip_speed:
        speed_table(args)


if __name__ == "__main__":
    main()
