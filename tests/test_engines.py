"""The Ray engine: same catalogue as the local engine, crash / hang isolation, artifact shipping."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

ray = pytest.importorskip("ray")

from tests.test_build import catalogue_content  # noqa: E402
from ucad_cl.build import BuildOptions, MeshRef, build  # noqa: E402
from ucad_cl.engines.ray import MARKER_PREFIX, _process_one, run_ray  # noqa: E402

OPTS = BuildOptions(azimuth_step=90.0, size=64)
QUIET = dict(progress=False, log=lambda *a: None)


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    from ucad_cl.synth import write_library
    out = tmp_path_factory.mktemp("raylib")
    write_library(out, 6, seed=21, messy_fraction=0.0, progress=False)
    (out / "broken.glb").write_bytes(b"glTF\x02\x00\x00\x00garbage")
    return out


def _todo(paths):
    """(MeshRef, force) pairs, as the build hands them to an engine."""
    return [(MeshRef(str(p), Path(p).stat().st_size, Path(p).stat().st_mtime), False)
            for p in paths]


def test_bad_arguments_and_missing_ray(library, tmp_path, monkeypatch):
    todo = _todo([library / "broken.glb"])
    with pytest.raises(ValueError, match="timeout must be > 0"):
        run_ray(todo, OPTS, print, staging=tmp_path, timeout=0)
    with pytest.raises(ValueError, match="num_cpus must be >= 1"):
        run_ray(todo, OPTS, print, staging=tmp_path, num_cpus=0)
    with pytest.raises(ValueError, match="max_in_flight must be >= 1"):
        run_ray(todo, OPTS, print, staging=tmp_path, max_in_flight=0)
    assert not ray.is_initialized()
    with pytest.raises(ConnectionError, match="could not connect to the Ray cluster at 'auto'"):
        run_ray(todo, OPTS, print, address="auto", staging=tmp_path, **QUIET)
    monkeypatch.setitem(sys.modules, "ray", None)            # as if ray were not installed
    with pytest.raises(ImportError, match=r"pip install -e '\.\[ray\]'"):
        run_ray(todo, OPTS, print, staging=tmp_path)


def test_local_cluster_is_started_and_shut_down(library, tmp_path):
    assert not ray.is_initialized()
    got = []
    run_ray(_todo([library / "broken.glb"]), OPTS, got.append, address=None, num_cpus=1,
            staging=tmp_path / "staging", **QUIET)
    assert not ray.is_initialized()                          # we started it: we stopped it
    assert [(e.state, e.reason) for e in got] == [("rejected", "unreadable")]
    run_ray([], OPTS, got.append, staging=tmp_path, **QUIET)  # nothing to do: no cluster
    assert not ray.is_initialized() and len(got) == 1


@pytest.fixture(scope="module")
def cluster():
    import tests.faults
    ray.init(num_cpus=2, include_dashboard=False, logging_level="WARNING")
    ray.cloudpickle.register_pickle_by_value(tests.faults)   # workers need not import tests/
    yield
    ray.shutdown()


def test_ray_build_equals_local_build(library, tmp_path, runtime, cluster):
    loc, dist = tmp_path / "local", tmp_path / "ray"
    s_loc = build(library, loc, OPTS, workers=1, **QUIET)
    s_ray = build(library, dist, OPTS, engine="ray", **QUIET)
    assert (s_ray.accepted, s_ray.rejected, s_ray.reasons) == (6, 1, {"unreadable": 1})
    assert (s_loc.accepted, s_loc.rejected, s_loc.reasons) == (6, 1, {"unreadable": 1})
    a, b = catalogue_content(loc), catalogue_content(dist)
    assert len(a) == 7 and a == b                            # bit-identical artifacts included
    assert all(rec["artifacts"] for rec in b.values() if rec["state"] == "accepted")
    assert not (dist / "staging").exists()
    s2 = build(library, dist, OPTS, engine="ray", **QUIET)   # resumable: all unchanged
    assert s2.skipped == 7 and s2.processed == 0
    from ucad_catalog.store import Catalog
    with Catalog.open(dist, create=False) as c:
        assert c.verify() == []


def test_crashing_loader_is_rejected_and_build_completes(library, tmp_path, runtime, cluster):
    from tests.faults import faulty_loader
    names = sorted(p.name for p in library.glob("synth_*.glb"))
    cat = tmp_path / "cat"
    s = build(library, cat, OPTS, engine="ray", loader=faulty_loader(crash=[names[1]]), **QUIET)
    by_name = {rec["path"]: rec for rec in catalogue_content(cat).values()}
    assert len(by_name) == 7
    assert (by_name[names[1]]["state"], by_name[names[1]]["reason"]) == ("rejected",
                                                                         "loader_crashed")
    assert s.accepted == 5 and s.reasons == {"unreadable": 1, "loader_crashed": 1}
    assert all(by_name[n]["state"] == "accepted" for n in names if n != names[1])


def test_hanging_task_times_out(library, tmp_path, runtime, cluster):
    """Cancelled after the timeout, resubmitted once with twice the time, then rejected. (The
    clock of a Ray task includes a fresh worker's start-up: 8 s leaves room on a loaded machine.)"""
    from tests.faults import faulty_loader
    names = sorted(p.name for p in library.glob("synth_*.glb"))
    got = []
    run_ray(_todo([library / names[2], library / names[3]]), OPTS, got.append, timeout=8.0,
            staging=tmp_path / "staging", loader=faulty_loader(hang=[names[2]]), **QUIET)
    by_name = {Path(e.path).name: e for e in got}
    assert (by_name[names[2]].state, by_name[names[2]].reason) == ("rejected", "timeout")
    assert by_name[names[3]].state == "accepted", (by_name[names[3]].reason, by_name[names[3]].detail)


def test_artifacts_are_paths_when_staging_is_shared_else_bytes(library, tmp_path, runtime):
    """Run in this process: with the driver's marker visible the EXR comes back as a staged
    file, without it as bytes; the bytes are identical either way."""
    ref, force = _todo([sorted(library.glob("synth_*.glb"))[0]])[0]
    staging = tmp_path / "staging"
    staging.mkdir()
    (staging / f"{MARKER_PREFIX}tok").write_text("")
    shared = _process_one(ref, force, OPTS, str(staging), "tok")
    private = _process_one(ref, force, OPTS, str(staging), "not-the-token")
    assert shared.state == private.state == "accepted"
    exr = shared.artifacts["views.exr"]
    assert isinstance(exr, Path) and exr.is_relative_to(staging)
    assert isinstance(private.artifacts["views.exr"], bytes)
    assert private.artifacts["views.exr"] == exr.read_bytes()
    assert set(shared.artifacts) == set(private.artifacts)
    assert all(shared.artifacts[k] == private.artifacts[k] for k in shared.artifacts
               if k != "views.exr")
    assert sorted(p.name for p in staging.rglob("*.exr")) == [exr.name]   # private one removed
