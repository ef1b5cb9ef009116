"""Golden per-mesh results: the guard behind the ``CODE_VERSION`` rule (CONTRIBUTING.md).

A build re-processes a catalogued mesh only when its options hash changes, and the hash holds
``ucad_cl.jobs.CODE_VERSION``: a change that alters per-mesh results without a bump leaves old
catalogues stale. This test runs the build's per-mesh pipeline (``ucad_cl.pipeline.Pipeline``:
ingest, orient, filter, render, edges, segment, classify, features) on a fixed set of small
generated vehicles and compares what a catalogue would store with ``tests/golden_results.json``,
which keeps one set of digests per ``CODE_VERSION``.

* Exact digests (sha256, 16 hex digits) of the discrete results: verdict, orientation (rotation,
  source, flags, cue names), canonical vertices (rounded to 1e-9), cameras, material and
  triangle id maps, edges, the part table (part, decision, view, pixels), the part sheet PNG.
* Fingerprints of the float results, compared with a relative tolerance of 1e-4 (so float
  rounding on another OpenCL device is not a "result change"): confidences and cue values,
  depth and pose features (mean, std and four fixed +-1 projections), scores, IoU and labeller
  probabilities, per-view statistics.

The registry's rejection codes are stored too: a new code is a verdict a catalogued mesh may
get, so adding one without a bump fails even when no mesh of the set hits it.

Refresh (after bumping CODE_VERSION): ``.venv/bin/python tests/test_golden.py --update``. It adds
the digests of the current CODE_VERSION and refuses to change those of a version already stored.
"""
from __future__ import annotations

import gzip
import hashlib
import io
import json
import re
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
GOLDEN = ROOT / "tests" / "golden_results.json"
REFRESH = ".venv/bin/python tests/test_golden.py --update"
RTOL, ATOL = 1e-4, 1e-6

#: the fixed set: name -> make_vehicle arguments (about 3,000 triangles each; one is rejected)
MESHES: dict[str, dict] = {
    "sedan_plain": dict(seed=101, kind="sedan", target_triangles=3000),
    "pickup_posed": dict(seed=102, kind="pickup", target_triangles=3000, pose="axis",
                         realism=("lens_lamps", "dark_trim")),
    "van_z_up": dict(seed=103, kind="van", target_triangles=3000, messy=("z_up",),
                     realism=("shared_black", "mirror_glass")),
    "bus_trailer": dict(seed=104, kind="bus", target_triangles=3000, body="trailer",
                        realism=("misleading_names",)),
    "one_material": dict(seed=105, kind="sedan", target_triangles=3000,
                         messy=("single_material",)),
}
#: build options of the set: small renders keep the test under 20 s
OPTIONS = dict(azimuth_step=30.0, size=64)


def _sha(*parts) -> str:
    h = hashlib.sha256()
    for p in parts:
        h.update(np.ascontiguousarray(p).tobytes() if isinstance(p, np.ndarray)
                 else json.dumps(p, sort_keys=True).encode())
    return h.hexdigest()[:16]


def _fingerprint(a) -> list[float]:
    """mean, std and four fixed +-1 projections (over the finite values, scaled by their count)
    of a float array: moves with any real change, stable under float rounding."""
    a = np.asarray(a, np.float64).ravel()
    a = a[np.isfinite(a)]
    if a.size == 0:
        return [0.0] * 7
    signs = np.random.default_rng(0).integers(0, 2, size=(4, a.size)) * 2 - 1
    return [float(a.size), float(a.mean()), float(a.std()), *(signs @ a / a.size).tolist()]


def mesh_results(entry, mesh, library: Path) -> dict:
    """{'exact': {name: digest}, 'approx': {name: [floats]}} of one pipeline result."""
    from ucad_catalog.exr import read_viewset_exr

    exact: dict[str, str] = {}
    approx: dict[str, list[float]] = {}
    detail = entry.detail.replace(str(library), "<library>")
    exact["verdict"] = _sha([entry.state, entry.reason, detail, entry.n_triangles,
                             entry.n_materials])
    o = entry.orientation or {}
    exact["orientation"] = _sha([np.round(o.get("rotation", []), 6).tolist(), o.get("source"),
                                 o.get("flags"), sorted(o.get("cues", {})), o.get("uncertain")])
    approx["orientation"] = [o.get("up_confidence", 0.0), o.get("front_confidence", 0.0),
                             o.get("symmetry", 0.0), o.get("mirror_z", 0.0),
                             *(v for _, v in sorted(o.get("cues", {}).items()))]
    exact["vertices"] = _sha(np.round(np.asarray(mesh.vertices, np.float64), 9),
                             np.asarray(mesh.faces), np.asarray(mesh.face_material),
                             np.round(np.asarray(entry.file_to_norm, np.float64), 9))
    if entry.state != "accepted":
        return {"exact": exact, "approx": approx}
    exact["cameras"] = _sha(*[np.round(np.concatenate([v.K.ravel(), v.w2c.ravel()]), 9)
                              for v in entry.views])
    approx["view_stats"] = [float(v.stats[k]) for v in entry.views for k in sorted(v.stats)]
    views, _ = read_viewset_exr(entry.artifacts["views.exr"])
    exact["views"] = _sha(views.mat_id, views.tri_id)
    approx["depth"] = _fingerprint(views.depth)
    edges = np.load(io.BytesIO(gzip.decompress(entry.artifacts["edges.npy.gz"])))
    exact["edges"] = _sha(edges)
    approx["features"] = _fingerprint(np.load(io.BytesIO(entry.artifacts["features.npy"])))
    rows = [[m.index, m.name, m.part, m.decision, m.view, m.pixels,
             {k: v for k, v in m.props.items() if not isinstance(v, float)}]
            for m in entry.materials]
    exact["parts"] = _sha(rows)
    approx["scores"] = [x for m in entry.materials
                        for x in (m.score, m.iou, float(m.props.get("prob") or 0.0))]
    for kind, data in sorted(entry.artifacts.items()):           # parts.png and any new kind
        if kind not in ("views.exr", "edges.npy.gz", "features.npy"):
            exact[kind] = hashlib.sha256(data if isinstance(data, bytes)
                                         else Path(data).read_bytes()).hexdigest()[:16]
    return {"exact": exact, "approx": approx}


def compute(workdir: Path) -> dict[str, dict]:
    """The results of every mesh of ``MESHES`` (written and staged under ``workdir``)."""
    from ucad_cl.jobs import BuildOptions, MeshRef
    from ucad_cl.pipeline import Pipeline
    from ucad_cl.synth import make_vehicle

    library = workdir / "library"
    library.mkdir(parents=True, exist_ok=True)
    pipeline = Pipeline(BuildOptions(**OPTIONS))
    out = {}
    for name, recipe in MESHES.items():
        args = dict(recipe)
        path = make_vehicle(args.pop("seed"), name=name, **args).write(library)
        ref = MeshRef(str(path), path.stat().st_size, 0.0)
        mesh, seconds = pipeline.load(ref)
        entry = pipeline.process(ref, mesh, seconds, workdir / "staging")
        out[name] = mesh_results(entry, mesh, library)
    return out


def _round(results: dict) -> dict:
    return {m: {"exact": r["exact"],
                "approx": {k: [float(f"{x:.7g}") for x in v] for k, v in r["approx"].items()}}
            for m, r in results.items()}


def differences(got: dict, want: dict) -> list[str]:
    """Names of the results that differ: 'MESH: COMPONENT'."""
    diffs = []
    for name in sorted(set(got) | set(want)):
        g, w = got.get(name), want.get(name)
        if g is None or w is None:
            diffs.append(f"{name}: {'missing' if g is None else 'not in the golden file'}")
            continue
        for k in sorted(set(g["exact"]) | set(w["exact"])):
            if g["exact"].get(k) != w["exact"].get(k):
                diffs.append(f"{name}: {k}")
        for k in sorted(set(g["approx"]) | set(w["approx"])):
            a, b = g["approx"].get(k), w["approx"].get(k)
            if a is None or b is None or len(a) != len(b) or not np.allclose(a, b, rtol=RTOL,
                                                                             atol=ATOL):
                diffs.append(f"{name}: {k} (values)")
    return diffs


def dumps(data: dict) -> str:
    """JSON with one line per list of numbers (short diffs)."""
    text = json.dumps(data, indent=1, sort_keys=True)
    return re.sub(r"\[\s+([^\[\]{}]*?)\s+\]",
                  lambda m: "[" + " ".join(m.group(1).split()) + "]", text) + "\n"


def load_golden() -> dict:
    return json.loads(GOLDEN.read_text(encoding="utf-8")) if GOLDEN.exists() else {}


def rejection_codes() -> list[str]:
    """The registry's rejection codes: a new one is a new verdict some catalogued mesh may
    get, so it comes with a CODE_VERSION bump even when no mesh of the set hits it."""
    from ucad_cl import reasons

    return sorted(reasons.of_kind(reasons.REJECTION))


def current(workdir: Path) -> dict:
    """What the golden file stores for one CODE_VERSION."""
    return {"meshes": _round(compute(workdir)), "rejection_codes": rejection_codes()}


def mismatches(got: dict, want: dict) -> list[str]:
    """What differs between two stored entries: 'MESH: COMPONENT' or the codes added/removed."""
    diffs = differences(got["meshes"], want["meshes"])
    added = sorted(set(got["rejection_codes"]) - set(want["rejection_codes"]))
    removed = sorted(set(want["rejection_codes"]) - set(got["rejection_codes"]))
    if added or removed:
        diffs.append(f"rejection codes added {added}, removed {removed} (ucad_cl/reasons.py)")
    return diffs


def test_per_mesh_results_match_the_code_version(tmp_path):
    """Results of the fixed set, and the registry's rejection codes, equal those stored for
    the current CODE_VERSION."""
    from ucad_cl.jobs import CODE_VERSION

    golden = load_golden().get("versions", {})
    assert CODE_VERSION in golden, (
        f"tests/golden_results.json has no results for CODE_VERSION {CODE_VERSION!r} "
        f"(ucad_cl/jobs.py): run `{REFRESH}` and commit the file")
    diffs = mismatches(current(tmp_path), golden[CODE_VERSION])
    assert not diffs, (
        f"per-mesh results or verdicts changed without a CODE_VERSION bump ({len(diffs)}: "
        f"{', '.join(diffs[:8])}{' ...' if len(diffs) > 8 else ''}). If the change is meant, "
        f"bump CODE_VERSION in ucad_cl/jobs.py (existing catalogues then re-process their "
        f"meshes), run `{REFRESH}` and commit tests/golden_results.json; if not, it is a bug")


def test_golden_set_covers_accept_and_reject():
    """The stored set holds accepted meshes with every component and one rejection."""
    from ucad_cl.jobs import CODE_VERSION

    stored = load_golden().get("versions", {}).get(CODE_VERSION, {}).get("meshes", {})
    assert set(stored) == set(MESHES), f"run `{REFRESH}`"
    assert "views" not in stored["one_material"]["exact"]
    assert all({"views", "edges", "parts", "parts.png"} <= set(stored[m]["exact"])
               for m in MESHES if m != "one_material")


def update() -> int:
    """Store the current CODE_VERSION's results; refuse to change a stored version's."""
    import tempfile

    from ucad_cl.jobs import CODE_VERSION

    data = load_golden() or {"about": "per-mesh result digests by CODE_VERSION "
                                      "(tests/test_golden.py)", "versions": {}}
    with tempfile.TemporaryDirectory() as tmp:
        got = current(Path(tmp))
    stored = data["versions"].get(CODE_VERSION)
    if stored is not None:
        diffs = mismatches(got, stored)
        if diffs:
            print(f"error: results differ from those stored for CODE_VERSION {CODE_VERSION} "
                  f"({', '.join(diffs[:8])}): bump CODE_VERSION in ucad_cl/jobs.py first",
                  file=sys.stderr)
            return 1
        print(f"CODE_VERSION {CODE_VERSION}: results unchanged, nothing to store")
        return 0
    data["versions"][CODE_VERSION] = got
    GOLDEN.write_text(dumps(data), encoding="utf-8")
    print(f"stored the results of CODE_VERSION {CODE_VERSION} in {GOLDEN.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    if sys.argv[1:] != ["--update"]:
        print(f"usage: {REFRESH}", file=sys.stderr)
        sys.exit(2)
    sys.exit(update())
