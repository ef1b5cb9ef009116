"""Orientation: the canonical vehicle frame found by ``ucad_cl.orient`` against a plain baseline.

Baseline: the file's longest bounding-box axis is the length and its shortest the height, both
taken in their positive direction (it cannot tell up from down or front from back).

Table 1: every real model of ``../shared/data/vehicles`` (manifest ``up`` / ``front``) posed in
all 24 axis-aligned rotations and 10 random yaws about its true up (seeded per model): up correct
(within 10 deg), front correct (within 15 deg), median yaw error (the front projected onto the
plane perpendicular to the true up), per model and pooled, with the deciding cues of every miss.
``godot_truck_town_vehicles.glb`` (five vehicles overlapping in one file) is scored on up only.
These models were looked at while the cues were designed: their figures are NOT held out.

Table 2: generated vehicles (``ucad_cl.synth``, written as GLB and re-loaded through ingest) with
seeds from --seed (never used for development or tuning), cycling through the pose cases (as
built, 24 axis poses, yaw, tilt up to 3 deg, Z-up, arbitrary 3-D rotation) and bodies (plain,
trailer, no wheels, two vehicles side by side, both ends alike; the last is scored on up only
and must come out flagged uncertain). Held out.

Table 2b: low-poly generated vehicles (seeds from --lowpoly-seed, never used for development or
tuning; the cues were tuned on seeds 700000-710223): lamps in the body's texture (textured_body),
no emission, MTL-like materials, one glass / no glass / opaque glass, meaningless names, in
every kind, each plain, cartoon, wedge and cartoon + wedge (``synth.SHAPE_TRAITS``), re-posed
by an axis rotation; front right, flagged (front_ambiguous) and wrong with confidence >= 0.5
(the worst outcome), with all cues and without the cabin and bed cues (main's estimate before
them). Held out.

Table 3: ablation, each cue left out in turn (real models in 3 poses each; generated: the first
--ablate vehicles of table 2).

Table 4: milliseconds per mesh (process CPU time, median and p90) for 50k-triangle generated
vehicles (all seven kinds) and for the real models: the coarse-to-fine cascade against the
full estimate alone, interleaved, split by the path the cascade takes, with the fast-path
share. Table 2 also gives the fast-path share of the generated vehicles.

    python bench/orient.py                      # the full run (~15 min on a loaded 2-core box)
    python bench/orient.py --generated 60 --ablate 30 --real-yaws 3     # quick look
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from ucad_cl.synth import axis_angle, axis_rotations  # noqa: E402

VEHICLES = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "vehicles"
MULTI = {"godot_truck_town_vehicles.glb"}          # several vehicles: scored on up only


def angle(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    c = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def about(axis, deg) -> np.ndarray:
    """Rotation by ``deg`` degrees about ``axis``."""
    return axis_angle(axis, math.radians(deg))


def repose(mesh, Q):
    """The mesh as ingest gives a file posed by rotation Q (a signed permutation exactly)."""
    v = np.asarray(mesh.vertices, np.float64)
    if np.all(np.isin(Q, (-1.0, 0.0, 1.0))):
        cols = np.argmax(np.abs(Q), axis=1)
        v = v[:, cols] * Q[np.arange(3), cols]
    else:
        v = v @ Q.T
    lo, hi = v.min(0), v.max(0)
    return replace(mesh, vertices=(v - (lo + hi) / 2) / np.sqrt(np.sort((hi - lo) ** 2).sum()),
                   orientation=None)


def baseline(mesh) -> np.ndarray:
    """Rotation rows (front, up, right): longest box axis = front (+), shortest = up (+)."""
    ext = np.ptp(np.asarray(mesh.vertices), axis=0)
    order = np.argsort(-ext, kind="stable")
    f, u = np.eye(3)[order[0]], np.eye(3)[order[2]]
    return np.stack([f, u, np.cross(f, u)])


def score(R, up, front):
    """(up error, front error, yaw error) in degrees; front/yaw None without a front."""
    ue = angle(R[1], up)
    if front is None:
        return ue, None, None
    fe = angle(R[0], front)
    u = np.asarray(up, float) / np.linalg.norm(up)
    fp = R[0] - (R[0] @ u) * u
    ye = angle(fp, front) if np.linalg.norm(fp) > 1e-9 else 180.0
    return ue, fe, ye


def summary(rows) -> tuple[float, float, float, int, int]:
    """rows of (up_err, front_err|None, yaw|None) -> (up %, front %, median yaw, n, n_front)."""
    up = [r[0] <= 10 for r in rows]
    fr = [r[1] <= 15 for r in rows if r[1] is not None]
    yaw = [r[2] for r in rows if r[2] is not None]
    return (100 * np.mean(up), 100 * np.mean(fr) if fr else float("nan"),
            float(np.median(yaw)) if yaw else float("nan"), len(up), len(fr))


def deciding(o, keep=4) -> str:
    cues = sorted(o.cues.items(), key=lambda kv: -abs(kv[1]))[:keep]
    return ", ".join(f"{k} {v:+.2f}" for k, v in cues) + (f" [{', '.join(o.flags)}]"
                                                           if o.flags else "")


# ----------------------------------------------------------------------------- real models

def real_models(args):
    from ucad_cl.ingest import load_mesh
    from ucad_cl.orient import AXES, estimate_orientation

    manifest = json.loads((VEHICLES / "manifest.json").read_text())["models"]
    rows_all, base_all, yaw_all, per_model, misses, loaded = [], [], [], [], [], {}
    for model in manifest:
        mesh = load_mesh(VEHICLES / model["file"], orientation=None)
        loaded[model["file"]] = mesh
        up0 = AXES[model["up"]]
        front0 = None if model["file"] in MULTI else AXES[model["front"]]
        rng = np.random.default_rng(list(model["file"].encode()))     # seeded per model
        poses = [("axis", Q) for Q in axis_rotations()] + [
            ("yaw", about(up0, a)) for a in rng.uniform(0, 360, args.real_yaws)]
        rows, base, yaws = [], [], []
        for kind, Q in poses:
            m = repose(mesh, Q)
            o = estimate_orientation(m)
            up, front = Q @ up0, (Q @ front0 if front0 is not None else None)
            r = score(o.rotation, up, front)
            rows.append(r)
            base.append(score(baseline(m), up, front))
            if kind == "yaw" and r[2] is not None:
                yaws.append(r[2])
            if r[0] > 10 or (r[1] is not None and r[1] > 15):
                misses.append((model["file"], kind, r, o))
        rows_all += rows
        base_all += base
        yaw_all += yaws
        per_model.append((model["file"], summary(rows), summary(base),
                          float(np.median(yaws)) if yaws else float("nan")))
    print("\nTable 1: real models x (24 axis-aligned poses + %d yaws); NOT held out" % args.real_yaws)
    print("(yaw med: median yaw error over all poses; yawed: over the random-yaw poses only)")
    print(f"{'model':44s} {'up %':>6s} {'front %':>8s} {'yaw med':>8s} {'yawed':>6s} | "
          f"{'base up':>8s} {'base fr':>8s} {'base yaw':>9s}")
    for name, s, b, y in per_model:
        print(f"{name[:44]:44s} {s[0]:6.1f} {s[1]:8.1f} {s[2]:8.2f} {y:6.2f} | {b[0]:8.1f} "
              f"{b[1]:8.1f} {b[2]:9.2f}")
    s, b = summary(rows_all), summary(base_all)
    yw = float(np.median(yaw_all)) if yaw_all else float("nan")
    print(f"{'POOLED (%d poses, %d with a front)' % (s[3], s[4]):44s} {s[0]:6.1f} {s[1]:8.1f} "
          f"{s[2]:8.2f} {yw:6.2f} | {b[0]:8.1f} {b[1]:8.1f} {b[2]:9.2f}")
    print("goals: up >= 99 %, front >= 97 %, median yaw error <= 2 deg")
    print(f"misses ({len(misses)}):" if misses else "misses: none")
    for name, kind, r, o in misses:
        print(f"  {name} ({kind}): up {r[0]:.1f} front {r[1] if r[1] is None else round(r[1], 1)}"
              f" conf up {o.up_confidence:.2f} front {o.front_confidence:.2f}; {deciding(o)}")
    return loaded


# ----------------------------------------------------------------------------- generated

POSES = ("as built", "axis", "yaw", "tilt", "z_up", "rotated")
BODIES = ("plain", "trailer", "plain", "missing_wheels", "plain", "two_vehicles", "plain",
          "symmetric_ends")


def generated_case(i: int, seed0: int, detail_tris: int):
    from ucad_cl.synth import KINDS, make_vehicle

    kind = KINDS[i % len(KINDS)]
    pose = POSES[(i // len(KINDS)) % len(POSES)]
    body = BODIES[(i // (len(KINDS) * len(POSES))) % len(BODIES)]
    kw = dict(target_triangles=detail_tris, name=f"gen_{i:04d}")
    if pose in ("axis", "yaw", "tilt"):
        kw["pose"] = pose
    elif pose != "as built":
        kw["messy"] = (pose,)
    if body == "missing_wheels":
        kw["messy"] = kw.get("messy", ()) + ("missing_wheels",)
    elif body != "plain":
        kw["body"] = body
    return make_vehicle(seed0 + i, kind, **kw), kind, pose, body


def generated(args, disabled_sets=None):
    from ucad_cl.ingest import load_mesh
    from ucad_cl.orient import estimate_orientation, takes_fast_path

    rows, base, cases, misses, fast_path = [], [], [], [], []
    flags_ok = {"symmetric_ends": [], "two_vehicles": []}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.generated):
            v, kind, pose, body = generated_case(i, args.seed, args.triangles)
            mesh = load_mesh(v.write(tmp), orientation=None)
            t = v.truth["orientation"]
            front = t["front"] if t["front_defined"] else None
            o = estimate_orientation(mesh)
            fast_path.append(takes_fast_path(mesh))
            r = score(o.rotation, t["up"], front)
            rows.append(r)
            base.append(score(baseline(mesh), t["up"], front))
            cases.append((kind, pose, body, mesh, t, front))
            if body == "symmetric_ends":
                flags_ok[body].append(o.uncertain)
            if body == "two_vehicles":
                flags_ok[body].append("multiple_vehicles" in o.flags)
            if r[0] > 10 or (r[1] is not None and r[1] > 15):
                misses.append((i, kind, pose, body, r, o))
    print(f"\nTable 2: {args.generated} generated vehicles, seeds {args.seed}..."
          f"{args.seed + args.generated - 1} (held out), through GLB + ingest "
          f"({time.perf_counter() - t0:.0f} s)")
    print(f"{'group':30s} {'n':>4s} {'up %':>6s} {'front %':>8s} {'yaw med':>8s} | "
          f"{'base up':>8s} {'base fr':>8s} | {'fast %':>7s}")
    for label, sel in [("pooled", lambda c: True)] + [
            (f"pose {p}", lambda c, p=p: c[1] == p) for p in POSES] + [
            (f"body {bd}", lambda c, bd=bd: c[2] == bd) for bd in dict.fromkeys(BODIES)]:
        idx = [k for k, c in enumerate(cases) if sel(c)]
        if not idx:
            continue
        s_ = summary([rows[k] for k in idx])
        b_ = summary([base[k] for k in idx])
        print(f"{label:30s} {len(idx):4d} {s_[0]:6.1f} {s_[1]:8.1f} {s_[2]:8.2f} | {b_[0]:8.1f} "
              f"{b_[1]:8.1f} | {100 * np.mean([fast_path[k] for k in idx]):7.1f}")
    print("goals: up >= 99.5 %, front >= 98 %")
    for body, ok in flags_ok.items():
        if ok:
            what = "flagged uncertain" if body == "symmetric_ends" else "flagged multiple_vehicles"
            print(f"{body}: {sum(ok)}/{len(ok)} {what}")
    print(f"misses ({len(misses)}):" if misses else "misses: none")
    for i, kind, pose, body, r, o in misses:
        print(f"  #{i} {kind} {pose} {body}: up {r[0]:.1f} front "
              f"{'-' if r[1] is None else round(r[1], 1)} conf up {o.up_confidence:.2f} front "
              f"{o.front_confidence:.2f}; {deciding(o)}")
    return cases


LOWPOLY = (("textured_body", "plain_lights", "mtl_like", "one_glass", "meaningless_names"),
           ("textured_body", "plain_lights", "mtl_like", "no_glass", "meaningless_names"),
           ("textured_body", "mtl_like", "opaque_glass", "one_glass", "meaningless_names"),
           ("one_paint", "plain_lights", "mtl_like", "meaningless_names"))
SHAPES = ((), ("cartoon",), ("wedge",), ("cartoon", "wedge"))


def lowpoly(args):
    from ucad_cl.orient import estimate_orientation
    from ucad_cl.synth import KINDS, make_vehicle

    rows: dict[str, list] = {}
    for i in range(args.lowpoly):
        kind = KINDS[i % len(KINDS)]
        shape = SHAPES[(i // len(KINDS)) % len(SHAPES)]
        v = make_vehicle(args.lowpoly_seed + i, kind, target_triangles=8000,
                         realism=LOWPOLY[i % len(LOWPOLY)] + shape)
        Q = axis_rotations()[i % 24]
        m = repose(v.mesh(), Q)
        for label, off in (("all cues", ()), ("- cabin, bed", ("cabin", "bed"))):
            o = estimate_orientation(m, disabled=off)
            ue, fe, _ = score(o.rotation, Q @ np.array([0.0, 1, 0]), Q @ np.array([1.0, 0, 0]))
            r = (ue <= 10, fe <= 15, "front_ambiguous" in o.flags,
                 fe > 15 and o.front_confidence >= 0.5)
            for g in ("pooled", f"kind {kind}", f"shape {'+'.join(shape) or 'plain'}"):
                rows.setdefault(g, []).append((label, r))
    print(f"\nTable 2b: {args.lowpoly} low-poly generated vehicles, seeds {args.lowpoly_seed}..."
          f"{args.lowpoly_seed + args.lowpoly - 1} (held out)")
    print(f"{'group':22s} {'n':>4s} | {'up %':>6s} {'front %':>8s} {'flag %':>7s} "
          f"{'wrong>=.5':>9s} | {'- cabin, bed: front %':>21s} {'flag %':>7s} {'wrong>=.5':>9s}")
    for g, rs in rows.items():
        a = np.array([r for lab, r in rs if lab == "all cues"], float)
        b = np.array([r for lab, r in rs if lab == "- cabin, bed"], float)
        print(f"{g:22s} {len(a):4d} | {100 * a[:, 0].mean():6.1f} {100 * a[:, 1].mean():8.1f} "
              f"{100 * a[:, 2].mean():7.1f} {int(a[:, 3].sum()):9d} | "
              f"{100 * b[:, 1].mean():21.1f} {100 * b[:, 2].mean():7.1f} {int(b[:, 3].sum()):9d}")


# ----------------------------------------------------------------------------- ablation

def ablation(args, loaded, cases):
    from ucad_cl.orient import AXES, FRONT_WEIGHTS, UP_WEIGHTS, estimate_orientation

    manifest = json.loads((VEHICLES / "manifest.json").read_text())["models"] if loaded else []
    real = []
    for model in manifest:
        mesh = loaded[model["file"]]
        up0 = AXES[model["up"]]
        front0 = None if model["file"] in MULTI else AXES[model["front"]]
        for Q in (np.eye(3), axis_rotations()[7], about(up0, 37.0)):
            real.append((repose(mesh, Q), Q @ up0, Q @ front0 if front0 is not None else None))
    gen = [(c[3], c[4]["up"], c[5]) for c in cases[:args.ablate]]
    groups = [("(all cues)", ())] + [(f"- {k}", (k,)) for k in UP_WEIGHTS] + [
        (f"- {k}", (k,)) for k in FRONT_WEIGHTS] + [
        ("- all names", ("names", "names_up", "wheel_names_low")),
        ("geometry only", ("names", "names_up", "wheel_names_low", "lamp_colours",
                           "windscreen", "cab_glass", "glass_high", "lamps_low"))]
    print(f"\nTable 3: ablation (real: {len(real)} poses, NOT held out; generated: {len(gen)}, "
          "held out)")
    print(f"{'cues':28s} {'real up':>8s} {'real fr':>8s} {'gen up':>8s} {'gen fr':>8s}")
    for label, off in groups:
        r = [score(estimate_orientation(m, disabled=off).rotation, u, f) for m, u, f in real]
        g = [score(estimate_orientation(m, disabled=off).rotation, u, f) for m, u, f in gen]
        sr = summary(r) if r else (float("nan"),) * 2
        sg = summary(g) if g else (float("nan"),) * 2
        print(f"{label:28s} {sr[0]:8.1f} {sr[1]:8.1f} {sg[0]:8.1f} {sg[1]:8.1f}")


# ----------------------------------------------------------------------------- speed

def speed(args, loaded):
    """Cascade (``estimate_orientation``) against the full estimate alone (``cascade=False``,
    today's estimate before the cascade), timed interleaved mesh by mesh, split by the path
    the cascade takes (``takes_fast_path``)."""
    from ucad_cl.orient import estimate_orientation, takes_fast_path
    from ucad_cl.synth import KINDS, make_vehicle

    gen = [make_vehicle(args.seed + 10_000 + k, KINDS[k % len(KINDS)],
                        target_triangles=50_000).mesh() for k in range(args.speed_meshes)]
    sets = [("generated 50k", gen), ("real models", list(loaded.values()))]

    def cpu(fn, mesh) -> float:
        t = time.process_time()
        fn(mesh)
        return time.process_time() - t

    print("\nTable 4: orientation time, process CPU ms per mesh: the cascade against the full "
          "estimate alone,\ninterleaved mesh by mesh, x %d runs (the machine is shared: "
          "compare the columns, not runs)" % args.repeats)
    print(f"{'meshes':34s} {'n':>4s} {'fast %':>7s} | {'cascade med':>11s} {'p90':>6s} | "
          f"{'full med':>9s} {'p90':>6s} | {'ratio med':>9s}")
    for label, meshes in sets:
        if not meshes:
            continue
        fast = [takes_fast_path(m) for m in meshes]
        for m in meshes:                                     # warm up (imports, caches)
            estimate_orientation(m)
        ours = [[] for _ in meshes]
        full = [[] for _ in meshes]
        for _ in range(args.repeats):
            for k, m in enumerate(meshes):
                ours[k].append(cpu(estimate_orientation, m))
                full[k].append(cpu(lambda m_: estimate_orientation(m_, cascade=False), m))
        for sub, sel in (("fast path", [f for f in fast]), ("full path", [not f for f in fast]),
                         ("all", [True] * len(fast))):
            idx = [k for k, on in enumerate(sel) if on]
            if not idx:
                continue
            o = 1000 * np.array([t for k in idx for t in ours[k]])
            f = 1000 * np.array([t for k in idx for t in full[k]])
            print(f"{label[:22] + ', ' + sub:34s} {len(idx):4d} "
                  f"{100 * np.mean([fast[k] for k in idx]):7.1f} | {np.median(o):11.1f} "
                  f"{np.quantile(o, 0.9):6.1f} | {np.median(f):9.1f} {np.quantile(f, 0.9):6.1f} | "
                  f"{np.median(o) / np.median(f):9.2f}")
    print("goal: <= 10 ms median per 50k-triangle mesh")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--generated", type=int, default=500, help="generated vehicles (table 2)")
    ap.add_argument("--seed", type=int, default=900_000, help="first generator seed")
    ap.add_argument("--triangles", type=int, default=20_000, help="triangles per generated car")
    ap.add_argument("--real-yaws", type=int, default=10, help="random yaws per real model")
    ap.add_argument("--lowpoly", type=int, default=280, help="low-poly vehicles (table 2b)")
    ap.add_argument("--lowpoly-seed", type=int, default=960_000,
                    help="first generator seed of table 2b")
    ap.add_argument("--ablate", type=int, default=120, help="generated vehicles in table 3")
    ap.add_argument("--repeats", type=int, default=3, help="timing repeats (table 4)")
    ap.add_argument("--speed-meshes", type=int, default=21,
                    help="generated 50k-triangle vehicles timed in table 4")
    ap.add_argument("--skip", nargs="*", default=[], choices=["real", "generated", "lowpoly",
                                                             "ablation", "speed"])
    args = ap.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    loaded, cases = {}, []
    if "real" not in args.skip and (VEHICLES / "manifest.json").exists():
        loaded = real_models(args)
    if "generated" not in args.skip:
        cases = generated(args)
    if "lowpoly" not in args.skip:
        lowpoly(args)
    if "ablation" not in args.skip and (loaded or cases):
        ablation(args, loaded, cases)
    if "speed" not in args.skip:
        speed(args, loaded)


if __name__ == "__main__":
    main()
