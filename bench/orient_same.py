"""Orientation records of this tree against another revision's, and their speed, in one process.

Loads ``ucad_cl/orient`` of ``--before`` (a git revision, default ``main``; the one module
``orient.py`` before the split, the package after it) beside this tree's
and, on the same meshes, checks that both give the same records: ``estimate_orientation`` with
the cascade and without it (``cascade=False``), rotation bits, confidences, flags, cues and
symmetry, and for the real models also ``orient_mesh`` (canonical vertices, ``file_to_norm``,
``mirror_z``). Meshes: generated vehicles (``ucad_cl.synth``, the pose and body cases of
``bench/orient.py`` table 2, through GLB + ingest) from the tuning seeds (--seed, default
800000; never the held-out 900000-900499), 50k-triangle generated vehicles as built and in one
axis pose, and the real models of ``../shared/data/vehicles`` in five poses (as built, two axis
poses, a yaw, an arbitrary rotation).

Then times both, alternating old and new mesh by mesh (process CPU ms per mesh, median and p90,
split by the path the new cascade takes) on the 50k-triangle vehicles and the real models.

    python bench/orient_same.py                        # 60 generated + 21 x 50k + real models
    python bench/orient_same.py --generated 500 --before 9ba4a35
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import numpy as np  # noqa: E402

from label_speed import load_revision  # noqa: E402
from orient import VEHICLES, generated_case, repose  # noqa: E402


def record(o) -> tuple:
    """Everything an Orientation decides, rotation as bits."""
    return (np.asarray(o.rotation, np.float64).tobytes(), o.up_confidence, o.front_confidence,
            o.flags, tuple(sorted(o.cues.items())), o.symmetry, o.source)


def placed(m) -> tuple:
    """``orient_mesh``'s result: canonical vertices (hash), file_to_norm bits, mirror_z."""
    return (hashlib.sha1(np.ascontiguousarray(m.vertices).tobytes()).hexdigest(),
            np.asarray(m.file_to_norm).tobytes(), m.orientation.mirror_z)


def cases(args) -> tuple[list, list, list]:
    """(generated via GLB, 50k-triangle generated, real models), each [(name, mesh)]."""
    from ucad_cl.ingest import load_mesh
    from ucad_cl.synth import KINDS, axis_angle, axis_rotations, make_vehicle

    glb = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.generated):
            v, kind, pose, body = generated_case(i, args.seed, args.triangles)
            glb.append((f"#{i} {kind} {pose} {body}", load_mesh(v.write(tmp), orientation=None)))
    big = []
    for k in range(args.speed_meshes):
        m = make_vehicle(args.seed + 20_000 + k, KINDS[k % len(KINDS)],
                         target_triangles=50_000).mesh()
        big += [(f"50k #{k}", m), (f"50k #{k} axis 7", repose(m, axis_rotations()[7]))]
    real = []
    if (VEHICLES / "manifest.json").exists():
        poses = [("as built", np.eye(3)), ("axis 7", axis_rotations()[7]),
                 ("axis 13", axis_rotations()[13]),
                 ("yaw 37", axis_angle([0, 1, 0], math.radians(37))),
                 ("rotated", axis_angle([0.3, -0.8, 0.5], math.radians(131)))]
        for model in json.loads((VEHICLES / "manifest.json").read_text())["models"]:
            mesh = load_mesh(VEHICLES / model["file"], orientation=None)
            real += [(f"{model['file']} {p}", repose(mesh, Q)) for p, Q in poses]
    return glb, big, real


def compare(old, new, meshes, placement: bool) -> tuple[int, list[str]]:
    """(records compared, 'mesh: what' of those that differ)."""
    def answers(mod, m) -> list[tuple[str, tuple]]:
        out = [("cascade", record(mod.estimate_orientation(m))),
               ("full", record(mod.estimate_orientation(m, cascade=False)))]
        return out + ([("orient_mesh", placed(mod.orient_mesh(m)))] if placement else [])

    n, differ = 0, []
    for name, m in meshes:
        for (what, a), (_, b) in zip(answers(old, m), answers(new, m)):
            n += 1
            if a != b:
                differ.append(f"{name}: {what}")
    return n, differ


def timing(old, new, meshes, repeats: int, label: str) -> None:
    def cpu(fn, m) -> float:
        t = time.process_time()
        fn(m)
        return 1000.0 * (time.process_time() - t)

    fast = np.array([new.takes_fast_path(m) for _, m in meshes])
    for _, m in meshes:                                      # warm up
        old.estimate_orientation(m)
        new.estimate_orientation(m)
    to: list[list[float]] = [[] for _ in meshes]
    tn: list[list[float]] = [[] for _ in meshes]
    for r in range(repeats):
        for k, (_, m) in enumerate(meshes):
            first, second = ((old, to), (new, tn)) if (r + k) % 2 else ((new, tn), (old, to))
            first[1][k].append(cpu(first[0].estimate_orientation, m))
            second[1][k].append(cpu(second[0].estimate_orientation, m))
    for sub, sel in (("fast path", fast), ("full path", ~fast), ("all", np.ones_like(fast))):
        idx = np.flatnonzero(sel)
        if idx.size:
            o = np.array([t for k in idx for t in to[k]])
            n = np.array([t for k in idx for t in tn[k]])
            print(f"{label + ', ' + sub:28s} {idx.size:4d} | {np.median(o):7.2f} "
                  f"{np.quantile(o, 0.9):6.2f} | {np.median(n):7.2f} {np.quantile(n, 0.9):6.2f}"
                  f" | {np.median(n) / np.median(o):5.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--before", default="main", help="git revision to compare against")
    ap.add_argument("--generated", type=int, default=60, help="generated vehicles via GLB")
    ap.add_argument("--seed", type=int, default=800_000, help="first generator seed (tuning)")
    ap.add_argument("--triangles", type=int, default=20_000)
    ap.add_argument("--speed-meshes", type=int, default=21, help="50k-triangle vehicles")
    ap.add_argument("--repeats", type=int, default=5, help="timing repeats")
    args = ap.parse_args()
    old = load_revision(args.before, "orient", "orient_before")
    from ucad_cl import orient as new

    glb, big, real = cases(args)
    total, differ = 0, []
    for meshes, placement in ((glb, False), (big, False), (real, True)):
        n, d = compare(old, new, meshes, placement)
        total, differ = total + n, differ + d
    print(f"records: {total} compared ({len(glb)} generated via GLB, {len(big)} 50k-triangle "
          f"poses, {len(real)} real model poses), {len(differ)} differ")
    for line in differ[:20]:
        print("  " + line)
    print(f"\nprocess CPU ms per mesh, {args.before} against this tree, alternating, x "
          f"{args.repeats}")
    print(f"{'meshes':28s} {'n':>4s} | {'before':>7s} {'p90':>6s} | {'now':>7s} {'p90':>6s} |"
          f" ratio")
    timing(old, new, big[::2], args.repeats, "generated 50k")
    if real:
        timing(old, new, real[::5], args.repeats, "real models")


if __name__ == "__main__":
    main()
