"""Benchmark: retrieval of the fit (``ucad_cl.fit``) over a catalogue of >= 100 generated meshes.

    .venv/bin/python bench/retrieval.py --seed 11 --count 110 --refs 30      # tuning seed
    .venv/bin/python bench/retrieval.py --seed 250025 --count 80 \\
        --catalog /tmp/ucad-fitbench/catalog_80 --library /tmp/ucad-fitbench/synth_250025_80

A generated library (``synth.write_library(..., seed, messy_fraction=0)``) is written and
catalogued once with default build options (256 px, azimuth step 5, elevation 15: the ring the
fit's pose search reads) into ``--work`` (reused; the build skips unchanged meshes), unless
``--catalog`` and ``--library`` name an existing pair (the catalogue may hold more meshes, e.g.
``bench/fit.py``'s real models as distractors).

References: ``--refs`` vehicles spread evenly over the library, one photo-like reference each
(``bench/fit.draw_reference``: Embree, off-grid camera, clutter, noise, JPEG; generator
``--ref-seed`` + index), the box jittered by up to 3 %.

Per reference:

* ``HOG rank``: the truth's rank among distinct meshes when every mesh is scored by its best
  stored view's squared HOG distance to the photo's query (``pose.query_features``, background
  replaced; GrabCut in the box, or the true mask with ``--true-mask``); exact float64 over every
  row. Reported as top-1/5/20/50 shares.
* ``kind``: the first mesh is of the truth's kind (sedan, van, ...: the library's JSON; a mesh
  outside the library, e.g. a real model, counts as another kind).
* ``az error``: degrees between the true camera azimuth and the azimuth of the best row of the
  first mesh (the mirror twin -a folded: generated vehicles are left/right symmetric).
* with ``--fit``: ``fit_photo``'s own answer (its preselection, exact ranking and the pose
  re-rank of ``fit.RERANK_POSE`` meshes): top-1 and seconds per photo, and the IoU against the
  true mask of GrabCut's first mask (``foreground.object_mask``) and of the object the fit
  used (``FitResult.object``: GrabCut rerun seeded by the first meshes' stored silhouettes).

``--real``: the references are ``bench/fit.py``'s real models (one each, 360 x 480) in the
catalogue given by ``--catalog`` (``--library``: its generated library, for the kinds; real
models have no kind: "right kind" is left out).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from fit import Vehicle, draw_reference, real_vehicles  # noqa: E402

TOPS = (1, 5, 20, 50)


def library(work: Path, seed: int, count: int) -> Path:
    from ucad_cl.synth import write_library

    lib = work / f"synth_{seed}_{count}"
    if not (lib / "done").exists():
        write_library(lib, count, seed, messy_fraction=0.0, progress=False)
        (lib / "done").write_text("ok\n")
    return lib


def catalogue(work: Path, lib: Path) -> Path:
    from ucad_cl.build import build
    from ucad_cl.jobs import BuildOptions

    cat = work / f"catalog_{lib.name}"
    build(lib, cat, BuildOptions(), workers=2, progress=False, log=lambda *a: None)
    return cat


def vehicle(js: Path) -> Vehicle:
    from ucad_cl.synth import make_vehicle

    t = json.loads(js.read_text())
    v = make_vehicle(int(t["seed"]), t["kind"], name=t["name"])
    mesh = v.mesh()
    parts = dict(v.truth["materials"])
    return Vehicle(t["name"], "generated", mesh,
                   [parts.get(m.name, "other") for m in mesh.materials], js.with_suffix(".glb"))


def kind_of(lib: Path, meta) -> str:
    """The generator's kind of a catalogued mesh of ``lib`` ('' for a mesh of another library)."""
    if Path(meta.library_root).resolve() != lib.resolve():
        return ""
    js = lib / Path(meta.path).with_suffix(".json")
    return str(json.loads(js.read_text())["kind"]) if js.is_file() else ""


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two (H, W) bool masks (0 when both are empty)."""
    union = np.count_nonzero(a | b)
    return float(np.count_nonzero(a & b) / union) if union else 0.0


def az_error(a: float, b: float) -> float:
    """Degrees between azimuths a and b, the mirror twin (-b) folded."""
    d = [abs((a - x + 180.0) % 360.0 - 180.0) for x in (b, -b)]
    return float(min(d))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=11, help="generated library seed")
    ap.add_argument("--count", type=int, default=110, help="generated meshes (>= 100)")
    ap.add_argument("--refs", type=int, default=30, help="references (one per vehicle)")
    ap.add_argument("--ref-seed", type=int, default=7000)
    ap.add_argument("--work", type=Path, default=Path("/tmp/ucad-retrieval"))
    ap.add_argument("--catalog", type=Path, default=None, help="an existing catalogue ...")
    ap.add_argument("--library", type=Path, default=None, help="... and its generated library")
    ap.add_argument("--true-mask", action="store_true", help="query with the true mask")
    ap.add_argument("--fit", action="store_true", help="also run fit_photo (top-1, seconds)")
    ap.add_argument("--real", action="store_true",
                    help="references of bench/fit.py's real models (needs --catalog)")
    ap.add_argument("--json", type=Path, default=None, help="write per-reference rows here")
    args = ap.parse_args(argv)

    from ucad_catalog.reader import CatalogReader
    from ucad_cl.features import HogExtractor
    from ucad_cl.fit import fit_photo
    from ucad_cl.foreground import object_mask
    from ucad_cl.jobs import content_sha256
    from ucad_cl.pose import query_features

    if (args.catalog is None) != (args.library is None):
        ap.error("--catalog and --library go together")
    if args.real and args.catalog is None:
        ap.error("--real needs --catalog (and --library): bench/fit.py's catalogue")
    args.work.mkdir(parents=True, exist_ok=True)
    lib = args.library or library(args.work, args.seed, args.count)
    cat = args.catalog or catalogue(args.work, lib)
    rows = []
    from ucad_cl.ingest import MeshLoader

    with CatalogReader(cat) as reader, MeshLoader() as mesh_loader:   # one mesh reader for the run
        metas = [m for m in reader.meshes() if m.state == "accepted"]
        ids = [m.sha256 for m in metas]
        feats = [np.asarray(reader.features(k), np.float64) for k in ids]
        azs = [np.array([v.azimuth for v in reader.view_angles(k)]) for k in ids]
        kinds = [kind_of(lib, m) for m in metas]
        print(f"catalogue {cat}: {len(ids)} accepted meshes, {sum(map(len, feats))} views")
        files = sorted(lib.glob("*.json"))
        step = max(1, len(files) // args.refs)
        hog = HogExtractor()
        if args.real:
            todo = [v for v in real_vehicles(None)
                    if content_sha256(v.path) in ids][:args.refs]
        else:
            todo = [vehicle(js) for js in files[::step][:args.refs]]
        for i, v in enumerate(todo):
            ref, box = draw_reference(v, i, (360, 480) if args.real else (480, 640),
                                      ref_seed=args.ref_seed)
            truth = content_sha256(v.path)
            given = {"mask": ref.mask} if args.true_mask else {"box": box}
            q, _ = query_features(ref.image, hog, **given)
            dist = [((f - q) ** 2).sum(axis=1) for f in feats]
            best = np.array([float(d.min()) for d in dist])
            order = np.argsort(best, kind="stable")      # ties: catalogue order
            rank = int(np.flatnonzero(order == ids.index(truth))[0])
            first = int(order[0])
            err = az_error(ref.azimuth, float(azs[first][int(np.argmin(dist[first]))]))
            row = {"vehicle": v.name, "rank": rank, "az_error": err,
                   "same_kind": (kinds[first] == kinds[ids.index(truth)] if not args.real
                                 else None),
                   "true_azimuth": ref.azimuth, "true_elevation": ref.elevation}
            if args.fit:
                t = time.perf_counter()
                res = fit_photo(ref.image, catalog=reader, mesh_loader=mesh_loader, **given)
                row["fit_top1"] = res.mesh_id == truth
                row["seconds"] = time.perf_counter() - t
                row["got"] = reader.mesh(res.mesh_id).path
                if not args.true_mask and res.object is not None:
                    first_mask = object_mask(ref.image, box=box).mask
                    row["iou_grabcut"] = iou(first_mask, ref.mask)
                    row["iou_fit"] = iou(res.object.mask, ref.mask)
            rows.append(row)
            print(f"{i:3d} {v.name[:28]:28s} HOG rank {rank:3d}  kind {row['same_kind']!s:5s}"
                  f"  az error {err:5.1f}"
                  + (f"  fit top-1 {int(row['fit_top1'])}  {row['seconds']:.2f} s"
                     if args.fit else "")
                  + (f"  IoU {row['iou_grabcut']:.2f} -> {row['iou_fit']:.2f}"
                     if "iou_fit" in row else "")
                  + (f"  (got {row['got']})" if args.fit and not row["fit_top1"] else ""),
                  flush=True)
    ranks = np.array([r["rank"] for r in rows])
    errs = np.array([r["az_error"] for r in rows])
    print(f"\n{len(rows)} references, {len(ids)} meshes, query "
          f"{'true mask' if args.true_mask else 'box (GrabCut)'}")
    print("HOG " + ", ".join(f"top-{k} {np.mean(ranks < k):.0%}" for k in TOPS)
          + ("" if args.real else
             f"; first mesh of the right kind {np.mean([r['same_kind'] for r in rows]):.0%}")
          + f", its azimuth within 10 deg: {np.mean(errs <= 10):.0%}")
    if args.fit:
        print(f"fit_photo top-1 {np.mean([r['fit_top1'] for r in rows]):.0%}, "
              f"median {np.median([r['seconds'] for r in rows]):.2f} s per photo")
        if rows and "iou_fit" in rows[0]:
            a = np.array([[r["iou_grabcut"], r["iou_fit"]] for r in rows])
            print(f"object mask IoU against the true mask: GrabCut median {np.median(a[:, 0]):.3f}"
                  f" (mean {a[:, 0].mean():.3f}), the fit's median {np.median(a[:, 1]):.3f} "
                  f"(mean {a[:, 1].mean():.3f})")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
