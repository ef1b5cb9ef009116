"""The fit (ucad_cl/fit.py, ucad_cl/light.py, `ucad-index fit`): colours recovered under a known
light, unseen parts keep their prior, a two-colour part is flagged, retrieval, hostile input."""
from __future__ import annotations

import json
import struct
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest

from tests.hostile_corpus import png_header_only
from ucad_cl.build import BuildOptions, build
from ucad_cl.colorimetry import delta_e2000, linear_to_lab

OPTS = BuildOptions(azimuth_step=30.0, elevations=(15.0,), size=128)
COLORS = {"body": (0.5, 0.06, 0.05), "wheel": (0.03, 0.03, 0.03), "rim": (0.6, 0.6, 0.6),
          "plate": (0.8, 0.8, 0.78), "interior": (0.12, 0.12, 0.12)}


@pytest.fixture(scope="module")
def catalogue(tmp_path_factory):
    from ucad_cl.synth import write_library
    root = tmp_path_factory.mktemp("fit")
    lib, cat = root / "lib", root / "cat"
    write_library(lib, 5, seed=23, messy_fraction=0.0, progress=False)
    build(lib, cat, OPTS, progress=False, log=lambda *a: None)
    return cat


def _mesh(cat, k):
    from ucad_catalog.reader import CatalogReader
    from ucad_cl.ingest import load_mesh
    from ucad_cl.orient import in_frame
    with CatalogReader(cat) as r:
        m = r.meshes()[k]
        rows = sorted(r.parts(m.sha256), key=lambda x: x.index)
    return m, in_frame(load_mesh(m.source, orientation=None), m.file_to_norm), rows


def _neutral_light():
    from ucad_cl.refphoto import RefLight
    return RefLight(sky_zenith=(0.35, 0.35, 0.35), sky_horizon=(0.4, 0.4, 0.4),
                    sun_color=(0.9, 0.9, 0.9), ground=(0.12, 0.12, 0.12))


def _de(fitted, truth, scale=1.0) -> float:
    return float(delta_e2000(linear_to_lab(np.asarray(fitted) * scale),
                             linear_to_lab(np.asarray(truth))))


def _exposure(fitted, truth) -> float:
    """The one exposure factor (least squares over the body's channels)."""
    f, t = np.asarray(fitted), np.asarray(truth)
    return float(f @ t / (f @ f))


def test_light_model_recovers_its_own_colours_exactly():
    """Closed form + search: pixels drawn from the light model itself under a known light are
    recovered within CIEDE2000 0.5 (no exposure factor needed: E_up = 1 holds)."""
    from ucad_cl.light import Lighting, Samples, fit_light, predict, sun_direction

    rng = np.random.default_rng(3)
    n = 6000
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    view = np.tile([0.8, 0.3, -0.52], (n, 1))
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    flip = (nrm * view).sum(1) < 0
    nrm[flip] *= -1
    part = rng.integers(0, 3, n)
    truth = np.array([[0.55, 0.08, 0.06], [0.03, 0.03, 0.03], [0.6, 0.62, 0.65]])
    s = Samples(rgb=np.zeros((n, 3)), normal=nrm, view=view, part=part,
                coat=np.array([1.0, 0.0, 0.0])[part], metallic=np.array([0.5, 0.0, 1.0])[part],
                roughness=np.array([0.35, 0.9, 0.25])[part])
    d = sun_direction(60.0, 30.0)
    sky = np.array([0.3, 0.3, 0.3])
    light = Lighting(sky=sky, sun=(1 - sky) / d[1], sun_dir=d)
    s.rgb = predict(s, light, truth) + rng.normal(0, 0.002, (n, 3))
    fit = fit_light(s, 3)
    for p in range(3):
        assert _de(fit.albedo[p], truth[p]) < 0.5, (p, fit.albedo[p], truth[p])
    assert abs(float(fit.lighting.sun_dir @ d)) > np.cos(np.radians(12))


def test_light_search_scores_equal_the_objective_pixel_by_pixel():
    """The light search scores a candidate light (sun direction, sky share) from per-part sums
    (``light._Moments``: the sums that do not depend on the sun shared by every direction of a
    search through ``light._Scorer``, the three channels evaluated together): each score
    equals the objective computed pixel by pixel (``objective`` of ``solve_albedo``'s colours
    under that light, NumPy), for random samples with painted, matte and metal parts, suns
    high and low, sky shares 0-1."""
    from ucad_cl.light import (Lighting, Samples, _Moments, _Scorer, objective, solve_albedo,
                               sun_direction)

    rng = np.random.default_rng(11)
    for n, P in ((40, 1), (900, 4), (3000, 7)):
        nrm = rng.normal(size=(n, 3))
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        view = rng.normal(size=(n, 3))
        view /= np.linalg.norm(view, axis=1, keepdims=True)
        part = np.arange(n) % P
        s = Samples(rgb=rng.random((n, 3)), normal=nrm, view=view, part=part,
                    coat=(part % 2).astype(np.float64), metallic=(part % 3 == 2) * 0.8,
                    roughness=rng.random(n))
        scorer = _Scorer(s, P)
        for az, el in ((0.0, 5.0), (75.0, 30.0), (200.0, 62.0)):
            d = sun_direction(az, el)
            B0, B1, _, _ = scorer.free.sun_terms(d)
            mom = _Moments(scorer, B0, B1)
            shares = np.array([0.0, 0.35, 1.0])
            got = mom.losses(shares, range(3))
            for g, score in zip(shares, got):
                light = Lighting(sky=np.full(3, g), sun=np.full(3, (1 - g) / max(d[1], 1e-3)),
                                 sun_dir=d)
                want = objective(s, light, solve_albedo(s, light, P), P)
                assert score == pytest.approx(want, rel=1e-9, abs=1e-12), (n, P, az, g)


def test_known_colours_under_known_light(catalogue, tmp_path):
    """Photo-like Embree references (not the project's renderer) of known part colours under a
    known neutral daylight, the true mask given: the body colour after one exposure factor.
    Measured CIEDE2000 2.1, 0.08, 0.14 (ground 0.1 of E_up, reflection folding and the
    white-balance check of ucad_cl/light.py; before them 2.2, 3.4, 2.0): the median is within
    the issue's 1; the view at azimuth 30 (its tyre mask holds paint, so it is flagged and no
    white balance is applied) stays near 2. The bounds catch a regression."""
    from ucad_cl.fit import fit_photo
    from ucad_cl.refphoto import render_reference

    m, mesh, rows = _mesh(catalogue, 1)
    des = []
    for az in (30.0, 130.0, 230.0):
        ref = render_reference(mesh, [r.part for r in rows], COLORS, azimuth=az, elevation=8.0,
                               light=_neutral_light(), seed=1, background="plain", noise=0.0,
                               jpeg_quality=None)
        res = fit_photo(ref.image, mask=ref.mask, catalog=catalogue, mesh=m.sha256[:12])
        body = res.parts["body"]
        assert body.status == "fitted" and body.pixels > 1000
        s = _exposure(body.color_linear, COLORS["body"])
        assert s > 0
        des.append(_de(body.color_linear, COLORS["body"], s))
        # a tyre is reported dark grey, or flagged with its prior colour (its mask holds paint)
        tyre = res.parts["wheel"]
        c = np.asarray(tyre.color_linear)
        assert float(c.max() / c.min()) < 1.3 and float(c.mean()) < 0.2, (az, tyre)
        assert tyre.status == "fitted" or tyre.reason.endswith("prior colour kept"), tyre
    assert float(np.median(des)) < 1.0 and max(des) < 4.0, des
    # deterministic: the same input gives the same JSON (timings aside)
    again = fit_photo(ref.image, mask=ref.mask, catalog=catalogue, mesh=m.sha256[:12])
    a, b = res.to_json(), again.to_json()
    a.pop("seconds"), b.pop("seconds")
    assert json.dumps(a) == json.dumps(b)


def test_heavy_mesh_is_posed_on_its_render_proxy(catalogue, monkeypatch):
    """A mesh over POSE_PROXY_FROM triangles is posed on its render proxy (here every mesh,
    clustered coarsely: 96 cells, about 23 % of the faces gone) and fitted with the mesh
    itself: the pose stays within 4 deg of the photo's and the body colour within CIEDE2000 4,
    box given, cluttered background (measured since stop 53, the pose search framed by the
    refined object mask: 1.5 and 3.25 deg off, the whole mesh the same; dE 1.3 and 0.5; with
    the pose framed by the box, stop 52: 3.0 and 0.25 deg, the whole mesh 0.75 and 0.25)."""
    from ucad_cl import fit
    from ucad_cl.decimate import render_proxy
    from ucad_cl.refphoto import render_reference

    m, mesh, rows = _mesh(catalogue, 1)
    assert render_proxy(mesh, 96).n_faces < 0.85 * mesh.n_faces
    monkeypatch.setattr(fit, "POSE_PROXY_FROM", 0)
    monkeypatch.setattr(fit, "POSE_PROXY_CELLS", 96)
    for az in (40.0, 200.0):
        ref = render_reference(mesh, [r.part for r in rows], COLORS, azimuth=az, elevation=8.0,
                               light=_neutral_light(), seed=1, background="clutter")
        res = fit.fit_photo(ref.image, box=ref.box, catalog=catalogue, mesh=m.sha256[:12])
        assert res.pose.source == "refined" and res.mesh is not None
        assert abs((res.pose.azimuth - az + 180.0) % 360.0 - 180.0) <= 4.0, res.pose
        assert abs(res.pose.elevation - 8.0) <= 3.0, res.pose
        body = res.parts["body"]
        assert _de(body.color_linear, COLORS["body"],
                   _exposure(body.color_linear, COLORS["body"])) < 4.0, body
        assert res.mesh.n_faces == mesh.n_faces              # the GLB gets the whole mesh


def _projected_box(mesh, K, w2c) -> np.ndarray:
    """(x0, y0, x1, y1) of the mesh's vertices projected by K, w2c (pixel edges)."""
    v = np.c_[mesh.vertices, np.ones(len(mesh.vertices))] @ np.asarray(w2c).T
    p = v[:, :3] @ np.asarray(K).T
    xy = p[:, :2] / p[:, 2:]
    return np.r_[xy.min(0), xy.max(0)]


def test_large_photo_is_analysed_in_a_window(catalogue):
    """A 1600 x 1200 photo (over ANALYSIS_PIXELS, its box over ANALYSIS_SIDE) is analysed
    in a scaled window around the box: the answers are those of the same view rendered at a
    quarter of the size (azimuth within 3 deg, body colour within CIEDE2000 1 of the small
    photo's fit after one exposure factor), and the pose and object come back in the large photo's pixels: the mesh
    projected by the fitted K, w2c lands where the reference's true camera puts it (box corners
    within 2 % of the box side), the object mask has the photo's shape and covers the true
    vehicle as well as the small photo's GrabCut does (IoU within 0.02; 0.99 from the true
    mask), for a box and for a mask."""
    from ucad_cl.fit import fit_photo
    from ucad_cl.foreground import ANALYSIS_PIXELS, ANALYSIS_SIDE
    from ucad_cl.refphoto import render_reference

    m, mesh, rows = _mesh(catalogue, 1)
    kw = dict(azimuth=130.0, elevation=8.0, light=_neutral_light(), seed=1,
              background="plain", noise=0.0, jpeg_quality=None, samples=1)
    parts = [r.part for r in rows]
    small = render_reference(mesh, parts, COLORS, size=(300, 400), **kw)
    big = render_reference(mesh, parts, COLORS, size=(1200, 1600), **kw)
    assert big.mask.size > ANALYSIS_PIXELS
    assert max(big.box[2] - big.box[0], big.box[3] - big.box[1]) > ANALYSIS_SIDE
    key = m.sha256[:12]
    a = fit_photo(small.image, box=small.box, catalog=catalogue, mesh=key)
    iou_small = (a.object.mask & small.mask).sum() / (a.object.mask | small.mask).sum()
    truth = _projected_box(mesh, big.K, big.w2c)
    side = float((truth[2:] - truth[:2]).max())
    for given in ({"box": big.box}, {"mask": big.mask}):
        b = fit_photo(big.image, catalog=catalogue, mesh=key, **given)
        assert abs((b.pose.azimuth - a.pose.azimuth + 180.0) % 360.0 - 180.0) < 3.0, given.keys()
        fb, fa = b.parts["body"].color_linear, a.parts["body"].color_linear
        assert _de(fb, fa, _exposure(fb, fa)) < 1.0, (fb, fa)
        fitted = _projected_box(mesh, b.pose.K, b.pose.w2c)
        assert np.abs(fitted - truth).max() < 0.02 * side, (fitted, truth)
        assert b.object.mask.shape == big.mask.shape
        iou = (b.object.mask & big.mask).sum() / (b.object.mask | big.mask).sum()
        assert iou >= (0.99 if "mask" in given else iou_small - 0.02), (iou, iou_small)


def test_black_paint_is_not_fitted_as_zero(catalogue):
    """A black body (albedo 0.015) under the known light: its pixels are mostly the clear
    coat's reflection, which the light model over-estimates; subtracting it gave 0 in every
    channel (L* 0) before the reflection was folded into the colour (ucad_cl/light.py). Now
    the body is a dark neutral grey (measured: 0.036 against rims 0.705, chroma CIEDE2000 0.7
    after its own exposure), darker than the rims by more than 10x (truth: 40x; the folded
    reflection makes it lighter than true)."""
    from ucad_cl.fit import fit_photo
    from ucad_cl.light import LUMA
    from ucad_cl.refphoto import render_reference

    colors = dict(COLORS, body=(0.015, 0.015, 0.016))
    m, mesh, rows = _mesh(catalogue, 1)
    ref = render_reference(mesh, [r.part for r in rows], colors, azimuth=130.0, elevation=8.0,
                           light=_neutral_light(), seed=1, background="plain", noise=0.0,
                           jpeg_quality=None)
    res = fit_photo(ref.image, mask=ref.mask, catalog=catalogue, mesh=m.sha256[:12])
    body, rim = res.parts["body"], res.parts["rim"]
    assert body.status == "fitted" and body.reflection == "folded"
    lb, lr = float(LUMA @ body.color_linear), float(LUMA @ rim.color_linear)
    assert 0.0 < lb < 0.1 * lr, (body.color_linear, rim.color_linear)
    assert _de(body.color_linear, colors["body"], _exposure(body.color_linear,
                                                            colors["body"])) < 1.5
    assert res.to_json()["parts"]["body"]["reflection"] == "folded"


def test_white_balance_only_for_a_plausible_cast(monkeypatch):
    """light.balance moves half (BALANCE_SHARE, in log gains) of a tyre's cast into the light
    when it is one a camera leaves (gains within BALANCE_RANGE): the tyre keeps the square root
    of its cast (all of it balanced away with BALANCE_SHARE = 1: grey) and the paint loses as
    much; a tyre far from grey (its mask on red paint) gives no gains and leaves the colours
    as they are."""
    import ucad_cl.light as light_mod
    from ucad_cl.light import BALANCE_RANGE, LightFit, Lighting, balance, sun_direction

    def fit(tyre):
        d = sun_direction(0.0, 45.0)
        light = Lighting(sky=np.full(3, 0.3), sun=np.full(3, 0.7 / d[1]), sun_dir=d)
        albedo = np.array([[0.5, 0.1, 0.08], tyre])
        return LightFit(lighting=light, albedo=albedo, loss=0.0, kept=np.ones(1, bool))

    cast = np.array([1.08, 1.0, 0.9])               # a warm cast, within the range
    assert light_mod.BALANCE_SHARE == 0.5
    out, g = balance(fit(0.03 * cast), {1: 100.0})
    assert BALANCE_RANGE[0] <= g.min() and g.max() <= BALANCE_RANGE[1]
    t = out.albedo[1] / np.sqrt(cast)
    assert float(t.max() - t.min()) < 1e-9 * float(t.max())            # half the cast is left
    assert np.allclose(out.albedo[0] * g, [0.5, 0.1, 0.08])             # paint / gains
    assert np.allclose(out.lighting.sky, 0.3 * g)                       # the light takes it
    monkeypatch.setattr(light_mod, "BALANCE_SHARE", 1.0)                # all of the cast
    out, g1 = balance(fit(0.03 * cast), {1: 100.0})
    t = out.albedo[1]
    assert float(t.max() - t.min()) < 1e-9 * float(t.max())            # the tyre is grey
    assert np.allclose(g1 ** 0.5 / float(light_mod.LUMA @ g1 ** 0.5), g)
    out, g = balance(fit(np.array([0.09, 0.03, 0.03])), {1: 100.0})    # red: not a cast
    assert np.all(g == 1.0) and np.allclose(out.albedo[0], [0.5, 0.1, 0.08])


def test_unseen_part_keeps_its_prior(catalogue):
    """Seen from the side, the number plates (front and rear) are not visible: status prior,
    the prior's colour (ucad_catalog.parts)."""
    from ucad_catalog.parts import PART_MATERIALS
    from ucad_cl.fit import fit_photo
    from ucad_cl.refphoto import render_reference

    m, mesh, rows = _mesh(catalogue, 2)
    assert any(r.part == "plate" for r in rows)
    ref = render_reference(mesh, [r.part for r in rows], COLORS, azimuth=90.0, elevation=5.0,
                           light=_neutral_light(), seed=2, background="plain", noise=0.0,
                           jpeg_quality=None)
    assert not (ref.part_map == 6).any()           # the truth: no plate pixel
    res = fit_photo(ref.image, mask=ref.mask, catalog=catalogue, mesh=m.sha256[:12])
    plate = res.parts["plate"]
    assert plate.status == "prior" and plate.pixels == 0
    prior = PART_MATERIALS["plate"]["pbrMetallicRoughness"]["baseColorFactor"][:3]
    assert np.allclose(plate.color_linear, prior)
    assert res.parts["body"].status == "fitted"


def test_two_colour_part_is_flagged(catalogue):
    """The ambulance case: the reference paints the doors white and the rest red, the catalogue
    calls both 'body': the body is flagged with a 'two colours' reason; one colour is not."""
    from ucad_cl.fit import fit_photo
    from ucad_cl.refphoto import render_reference

    from ucad_catalog.reader import CatalogReader

    def door_share(rows):
        paint = [r for r in rows if r.part == "body"]
        return (sum(r.pixels for r in paint if "door" in r.name)
                / max(1, sum(r.pixels for r in paint)))
    with CatalogReader(catalogue) as r:         # the vehicle with the largest doors
        k = max(range(len(r.meshes())), key=lambda i: door_share(r.parts(r.meshes()[i].sha256)))
    m, mesh, rows = _mesh(catalogue, k)
    parts = [("other" if r.part == "body" and "door" in r.name else r.part) for r in rows]
    assert parts.count("other") >= 2
    colors = dict(COLORS, other=(0.8, 0.8, 0.8))
    ref = render_reference(mesh, parts, colors, azimuth=80.0, elevation=10.0,
                           light=_neutral_light(), seed=3, background="plain", noise=0.0,
                           jpeg_quality=None)
    res = fit_photo(ref.image, mask=ref.mask, catalog=catalogue, mesh=m.sha256[:12])
    assert res.parts["body"].status == "flagged", res.parts["body"]
    assert res.parts["body"].reason.startswith("two colours")
    one = render_reference(mesh, [r.part for r in rows], COLORS, azimuth=80.0, elevation=10.0,
                           light=_neutral_light(), seed=3, background="plain", noise=0.0,
                           jpeg_quality=None)
    res = fit_photo(one.image, mask=one.mask, catalog=catalogue, mesh=m.sha256[:12])
    assert res.parts["body"].status == "fitted", res.parts["body"]


def test_retrieval_preselection_keeps_the_answer(catalogue, monkeypatch):
    """Over PRESELECT_ROWS stored rows, retrieval keeps the rows of largest float32 dot
    product before the exact rank: with 16 of the 60 rows kept it finds the same mesh and
    candidates as the exact search of all of them."""
    import ucad_cl.fit as fit
    from ucad_cl.refphoto import render_reference

    m, mesh, rows = _mesh(catalogue, 3)
    ref = render_reference(mesh, [r.part for r in rows], COLORS, azimuth=50.0, elevation=12.0,
                           seed=4, background="plain")
    exact = fit.fit_photo(ref.image, mask=ref.mask, catalog=catalogue)
    monkeypatch.setattr(fit, "PRESELECT_ROWS", 16)
    pre = fit.fit_photo(ref.image, mask=ref.mask, catalog=catalogue)
    assert pre.mesh_id == exact.mesh_id == m.sha256
    assert [c.mesh_id for c in pre.candidates][:2] == [c.mesh_id for c in exact.candidates][:2]


def test_a_photos_queries_read_each_index_row_once(catalogue, monkeypatch):
    """Retrieval's rows through the search index (``_StoredRows``): for each of several queries
    the rows, their dot products and their meshes and views are those a fresh read of the
    index gives (``SearchIndex.preselect`` then ``rows``; NumPy's float32 dot products), and a
    row asked for by several queries is read once, the store growing past its first size."""
    import ucad_cl.fit as fit
    from ucad_catalog.reader import CatalogReader

    monkeypatch.setattr(fit, "INDEX_FROM", 0)
    monkeypatch.setattr(fit, "INDEX_ROWS", 6)        # a store of 24 rows first, of 60
    rng = np.random.default_rng(5)
    with CatalogReader(catalogue) as r:
        idx = r.search_index()[0]
        assert idx is not None and len(idx.mesh) == 60
        stored = fit._StoredRows(r, [])
        union: set[int] = set()
        for k in range(12):
            q = idx.rows(np.array([5 * k]))[0] + rng.normal(0, 0.05, idx.mean.shape[0])
            got = stored.rows(q)
            near = idx.preselect(q, 6)
            union |= set(near.tolist())
            want = idx.rows(near)
            assert np.array_equal(got.take(), want)
            assert np.array_equal(got.take(np.array([4, 1])), want[[4, 1]])
            assert np.array_equal(got.mesh_of, idx.mesh[near])
            assert np.array_equal(got.view_of, idx.view[near])
            unit = (q / np.linalg.norm(q)).astype(np.float32)
            assert np.allclose(got.scores(q), want @ unit, rtol=0, atol=1e-6)
        assert stored.n_read == len(union) > 24 and stored.read is not None
        assert sorted(np.flatnonzero(stored.at >= 0).tolist()) == sorted(union)
    assert not stored.notes


def test_retrieval_leaves_out_a_mesh_without_features_with_a_note(catalogue, tmp_path):
    """A catalogue whose features object of one mesh is gone (a damaged copy): retrieval
    searches the others, finds the right mesh, and the result says which mesh was left out;
    fits of several photos with one reader read the stacked features once."""
    import shutil
    import sqlite3

    import ucad_cl.fit as fit
    from ucad_catalog.reader import CatalogReader
    from ucad_cl.refphoto import render_reference

    m, mesh, rows = _mesh(catalogue, 3)
    gone = _mesh(catalogue, 0)[0].sha256
    copy = tmp_path / "cat"
    shutil.copytree(catalogue, copy)
    with sqlite3.connect(copy / "catalog.sqlite") as con:
        obj = con.execute("SELECT a.sha256 FROM artifacts a JOIN meshes x ON a.mesh_id=x.id "
                          "WHERE x.sha256=? AND a.kind='features.npy'", (gone,)).fetchone()[0]
    (copy / "objects" / obj[:2] / obj).unlink()
    ref = render_reference(mesh, [r.part for r in rows], COLORS, azimuth=50.0, elevation=12.0,
                           seed=4, background="plain")
    with CatalogReader(copy) as r:
        res = fit.fit_photo(ref.image, mask=ref.mask, catalog=r)
        table = r.feature_table()
        again = fit.fit_photo(ref.image, mask=ref.mask, catalog=r)
        assert r.feature_table() is table
    assert res.mesh_id == again.mesh_id == m.sha256
    assert gone not in [c.mesh_id for c in res.candidates]
    assert any(f"left out of retrieval, e.g. {gone[:12]}" in n for n in res.notes), res.notes


def test_retrieval_through_the_search_index_keeps_the_answer(catalogue, tmp_path, monkeypatch):
    """With the build's search index (used from INDEX_FROM rows: here from 0), retrieval
    ranks the INDEX_ROWS rows nearest in its projection (24 of the 60 here) read in full: the
    same mesh, view and candidates as the search of every stored row (the same catalogue
    without its index, which a note says), and no note; an object gone after indexing: a note,
    and every row read instead."""
    import shutil

    import ucad_cl.fit as fit
    from ucad_catalog.reader import CatalogReader
    from ucad_cl.refphoto import render_reference

    m, mesh, rows = _mesh(catalogue, 3)
    plain = tmp_path / "cat"
    shutil.copytree(catalogue, plain)
    (plain / "search_index.npz").unlink()
    ref = render_reference(mesh, [r.part for r in rows], COLORS, azimuth=50.0, elevation=12.0,
                           seed=4, background="plain")
    monkeypatch.setattr(fit, "INDEX_FROM", 0)          # the index even for 60 rows
    with CatalogReader(plain) as r:
        assert r.search_index()[1].startswith("no search index")
        every = fit.fit_photo(ref.image, mask=ref.mask, catalog=r)
    assert any(n.startswith("no search index") and "every stored row read" in n
               for n in every.notes), every.notes
    monkeypatch.setattr(fit, "INDEX_ROWS", 24)
    with CatalogReader(catalogue) as r:
        assert r.search_index()[0] is not None
        indexed = fit.fit_photo(ref.image, mask=ref.mask, catalog=r)
    assert indexed.mesh_id == every.mesh_id == m.sha256
    assert [(c.mesh_id, c.view) for c in indexed.candidates] == \
        [(c.mesh_id, c.view) for c in every.candidates]
    assert not [n for n in indexed.notes if "search index" in n or "left out" in n]

    import sqlite3                           # an object gone after indexing: said, then every row
    damaged = tmp_path / "damaged"
    shutil.copytree(catalogue, damaged)
    gone = _mesh(catalogue, 0)[0].sha256
    with sqlite3.connect(damaged / "catalog.sqlite") as con:
        obj = con.execute("SELECT a.sha256 FROM artifacts a JOIN meshes x ON a.mesh_id=x.id "
                          "WHERE x.sha256=? AND a.kind='features.npy'", (gone,)).fetchone()[0]
    (damaged / "objects" / obj[:2] / obj).unlink()
    monkeypatch.setattr(fit, "INDEX_ROWS", 10 ** 6)     # every row: the gone one is read
    res = fit.fit_photo(ref.image, mask=ref.mask, catalog=damaged)
    assert res.mesh_id == m.sha256
    assert any(n.startswith(f"search index not used (mesh {gone[:12]}") for n in res.notes)
    assert any(f"left out of retrieval, e.g. {gone[:12]}" in n for n in res.notes), res.notes


def test_fine_rerank_scores_match_the_meshes_own_renders(catalogue):
    """Retrieval's re-rank of the first meshes: each one's score is its stored view's HOG
    distance + FINE_WEIGHT x the finer HOG's distance (the stored view shaded from its maps
    alone) + EDGE_WEIGHT x its boundaries' distance to the photo's edges + RECALL_WEIGHT x the
    photo's inside edges' distance to its boundaries + REGION_WEIGHT x the colour variance its
    material regions leave; recomputed from each mesh's own render at that view (render_views
    + shade_views, as the build shades) it agrees to 10 % of the finer distance (0.5-1 here;
    shading from the maps moves it by 0.03-0.08 on these 128 px views); the list is in score
    order and finds the mesh."""
    import ucad_cl.fit as fit
    from ucad_catalog.reader import CatalogReader
    from ucad_catalog.views import CameraRing
    from ucad_cl.cues import (boundary_points, edge_distance, edge_recall, photo_edges,
                              region_residual)
    from ucad_cl.features import HogExtractor, unit_rows
    from ucad_cl.pose import query_features
    from ucad_cl.refphoto import render_reference
    from ucad_cl.render import render_views
    from ucad_cl.shade import shade_views

    m, mesh, rows = _mesh(catalogue, 2)
    ref = render_reference(mesh, [r.part for r in rows], COLORS, azimuth=130.0, elevation=10.0,
                           seed=6, background="plain")
    res = fit.fit_photo(ref.image, mask=ref.mask, catalog=catalogue)
    assert res.candidates[0].mesh_id == m.sha256
    hogs = (HogExtractor(), HogExtractor(**fit.FINE_HOG))
    q = [unit_rows(query_features(ref.image, h, mask=ref.mask)[0][None])[0][0] for h in hogs]
    scores = [c.score for c in res.candidates[:fit.FINE_MESHES]]
    assert scores == sorted(scores)
    edges = photo_edges(ref.image, ref.mask)
    with CatalogReader(catalogue) as r:
        for c in res.candidates[:fit.FINE_MESHES]:
            _, other, _ = _mesh(catalogue, [x.sha256 for x in r.meshes()].index(c.mesh_id))
            v = r.views(c.mesh_id)[c.view]
            ring = CameraRing(K=v.K, w2c=v.w2c[None], width=int(round(2 * v.K[0, 2])),
                              height=int(round(2 * v.K[1, 2])), azimuth=np.array([v.azimuth]),
                              elevation=np.array([v.elevation]), distance=1.0, near=0.01)
            views = render_views(other, ring)
            img = shade_views(other, views, background=(128, 128, 128))
            d = [2.0 - 2.0 * float(unit_rows(h.extract(img, np.isfinite(views.depth)).feats)[0][0]
                                   @ qq) for h, qq in zip(hogs, q)]
            bp = boundary_points(views.mat_id[0])
            d_edge, d_recall = edge_distance(edges, *bp), edge_recall(edges, *bp)
            d_region = region_residual(edges, views.mat_id[0])
            assert 0.0 < d_edge < 1.0 and 0.0 < d_recall < 1.0 and 0.0 < d_region < 1.0
            total = (d[0] + fit.FINE_WEIGHT * d[1] + fit.EDGE_WEIGHT * d_edge
                     + fit.RECALL_WEIGHT * d_recall + fit.REGION_WEIGHT * d_region)
            assert abs(c.score - total) < 0.1 * fit.FINE_WEIGHT * d[1], (c, d, d_edge)


def test_retrieval_the_same_on_one_or_two_shading_threads(catalogue, monkeypatch):
    """The re-rank shades its stored views on SHADE_THREADS threads while reading the next:
    from a box in clutter (GrabCut, four object masks, every mesh re-ranked), one thread and
    two give the same answer, candidates, scores, pose and colours, and so do two runs."""
    import ucad_cl.fit as fit
    from ucad_cl.refphoto import render_reference

    m, mesh, rows = _mesh(catalogue, 1)
    ref = render_reference(mesh, [r.part for r in rows], COLORS, azimuth=300.0, elevation=15.0,
                           seed=8, background="clutter")

    def answer():
        out = fit.fit_photo(ref.image, box=ref.box, catalog=catalogue).to_json()
        out.pop("seconds")
        return out

    runs = []
    for threads in (1, 2, 2):
        monkeypatch.setattr(fit, "SHADE_THREADS", threads)
        runs.append(answer())
    assert runs[0] == runs[1] == runs[2]
    assert runs[0]["mesh_id"] == m.sha256 and len(runs[0]["candidates"]) == 5


def test_prefilter_passes_the_meshes_nearest_by_hog_and_edges(catalogue, monkeypatch):
    """With more meshes than FINE_MESHES, the re-rank describes those of the first
    PREFILTER_MESHES by HOG of least d + EDGE_WEIGHT x d_edge at their HOG-best view: recomputed
    here from the stored features (NumPy, float64) and the stored material maps, the first
    FINE_MESHES candidates are that set and the others follow in HOG order. Two photos; in the
    second (a front view) the HOG order puts the true mesh third and the pre-filter passes it
    on to the re-rank."""
    import ucad_cl.fit as fit
    from ucad_catalog.reader import CatalogReader
    from ucad_cl.cues import boundary_points, edge_distance, photo_edges
    from ucad_cl.features import HogExtractor, unit_rows
    from ucad_cl.pose import query_features
    from ucad_cl.refphoto import render_reference

    monkeypatch.setattr(fit, "FINE_MESHES", 2)
    monkeypatch.setattr(fit, "PREFILTER_MESHES", 4)
    differs = []
    for k, az in ((1, 200.0), (3, 0.0)):
        m, mesh, rows = _mesh(catalogue, k)
        ref = render_reference(mesh, [r.part for r in rows], COLORS, azimuth=az,
                               elevation=10.0, seed=7, background="plain")
        res = fit.fit_photo(ref.image, mask=ref.mask, catalog=catalogue)
        q = unit_rows(query_features(ref.image, HogExtractor(), mask=ref.mask)[0][None])[0][0]
        edges = photo_edges(ref.image, ref.mask)
        with CatalogReader(catalogue) as r:
            t = r.feature_table()
            d = 2.0 - 2.0 * unit_rows(np.asarray(t.feats, np.float64))[0] @ q
            best = {}                                  # mesh -> (d, row) of its best row
            for row in np.lexsort((np.arange(len(d)), d)):
                best.setdefault(int(t.mesh[row]), (float(d[row]), int(row)))
            order = sorted(best, key=lambda j: best[j])
            pre = []
            for j in order[:4]:
                sha = t.meshes[j].sha256
                mat = np.asarray(r.material_map(sha, int(t.view[best[j][1]])))
                pre.append((best[j][0] + fit.EDGE_WEIGHT * edge_distance(
                    edges, *boundary_points(mat)), j))
            keep = {t.meshes[j].sha256 for _, j in sorted(pre)[:2]}
            rest = [t.meshes[j].sha256 for j in order if t.meshes[j].sha256 not in keep]
        assert {c.mesh_id for c in res.candidates[:2]} == keep, k
        assert [c.mesh_id for c in res.candidates[2:]] == rest[:len(res.candidates) - 2], k
        differs.append(keep != {t.meshes[j].sha256 for j in order[:2]})
    assert differs == [False, True]
    assert m.sha256 in keep and m.sha256 not in {t.meshes[j].sha256 for j in order[:2]}


def test_refined_object_mask_beats_grabcut_in_clutter(catalogue):
    """With a box, GrabCut is rerun seeded by the first retrieved meshes' stored silhouettes:
    on a black car in a cluttered street its object overlaps the reference's true mask (Embree
    ray casts, not the project's renderer) better than GrabCut's first mask does."""
    from ucad_cl.foreground import object_mask
    from ucad_cl.refphoto import draw_light, render_reference
    from ucad_cl.fit import fit_photo

    def iou(a, b):
        return np.count_nonzero(a & b) / np.count_nonzero(a | b)

    m, mesh, rows = _mesh(catalogue, 3)
    black = dict(COLORS, body=(0.03, 0.03, 0.035))
    ref = render_reference(mesh, [r.part for r in rows], black, azimuth=140.0, elevation=10.0,
                           seed=7, background="clutter", size=(240, 320),
                           light=draw_light(np.random.default_rng(7)))
    first = iou(object_mask(ref.image, box=ref.box).mask, ref.mask)
    res = fit_photo(ref.image, box=ref.box, catalog=catalogue)
    assert res.object is not None and res.object_source == "grabcut"
    refined = iou(res.object.mask, ref.mask)
    assert refined >= 0.93 and refined >= first + 0.05, (first, refined)
    # retrieval on the refined object keeps the truck in its first two (the fine re-rank puts
    # a pickup 0.07 ahead of it on this black body at 128 px; without a pose re-rank of two,
    # fit.RERANK_POSE = 1, the pickup is fitted: docs/FIT.md, "The finer HOG re-rank")
    assert m.sha256 in [c.mesh_id for c in res.candidates[:2]]


def test_retrieval_finds_the_mesh_and_cli_writes_outputs(catalogue, tmp_path, capsys):
    """Without --mesh the catalogue-wide search picks the right one of five meshes; the CLI
    writes the JSON (the interface's field names), the GLB with fitted colours and the PNG."""
    import cv2

    from ucad_cl.cli import main
    from ucad_cl.refphoto import render_reference

    m, mesh, rows = _mesh(catalogue, 3)
    ref = render_reference(mesh, [r.part for r in rows], COLORS, azimuth=50.0, elevation=12.0,
                           seed=4, background="clutter")
    photo = tmp_path / "street.png"
    cv2.imwrite(str(photo), ref.image[:, :, ::-1])
    out = tmp_path / "fits"
    assert main(["fit", str(photo), "--box", *map(str, ref.box), "--catalog", str(catalogue),
                 "--out", str(out)]) == 0
    doc = json.loads((out / "street.json").read_text())
    assert doc["mesh_id"] == m.sha256
    assert {"mesh_id", "mesh_path", "pose", "lighting", "parts", "materials", "candidates",
            "seconds"} <= set(doc)
    assert {"azimuth", "elevation", "K", "w2c"} <= set(doc["pose"])
    body = doc["parts"]["body"]
    assert {"color_linear", "color_srgb", "metallic", "roughness", "pixels", "residual",
            "status"} <= set(body)
    assert [x["name"] for x in doc["materials"]] == [r.name for r in rows]
    assert len(doc["candidates"]) >= 2 and doc["candidates"][0]["mesh_id"] == m.sha256
    scores = [c["score"] for c in doc["candidates"]]        # how far the answer is ahead
    assert doc["retrieval_margin"] == pytest.approx((min(scores[1:]) - scores[0]) / scores[0],
                                                    abs=2e-5)
    png = cv2.imread(str(out / "street.png"))
    assert png is not None and png.shape[1] > 3 * png.shape[0]
    glb = (out / "street.glb").read_bytes()
    n = struct.unpack("<I", glb[12:16])[0]
    gltf = json.loads(glb[20:20 + n])
    paint = [mt for mt in gltf["materials"] if mt["extras"]["ucad"]["part"] == "body"]
    assert paint and all(mt["pbrMetallicRoughness"]["baseColorFactor"][:3] ==
                         [min(max(c, 0.0), 1.0) for c in body["color_linear"]] for mt in paint)
    assert "KHR_materials_clearcoat" in paint[0]["extensions"]


def test_retrieval_margin_and_its_uncertain_note(catalogue, monkeypatch):
    """retrieval_margin: how far the answer's score is ahead of the least of the next listed
    meshes', relative to it (None with one candidate or a zero score); a fit whose margin is
    below UNCERTAIN_MARGIN says so in a note naming the next mesh, one above it does not, and
    a fit with the mesh given has no margin."""
    from ucad_cl import fit
    from ucad_cl.refphoto import render_reference

    def c(score, name="x.glb"):
        return fit.Candidate("0" * 64, name, 0, 0.0, 15.0, score)

    assert fit.retrieval_margin([c(2.0), c(2.5), c(2.1)]) == pytest.approx(0.05)
    assert fit.retrieval_margin([c(2.0), c(1.9)]) == pytest.approx(-0.05)   # a pose re-rank
    assert fit.retrieval_margin([c(2.0)]) is None and fit.retrieval_margin([]) is None
    assert fit.retrieval_margin([c(0.0), c(1.0)]) is None
    copies = [c(2.0, "a.glb"), c(2.0, "copy.glb"), c(2.01, "b.glb"), c(2.5, "d.glb")]
    assert fit.retrieval_margin(copies) == pytest.approx(0.005)      # a copy is not counted
    assert fit.retrieval_margin(copies[:2]) is None
    said = fit._Fit.__new__(fit._Fit)
    said.notes = []
    said._say_how_sure(copies, fit.retrieval_margin(copies))
    assert said.notes[0].startswith("copy.glb scores exactly as this mesh")
    assert said.notes[1].startswith("retrieval is uncertain: the next mesh (b.glb)")
    m, mesh, rows = _mesh(catalogue, 1)
    ref = render_reference(mesh, [r.part for r in rows], COLORS, azimuth=130.0, elevation=12.0,
                           seed=3, background="clutter")
    res = fit.fit_photo(ref.image, box=ref.box, catalog=catalogue)
    scores = [x.score for x in res.candidates]
    assert res.retrieval_margin == pytest.approx((min(scores[1:]) - scores[0]) / scores[0])
    said = [n for n in res.notes if n.startswith("retrieval is uncertain")]
    assert not said if res.retrieval_margin >= fit.UNCERTAIN_MARGIN else said
    monkeypatch.setattr(fit, "UNCERTAIN_MARGIN", res.retrieval_margin + 1e-9)
    again = fit.fit_photo(ref.image, box=ref.box, catalog=catalogue)
    [note] = [n for n in again.notes if n.startswith("retrieval is uncertain")]
    nxt = min((x for x in res.candidates[1:] if x.score != scores[0]), key=lambda x: x.score)
    assert Path(nxt.mesh_path).name in note
    from ucad_cl.commands.fit import UNCERTAIN_BAND, overview
    sure, unsure = overview(replace(res, retrieval_margin=None)), overview(again)
    band = np.all(unsure == UNCERTAIN_BAND, axis=2)            # the picture says it too
    assert sure.shape == unsure.shape and band[:12, -1].all() and not band[-1].any()
    rows = ~np.all(sure == unsure, axis=(1, 2))
    assert rows[:12].all() and not rows[len(rows) // 8:].any()  # only the band differs
    given = fit.fit_photo(ref.image, box=ref.box, catalog=catalogue, mesh=m.sha256[:12])
    assert given.retrieval_margin is None and given.to_json()["retrieval_margin"] is None
    assert not any(n.startswith("retrieval is uncertain") for n in given.notes)


@dataclass
class _CutPhoto:
    sha: str
    azimuth: float
    image: np.ndarray       # the reference with 30 % of the vehicle's box cut off on the left
    box: tuple              # the box reaching the photo's left edge
    mask: np.ndarray        # the vehicle's pixels the photo shows
    mesh: object


@pytest.fixture(scope="module")
def cut_photos(catalogue) -> list[_CutPhoto]:
    """Four photos of each of the five meshes (elevation 12 deg, cluttered background), each
    with the left 30 % of the vehicle's box cut off by the photo's edge (drawn once: two tests
    read them, neither changes them)."""
    from ucad_cl.refphoto import render_reference

    out = []
    for k in range(5):
        m, mesh, rows = _mesh(catalogue, k)
        for az in (40.0, 140.0, 220.0, 320.0):
            ref = render_reference(mesh, [r.part for r in rows], COLORS, azimuth=az,
                                   elevation=12.0, seed=k, background="clutter")
            x0, y0, x1, y1 = ref.box
            c = int(round(x0 + 0.3 * (x1 - x0)))
            image, mask = np.ascontiguousarray(ref.image[:, c:]), ref.mask[:, c:].copy()
            image.flags.writeable = mask.flags.writeable = False
            out.append(_CutPhoto(m.sha256, az, image, (0, y0, x1 - c, y1), mask, mesh))
    return out


def test_a_vehicle_cut_by_the_photos_edge_is_retrieved(catalogue, cut_photos, monkeypatch):
    """Photos with 30 % of the vehicle cut off by the left edge (the box at the edge): retrieval
    that also assumes the vehicle going on past the edge finds more of the five meshes than
    retrieval of the visible part alone (15 against 12 of 20 when written), and says so."""
    import ucad_cl.fit as fit_mod
    import ucad_cl.foreground as fg

    photos = cut_photos
    found, shipped = {}, fg.PAST_EDGE
    for past in (shipped, ()):
        monkeypatch.setattr(fg, "PAST_EDGE", past)
        res = [fit_mod.fit_photo(p.image, box=p.box, catalog=catalogue) for p in photos]
        found[past] = sum(r.mesh_id == p.sha for p, r in zip(photos, res))
        if past:
            assert all(any("photo's edge" in n for n in r.notes) for r in res)
    assert found[shipped] >= 14 and found[shipped] >= found[()] + 2, found


def test_a_vehicle_cut_by_the_photos_edge_is_posed_past_the_edge(catalogue, cut_photos,
                                                                 monkeypatch):
    """The same kind of photos (30 % cut off by the left edge) with the mesh given: the pose
    searched on the photo grown past the edge (the hypothesis nearest to the mesh's stored
    views, the photo's camera moved with it) is nearer the true azimuth than the pose of the
    visible part alone, its elevation about as near, and its K is in the photo's pixels (the
    render at the pose covers the visible vehicle); with the visible pixels given as the mask
    (half of the photos), nearer in azimuth too."""
    import ucad_cl.fit as fit_mod
    import ucad_cl.foreground as fg
    from ucad_cl.cameras import single_camera
    from ucad_cl.pose import az_diff
    from ucad_cl.render import render_views

    photos = cut_photos
    err, shipped = {}, fg.PAST_EDGE
    for past in (shipped, ()):
        monkeypatch.setattr(fg, "PAST_EDGE", past)
        res = [fit_mod.fit_photo(p.image, box=p.box, catalog=catalogue, mesh=p.sha)
               for p in photos]
        err[past] = (np.median([az_diff(r.pose.azimuth, p.azimuth) for p, r in zip(photos, res)]),
                     np.median([abs(r.pose.elevation - 12.0) for r in res]))
        if past:                               # the pose's camera in the photo's pixels
            grown = sum(any("grown past its edge" in n for n in r.notes) for r in res)
            assert grown >= len(res) // 2           # (17 of 20 when written; a note says so)
            iou = []
            for p, r in zip(photos, res):
                H, W = p.mask.shape
                sil = np.isfinite(render_views(p.mesh, single_camera(
                    r.pose.K, r.pose.w2c, W, H)).depth[0])
                iou.append((sil & p.mask).sum() / (sil | p.mask).sum())
            assert np.median(iou) > 0.8, iou
    # (when written: median |azimuth error| 10.3 against 17.1 deg, elevation 4.1 against 2.6;
    # on the bench's held-out draws the elevation error fell too: docs/FIT.md)
    assert err[shipped][0] < err[()][0] - 2.0 and err[shipped][1] <= err[()][1] + 2.0, err
    by_mask = {}                            # the vehicle's visible pixels given as the mask
    for past in (shipped, ()):
        monkeypatch.setattr(fg, "PAST_EDGE", past)
        res = [fit_mod.fit_photo(p.image, mask=p.mask, catalog=catalogue, mesh=p.sha)
               for p in photos[::2]]
        by_mask[past] = np.median([az_diff(r.pose.azimuth, p.azimuth)
                                   for p, r in zip(photos[::2], res)])
    assert by_mask[shipped] < by_mask[()] - 2.0, by_mask    # (4.3 against 12.8 when written)


# ----------------------------------------------------------------------------- hostile input

@pytest.mark.parametrize("fov", [15.0, 80.0])
def test_a_known_field_of_view_gives_the_photos_camera(catalogue, fov):
    """A long-lens and a wide-lens photo (15 and 80 deg over the narrower side; the fit assumes
    45 without ``fov``): told the field of view, the fit's camera has the photo's focal length
    within 20 % and the pose within 2 deg (measured: +16 / +14 %, 0.5 / 1.25 deg in azimuth);
    assuming 45 deg, the focal length is off by over 40 % (-55 / +55 %; 3.25 / 4.75 deg in
    azimuth: the distance, hence the perspective, follows it)."""
    from ucad_cl import fit
    from ucad_cl.refphoto import render_reference

    m, mesh, rows = _mesh(catalogue, 1)
    ref = render_reference(mesh, [r.part for r in rows], COLORS, azimuth=35.0, elevation=10.0,
                           fov=fov, fill=0.8, offset=(0.4, -0.2), light=_neutral_light(),
                           seed=2, background="clutter")
    f_true = float(ref.K[0, 0])
    told = fit.fit_photo(ref.image, box=ref.box, catalog=catalogue, mesh=m.sha256[:12], fov=fov)
    guess = fit.fit_photo(ref.image, box=ref.box, catalog=catalogue, mesh=m.sha256[:12])
    assert abs(told.pose.K[0, 0] / f_true - 1.0) < 0.2, (told.pose.K, f_true)
    assert abs(guess.pose.K[0, 0] / f_true - 1.0) > 0.4, (guess.pose.K, f_true)
    assert abs((told.pose.azimuth - 35.0 + 180.0) % 360.0 - 180.0) <= 2.0, told.pose
    assert abs(told.pose.elevation - 10.0) <= 2.0, told.pose
    with pytest.raises(ValueError, match="field of view"):
        fit.fit_photo(ref.image, box=ref.box, catalog=catalogue, mesh=m.sha256[:12], fov=0.0)


@pytest.fixture(scope="module")
def photo(catalogue, tmp_path_factory):
    import cv2

    from ucad_cl.refphoto import render_reference

    m, mesh, rows = _mesh(catalogue, 1)
    ref = render_reference(mesh, [r.part for r in rows], COLORS, azimuth=30.0, elevation=10.0,
                           seed=5, background="plain", size=(240, 320))
    d = tmp_path_factory.mktemp("photos")
    cv2.imwrite(str(d / "car.png"), ref.image[:, :, ::-1])
    cv2.imwrite(str(d / "car_mask.png"), ref.mask.astype(np.uint8) * 255)  # beside it: its mask
    return d / "car.png", ref.box, m


def _one_line_error(capsys, code, rc):
    err = capsys.readouterr().err.strip()
    assert rc == code and "Traceback" not in err and len(err.splitlines()) == 1, err
    return err


def test_hostile_inputs_get_one_line(catalogue, photo, tmp_path, capsys):
    from ucad_cl.cli import main

    path, box, m = photo
    cat, out = str(catalogue), str(tmp_path / "o")
    base = ["fit", "--catalog", cat, "--out", out, "--mesh", m.sha256[:12]]
    b = [str(v) for v in box]
    err = _one_line_error(capsys, 2, main(base + [str(path), "--box", "900", "900", "990",
                                                  "990"]))
    assert "empty inside" in err
    err = _one_line_error(capsys, 2, main(base + [str(path), "--box", "5", "5", "5", "60"]))
    assert "too small" in err or "empty" in err
    err = _one_line_error(capsys, 2, main(base + [str(path), "--box", "0", "0", "40", "30"]))
    assert "no vehicle" in err or "enough pixels" in err
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 20)
    err = _one_line_error(capsys, 2, main(base + [str(bad), "--box", *b]))
    assert "cannot read" in err
    huge = tmp_path / "huge.png"
    png_header_only(huge, 20000, 20000)
    err = _one_line_error(capsys, 2, main(base + [str(huge), "--box", *b]))
    assert "megapixels" in err
    for fov in ("0", "nan", "200"):
        err = _one_line_error(capsys, 2, main(base + [str(path), "--box", *b, "--fov", fov]))
        assert "field of view" in err
    err = _one_line_error(capsys, 2, main(["fit", "--catalog", cat, "--out", out, "--mesh",
                                           "no-such-mesh.glb", str(path), "--box", *b]))
    assert "no-such-mesh" in err
    _one_line_error(capsys, 2, main(["fit", "--catalog", str(tmp_path / "nocat"), "--out", out,
                                     str(path), "--box", *b]))


def test_damaged_catalogue_and_unwritable_out_get_one_line(catalogue, photo, tmp_path, capsys):
    """A view stack that is truncated or gone (read inside the fit, after retrieval) and an
    output folder that cannot be made: one line and exit 2, no traceback."""
    import shutil
    import sqlite3

    from ucad_cl.cli import main

    path, box, m = photo
    b = [str(v) for v in box]
    damaged = tmp_path / "damaged"
    shutil.copytree(catalogue, damaged)
    with sqlite3.connect(damaged / "catalog.sqlite") as con:
        obj = con.execute("SELECT a.sha256 FROM artifacts a JOIN meshes x ON a.mesh_id=x.id "
                          "WHERE x.sha256=? AND a.kind='views.exr'", (m.sha256,)).fetchone()[0]
    stack = damaged / "objects" / obj[:2] / obj
    args = ["fit", str(path), "--box", *b, "--catalog", str(damaged), "--mesh", m.sha256[:12],
            "--out", str(tmp_path / "o")]
    stack.write_bytes(stack.read_bytes()[:200])
    err = _one_line_error(capsys, 2, main(args))
    assert "catalogue is damaged" in err and m.sha256[:12] in err, err
    stack.unlink()
    err = _one_line_error(capsys, 2, main(args))
    assert "catalogue is damaged" in err and obj in err, err
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    err = _one_line_error(capsys, 2, main(["fit", str(path), "--box", *b, "--catalog",
                                           str(catalogue), "--mesh", m.sha256[:12],
                                           "--out", str(blocker / "o")]))
    assert "cannot write the outputs" in err, err


def test_grayscale_and_16_bit_photos_are_converted(photo, catalogue, tmp_path, capsys):
    import cv2

    from ucad_cl.cli import main

    import psutil

    path, box, m = photo
    img = cv2.imread(str(path))
    gray, deep = tmp_path / "gray.png", tmp_path / "deep.png"
    before = {p.pid for p in psutil.Process().children()}
    cv2.imwrite(str(gray), cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
    cv2.imwrite(str(deep), img.astype(np.uint16) * 257)
    for p in (gray, deep):
        assert main(["fit", str(p), "--box", *map(str, box), "--catalog", str(catalogue),
                     "--mesh", m.sha256[:12], "--out", str(tmp_path / "o")]) == 0
        assert (tmp_path / "o" / f"{p.stem}.json").exists()
        assert {p.pid for p in psutil.Process().children()} <= before   # the mesh reader's
    capsys.readouterr()                                                  # child is gone
    doc = json.loads((tmp_path / "o" / "deep.json").read_text())
    assert doc["mesh_id"] == m.sha256


def test_jpeg_exif_orientation_is_applied(photo, catalogue, tmp_path, capsys):
    """A phone JPEG stored sideways with EXIF orientation 6 (turn 90 deg clockwise to show) is
    read as shown (PIL's exif_transpose as the reference), so the box drawn on the shown photo
    finds the vehicle: the same mesh and body colour as the upright PNG."""
    import cv2
    from PIL import Image, ImageOps

    from ucad_cl.cli import main
    from ucad_cl.commands.common import read_image

    path, box, m = photo
    upright = cv2.imread(str(path))[:, :, ::-1]
    im = Image.fromarray(np.ascontiguousarray(np.rot90(upright)))      # stored turned left
    exif = im.getexif()
    exif[0x0112] = 6
    turned = tmp_path / "phone.jpg"
    im.save(turned, exif=exif.tobytes(), quality=100, subsampling=0)   # JPEG loss aside
    shown = read_image(turned)
    with Image.open(turned) as ref:
        assert np.array_equal(shown, np.asarray(ImageOps.exif_transpose(ref).convert("RGB")))
    assert shown.shape == upright.shape
    assert np.abs(shown.astype(int) - upright).mean() < 3.0
    out = tmp_path / "o"
    for p in (path, turned):
        assert main(["fit", str(p), "--box", *map(str, box), "--catalog", str(catalogue),
                     "--mesh", m.sha256[:12], "--out", str(out)]) == 0
    capsys.readouterr()
    a, b = (json.loads((out / f"{p.stem}.json").read_text()) for p in (path, turned))
    assert b["mesh_id"] == a["mesh_id"] == m.sha256
    fa, fb = (np.array(d["parts"]["body"]["color_linear"]) for d in (a, b))
    assert _de(fb, fa) < 1.0, (fa, fb)


def test_mask_files_0_1_0_255_soft_and_jpeg_give_the_vehicle(photo, tmp_path):
    """read_mask: a 0/1 PNG, a 0/255 PNG, a soft matte (0-255, blurred edges) and the 0/255
    mask saved as JPEG (its faint noise off the vehicle) all give the true mask within the
    blur's / JPEG's boundary pixels (``> 0`` took the JPEG's noise: it is checked to have some);
    an all-zero mask gives none (the fit then says the mask is empty)."""
    import cv2

    from ucad_cl.commands.common import read_mask

    path, box, m = photo
    truth = cv2.imread(str(path.with_name("car_mask.png")), cv2.IMREAD_GRAYSCALE) > 0
    u8 = truth.astype(np.uint8)
    files = {"01.png": u8, "0255.png": u8 * 255,
             "soft.png": cv2.GaussianBlur(u8 * 255, (5, 5), 1.5)}
    for name, img in files.items():
        cv2.imwrite(str(tmp_path / name), img)
    cv2.imwrite(str(tmp_path / "mask.jpg"), u8 * 255, [cv2.IMWRITE_JPEG_QUALITY, 75])
    noisy = cv2.imread(str(tmp_path / "mask.jpg"), cv2.IMREAD_GRAYSCALE)
    assert ((noisy > 0) & ~truth).sum() > 50          # the noise a "> 0" rule took in
    edge = cv2.dilate(u8, np.ones((5, 5), np.uint8)) != cv2.erode(u8, np.ones((5, 5), np.uint8))
    for name in (*files, "mask.jpg"):
        got = read_mask(tmp_path / name, truth.shape)
        assert not ((got ^ truth) & ~edge).any(), name
    cv2.imwrite(str(tmp_path / "zero.png"), u8 * 0)
    assert not read_mask(tmp_path / "zero.png", truth.shape).any()


def test_moved_mesh_file_falls_back_to_the_stored_view(photo, catalogue, tmp_path, capsys):
    from ucad_cl.cli import main

    path, box, m = photo
    src = m.source
    hidden = src.with_name(src.name + ".away")
    src.rename(hidden)
    try:
        rc = main(["fit", str(path), "--box", *map(str, box), "--catalog", str(catalogue),
                   "--mesh", m.sha256[:12], "--out", str(tmp_path / "o")])
    finally:
        hidden.rename(src)
    out = capsys.readouterr().out
    assert rc == 0 and "moved" in out
    doc = json.loads((tmp_path / "o" / "car.json").read_text())
    assert doc["pose"]["source"] == "stored view" and doc["glb"] is None
    assert not (tmp_path / "o" / "car.glb").exists()
    assert doc["parts"]["body"]["status"] in ("fitted", "flagged")


def _segfaulting_reader(path, clean=True, **kwargs):
    import os
    import signal
    os.kill(os.getpid(), signal.SIGSEGV)


def test_mesh_loader_child_reused_crash_falls_back_no_child_left(photo, catalogue, monkeypatch):
    """``ingest.MeshLoader``: isolated, the mesh is read in a child interpreter (its reader
    imported there before the first load), the default in a process that has not imported
    the reader (a fresh one; not this test process) and not used when the mesh is given (no
    retrieval to hide the child's start behind); the mesh read there gives the fit's answer
    (the same JSON as read here); one loader serves several photos with one child; a reader
    that crashes (SIGSEGV) costs that fit its refined pose, not the process (the nearest
    stored view, with a note naming the crash), and the next load starts a new child. No
    child is left once the fits and the loader are done."""
    import functools
    import subprocess
    import sys

    import cv2
    import psutil

    import ucad_cl.fit as fit_mod
    import ucad_cl.ingest as ingest_mod
    from ucad_cl.ingest import load_mesh_isolated

    path, box, m = photo
    image = cv2.imread(str(path))[:, :, ::-1].copy()
    before = {p.pid for p in psutil.Process().children()}

    def children():
        return {p.pid for p in psutil.Process().children()} - before

    code = "import ucad_cl.fit as f; m = f.MeshLoader(); print(m.isolated); m.close()"
    fresh = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           check=True, cwd=Path(__file__).resolve().parents[1]).stdout.split()
    assert fresh == ["True"]
    with ingest_mod.MeshLoader() as here:
        assert not here.isolated and not children()     # trimesh is imported in this process
    res = fit_mod.fit_photo(image, box=box, catalog=catalogue, mesh=m.sha256[:12])
    assert res.mesh is not None and res.pose.source == "refined" and not children()
    with ingest_mod.MeshLoader(isolated=True) as mesh_loader:
        for _ in range(2):
            again = fit_mod.fit_photo(image, box=box, catalog=catalogue, mesh=m.sha256[:12],
                                      mesh_loader=mesh_loader)
            assert again.pose.source == "refined" and len(children()) == 1
        a, b = res.to_json(), again.to_json()
        a.pop("seconds"), b.pop("seconds")
        assert json.dumps(a) == json.dumps(b)
        with monkeypatch.context() as mp:
            mp.setattr(ingest_mod, "load_mesh_isolated",
                       functools.partial(load_mesh_isolated, loader=_segfaulting_reader))
            res = fit_mod.fit_photo(image, box=box, catalog=catalogue, mesh=m.sha256[:12],
                                    mesh_loader=mesh_loader)
        assert res.mesh is None and res.pose.source == "stored view"
        assert any("cannot be read" in n and "SIGSEGV" in n for n in res.notes), res.notes
        assert res.parts["body"].status in ("fitted", "flagged")
        res = fit_mod.fit_photo(image, box=box, catalog=catalogue, mesh=m.sha256[:12],
                                mesh_loader=mesh_loader)
        assert res.pose.source == "refined"
    assert not children()


def test_cli_starts_the_mesh_reader_first_and_uses_only_that_child(photo, catalogue, tmp_path):
    """``ucad-index fit ... --mesh M`` in a fresh interpreter: one child process in all, started
    before the parser's modules are imported (``cli._mesh_reader_ahead``), and the mesh read
    there (the pose refined, trimesh never imported here); the command word is found past
    the global ``--device`` value; other commands start none."""
    import subprocess
    import sys

    from ucad_cl.cli import _command_of

    assert _command_of(["--device", "fit", "show", "x"]) == "show"
    assert _command_of(["--version"]) is None and _command_of(["fit", "--help"]) == "fit"
    path, box, m = photo
    out = tmp_path / "o"
    args = ["fit", str(path), "--box", *map(str, box), "--catalog", str(catalogue), "--out",
            str(out), "--mesh", m.sha256[:12]]
    code = ("import sys, ucad_cl.system as s\n"
            "seen = []\n"
            "start = s.IsolatedChild.__init__\n"
            "def counted(self, *a, **k):\n"
            "    seen.append(sorted(m for m in sys.modules if m.startswith('ucad_cl.')))\n"
            "    start(self, *a, **k)\n"
            "s.IsolatedChild.__init__ = counted\n"
            "from ucad_cl.cli import main\n"
            f"assert main({args!r}) == 0\n"
            "assert len(seen) == 1, len(seen)\n"
            "assert 'ucad_cl.fit' not in seen[0] and 'ucad_cl.commands.fit' not in seen[0]\n"
            "assert 'trimesh' not in sys.modules\n"
            f"assert main(['status', '--catalog', {str(catalogue)!r}]) == 0 and len(seen) == 1\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300, cwd=Path(__file__).resolve().parents[1])
    assert run.returncode == 0, run.stderr[-2000:]
    doc = json.loads((out / f"{path.stem}.json").read_text())
    assert doc["mesh_id"] == m.sha256 and doc["pose"]["source"] == "refined"


def test_no_process_for_the_mesh_reader_is_one_line(photo, catalogue, tmp_path, capsys,
                                                     monkeypatch):
    """When no child process can be started for the mesh reader (process or memory limits),
    the fit says so in one line with exit status 2, never a traceback (a process that has not
    imported the reader: trimesh taken out of ``sys.modules`` for the test)."""
    import sys

    import ucad_cl.system as system
    from ucad_cl.cli import main

    def refuse(*args, **kwargs):
        raise OSError(11, "Resource temporarily unavailable")

    path, box, m = photo
    monkeypatch.delitem(sys.modules, "trimesh")
    monkeypatch.setattr(system.subprocess, "Popen", refuse)
    rc = main(["fit", str(path), "--box", *map(str, box), "--catalog", str(catalogue),
               "--out", str(tmp_path / "o")])
    err = _one_line_error(capsys, 2, rc)
    assert "cannot start the mesh reader's process" in err and "Resource" in err


def test_photo_list_with_progress(photo, catalogue, tmp_path, capsys):
    from ucad_cl.cli import main

    path, box, m = photo
    lst = tmp_path / "list.csv"
    lst.write_text("path,x0,y0,x1,y1,mesh\n"
                   f"{path},{box[0]},{box[1]},{box[2]},{box[3]},{m.sha256[:12]}\n"
                   f"{tmp_path / 'missing.png'},0,0,10,10,\n")
    rc = main(["fit", "--photos", str(lst), "--catalog", str(catalogue), "--out",
               str(tmp_path / "o")])
    captured = capsys.readouterr()
    assert rc == 1 and "1 fitted, 1 failed" in captured.out
    assert "missing.png: no such file" in captured.err


def test_photo_list_saved_by_a_spreadsheet(tmp_path):
    """A list saved by a spreadsheet (UTF-8 with a byte-order mark, CRLF line ends) reads as
    the same list without them: the header is found and the first path has no stray mark."""
    from ucad_cl.commands.fit import read_list

    text = "path,x0,y0,x1,y1,mesh\na.png,1,2,30,40,\nb.png,5,6,70,80,3f2a9c01\n"
    plain, excel = tmp_path / "plain.csv", tmp_path / "excel.csv"
    plain.write_text(text, encoding="utf-8")
    excel.write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode())
    assert read_list(excel) == read_list(plain) == [
        (tmp_path / "a.png", [1.0, 2.0, 30.0, 40.0], None, None),
        (tmp_path / "b.png", [5.0, 6.0, 70.0, 80.0], None, "3f2a9c01")]
    headless = tmp_path / "headless.csv"
    headless.write_bytes(b"\xef\xbb\xbfa.png,1,2,30,40\r\n")
    assert read_list(headless) == [(tmp_path / "a.png", [1.0, 2.0, 30.0, 40.0], None, None)]


def test_photo_list_with_mask_column(photo, catalogue, tmp_path, capsys):
    """A list with a header naming its columns: a row with a vehicle mask is fitted on that
    mask (the JSON says so, as --mask does); a row giving a box and a mask, and a header with an
    unknown column, get one line naming the line."""
    from ucad_cl.cli import main

    path, box, m = photo
    for name in ("car.png", "car_mask.png"):                  # paths relative to the list
        (tmp_path / name).write_bytes((path.parent / name).read_bytes())
    lst = tmp_path / "list.csv"
    lst.write_text(f"path,mask,mesh\ncar.png,car_mask.png,{m.sha256[:12]}\n")
    out = tmp_path / "o"
    assert main(["fit", "--photos", str(lst), "--catalog", str(catalogue), "--out",
                 str(out)]) == 0
    assert "1 fitted, 0 failed" in capsys.readouterr().out
    doc = json.loads((out / "car.json").read_text())
    assert doc["mesh_id"] == m.sha256 and doc["object"] == "mask"
    assert doc["parts"]["body"]["status"] in ("fitted", "flagged")
    both = tmp_path / "both.csv"
    both.write_text("path,x0,y0,x1,y1,mask\n"
                    f"car.png,{box[0]},{box[1]},{box[2]},{box[3]},car_mask.png\n")
    err = _one_line_error(capsys, 2, main(["fit", "--photos", str(both), "--catalog",
                                           str(catalogue), "--out", str(out)]))
    assert "line 2" in err and "not both" in err
    bad = tmp_path / "bad.csv"
    bad.write_text("path,box,mesh\ncar.png,1,\n")
    err = _one_line_error(capsys, 2, main(["fit", "--photos", str(bad), "--catalog",
                                           str(catalogue), "--out", str(out)]))
    assert "line 1" in err and "box" in err


def _red_segmenter(tmp_path: Path, fixed: tuple[int, int] | None = None) -> str:
    """onnx:MODEL:CONFIG of a 1x1 convolution: class 1 (body) where 10 R - 5 G - 5 B > 1
    (``fixed``: the input's (H, W) fixed in the graph, not the config's)."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    w = np.array([[0, 0, 0], [10, -5, -5]], np.float32).reshape(2, 3, 1, 1)
    b = np.array([1, 0], np.float32)
    graph = helper.make_graph(
        [helper.make_node("Conv", ["image", "w", "b"], ["logits"])], "red_seg",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT,
                                       ["N", 3, *(fixed or ("H", "W"))])],
        [helper.make_tensor_value_info("logits", TensorProto.FLOAT, ["N", 2, "H", "W"])],
        initializer=[numpy_helper.from_array(w, "w"), numpy_helper.from_array(b, "b")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.save(model, str(tmp_path / "seg.onnx"))
    (tmp_path / "seg.json").write_text(json.dumps({"classes": {"0": "other", "1": "body"},
                                                   "input_size": [64, 96]}))
    return f"onnx:{tmp_path / 'seg.onnx'}:{tmp_path / 'seg.json'}"


def test_onnx_photo_segmenter_replaces_the_rendered_masks(photo, catalogue, tmp_path, capsys):
    """--segmenter onnx:...: the part masks come from the model run on the photo (here: red
    pixels are body), inside the render's silhouette; parts the model does not name show no
    pixel (status prior)."""
    from ucad_cl.cli import main

    path, box, m = photo
    spec = _red_segmenter(tmp_path)
    out = tmp_path / "o"
    assert main(["fit", str(path), "--box", *map(str, box), "--catalog", str(catalogue),
                 "--mesh", m.sha256[:12], "--segmenter", spec, "--out", str(out)]) == 0
    doc = json.loads((out / "car.json").read_text())
    assert doc["parts"]["body"]["status"] == "fitted" and doc["parts"]["body"]["pixels"] > 100
    assert doc["parts"]["wheel"]["status"] == "prior"
    c = doc["parts"]["body"]["color_linear"]
    assert c[0] > 3 * max(c[1], c[2])                 # the red paint (COLORS["body"])
    assert main(["fit", str(path), "--box", *map(str, box), "--catalog", str(catalogue),
                 "--segmenter", "onnx:nowhere.onnx:x.json", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    (tmp_path / "fixed").mkdir()                  # a model that refuses the config's input size
    bad = _red_segmenter(tmp_path / "fixed", fixed=(16, 16))
    assert main(["fit", str(path), "--box", *map(str, box), "--catalog", str(catalogue),
                 "--mesh", m.sha256[:12], "--segmenter", bad, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "seg.onnx: the segmenter (input_size" in err, err


def test_box_photos_are_posed_on_the_refined_object_mask(catalogue, tmp_path, monkeypatch):
    """With a box and the mesh given, the pose search is framed by GrabCut's refined object
    (fit._pose_given), not by the box: over twenty cluttered photo-like references (Embree)
    of the five vehicles at random azimuths and elevations of 3-25 deg, against the build's
    default rings, its median |azimuth error| is smaller and it turns no more vehicles back to
    front (measured: 1.29 against 2.16 deg, one against two turned; the bench's held-out
    draws: docs/FIT.md, "The pose framed by the object's mask")."""
    from ucad_cl import fit
    from ucad_cl.pose import az_diff
    from ucad_cl.refphoto import draw_light, render_reference

    cat = tmp_path / "rings"
    build(catalogue.parent / "lib", cat, BuildOptions(), progress=False, log=lambda *a: None)
    rng = np.random.default_rng(5)
    photos = []
    for k in range(5):
        m, mesh, rows = _mesh(catalogue, k)
        for _ in range(4):
            az, el = float(rng.uniform(0, 360)), float(rng.uniform(3, 25))
            ref = render_reference(mesh, [r.part for r in rows], COLORS, azimuth=az,
                                   elevation=el, seed=int(rng.integers(1 << 30)),
                                   background="clutter", size=(240, 320), light=draw_light(rng))
            photos.append((m.sha256, ref, az))
    framed = []
    shipped = fit._pose_given

    def spy(box, obj, canvas):
        framed.append(sorted(shipped(box, obj, canvas)))
        return shipped(box, obj, canvas)

    err = {}
    for name, rule in (("mask", spy), ("box", lambda box, obj, canvas: {"box": box})):
        monkeypatch.setattr(fit, "_pose_given", rule)
        err[name] = np.array([az_diff(fit.fit_photo(ref.image, box=ref.box, catalog=cat,
                                                    mesh=sha).pose.azimuth, az)
                              for sha, ref, az in photos])
    assert framed == [["mask"]] * len(photos)          # GrabCut kept every vehicle
    assert np.median(err["mask"]) < np.median(err["box"]) - 0.5, err
    assert np.sum(err["mask"] > 90) <= np.sum(err["box"] > 90), err


def test_second_stored_ring_poses_and_finds_low_photos(catalogue, tmp_path):
    """Photos taken from 2 deg above the ground (ten: five vehicles, two azimuths, box given,
    clutter): against the build's default rings (15 then 5 deg) the pose is found within 3 deg
    of elevation for at least 8 and retrieval is right at least as often as against the 15 deg
    ring alone, which leaves elevation errors of 3-16 deg (measured at 30 deg azimuth steps and
    128 px: median |elevation error| 0.65 against 7.0 deg, retrieval 7 against 5 of 10)."""
    from dataclasses import replace

    from ucad_cl import fit
    from ucad_cl.refphoto import render_reference

    two = tmp_path / "two"
    build(catalogue.parent / "lib", two, replace(OPTS, elevations=BuildOptions().elevations),
          progress=False, log=lambda *a: None)
    el_err = {"one": [], "two": []}
    found = {"one": 0, "two": 0}
    for k in range(5):
        m, mesh, rows = _mesh(catalogue, k)
        for az in (35.0 + 70 * k, 200.0 + 40 * k):
            ref = render_reference(mesh, [r.part for r in rows], COLORS, azimuth=az,
                                   elevation=2.0, light=_neutral_light(), seed=k,
                                   background="clutter")
            for name, cat in (("one", catalogue), ("two", two)):
                given = fit.fit_photo(ref.image, box=ref.box, catalog=cat, mesh=m.sha256[:12])
                el_err[name].append(abs(given.pose.elevation - 2.0))
                found[name] += fit.fit_photo(ref.image, box=ref.box,
                                             catalog=cat).mesh_id == m.sha256
    assert sum(e <= 3.0 for e in el_err["two"]) >= 8, el_err
    assert np.median(el_err["two"]) <= 1.5 < 3.0 < np.median(el_err["one"]), el_err
    assert found["two"] >= max(found["one"], 6), found


def test_retrieval_keeps_the_object_mask_whose_answer_is_nearest(catalogue, monkeypatch):
    """With a box, retrieval also runs on GrabCut seeded by each first mesh's stored silhouette
    alone and keeps the answer that scores best: the same answer and scores as the minimum
    over those masks each retrieved by a fresh fit (no shared view, row or finer-HOG caches;
    ties: the voted mask, then the seeds' order), with the voted mask as the object, and for
    at least one of the cluttered photos a single seed's mask wins. When the voted mask's
    answer is sure (its retrieval_margin at least SURE_MARGIN) it is the answer, the single-seed
    masks untried. Over rings coarser than SEED_MASK_STEP (this catalogue's 30 deg) only the
    voted mask is tried."""
    import ucad_cl.fit as fit
    from ucad_catalog.reader import CatalogReader
    from ucad_cl.foreground import object_mask
    from ucad_cl.refphoto import draw_light, render_reference

    won_alone = 0
    with CatalogReader(catalogue) as r:
        for k, az in ((3, 140.0), (1, 60.0), (4, 220.0)):
            m, mesh, rows = _mesh(catalogue, k)
            ref = render_reference(mesh, [x.part for x in rows], COLORS, azimuth=az,
                                   elevation=10.0, seed=k, background="clutter",
                                   size=(240, 320), light=draw_light(np.random.default_rng(k)))
            first = object_mask(ref.image, box=ref.box, follow_edges=True)
            seeds = fit._Fit(r, None)._first_views(ref.image, first)
            assert len(seeds) == fit.REFINE_MESHES
            placed = fit._Fit(r, None)._placed_silhouettes(ref.image, first, seeds)
            masks = [fit._Fit(r, None)._refined_object(ref.image, first, placed)]
            masks += [fit._Fit(r, None)._refined_object(ref.image, first, [p]) for p in placed]
            tried = []
            for i, om in enumerate(masks):
                if om is not None:
                    _, cands, _ = fit._Fit(r, None)._pick_mesh(ref.image, om, None)
                    tried.append((cands[0].score, i, om, cands))
            score, i, best, cands = min(tried, key=lambda t: t[:2])
            monkeypatch.setattr(fit, "SEED_MASK_STEP", 360.0)
            monkeypatch.setattr(fit, "SURE_MARGIN", np.inf)         # never sure: every mask
            obj, meta, got, _, _ = fit._Fit(r, None)._object_and_mesh(ref.image, first, None)
            assert meta.sha256 == got[0].mesh_id == cands[0].mesh_id
            assert [(c.mesh_id, c.view, c.score) for c in got] == \
                [(c.mesh_id, c.view, c.score) for c in cands]
            assert np.array_equal(obj.mask, masks[0].mask)
            won_alone += i > 0
            voted = tried[0][3]
            margin = fit.retrieval_margin(voted)
            assert margin is not None and tried[0][1] == 0
            monkeypatch.setattr(fit, "SURE_MARGIN", margin)         # sure: the voted mask's
            obj, meta, got, _, _ = fit._Fit(r, None)._object_and_mesh(ref.image, first, None)
            assert [(c.mesh_id, c.view, c.score) for c in got] == \
                [(c.mesh_id, c.view, c.score) for c in voted] and meta.sha256 == voted[0].mesh_id
            monkeypatch.setattr(fit, "SURE_MARGIN", margin + 1e-9)  # just short of sure: all
            _, _, got, _, _ = fit._Fit(r, None)._object_and_mesh(ref.image, first, None)
            assert [(c.mesh_id, c.score) for c in got] == [(c.mesh_id, c.score) for c in cands]
            monkeypatch.setattr(fit, "SEED_MASK_STEP", 10.0)
            obj, _, got, _, _ = fit._Fit(r, None)._object_and_mesh(ref.image, first, None)
            assert np.array_equal(obj.mask, masks[0].mask)
    assert won_alone >= 1


def test_retrieval_searches_a_repeated_object_mask_once(catalogue, monkeypatch):
    """An object mask equal to one already tried is not searched again (it would give the same
    answer): with every seed's GrabCut giving the voted mask, retrieval searches once and
    answers as the voted mask's own search."""
    import ucad_cl.fit as fit
    from ucad_catalog.reader import CatalogReader
    from ucad_cl.foreground import object_mask
    from ucad_cl.refphoto import render_reference

    m, mesh, rows = _mesh(catalogue, 2)
    ref = render_reference(mesh, [x.part for x in rows], COLORS, azimuth=40.0, elevation=12.0,
                           seed=8, background="clutter")
    monkeypatch.setattr(fit, "SEED_MASK_STEP", 360.0)       # seed masks over this 30 deg ring
    refined, pick = fit._Fit._refined_object, fit._Fit._pick_mesh
    voted, searched = [], []

    def same_mask(self, photo, first, placed):               # every seed: the voted mask
        if not voted:
            voted.append(refined(self, photo, first, placed))
        return voted[0]

    monkeypatch.setattr(fit._Fit, "_refined_object", same_mask)
    monkeypatch.setattr(fit._Fit, "_pick_mesh",
                        lambda self, photo, obj, key: searched.append(obj) or pick(self, photo,
                                                                                     obj, key))
    with CatalogReader(catalogue) as r:
        first = object_mask(ref.image, box=ref.box, follow_edges=True)
        obj, meta, got, _, _ = fit._Fit(r, None)._object_and_mesh(ref.image, first, None)
        assert len(searched) == 1 and searched[0] is voted[0] is obj
        _, alone, _ = pick(fit._Fit(r, None), ref.image, voted[0], None)
    assert [(c.mesh_id, c.view, c.score) for c in got] == \
        [(c.mesh_id, c.view, c.score) for c in alone]
    assert meta.sha256 == m.sha256


def test_vgg_term_through_the_fit_and_the_cli(photo, catalogue, tmp_path, capsys):
    """--vgg onnx:MODEL:CONFIG (here a small random convolutional network: no VGG ships or
    downloads, tests/test_vgg.py): the fit's JSON records l_vgg and the objective falling
    (``vgg``; null without the option), the body colour stays near the truth (after the one
    exposure factor) and near the fit without the term, the same input gives the same JSON
    (a --photos batch too), and a bad spec is one line with exit status 2."""
    from tests.test_vgg import tiny_net
    from ucad_cl.cli import main

    path, box, m = photo
    spec = tiny_net(tmp_path)
    args = ["fit", str(path), "--box", *map(str, box), "--catalog", str(catalogue),
            "--mesh", m.sha256[:12]]
    docs = []
    for extra, out in (([], "plain"), (["--vgg", spec], "vgg"), (["--vgg", spec], "again")):
        assert main(args + extra + ["--out", str(tmp_path / out)]) == 0
        docs.append(json.loads((tmp_path / out / "car.json").read_text()))
    plain, vgg, again = docs
    assert plain["vgg"] is None
    v = vgg["vgg"]
    assert v["model"] == "tiny.onnx" and v["weight"] == 1.0 and v["jacobians"] >= 1
    assert v["l_vgg_after"] < v["l_vgg_before"] and v["loss_after"] < v["loss_before"], v
    assert "l_vgg (tiny.onnx" in capsys.readouterr().out
    body = [np.asarray(d["parts"]["body"]["color_linear"]) for d in (plain, vgg)]
    s = _exposure(body[1], COLORS["body"])
    assert _de(body[1], COLORS["body"], s) < 4.0, body     # measured 1.8 (2.3 without)
    assert _de(body[1], body[0]) < 6.0, body        # measured 3.0: the random net pulls
    lst = tmp_path / "list.csv"                     # a --photos batch takes the term too
    lst.write_text(f"{path},{box[0]},{box[1]},{box[2]},{box[3]},{m.sha256[:12]}\n")
    assert main(["fit", "--photos", str(lst), "--catalog", str(catalogue), "--vgg", spec,
                 "--out", str(tmp_path / "batch")]) == 0
    docs.append(json.loads((tmp_path / "batch" / "car.json").read_text()))
    for d in docs[1:]:
        d.pop("seconds"), d["vgg"].pop("seconds"), d.pop("glb")
    assert json.dumps(vgg) == json.dumps(again) == json.dumps(docs[3])
    assert main(args + ["--vgg", "onnx:nowhere.onnx:x.json", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err and "--vgg" in err, err
