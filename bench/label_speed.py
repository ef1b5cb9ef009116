"""Labeller speed, this tree's code against another revision's, interleaved in one process.

Loads ``ucad_cl/labeller.py``, ``ucad_cl/segment.py`` and the shipped model of ``--before`` (a
git revision, default ``main``) beside this tree's, then on the same meshes and views
(generated vehicles of about --triangles triangles, cached like ``bench/build.py``'s library,
and the real models of ``../shared/data/vehicles`` when present) checks that both give the
same answer (features within 1e-6, identical parts, probabilities, splits and masks; a change
of features or model is listed as differences) and times, alternating old and new within every
repetition:

* label: ``label_materials`` (features, the layer behind glass, ONNX trees, splits);
* segment: ``LabellerSegmenter.segment`` (label + painting the masks), as the build calls it;
* prior: the hand-written ``PriorSegmenter.segment`` of each revision (the "added" baseline of
  ``bench/build.py``'s labelling row: painting the masks is common to both segmenters).

Wall ms per mesh: median over meshes and repetitions, and the median over meshes of each mesh's
minimum; CPU ms the same for process time. One PoCL thread (``POCL_MAX_PTHREAD_COUNT=1``) as in
a build worker, views 72 x 256 px at 15 degrees as the build's default ring.

    python bench/label_speed.py                    # 6 generated meshes + the real models
    python bench/label_speed.py --before 9ad7800   # against the code before the speed pass
    python bench/label_speed.py --before HEAD~3 --count 10 --reps 7
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("POCL_MAX_PTHREAD_COUNT", "1")
ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
VEHICLES = ROOT.parent / "shared" / "data" / "vehicles"


def load_revision(rev: str, module: str, as_name: str):
    """``ucad_cl/<module>.py`` of git revision ``rev`` as module ``ucad_cl.<as_name>``, or the
    package ``ucad_cl/<module>/`` of that revision (its files written to a temporary folder)."""
    show = subprocess.run(["git", "show", f"{rev}:ucad_cl/{module}.py"], cwd=ROOT,
                          capture_output=True, text=True)
    if show.returncode != 0:
        return _load_package_revision(rev, module, as_name)
    src = show.stdout
    name = f"ucad_cl.{as_name}"
    spec = importlib.util.spec_from_loader(name, loader=None, origin=str(ROOT / "ucad_cl"))
    mod = importlib.util.module_from_spec(spec)
    mod.__file__ = str(ROOT / "ucad_cl" / f"{module}.py")     # MODEL_DIR beside it
    sys.modules[name] = mod
    exec(compile(src, f"{rev}:ucad_cl/{module}.py", "exec"), mod.__dict__)
    return mod


def _load_package_revision(rev: str, module: str, as_name: str):
    """The package ``ucad_cl/<module>/`` of revision ``rev`` as ``ucad_cl.<as_name>``: its
    ``.py`` files copied to a temporary folder that serves as the package's path (relative
    imports of ``ucad_cl`` modules resolve to this tree's)."""
    import tempfile

    files = subprocess.run(["git", "ls-tree", "--name-only", f"{rev}:ucad_cl/{module}"],
                           cwd=ROOT, check=True, capture_output=True, text=True).stdout.split()
    folder = Path(tempfile.mkdtemp(prefix=f"{as_name}-")) / as_name
    folder.mkdir()
    for f in files:
        if f.endswith(".py"):
            (folder / f).write_text(subprocess.run(
                ["git", "show", f"{rev}:ucad_cl/{module}/{f}"], cwd=ROOT, check=True,
                capture_output=True, text=True).stdout, encoding="utf-8")
    name = f"ucad_cl.{as_name}"
    spec = importlib.util.spec_from_file_location(name, folder / "__init__.py",
                                                  submodule_search_locations=[str(folder)])
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def meshes(args):
    """[(name, mesh, views)]: generated vehicles, then the manifest's real models."""
    from ucad_cl.cameras import make_ring
    from ucad_cl.filter import filter_mesh
    from ucad_cl.ingest import IngestError, load_mesh
    from ucad_cl.render import render_views
    from ucad_cl.synth import write_library

    ring = make_ring(azimuth_step=5.0, elevations=(15.0,), size=256)
    lib = args.library / f"n{args.count}_t{args.triangles}"
    if not (lib / ".complete").exists():
        write_library(lib, args.count, seed=2026, target_triangles=args.triangles)
        (lib / ".complete").write_text("ok")
    paths = sorted(lib.glob("*.glb"))
    if args.real and (VEHICLES / "manifest.json").exists():
        import json
        manifest = json.loads((VEHICLES / "manifest.json").read_text(encoding="utf-8"))
        paths += [VEHICLES / m["file"] for m in manifest["models"]]
    out = []
    for p in paths:
        try:
            mesh = load_mesh(p)
        except IngestError as exc:
            print(f"skipped {p.name}: {exc}")
            continue
        if not filter_mesh(mesh).accepted:
            continue
        views = render_views(mesh, ring)
        views.material_counts()                  # cached by the build's filter before segment
        out.append((p.name if lib not in p.parents else f"gen:{p.stem}", mesh, views))
    return out


def revision_model(rev: str) -> Path:
    """The shipped model (``labeller.onnx`` + ``labeller.json``) of git revision ``rev``,
    written to a temporary folder: the old code reads the old model (a tree whose features
    changed ships a model the old code refuses)."""
    import tempfile

    out = Path(tempfile.mkdtemp(prefix="ucad-model-")) / "labeller.onnx"
    for suffix in (".onnx", ".json"):
        blob = subprocess.run(["git", "show", f"{rev}:ucad_cl/models/labeller{suffix}"],
                              cwd=ROOT, capture_output=True, check=True).stdout
        out.with_suffix(suffix).write_bytes(blob)
    return out


def same_answer(name, old, new, mesh, views, old_seg, new_seg) -> tuple[list[str], float]:
    """Differences between the old and new code's features, labels and masks (empty: same)
    and the largest feature difference."""
    import numpy as np

    bad = []
    a = old.material_table(mesh, views)
    b = new.material_table(mesh, views)
    shared = [n for n in new.FEATURE_NAMES if n in old.FEATURE_NAMES]     # compared by name
    if len(shared) != len(new.FEATURE_NAMES) or len(shared) != len(old.FEATURE_NAMES):
        bad.append(f"feature columns {len(old.FEATURE_NAMES)} -> {len(new.FEATURE_NAMES)} "
                   f"({len(shared)} shared)")
    xa = a.X[:, [old.FEATURE_NAMES.index(n) for n in shared]].astype(np.float64)
    xb = b.X[:, [new.FEATURE_NAMES.index(n) for n in shared]].astype(np.float64)
    d = float(np.abs(xa - xb).max(initial=0))
    if d > 1e-6:
        col = int(np.abs(xa - xb).max(axis=0).argmax())
        bad.append(f"features differ by {d:.2e} (column {shared[col]})")
    for k in ("pixels", "behind_pixels", "face_comp", "comp_material", "wheels"):
        if not np.array_equal(getattr(a, k), getattr(b, k)):
            bad.append(f"{k} differ")
    for k in ("comp_area", "comp_box", "comp_rho"):
        if getattr(a, k).shape != getattr(b, k).shape or not np.allclose(
                getattr(a, k), getattr(b, k), rtol=0, atol=1e-9):
            bad.append(f"{k} differ")
    la, lb = old_seg.segment(mesh, views), new_seg.segment(mesh, views)
    if not np.array_equal(la.labels.part, lb.labels.part):
        bad.append("parts differ")
    if not np.array_equal(la.labels.prob, lb.labels.prob):
        bad.append(f"probabilities differ by "
                   f"{float(np.abs(la.labels.prob - lb.labels.prob).max()):.2e}")
    if la.labels.splits != lb.labels.splits:
        bad.append("splits differ")
    if not (np.array_equal(la.bits, lb.bits) and np.array_equal(la.confidence, lb.confidence)):
        bad.append("masks differ")
    return [f"{name}: {x}" for x in bad], d


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--before", default="main", help="git revision of the old code (main)")
    ap.add_argument("--count", type=int, default=6, help="generated meshes (6)")
    ap.add_argument("--triangles", type=int, default=50_000)
    ap.add_argument("--reps", type=int, default=5, help="repetitions per mesh (5)")
    ap.add_argument("--no-real", dest="real", action="store_false",
                    help="leave out the real models (their answers are checked, not timed)")
    ap.add_argument("--library", type=Path, default=Path("/tmp/ucad-bench-library"))
    args = ap.parse_args()

    import numpy as np

    from ucad_cl import labeller as new
    from ucad_cl import segment as new_segment
    from ucad_cl.runtime import get_runtime

    old = load_revision(args.before, "labeller", "_labeller_before")
    old_segment = load_revision(args.before, "segment", "_segment_before")
    old_segment.label_materials = old.label_materials   # its import named this tree's labeller
    old_segment.LabellerModel = old.LabellerModel
    rt = get_runtime()
    print(f"device: {rt.device.name.strip()} ({rt.device.platform.version.strip()}), "
          f"POCL_MAX_PTHREAD_COUNT={os.environ.get('POCL_MAX_PTHREAD_COUNT')}")
    segs = {"old": old_segment.LabellerSegmenter(revision_model(args.before), runtime=rt),
            "new": new_segment.LabellerSegmenter(runtime=rt)}
    model = segs["new"].model
    data = meshes(args)

    diffs, dmax = [], 0.0
    for name, mesh, views in data:
        bad, d = same_answer(name, old, new, mesh, views, segs["old"], segs["new"])
        diffs, dmax = diffs + bad, max(dmax, d)
    n_real = sum(not n.startswith("gen:") for n, _, _ in data)
    print(f"answers compared on {len(data) - n_real} generated + {n_real} real meshes: "
          + (f"same (features differ by at most {dmax:.1e}; parts, probabilities, splits, "
             "masks equal)"
             if not diffs else f"{len(diffs)} DIFFERENCES"))
    for d in diffs:
        print("  " + d)

    timed = [(n, m, v) for n, m, v in data if n.startswith("gen:")]
    calls = {
        "label old": lambda m, v: old.label_materials(m, v, model=segs["old"].model, runtime=rt),
        "label new": lambda m, v: new.label_materials(m, v, model=model, runtime=rt),
        "segment old": segs["old"].segment,
        "segment new": segs["new"].segment,
        "prior old": old_segment.PriorSegmenter().segment,
        "prior new": new_segment.PriorSegmenter().segment,
    }
    wall = {k: np.zeros((len(timed), args.reps)) for k in calls}
    cpu = {k: np.zeros((len(timed), args.reps)) for k in calls}
    for _, m, v in timed[:1]:
        for fn in calls.values():
            fn(m, v)                                                # warm up
    for r in range(args.reps):
        for i, (_, m, v) in enumerate(timed):
            for k, fn in calls.items():                             # old and new alternate
                t0, c0 = time.perf_counter(), time.process_time()
                fn(m, v)
                wall[k][i, r] = 1000 * (time.perf_counter() - t0)
                cpu[k][i, r] = 1000 * (time.process_time() - c0)
    tris = [m.n_faces for _, m, _ in timed]
    print(f"\n{len(timed)} generated meshes of {min(tris)}-{max(tris)} triangles, 72 views x "
          f"256 px, {args.reps} repetitions, old = {args.before}, new = this tree")
    print(f"{'call':>12} {'median ms':>10} {'min ms':>8} {'CPU ms':>8}   "
          "(min: median over meshes of each mesh's minimum)")
    for k in calls:
        print(f"{k:>12} {np.median(wall[k]):>10.1f} {np.median(wall[k].min(axis=1)):>8.1f} "
              f"{np.median(cpu[k]):>8.1f}")
    for which in ("old", "new"):
        seg, pri = wall[f"segment {which}"], wall[f"prior {which}"]
        print(f"{'added ' + which:>12} {np.median(seg) - np.median(pri):>10.1f} "
              f"{np.median(seg.min(axis=1)) - np.median(pri.min(axis=1)):>8.1f}"
              f"{'':>9}   (segment - prior, same revision)")
    ratio = wall["label old"] / wall["label new"]
    print(f"label old / new: median ratio {np.median(ratio):.2f} (per mesh and repetition)")


if __name__ == "__main__":
    main()
