"""Benchmark: where retrieval's first stage (the search's HOG distance) places the true mesh,
for saved photo-like references, against one catalogue and optionally more stored rings.

    .venv/bin/python bench/fit.py --library 960 --ref-seed 3636 --save /tmp/refs3636
    .venv/bin/python bench/first_stage.py /tmp/refs3636 --catalog /tmp/ucad-fitbench/catalog_960
    .venv/bin/python bench/first_stage.py /tmp/refs3636 --catalog CAT --also CAT_EL10_20 \\
        --also CAT_EL10_20:2

``REFS`` is what ``bench/fit.py --save`` writes (``truth.json`` and the photos). Per photo:
``fit_photo`` runs against ``--catalog`` (retrieval, the box given); the object it used
(``FitResult.object``) gives the first stage's query (``pose.query_features``: the 64 px HOG
with the background replaced, as the search computes it); every mesh is scored by its best
stored row's squared distance of unit rows (exact, float64 over every row of the catalogue's
``feature_table``, no search index). The truth's place is the number of meshes scored nearer.

``--also CAT[:STEP]`` adds the stored rows of another catalogue of the same library (the same
meshes by content, e.g. built with other ``--elevations``; ``:STEP`` keeps every STEP-th view,
views are azimuth-minor): each mesh then scores its best row over both, so a denser stored ring
is measured without building it whole. Rows: the catalogue alone, then each ``--also`` added in
turn. Columns per source (real, generated): first-stage top-1 / top-5 / top-20 and the places
of the rest; and the fit's own top-1 (its re-rank and pose step included) against the first
catalogue. Not a test: a measurement tool (docs/FIT.md, "The stored ring's density").
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ucad_cl.features import unit_rows  # noqa: E402  (the search's own float64 unit rows)


def queries(refs: Path, catalog: Path) -> tuple[np.ndarray, list[dict], list[str]]:
    """(Q, D) first-stage queries of the references, their truth rows, the fit's answers."""
    import cv2

    from ucad_catalog.reader import CatalogReader
    from ucad_cl.features import HogExtractor
    from ucad_cl.fit import fit_photo
    from ucad_cl.ingest import MeshLoader
    from ucad_cl.pose import query_features

    truth = json.loads((refs / "truth.json").read_text())
    qs, answers = [], []
    with CatalogReader(catalog) as reader, MeshLoader() as loader:
        for i, t in enumerate(truth):
            photo = cv2.imread(str(refs / t["photo"]), cv2.IMREAD_COLOR)
            if photo is None:
                raise SystemExit(f"{refs / t['photo']}: cannot read the photo")
            photo = np.ascontiguousarray(photo[..., ::-1])
            res = fit_photo(photo, box=tuple(t["box"]), catalog=reader, mesh_loader=loader)
            q, _ = query_features(photo, HogExtractor(), mask=res.object.mask)
            qs.append(q)
            answers.append(res.mesh_id)
            print(f"  {i + 1:3d}/{len(truth)} {t['photo'][:40]:40s} "
                  f"{'right' if res.mesh_id == t['mesh_id'] else 'wrong'}", flush=True)
    return np.stack(qs), truth, answers


def best_per_mesh(q: np.ndarray, catalog: str, shas: list[str] | None):
    """((nq, n_meshes) best squared distance per mesh, mesh order) over a catalogue's rows;
    ``catalog`` 'PATH[:STEP]' keeps every STEP-th view."""
    from ucad_catalog.reader import CatalogReader

    path, _, step = catalog.partition(":")
    with CatalogReader(path) as reader:
        tab = reader.feature_table()
        keep = np.asarray(tab.view) % int(step or 1) == 0
        rows = unit_rows(tab.feats[keep])[0]
        mine = [m.sha256 for m in tab.meshes]
        mesh_of = np.asarray(tab.mesh)[keep]
    shas = mine if shas is None else shas
    where = {s: i for i, s in enumerate(shas)}
    col = np.array([where.get(s, -1) for s in mine])[mesh_of]
    d = 2.0 - 2.0 * (q @ rows.T)
    best = np.full((len(q), len(shas)), np.inf)
    ok = col >= 0                                   # meshes outside the first catalogue: dropped
    for i in range(len(q)):
        np.minimum.at(best[i], col[ok], d[i, ok])
    return best, shas


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("refs", type=Path, help="references saved by bench/fit.py --save")
    ap.add_argument("--catalog", required=True, type=Path)
    ap.add_argument("--also", action="append", default=[], metavar="CAT[:STEP]",
                    help="stored rows of another catalogue of the same meshes, added in turn")
    args = ap.parse_args(argv)
    q, truth, answers = queries(args.refs, args.catalog)
    q = unit_rows(q)[0]
    best, shas = best_per_mesh(q, str(args.catalog), None)
    where = {s: i for i, s in enumerate(shas)}
    print("\n| stored rows | source | photos | first stage top-1 / top-5 / top-20 | "
          "places of the rest | the fit's top-1 (first catalogue) |")
    print("|---|---|---|---|---|---|")
    for label, more in [(str(args.catalog), None)] + [(f"+ {a}", a) for a in args.also]:
        if more is not None:
            best = np.minimum(best, best_per_mesh(q, more, shas)[0])
        place = np.array([int((best[i] < best[i, where[t["mesh_id"]]]).sum())
                          if t["mesh_id"] in where else -1 for i, t in enumerate(truth)])
        for source in ("real", "generated"):
            sel = [i for i, t in enumerate(truth) if t["source"] == source and place[i] >= 0]
            if not sel:
                continue
            p = place[sel]
            fit_right = sum(answers[i] == truth[i]["mesh_id"] for i in sel)
            rest = sorted(int(x) for x in p if x > 0)
            print(f"| {label} | {source} | {len(sel)} | {(p == 0).sum()} / {(p < 5).sum()} / "
                  f"{(p < 20).sum()} | {', '.join(map(str, rest)) or '-'} | {fit_right} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
