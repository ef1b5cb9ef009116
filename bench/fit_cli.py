"""Benchmark: one ``ucad-index fit`` call per photo, each in a fresh process, timed by its wall.

    .venv/bin/python bench/fit.py --save /tmp/refs            # photo-like references, once
    .venv/bin/python bench/fit_cli.py /tmp/refs --catalog /tmp/ucad-fitbench/catalog_960
    .venv/bin/python bench/fit_cli.py /tmp/refs --catalog CAT --against /path/to/other/checkout

What issue 25's "<= 2 s over 1,000 meshes, retrieval included" and "<= 1 s with the mesh given"
mean for a user: a lone call pays the interpreter's start, the imports, the OpenCL device's
start and the programs' loads from the disk caches, the catalogue's first reads, and the mesh
reader's child, none of which ``bench/fit.py`` (one process for all photos) sees.

``DIR`` holds ``photos.csv`` (``path,x0,y0,x1,y1``) and ``truth.json`` (``bench/fit.py
--save``); ``--mesh-given`` passes each photo's true mesh (``--mesh``) instead of retrieval.
Every photo is fitted ``--runs`` times; with ``--against ROOT`` (another checkout of this
project, run in ROOT) each call of this checkout is paired with one of that code, alternating,
and which of the two goes first alternates too (the second call of a pair finds the catalogue
pages the first read in the page cache: ~5 % when measured), so that the machine's drift and
the cache fall on both alike: the table gives both and the median of the paired ratios, and
the answers are compared (the JSON but ``seconds`` and ``glb``). Both checkouts are
byte-compiled first. On a shared 2-core machine single times are noise: read medians and
ratios (one checkout against itself: 0.99-1.035).
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def fit_call(root: Path, photo: Path, box: list[str], catalog: Path, out: Path,
             mesh: str | None) -> tuple[float, dict]:
    """(wall seconds, the JSON written) of one ``ucad-index fit`` in a fresh interpreter running
    the code at ``root``: run in ``root`` (``python -m`` puts the working folder first on
    ``sys.path``, ahead of ``PYTHONPATH``: from another checkout it would import that one's
    code), with ``root`` ahead of the caller's ``PYTHONPATH``."""
    photo, catalog, out = (Path(p).resolve() for p in (photo, catalog, out))
    cmd = [sys.executable, "-m", "ucad_cl.cli", "fit", str(photo), "--box", *box,
           "--catalog", str(catalog), "--out", str(out)] + (["--mesh", mesh] if mesh else [])
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(root)] + [p for p in [os.environ.get("PYTHONPATH", "")] if p]))
    t = time.perf_counter()
    done = subprocess.run(cmd, cwd=root, env=env, stdout=subprocess.DEVNULL,
                          stderr=subprocess.PIPE, text=True, check=False)
    wall = time.perf_counter() - t
    if done.returncode != 0:
        raise RuntimeError(f"{photo.name}: exit {done.returncode}: {done.stderr.strip()[-300:]}")
    return wall, json.loads((out / f"{photo.stem}.json").read_text(encoding="utf-8"))


def byte_compiled(root: Path) -> None:
    """Byte-compile the checkout's packages, as installing them does: a checkout without
    up-to-date ``.pyc`` files (a fresh worktree, sources edited under
    ``PYTHONDONTWRITEBYTECODE=1``) compiles those sources in every call (~1 ms a module, 0.05 s
    for ten, more for a whole package), which the other side of a pair may not."""
    import compileall

    for package in ("ucad_cl", "ucad_catalog"):
        if (root / package).is_dir():
            compileall.compile_dir(root / package, quiet=1)


def answer(doc: dict) -> str:
    """The JSON without what may differ between runs of the same code (seconds, paths)."""
    return json.dumps({k: v for k, v in doc.items() if k not in ("seconds", "glb")},
                      sort_keys=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("photos", type=Path, help="a folder written by bench/fit.py --save")
    ap.add_argument("--catalog", type=Path, required=True)
    ap.add_argument("--mesh-given", action="store_true",
                    help="give each photo's true mesh (--mesh) instead of retrieval")
    ap.add_argument("--runs", type=int, default=1, help="calls per photo and code")
    ap.add_argument("--limit", type=int, default=None, help="the first N photos only")
    ap.add_argument("--against", type=Path, default=None, metavar="ROOT",
                    help="another checkout to pair every call with (e.g. the last release)")
    args = ap.parse_args(argv)
    with open(args.photos / "photos.csv", newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))[:args.limit]
    truth = {t["photo"]: t for t in json.loads((args.photos / "truth.json").read_text())}
    codes = [("this", ROOT)] + ([("against", args.against.resolve())] if args.against else [])
    for _, root in codes:
        byte_compiled(root)
    walls: dict[str, list[float]] = {name: [] for name, _ in codes}
    stages: dict[str, list[float]] = {name: [] for name, _ in codes}
    ratios, differ = [], 0
    with tempfile.TemporaryDirectory() as tmp:
        for i, row in enumerate(rows):
            photo = args.photos / row["path"]
            box = [row[k] for k in ("x0", "y0", "x1", "y1")]
            mesh = truth[row["path"]]["mesh_id"] if args.mesh_given else None
            for run in range(args.runs):
                got = {}                            # who goes first alternates (ABBA): the
                order = codes if (i + run) % 2 == 0 else codes[::-1]   # second call of a pair
                for name, root in order:            # finds the first's pages in the cache
                    out = Path(tmp) / name
                    wall, doc = fit_call(root, photo, box, args.catalog, out, mesh)
                    walls[name].append(wall)
                    stages[name].append(sum(doc["seconds"].values()))
                    got[name] = (wall, answer(doc))
                if args.against:
                    ratios.append(got["this"][0] / got["against"][0])
                    differ += got["this"][1] != got["against"][1]
            print(f"  {i + 1}/{len(rows)} {row['path'][:40]:40s} "
                  + "  ".join(f"{n} {walls[n][-1]:.2f} s" for n, _ in codes), flush=True)
    how = "mesh given" if args.mesh_given else "retrieval"
    print(f"\n| code ({how}, {len(rows)} photos x {args.runs}) | wall median | wall p90 | "
          "stages median (the JSON's seconds) |")
    print("|---|---|---|---|")
    for name, root in codes:
        w = sorted(walls[name])
        print(f"| {name} ({root}) | {statistics.median(w):.2f} s | "
              f"{w[min(len(w) - 1, int(0.9 * len(w)))]:.2f} s | "
              f"{statistics.median(stages[name]):.2f} s |")
    if args.against:
        print(f"\npaired ratio this / against, median of {len(ratios)}: "
              f"{statistics.median(ratios):.3f}; answers that differ: {differ} of {len(ratios)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
