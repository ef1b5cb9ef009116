"""End-to-end catalogue builds: labels vs generator truth, resume after SIGKILL, crash isolation."""
from __future__ import annotations

import json
import math
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ucad_cl.build import BuildOptions, build, discover

OPTS = BuildOptions(azimuth_step=45.0, elevations=(15.0,), size=96)
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    from ucad_cl.synth import write_library
    out = tmp_path_factory.mktemp("lib")
    write_library(out, 8, seed=11, messy_fraction=0.0, progress=False)
    # two rejects: one material, and a broken file
    from ucad_cl.synth import make_vehicle
    v = make_vehicle(5, "sedan")
    single = out / "single_material.glb"
    import trimesh
    mesh = v.mesh()
    trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(single)
    (out / "broken.glb").write_bytes(b"glTF\x02\x00\x00\x00garbage")
    return out


def catalogue_content(path) -> dict:
    """What must be equal between two builds of the same library: rows and artifact hashes
    (not row ids, run ids, times)."""
    from ucad_catalog.reader import CatalogReader
    out = {}
    with CatalogReader(path) as r:
        for m in r.meshes(state=None):
            rec = r.record(m.sha256)
            out[m.sha256] = {
                "path": m.path, "state": m.state, "reason": m.reason,     # relative to the library
                "materials": [(p.index, p.name, p.part, round(p.score, 6), p.view, p.decision,
                               p.pixels) for p in r.parts(m.sha256)],
                "artifacts": sorted((k, v["sha256"]) for k, v in rec["artifacts"].items()),
                "views": len(rec["views"]),
                "file_to_norm": rec["file_to_norm"], "orientation": rec["orientation"],
                "n_triangles": rec["n_triangles"], "n_materials": rec["n_materials"],
            }
    return out


def content_difference(got: dict, want: dict, got_path=None, want_path=None) -> str:
    """Where two ``catalogue_content`` results differ: per mesh, each differing field, and for
    materials each differing row (so that a failure says which label moved); given both
    catalogues' paths, also where two view stacks differ (``stack_difference``)."""
    out = [f"meshes only in one: {sorted(set(got) ^ set(want))}"]
    for sha in sorted(set(got) & set(want)):
        for key in sorted(set(got[sha]) | set(want[sha])):
            a, b = got[sha].get(key), want[sha].get(key)
            if a == b:
                continue
            if key == "materials":
                rows = [f"{x} != {y}" for x, y in zip(a, b) if x != y]
                out.append(f"{want[sha]['path']}: materials differ: {rows}")
            else:
                out.append(f"{want[sha]['path']}: {key}: {a!r} != {b!r}")
            if key == "artifacts" and got_path is not None and want_path is not None \
                    and dict(a).get("views.exr") != dict(b).get("views.exr"):
                out.append(f"{want[sha]['path']}: {stack_difference(got_path, want_path, sha)}")
    return "\n".join(out)


def stack_difference(got_path, want_path, sha: str) -> str:
    """Where two catalogues' view stacks of mesh ``sha`` differ: the first differing byte, and
    per view and map the pixels that differ (count, first pixel, both values), or the cameras."""
    from ucad_catalog.reader import CatalogReader
    with CatalogReader(got_path) as a, CatalogReader(want_path) as b:
        raw = [r.artifact_path(sha, "views.exr").read_bytes() for r in (a, b)]
        n = min(map(len, raw))
        first = next((i for i in range(n) if raw[0][i] != raw[1][i]), n)
        out = [f"views.exr: {len(raw[0])} / {len(raw[1])} bytes, first difference at byte {first}"]
        for v in range(min(len(a.views(sha)), len(b.views(sha)))):
            x, y = a.view(sha, v), b.view(sha, v)
            for name in ("depth", "mat_id", "tri_id", "K", "w2c"):
                p, q = np.asarray(getattr(x, name)), np.asarray(getattr(y, name))
                if p.shape != q.shape:
                    out.append(f"view {v} {name}: shape {p.shape} != {q.shape}")
                    continue
                bits = f"u{p.dtype.itemsize}"                # bit for bit (NaN, -0.0)
                diff = np.argwhere(np.ascontiguousarray(p).view(bits)
                                   != np.ascontiguousarray(q).view(bits))
                if len(diff):
                    i = tuple(int(k) for k in diff[0])
                    out.append(f"view {v} {name}: {len(diff)} differ, first {i}: "
                               f"{p[i].item()!r} != {q[i].item()!r}")
    return "; ".join(out[:20])


def test_build_labels_rejections_and_skip(library, tmp_path, runtime):
    cat = tmp_path / "cat"
    s = build(library, cat, OPTS, progress=False, log=lambda *a: None)
    assert s.discovered == 10 and s.accepted == 8 and s.rejected == 2
    assert s.reasons == {"too_few_materials": 1, "unreadable": 1}
    content = catalogue_content(cat)
    ok = total = 0
    for rec in content.values():
        if rec["state"] != "accepted":
            continue
        truth = json.loads((library / rec["path"]).with_suffix(".json").read_text())["materials"]
        for _, name, part, *_ in rec["materials"]:
            if part != "unseen":
                total += 1
                ok += part == truth[name]
        assert {k for k, _ in rec["artifacts"]} >= {"views.exr", "features.npy", "parts.png",
                                                      "edges.npy.gz"}
    assert total > 100 and ok / total >= 0.80, f"labels: {ok}/{total}"
    # second run: everything unchanged is skipped
    s2 = build(library, cat, OPTS, progress=False, log=lambda *a: None)
    assert s2.skipped == 10 and s2.processed == 0
    # changed options: re-processed, same number of entries
    s3 = build(library, cat, BuildOptions(azimuth_step=90.0, size=96), progress=False,
               log=lambda *a: None)
    assert s3.processed == 10 and len(catalogue_content(cat)) == 10


def test_changed_file_is_reprocessed(library, tmp_path, runtime, monkeypatch):
    """A changed file is processed again, the others skipped; the search index follows every
    build (fresh, holding the new mesh); a build whose index process fails (killed) still
    finishes, says so in its log, and leaves the index stale (not used)."""
    import ucad_cl.build as build_mod
    from ucad_catalog.reader import CatalogReader

    def index_meshes(cat):
        with CatalogReader(cat) as r:
            idx, why = r.search_index()
            return (None if idx is None else {m.sha256 for m in idx.meshes}), why, \
                {m.sha256 for m in r.meshes()}

    lib = tmp_path / "lib"
    shutil.copytree(library, lib)
    cat = tmp_path / "cat"
    build(lib, cat, OPTS, progress=False, log=lambda *a: None)
    before = catalogue_content(cat)
    indexed, _, accepted = index_meshes(cat)
    assert indexed == accepted and len(accepted) == 8
    victim = sorted(lib.glob("synth_*.glb"))[0]
    from ucad_cl.synth import make_vehicle
    make_vehicle(99, "bus").scene.export(victim)
    s = build(lib, cat, OPTS, progress=False, log=lambda *a: None)
    assert s.processed == 1 and s.skipped == 9
    after = catalogue_content(cat)
    assert len(after) == len(before) and set(after) != set(before)
    indexed, _, accepted = index_meshes(cat)
    assert indexed == accepted and accepted != {k for k, v in before.items()
                                                if v["state"] == "accepted"}

    make_vehicle(98, "van").scene.export(victim)
    monkeypatch.setattr(build_mod, "INDEX_TIMEOUT", 0.001)    # its process killed at once
    s = build(lib, cat, OPTS, progress=False, log=lambda *a: None)
    assert s.processed == 1
    log = sorted((cat / "logs").glob("run-*.log"))[-1].read_text()
    assert "search index not written: its process ran over 0.001 s" in log and "finished:" in log
    indexed, why, _ = index_meshes(cat)
    assert indexed is None and "stale" in why


def _build_cmd(library, cat):
    return [sys.executable, "-m", "ucad_cl.cli", "build", str(library), "--catalog", str(cat),
            "--azimuth-step", "45", "--elevations", "15", "--size", "96"]   # = OPTS


def test_sigkill_resume_equals_uninterrupted_build(library, tmp_path, runtime):
    ref = tmp_path / "ref"
    build(library, ref, OPTS, progress=False, log=lambda *a: None)
    expected = catalogue_content(ref)
    cat = tmp_path / "killed"
    rng = random.Random(5)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    for _attempt in range(5):
        proc = subprocess.Popen(_build_cmd(library, cat), env=env, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, start_new_session=True)
        time.sleep(rng.uniform(0.5, 4.0))
        os.kill(proc.pid, signal.SIGKILL)          # the driver, mid-commit or anywhere
        proc.wait()
        time.sleep(1.5)                            # orphaned workers notice and exit
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    done = subprocess.run(_build_cmd(library, cat), env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    got = catalogue_content(cat)
    assert got == expected, content_difference(got, expected, cat, ref)
    from ucad_catalog.store import Catalog
    with Catalog.open(cat, create=False) as c:
        assert c.verify() == []


def test_crashing_and_hanging_loaders_are_isolated(library, tmp_path, runtime):
    """A native crash is recorded against the mesh the worker held alone; a hang is killed after
    --timeout, retried alone with twice the time, then recorded; the build goes on."""
    names = sorted(p.name for p in library.glob("synth_*.glb"))
    from tests.faults import faulty_loader
    cat = tmp_path / "cat"
    t0 = time.monotonic()
    s = build(library, cat, OPTS, progress=False, timeout=4.0, log=lambda *a: None,
              loader=faulty_loader(crash=[names[1]], hang=[names[4]]))
    content = catalogue_content(cat)
    by_name = {rec["path"]: rec for rec in content.values()}
    assert by_name[names[1]]["state"] == "rejected"
    assert by_name[names[1]]["reason"] == "loader_crashed"
    assert by_name[names[4]]["reason"] == "timeout"
    assert s.accepted == 6 and s.rejected == 4 and len(content) == 10, (s.reasons, content)
    assert s.retried >= 1 and time.monotonic() - t0 >= 4.0 + 8.0     # the hang had its retry
    log = (cat / "logs" / "run-00001.log").read_text()       # the run says what happened
    assert f"{names[1]} reason=loader_crashed" in log and "reason=timeout" in log
    assert "finished: 6 accepted, 4 rejected" in log
    # --retry-failed re-processes recorded failures (the fault is gone now); plain runs skip them
    assert build(library, cat, OPTS, progress=False, log=lambda *a: None).processed == 0
    s2 = build(library, cat, OPTS, progress=False, log=lambda *a: None,
               retry_failed=["timeout", "loader_crashed"])
    assert (s2.processed, s2.accepted, s2.skipped) == (2, 2, 8)
    assert {rec["state"] for rec in catalogue_content(cat).values()
            if rec["path"] in names[1:5:3]} == {"accepted"}


def test_two_workers_give_the_same_catalogue(library, tmp_path, runtime):
    """Same rows, and byte-identical exports, ids and paths included (issue 14)."""
    from ucad_catalog import CatalogReader

    a, b = tmp_path / "a", tmp_path / "b"
    build(library, a, OPTS, workers=1, progress=False, log=lambda *a: None)
    build(library, b, OPTS, workers=2, progress=False, log=lambda *a: None)
    assert catalogue_content(a) == catalogue_content(b)
    for cat in (a, b):
        with CatalogReader(cat) as r:
            r.export(tmp_path / f"{cat.name}.jsonl")
    for table in ("{}.jsonl", "{}.materials.jsonl"):
        ea = (tmp_path / table.format("a")).read_bytes()
        assert ea == (tmp_path / table.format("b")).read_bytes() and len(ea) > 1000
    rows = [json.loads(x) for x in (tmp_path / "a.jsonl").read_text().splitlines()]
    assert [r["path"] for r in rows] == sorted(Path(r.path).name for r in discover(library))
    assert all(len(r["id"]) == 64 and r["library_root"] == str(library) for r in rows)


def test_discover_layouts(tmp_path):
    shard = tmp_path / "glbs" / "000-001"
    shard.mkdir(parents=True)
    for uid in ("aaa", "bbb", "ccc"):
        (shard / f"{uid}.glb").write_bytes(b"x")
    (tmp_path / "notes.txt").write_text("not a mesh")
    assert [Path(r.path).stem for r in discover(tmp_path)] == ["aaa", "bbb", "ccc"]
    assert [Path(r.path).stem for r in discover(tmp_path, uids=["ccc", "aaa"])] == ["aaa", "ccc"]
    manifest = tmp_path / "list.txt"
    manifest.write_text("# meshes\nglbs/000-001/bbb.glb\n")
    assert [Path(r.path).stem for r in discover(manifest)] == ["bbb"]
    manifest.write_bytes(b"\xef\xbb\xbfglbs/000-001/bbb.glb\r\n")   # an editor's BOM, CRLF
    assert [Path(r.path) for r in discover(manifest)] == [shard / "bbb.glb"]
    (tmp_path / "m.json").write_text(json.dumps({"paths": ["glbs/000-001/aaa.glb"]}))
    assert [Path(r.path).stem for r in discover(tmp_path / "m.json")] == ["aaa"]
    with pytest.raises(FileNotFoundError, match="does not exist"):
        discover(tmp_path / "missing")
    from ucad_cl.build import read_uid_list
    ann = tmp_path / "annotations.json"
    ann.write_text(json.dumps({
        "aaa": {"name": "red car", "categories": [{"name": "cars-vehicles"}], "tags": [{"name": "car"}]},
        "bbb": {"name": "chair", "categories": [{"name": "furniture-home"}], "tags": []},
        "ccc": {"name": "truck", "categories": [], "tags": [{"name": "Truck"}]}}))
    assert read_uid_list(ann) == ["aaa", "bbb", "ccc"]
    assert read_uid_list(ann, ["car", "truck"]) == ["aaa", "ccc"]
    assert read_uid_list(ann, ["cars-vehicles"]) == ["aaa"]
    with pytest.raises(ValueError, match="annotations JSON"):
        read_uid_list(manifest, ["car"])


def test_real_models_build_without_crash(vehicles_dir, tmp_path, runtime):
    """Every real model of the shared manifest is processed, keyed by its path in the library
    (several models share a file name: car.obj, scene.gltf, ...): accepted, or rejected with the
    documented reason (a model of fewer than two materials: too_few_materials)."""
    cat = tmp_path / "real"
    s = build(vehicles_dir, cat, BuildOptions(azimuth_step=60.0, size=96), progress=False,
              log=lambda *a: None)
    content = {rec["path"]: rec for rec in catalogue_content(cat).values()}
    manifest = json.loads((vehicles_dir / "manifest.json").read_text())["models"]
    assert s.failed == 0 and s.processed == len(content) == len(manifest) >= 44
    for model in manifest:
        rec = content[model["file"]]
        want = ("rejected", "too_few_materials") if model["material_count"] < 2 else \
            ("accepted", None)
        assert (rec["state"], rec["reason"] or None) == want, (model["file"], rec)
    assert content["kenney_truck_green/vehicle-truck-green.glb"]["state"] == "rejected"


def test_pose_search_over_the_catalogue(library, tmp_path, runtime, capsys, monkeypatch):
    """`ucad-index pose IMAGE --box ... --catalog PATH`: the right mesh and the nearest view;
    through the build's search index (as the fit reads rows: ``fit.catalog_rows``), the same
    candidates; without the index when one is due, a note and every row."""
    import cv2

    from ucad_cl.cameras import make_ring
    from ucad_cl.cli import main
    from ucad_cl.ingest import load_mesh
    from ucad_cl.render import render_views
    from ucad_cl.shade import shade_views

    cat = tmp_path / "cat"
    build(library, cat, BuildOptions(azimuth_step=30.0, size=128), progress=False,
          log=lambda *a: None)
    target = sorted(library.glob("synth_*.glb"))[3]
    mesh = load_mesh(target)
    views = render_views(mesh, make_ring(azimuths=[100.0], elevations=[12.0], size=(200, 160)))
    img = shade_views(mesh, views, background=(70, 110, 50))[0]
    ys, xs = np.nonzero(np.isfinite(views.depth[0]))
    ref = tmp_path / "ref.png"
    cv2.imwrite(str(ref), np.ascontiguousarray(img[:, :, ::-1]))
    box = [str(v) for v in (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)]
    assert main(["pose", str(ref), "--box", *box, "--catalog", str(cat), "--top", "3"]) == 0
    lines = capsys.readouterr().out.splitlines()
    best = lines[1].split()
    assert best[-2] == str(target) and float(best[1]) in (90.0, 120.0), lines
    assert (tmp_path / "ref_pose.png").exists()
    assert main(["pose", str(ref), "--box", *box, "--catalog", str(cat), "--top", "3",
                 "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    from tests.test_cli import documented_keys
    assert list(doc) == documented_keys("pose catalogue output")     # ucad_catalog/SCHEMA.md
    assert [list(c) for c in doc["candidates"]] == [
        ["rank", "mesh", "sha256", "view", "azimuth", "elevation", "distance", "score", "K",
         "w2c"]] * 3
    assert [c["rank"] for c in doc["candidates"]] == [1, 2, 3]
    c0 = doc["candidates"][0]
    assert c0["mesh"] == str(target) and c0["azimuth"] == float(best[1])
    assert np.asarray(c0["K"]).shape == (3, 3) and np.asarray(c0["w2c"]).shape == (4, 4)
    assert c0["distance"] > 0 and c0["score"] >= 0
    # a large photo (1600 x 1280: foreground.PhotoWindow) of the same view: the same answer,
    # its object in the large photo's pixels
    views = render_views(mesh, make_ring(azimuths=[100.0], elevations=[12.0], size=(1600, 1280)))
    big_img = shade_views(mesh, views, background=(70, 110, 50))[0]
    ys, xs = np.nonzero(np.isfinite(views.depth[0]))
    big = tmp_path / "big.png"
    cv2.imwrite(str(big), np.ascontiguousarray(big_img[:, :, ::-1]))
    big_box = (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)
    assert main(["pose", str(big), "--box", *map(str, big_box), "--catalog", str(cat),
                 "--top", "3", "--json"]) == 0
    d2 = json.loads(capsys.readouterr().out)
    b0 = d2["candidates"][0]
    assert (b0["mesh"], b0["azimuth"], b0["elevation"]) == (c0["mesh"], c0["azimuth"],
                                                          c0["elevation"])
    assert b0["distance"] == pytest.approx(c0["distance"], rel=0.05)
    side = max(big_box[2] - big_box[0], big_box[3] - big_box[1])
    assert np.abs(np.subtract(d2["object"]["box"], big_box)).max() <= 0.02 * side
    # the vehicle cut by the photo's left edge (a third of its box): matched as going on past
    # the edge, still the right mesh; with --as-shown, no growth
    x0, y0, x1, y1 = (int(v) for v in box)
    c = x0 + (x1 - x0) // 3
    cut = tmp_path / "cut.png"
    cv2.imwrite(str(cut), np.ascontiguousarray(img[:, c:, ::-1]))
    cut_box = [str(v) for v in (0, y0, x1 - c, y1)]
    assert main(["pose", str(cut), "--box", *cut_box, "--catalog", str(cat), "--top", "3",
                 "--json"]) == 0
    d3 = json.loads(capsys.readouterr().out)
    assert d3["candidates"][0]["mesh"] == str(target)
    assert d3["past_edge"][0] > 0 and d3["past_edge"][1:] == [0, 0, 0], d3["past_edge"]
    assert main(["pose", str(cut), "--box", *cut_box, "--catalog", str(cat), "--top", "3",
                 "--json", "--as-shown"]) == 0
    assert json.loads(capsys.readouterr().out)["past_edge"] == [0, 0, 0, 0]
    assert main(["pose", str(cut), "--box", *cut_box, "--catalog", str(cat), "--top", "3"]) == 0
    assert "the vehicle touches the photo's edge: matched as going on past it by" in \
        capsys.readouterr().out
    assert main(["pose", str(ref), "--box", *box]) == 2           # neither MESH nor --catalog
    capsys.readouterr()
    import shutil

    import ucad_cl.fit as fit
    monkeypatch.setattr(fit, "INDEX_FROM", 0)          # the search index even for these rows
    monkeypatch.setattr(fit, "INDEX_ROWS", 40)         # ... and only its 40 nearest rows ranked
    assert main(["pose", str(ref), "--box", *box, "--catalog", str(cat), "--top", "3",
                 "--json"]) == 0
    out = capsys.readouterr()
    assert json.loads(out.out)["candidates"] == doc["candidates"] and "note" not in out.err
    plain = tmp_path / "plain"
    shutil.copytree(cat, plain)
    (plain / "search_index.npz").unlink()
    assert main(["pose", str(ref), "--box", *box, "--catalog", str(plain), "--top", "3",
                 "--json"]) == 0
    out = capsys.readouterr()
    assert json.loads(out.out)["candidates"] == doc["candidates"]
    assert "note: no search index" in out.err and "every stored row read" in out.err


def test_cli_parts_over_catalogue_and_render_edges(library, tmp_path, runtime, capsys):
    from ucad_cl.cli import main

    cat = tmp_path / "cat"
    build(library, cat, OPTS, progress=False, log=lambda *a: None)
    target = sorted(library.glob("synth_*.glb"))[2]
    assert main(["parts", "--catalog", str(cat), target.name]) == 0
    out = capsys.readouterr().out
    truth = json.loads(target.with_suffix(".json").read_text())["materials"]
    rows = [ln.split() for ln in out.splitlines()[2:]]
    assert len(rows) == len(truth) and all(r[0] in truth for r in rows)
    assert main(["parts", "--catalog", str(cat), "no-such-mesh"]) == 2
    out_dir = tmp_path / "r"
    assert main(["render", str(target), "--out", str(out_dir), "--azimuth-step", "90",
                 "--size", "64", "--edges"]) == 0
    pngs = sorted((out_dir / f"{target.stem}.edges").glob("*.png"))
    assert len(pngs) == 4
    import cv2
    img = cv2.imread(str(pngs[0]), cv2.IMREAD_GRAYSCALE)
    assert set(np.unique(img)) == {0, 255}
    assert main(["render", str(tmp_path / "missing.glb"), "--out", str(out_dir)]) == 1


def test_demo_command_builds_and_shows_where_to_look(tmp_path, runtime, capsys):
    """The README's first command, on a smaller sample."""
    from ucad_cl.cli import main

    assert main(["demo", "--out", str(tmp_path / "demo"), "--count", "4"]) == 0
    out = capsys.readouterr().out
    assert "look at:" in out and "status --catalog" in out
    sheets = sorted((tmp_path / "demo" / "sheets").glob("*.png"))
    assert len(sheets) >= 4
    assert main(["status", "--catalog", str(tmp_path / "demo" / "catalog")]) == 0
    assert "accepted: 4" in capsys.readouterr().out
    # every sheet shows its vehicle upright, the first view (azimuth 0) facing its front
    from ucad_catalog.reader import CatalogReader
    with CatalogReader(tmp_path / "demo" / "catalog") as r:
        for m in r.meshes():
            truth = json.loads(m.source.with_suffix(".json").read_text())["orientation"]
            R = np.asarray(m.orientation["rotation"])
            assert np.dot(R @ truth["up"], [0, 1, 0]) > math.cos(math.radians(10)), m.path
            assert np.dot(R @ truth["front"], [1, 0, 0]) > math.cos(math.radians(15)), m.path
            assert r.views(m.sha256)[0].azimuth == 0.0


def test_bad_segmenter_specs_fail_before_any_work(library, tmp_path):
    """A wrong --segmenter is a clear error in the driver (no worker, no catalogue)."""
    from ucad_cl.cli import main

    for spec, msg in (("onnx:model.onnx", "--segmenter onnx:model.onnx: expected onnx:MODEL"),
                      ("sam", "unknown segmenter"), ("masks:", "unknown segmenter")):
        with pytest.raises(ValueError, match=msg):
            build(library, tmp_path / "cat", BuildOptions(segmenter=spec), progress=False,
                  log=lambda *a: None)
    assert not (tmp_path / "cat").exists()
    assert main(["build", str(library), "--catalog", str(tmp_path / "c2"), "--segmenter",
                 "onnx:m.onnx"]) == 2
    # a missing labeller model fails in the driver too (its check runs in a child process)
    with pytest.raises(FileNotFoundError, match="nope.onnx"):
        build(library, tmp_path / "c3", BuildOptions(segmenter=f"labeller:{tmp_path}/nope.onnx"),
              progress=False, log=lambda *a: None)
    assert not (tmp_path / "c3").exists()
    # a file that is no ONNX model: a clear error naming the spec, not onnxruntime's traceback
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not a model")
    with pytest.raises(ValueError, match="bad.onnx: onnxruntime cannot load this model"):
        build(library, tmp_path / "c4", BuildOptions(segmenter=f"labeller:{bad}"), progress=False,
              log=lambda *a: None)
    assert main(["build", str(library), "--catalog", str(tmp_path / "c5"), "--segmenter",
                 f"labeller:{bad}"]) == 2
    assert not (tmp_path / "c4").exists() and not (tmp_path / "c5").exists()


def test_driver_loads_neither_opencl_nor_onnxruntime(tmp_path):
    """What the build driver checks before starting workers (the device report, the segmenter)
    runs in child processes: in a fresh interpreter, neither pyopencl nor onnxruntime gets
    imported, and the device reported is the one ``get_runtime`` picks in-process."""
    code = ("import json, sys\n"
            "from ucad_cl.runtime import pick_device_info\n"
            "from ucad_cl.segment import check_segmenter_spec\n"
            "info, why = pick_device_info()\n"
            "check_segmenter_spec('labeller')\n"
            "print(json.dumps([info.spec, why, [m for m in ('pyopencl', 'onnxruntime')\n"
            "                                   if m in sys.modules]]))\n")
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    spec, why, loaded = json.loads(run.stdout.strip().splitlines()[-1])
    assert loaded == []
    from ucad_cl.runtime import create_runtime
    rt = create_runtime()
    assert rt.info is not None and (spec, why) == (rt.info.spec, rt.why)


def test_second_ring_is_stored_for_retrieval_and_leaves_labels_alone(library, tmp_path,
                                                                     runtime):
    """The default rings (15 then 5 deg): the label ring's results are those of a 15 deg
    build alone (part rows, parts sheet, edges, verdicts), its views and features are the first
    rows of the stack; the 5 deg ring follows with views and features of its own, no edges."""
    from dataclasses import replace

    from ucad_catalog.reader import CatalogReader

    assert BuildOptions().elevations == (15.0, 5.0)
    one, two = tmp_path / "one", tmp_path / "two"
    build(library, one, OPTS, progress=False, log=lambda *a: None)
    build(library, two, replace(OPTS, elevations=(15.0, 5.0)), progress=False,
          log=lambda *a: None)
    a, b = catalogue_content(one), catalogue_content(two)
    assert a.keys() == b.keys()
    n = 8                                               # views a ring (45 deg azimuth step)
    with CatalogReader(one) as r1, CatalogReader(two) as r2:
        for sha, rec in a.items():
            assert (rec["state"], rec["reason"], rec["materials"]) == \
                (b[sha]["state"], b[sha]["reason"], b[sha]["materials"])
            if rec["state"] != "accepted":
                continue
            arts1, arts2 = dict(rec["artifacts"]), dict(b[sha]["artifacts"])
            assert arts1["parts.png"] == arts2["parts.png"]
            assert arts1["edges.npy.gz"] == arts2["edges.npy.gz"]
            assert (rec["views"], b[sha]["views"]) == (n, 2 * n)
            assert [v.elevation for v in r2.views(sha)] == [15.0] * n + [5.0] * n
            f1, f2 = r1.features(sha), r2.features(sha)
            assert f2.shape[0] == 2 * n and np.array_equal(f1, f2[:n])
            assert not np.allclose(f2[:n], f2[n:])
            for v in (0, 3):
                x, y = r1.view(sha, v), r2.view(sha, v)
                assert np.array_equal(x.tri_id, y.tri_id) and np.array_equal(x.depth, y.depth)
            low = r2.view(sha, n + 3)
            assert low.elevation == 5.0 and np.isfinite(low.depth).any()
            assert r2.edges(sha).shape[0] == n
            with pytest.raises(Exception, match="label ring"):
                r2.edges(sha, n)
