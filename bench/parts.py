"""Part labelling bench: leave-one-model-out accuracy on the real vehicles, generated held-out
vehicles, and the IoU-pass speed.

    .venv/bin/python bench/parts.py                       # everything (about 15-25 min on 2 cores)
    .venv/bin/python bench/parts.py --skip-speed --folds kenney_sedan/sedan.glb,o3dv_car.glb
    .venv/bin/python bench/parts.py --skip-speed --fast   # LOMO from cached feature rows (minutes)
    .venv/bin/python bench/parts.py --skip-speed --fast --seeds 3   # the same at 3 recipe seeds

Accuracy (needs the ``[train]`` extra). The learned labeller (``ucad_cl.labeller``) is retrained
for every fold without the scored real model (generated vehicles of the training recipe + the
other real models of ``../shared/data/vehicles``, the recipe of ``scripts/train_labeller.py``),
then the scored model goes through the whole path (render the build's ring, ``LabellerSegmenter``
painting masks, ``classify_parts``) with its names as published and with names hidden (materials
renamed m0, m1, ..., nodes n0, ...). Today's hand-written ``prior`` segmenter is scored side by
side on the same renders (it was tuned on these models: its figures are not held out). A
material is right when its part is the manifest's or one of its ``ambiguous_alternatives``;
'unseen' counts as not right (and is counted). Pixel-weighted: each material weighs its visible
pixels (behind-glass pixels for materials labelled through glass). The real models are brought
into the vehicle frame by the orientation stage (``--frame auto``, the default: what the
pipeline does with a file nobody labelled) or by the manifest's ``up``/``front``
(``--frame manifest``), for scoring and for the other folds' training rows alike
(``labeller_train.load_real_models``).

``--fast --seeds N``: the fast loop at N recipe seeds (stepping by ``--members``, so no two runs
share a generated draw), each seed's totals with their mean and range: a change of seed alone
moved one model's totals by 3-5 materials and the three-member average's by 1-2, so compare
recipes by these means (or seed by seed), not by one run.

``--fast``: the same leave-one-model-out from feature rows cached per model in ``--cache``
(names kept and hidden, truth, pixels; ``real_tables``; the cache keys hash the feature, name
and orientation code), scored per material by the argmax of
the labeller's probabilities (``fast_verdicts``: what ``classify_parts`` decides on the
labeller's own masks, less its mirror-pair unification), minutes instead of the full path; it
reproduced the full path's totals within a material (names kept 126 vs 125 of 162, hidden 116
vs 115, before the relative features).
Generated vehicles: seeds of another run than the training run (never trained on or tuned on),
scored with the model trained on all training data, against the generator's truth.

Speed: the histogram pass (``ucad_cl/kernels/parts.cl``) in views/s for several local sizes and
pixels-per-item, side by side with the NumPy peer (``np.bincount`` per view and part), medians of
``--repeats`` runs (total = host packing + upload + kernel + read back; kernel = enqueue to read
back), plus the first call per configuration and peak host memory. The first call includes
PoCL's per-local-size kernel compile only when its cache is cold: run with
``POCL_CACHE_DIR=$(mktemp -d) PYOPENCL_NO_CACHE=1`` to measure compile times.
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
VEHICLES = ROOT.parent / "shared" / "data" / "vehicles"

from ucad_cl.classify import classify_parts, part_histogram  # noqa: E402
from ucad_cl.render import render_views  # noqa: E402
from ucad_cl.names import name_priors  # noqa: E402
from ucad_cl.segment import LabellerSegmenter, PriorSegmenter  # noqa: E402
from ucad_cl.artifacts import PART_NAMES  # noqa: E402

COLS = list(PART_NAMES) + ["unseen"]


def numpy_histogram(mat_id, masks, n_ids):
    V, P = masks.shape[:2]
    out = np.zeros((V, n_ids, 1 + P), np.int64)
    for v in range(V):
        m = mat_id[v].ravel()
        out[v, :, 0] = np.bincount(m, minlength=n_ids)
        for p in range(P):
            out[v, :, 1 + p] = np.bincount(m[masks[v, p].ravel()], minlength=n_ids)
    return out


class Score:
    """Materials right / all, pixel-weighted, unseen count, never-visible materials (labelled
    from geometry, decision 'never-visible': counted and right apart, ``nv`` / ``nv_ok``) and a
    confusion matrix."""

    def __init__(self):
        self.ok = self.n = self.unseen = self.nv = self.nv_ok = 0
        self.px_ok = self.px = 0.0
        self.conf = np.zeros((len(PART_NAMES), len(COLS)), np.int64)

    def add(self, truth: str, alts, row) -> bool:
        right = row.part == truth or row.part in alts
        self.n += 1
        self.ok += right
        self.unseen += row.part == "unseen"
        if getattr(row, "decision", "") == "never-visible":
            self.nv += 1
            self.nv_ok += right
        self.px += row.pixels
        self.px_ok += row.pixels * right
        self.conf[PART_NAMES.index(truth), COLS.index(truth if right else row.part)] += 1
        return right

    def __iadd__(self, o):
        self.ok += o.ok; self.n += o.n; self.unseen += o.unseen  # noqa: E702
        self.nv += o.nv; self.nv_ok += o.nv_ok  # noqa: E702
        self.px_ok += o.px_ok; self.px += o.px; self.conf += o.conf  # noqa: E702
        return self

    def line(self) -> str:
        """Materials right (all, and the seen ones: all but the never-visible), pixel-weighted,
        never-visible right, unseen."""
        seen = self.n - self.nv
        return (f"materials right {self.ok:4d}/{self.n:<4d} = {self.acc:6.1%}   seen "
                f"{self.ok - self.nv_ok:4d}/{seen:<4d} = {(self.ok - self.nv_ok) / max(seen, 1):6.1%}"
                f"   pixel-weighted {self.pix:6.1%}   never-visible {self.nv_ok}/{self.nv}"
                f"   unseen {self.unseen}")

    @property
    def acc(self):
        return self.ok / max(self.n, 1)

    @property
    def pix(self):
        return self.px_ok / max(self.px, 1)


def score_model(mesh, truth, alts, views, segmenter) -> tuple[Score, list[str]]:
    masks = segmenter.segment(mesh, views)
    table = classify_parts(mesh, views, masks, priors=name_priors(mesh))
    sc, wrong = Score(), []
    for r, orig in zip(table.rows, truth["names"]):
        exp = truth["parts"].get(orig)
        if exp is None:
            continue
        if not sc.add(exp, alts.get(orig, []), r):
            wrong.append(f"{orig}:{r.part}/{exp}")
    return sc, wrong


def print_confusion(title, conf):
    print(f"\n{title} (rows: truth; columns: decided; an accepted alternative counts on the "
          "diagonal)")
    print(f"{'':9s}" + "".join(f"{c[:7]:>8s}" for c in COLS))
    for i, p in enumerate(PART_NAMES):
        print(f"{p:9s}" + "".join(f"{int(x):8d}" for x in conf[i]))


def accuracy_table(args):
    from ucad_cl import labeller_train as T

    models = T.load_real_models(VEHICLES, frame=args.frame)
    if args.folds:
        scored = [m for m in models if m.file in args.folds]
    else:
        scored = models
    ring = T.make_ring_of(0)
    print(f"\n## Labeller, leave-one-model-out on {len(scored)} real models "
          f"({ring.n_views} views, {ring.width} px; training recipe: {args.members} members, each "
          f"{args.vehicles} generated vehicles (seeds {args.seed}..{args.seed + args.members - 1}) "
          "+ the other real models)")
    t0 = time.perf_counter()
    synth = member_rows(args)
    real = T.real_rows(models)
    print(f"training rows: {sum(r.X.shape[0] for r in synth)} generated, "
          f"{sum(r.X.shape[0] for r in real.values())} real ({time.perf_counter() - t0:.0f} s)")
    tmp = Path(tempfile.mkdtemp(prefix="ucad-lomo-"))
    tot = {k: Score() for k in ("lab_named", "lab_hidden", "prior_named", "prior_hidden")}
    print(f"{'model':44s} {'mats':>4s} | {'labeller named':>14s} {'hidden':>13s} | "
          f"{'prior named':>13s} {'hidden':>13s} | wrong (labeller, names hidden)")
    for rm in scored:
        t1 = time.perf_counter()
        others = [r for f, r in real.items() if f != rm.file]
        clf = T.fit_members([T.Rows.concat([s] + others) for s in synth], args.seed)
        path = T.export_onnx(clf, tmp / f"fold_{len(list(tmp.iterdir()))}.onnx",
                             {"leave_out": rm.file})
        views = render_views(rm.mesh, ring)
        truth = {"names": [m.name for m in rm.mesh.materials], "parts": rm.truth}
        res = {}
        for tag, mesh in (("named", rm.mesh), ("hidden", T.hide_names(rm.mesh))):
            res[f"lab_{tag}"] = score_model(mesh, truth, rm.alternatives, views,
                                            LabellerSegmenter(path))
            res[f"prior_{tag}"] = (score_model(mesh, truth, rm.alternatives, views,
                                               PriorSegmenter()) if not args.no_prior
                                   else (Score(), []))
        for k, (sc, _) in res.items():
            tot[k] += sc
        cell = lambda k, res=res: f"{res[k][0].acc:6.0%} {res[k][0].pix:6.0%}"  # noqa: E731
        print(f"{rm.file:44s} {res['lab_named'][0].n:4d} | {cell('lab_named'):>14s} "
              f"{cell('lab_hidden'):>13s} | {cell('prior_named'):>13s} "
              f"{cell('prior_hidden'):>13s} | {'; '.join(res['lab_hidden'][1][:5])} "
              f"({time.perf_counter() - t1:.0f} s)", flush=True)
    print(f"\n{'ALL (pooled materials / pixel-weighted)':44s}")
    for k, sc in tot.items():
        print(f"  {k:14s} {sc.line()}")
    print_confusion("Confusion, labeller, names hidden, leave-one-model-out",
                    tot["lab_hidden"].conf)
    print_confusion("Confusion, labeller, names kept, leave-one-model-out", tot["lab_named"].conf)
    if args.generated:
        generated_table(args, synth, real)


def member_rows(args) -> list:
    """The generated training rows of each ensemble member (``labeller_train.member_seeds``)."""
    from ucad_cl import labeller_train as T

    return [load_synth_rows(args, s) for s in T.member_seeds(args.seed, args.members)]


def load_synth_rows(args, seed: int):
    """The recipe's generated training rows of run ``seed``, cached in ``--cache`` (keyed by
    count, seed, the recipe and the source of the feature and generator modules). Vehicle i of
    a run does not depend on the run's count, so a cache of more vehicles gives the rows of
    the first ``args.vehicles`` (e.g. ``--vehicles 500`` per fold from the shipped recipe's
    1000)."""
    from ucad_cl import labeller_train as T

    import hashlib

    import ucad_cl.labeller
    import ucad_cl.names
    import ucad_cl.synth

    key = hashlib.sha256(json.dumps([T.REALISM_PROB, T.HIDE_NAMES, T.RINGS]).encode()
                         + b"".join(Path(m.__file__).read_bytes() for m in (
                             ucad_cl.labeller, ucad_cl.names, ucad_cl.synth))).hexdigest()[:12]
    cache = Path(args.cache) / f"synth_{args.vehicles}_{seed}_{key}.npz"
    if cache.exists():
        z = np.load(cache, allow_pickle=True)
        return T.Rows(z["X"], z["y"], z["w"], z["group"])
    for big in sorted(Path(args.cache).glob(f"synth_*_{seed}_{key}.npz")):
        if int(big.name.split("_")[1]) > args.vehicles:
            z = np.load(big, allow_pickle=True)
            keep = np.array([int(str(g).split(":")[1]) < args.vehicles for g in z["group"]])
            return T.Rows(z["X"][keep], z["y"][keep], z["w"][keep], z["group"][keep])
    rows = T.synth_rows(args.vehicles, seed)
    cache.parent.mkdir(parents=True, exist_ok=True)
    np.savez(cache, X=rows.X, y=rows.y, w=rows.w, group=rows.group)
    return rows


def real_tables(models, args) -> dict[str, dict]:
    """{file: cached per-model facts} for the fast loop: feature rows on ring 0 (the build's
    ring, also the real training rows' ring, ``REAL_RINGS``) with names kept (``Xn``) and hidden
    (``Xh``), truth ``y`` (part index, -1 for a material the manifest does not name), ``alt``
    (M, P) accepted parts (truth and ``ambiguous_alternatives``), first-layer ``pixels`` and
    ``behind`` pixels. Cached in ``--cache`` keyed by the feature, name and orientation code, the
    frame, the file's sha256 and its manifest entry."""
    import hashlib

    from ucad_cl import labeller_train as T

    import ucad_cl.labeller
    import ucad_cl.names
    import ucad_cl.orient

    files = [Path(m.__file__) for m in (ucad_cl.labeller, ucad_cl.names)]
    files += sorted(Path(ucad_cl.orient.__file__).parent.glob("*.py"))      # a package
    src = b"".join(f.read_bytes() for f in files)
    out = {}
    for rm in models:
        key = hashlib.sha256(src + json.dumps([args.frame, rm.file, rm.mesh.sha256, rm.truth,
                                               rm.alternatives]).encode()).hexdigest()[:12]
        cache = Path(args.cache) / f"real_{key}.npz"
        if not cache.exists():
            views = render_views(rm.mesh, T.make_ring_of(0))
            tn = T.material_table(rm.mesh, views)
            th = T.material_table(T.hide_names(rm.mesh), views)
            names = [m.name for m in rm.mesh.materials]
            y = np.array([PART_NAMES.index(rm.truth[n]) if n in rm.truth else -1 for n in names])
            alt = np.zeros((len(names), len(PART_NAMES)), bool)
            for i, n in enumerate(names):
                for p in ([rm.truth[n]] if n in rm.truth else []) + list(rm.alternatives.get(n, [])):
                    alt[i, PART_NAMES.index(p)] = True
            cache.parent.mkdir(parents=True, exist_ok=True)
            np.savez(cache, Xn=tn.X, Xh=th.X, y=y, alt=alt, pixels=tn.pixels,
                     behind=tn.behind_pixels, names=np.array(names, object))
        z = np.load(cache, allow_pickle=True)
        out[rm.file] = {k: z[k] for k in z.files}
    return out


def fast_verdicts(t: dict, prob: np.ndarray, min_pixels: int = 4,
                  hidden: np.ndarray | None = None) -> tuple[Score, list]:
    """Material verdicts of the labeller's probabilities without masks: argmax part (ties ->
    PART_NAMES order); under ``min_pixels`` pixels its behind-glass pixels weigh it, and with
    fewer there too it takes ``hidden`` (the geometric part, ``labeller.never_visible_part``;
    default the argmax) as 'never-visible' (weight 0), as ``classify_parts``
    decides on self-painted masks (each material's pixels all lie in its own argmax part, so
    every view scores it 1). Left out: the mirror-pair unification of ``classify_parts``."""
    from types import SimpleNamespace

    sc, wrong = Score(), []
    for m, y in enumerate(t["y"]):
        if y < 0:
            continue
        part, decision = PART_NAMES[int(np.argmax(prob[m]))], "seen"
        px = int(t["pixels"][m])
        if px < min_pixels:
            px = int(t["behind"][m])
            if px < min_pixels:
                px, decision = 0, "never-visible"
                if hidden is not None:
                    part = PART_NAMES[int(hidden[m])]
        alts = [PART_NAMES[k] for k in np.flatnonzero(t["alt"][m])]
        if not sc.add(PART_NAMES[y], alts, SimpleNamespace(part=part, pixels=px,
                                                           decision=decision)):
            wrong.append((m, part))
    return sc, wrong


def manifest_facts() -> dict[str, dict]:
    """{file: {"group": source repository, "added": date or None}} from the shared manifest."""
    ms = json.loads((VEHICLES / "manifest.json").read_text(encoding="utf-8"))["models"]
    return {m["file"]: {"group": m.get("source_repo") or m["file"], "added": m.get("added")}
            for m in ms}


def folds_of(files, groups: str) -> list[list[str]]:
    """The leave-out folds: one model each (``groups="model"``), or (``"repo"``) every model of
    one source repository (the manifest's ``source_repo``) together, so no fold trains on a
    sibling of a scored model (same author, exporter, naming and materials); folds in order of
    their first model in ``files``."""
    if groups == "model":
        return [[f] for f in files]
    facts = manifest_facts()
    out: dict[str, list[str]] = {}
    for f in files:
        out.setdefault(facts[f]["group"], []).append(f)
    return list(out.values())


def fast_lomo(args, fit=None, tables=None, synth=None, log=print) -> dict:
    """Leave-out over cached feature rows (``real_tables``): for every fold (``folds_of``,
    ``args.groups``: one model, or one source repository), fit each member on its generated
    rows + the named rows of the real models outside the fold (only those without the
    manifest's ``added`` date with ``args.train_real == "original"``: the training set of the
    model shipped before them) (``fit(rows per member)``, default
    ``labeller_train.fit_members`` with the recipe's seed), predict the fold's names-kept and
    names-hidden rows, and score with ``fast_verdicts``. Returns {"named": Score, "hidden":
    Score, "per_model": {file: {...}}}."""
    from ucad_cl import labeller_train as T

    models = T.load_real_models(VEHICLES, frame=args.frame) if tables is None else None
    tables = tables if tables is not None else real_tables(models, args)
    synth = synth if synth is not None else member_rows(args)
    if getattr(args, "drop_cues", None):
        tables, synth = drop_cues(tables, synth, args.drop_cues)
    fit = fit or (lambda rows: T.fit_members(rows, args.seed))
    facts = manifest_facts()
    trainable = [f for f in tables
                 if getattr(args, "train_real", "all") == "all" or not facts[f]["added"]]
    real = {f: T.Rows(t["Xn"][t["y"] >= 0], t["y"][t["y"] >= 0],
                      np.full(int((t["y"] >= 0).sum()), T.REAL_WEIGHT),
                      np.array([f"real:{f}"] * int((t["y"] >= 0).sum()), object))
            for f, t in tables.items() if f in trainable}
    tot = {"named": Score(), "hidden": Score()}
    per = {}
    scored = [f for f in tables if not args.folds or f in args.folds]
    for fold in folds_of(scored, getattr(args, "groups", "model")):
        t0 = time.perf_counter()
        others = [r for g, r in real.items() if g not in fold]
        clf = fit([T.Rows.concat([s] + others) for s in synth])
        for f in fold:
            per[f] = _score_fold_model(T, clf, tables[f], tot, args.ablate)
            if log:
                _log_model(log, f, per[f], tables[f], time.perf_counter() - t0)
    return {"named": tot["named"], "hidden": tot["hidden"], "per_model": per, "tables": tables}


def drop_cues(tables: dict, synth: list, groups: list[str]) -> tuple[dict, list]:
    """Copies of the real ``tables`` and the generated ``synth`` rows with the columns of the
    cue ``groups`` (``labeller.CUE_GROUPS``; "all" for every one) set to 0, in training and
    scoring alike: the trees cannot split on a constant column, so the fold is fitted as without
    the cue (the column count, hence the trees' feature sampling, stays the same)."""
    from ucad_cl import labeller_train as T
    from ucad_cl.labeller import CUE_GROUPS, FEATURE_NAMES

    names = list(CUE_GROUPS) if "all" in groups else groups
    unknown = [g for g in names if g not in CUE_GROUPS]
    if unknown:
        raise SystemExit(f"error: --drop-cues: unknown cue {unknown[0]!r} "
                         f"(cues: {', '.join(CUE_GROUPS)}, all)")
    cols = [FEATURE_NAMES.index(c) for g in names for c in CUE_GROUPS[g]]

    def zero(X):
        X = np.array(X, copy=True)
        X[:, cols] = 0
        return X

    tables = {f: {**t, "Xn": zero(t["Xn"]), "Xh": zero(t["Xh"])} for f, t in tables.items()}
    synth = [T.Rows(zero(r.X), r.y, r.w, r.group) for r in synth]
    return tables, synth


def _score_fold_model(T, clf, t, tot, ablate=(), probs=None) -> dict:
    """Score one model's names-kept and names-hidden rows: probabilities of ``clf`` (a fitted
    ensemble, a ``LabellerModel``, or None with ``probs`` = {tag: saved raw probabilities}),
    then the labeller's rules as ``label_materials`` applies them (``wheel_assembly``, and
    ``never_visible_part`` for materials no view sees) unless ``ablate`` names them ("wheel",
    "hidden": the argmax as is). Returns {tag: (Score, wrong, raw probabilities)}."""
    from ucad_cl.labeller import never_visible_part, wheel_assembly

    res = {}
    for tag, X in (("named", t["Xn"]), ("hidden", t["Xh"])):
        raw = (probs[tag] if probs is not None else
               clf.predict(X) if hasattr(clf, "session") else T.predict(clf, X))
        prob = raw if "wheel" in ablate else wheel_assembly(raw, X)
        sc, wrong = fast_verdicts(t, prob, hidden=None if "hidden" in ablate
                                  else never_visible_part(X))
        tot[tag] += sc
        res[tag] = (sc, wrong, raw)
    return res


def _log_model(log, f, res, t, seconds):
    log(f"{f:44s} {res['named'][0].n:4d} | {res['named'][0].acc:6.0%} "
        f"{res['named'][0].pix:6.0%} | {res['hidden'][0].acc:6.0%} "
        f"{res['hidden'][0].pix:6.0%} | "
        + "; ".join(f"{t['names'][m]}:{p}/{PART_NAMES[t['y'][m]]}"
                    for m, p in res["hidden"][1][:6])
        + f" ({seconds:.0f} s)", flush=True)


def fast_table(args):
    """``--fast``: the leave-one-model-out table from cached feature rows (minutes); with
    ``--seeds N`` > 1, the totals at N recipe seeds (``seeds_table``) and their mean and range
    (the generated draw alone moves a single model's totals by a few materials)."""
    if args.seeds > 1:
        return seeds_table(args)
    if args.shipped:
        return shipped_table(args)
    if args.probs:
        return rescore_table(args)
    how = ("leave-one-model-out" if args.groups == "model" else
           "grouped leave-out (the models of one source repository left out together)")
    print(f"\n## Labeller, fast {how} over cached feature rows (frame "
          f"{args.frame}; {args.members} members of {args.vehicles} generated vehicles, seeds "
          f"{args.seed}..{args.seed + args.members - 1}, + the real models outside the fold"
          f"{' that the manifest does not mark added' if args.train_real == 'original' else ''}"
          f"; per-material argmax, no masks; cues dropped: {','.join(args.drop_cues) or 'none'})")
    print(f"{'model':44s} {'mats':>4s} | {'named':>13s} | {'hidden':>13s} | wrong (names hidden)")
    res = fast_lomo(args, log=lambda *a, **k: print(*a, **k))
    print_totals(res)
    if args.save_probs:
        np.savez_compressed(args.save_probs, **{f"{tag}:{f}": r[tag][2]
                                                for f, r in res["per_model"].items()
                                                for tag in ("named", "hidden")})
        print(f"held-out probabilities per model written to {args.save_probs}")


def print_totals(res) -> None:
    for k in ("named", "hidden"):
        sc = res[k]
        print(f"  names {k:7s} {sc.line()}")
    for k in ("hidden", "named"):
        print_confusion(f"Confusion, labeller, names {k}, fast leave-out", res[k].conf)


def rescore_table(args):
    """``--fast --probs FILE``: the held-out probabilities a ``--save-probs`` run wrote, scored
    again with the labeller's current rules (less ``--ablate``'s): a rule's contribution
    without refitting a fold."""
    from ucad_cl import labeller_train as T

    saved = np.load(args.probs, allow_pickle=True)
    tables = real_tables(T.load_real_models(VEHICLES, frame=args.frame), args)
    print(f"\n## Held-out probabilities of {args.probs} rescored (rules ablated: "
          f"{', '.join(args.ablate) or 'none'})")
    print(f"{'model':44s} {'mats':>4s} | {'named':>13s} | {'hidden':>13s} | wrong (names hidden)")
    tot = {"named": Score(), "hidden": Score()}
    for f, t in tables.items():
        if f"hidden:{f}" not in saved.files:
            continue
        probs = {tag: saved[f"{tag}:{f}"] for tag in ("named", "hidden")}
        _log_model(print, f, _score_fold_model(T, None, t, tot, args.ablate, probs), t, 0.0)
    print_totals(tot)


def shipped_table(args):
    """``--fast --shipped MODEL``: a trained model (not retrained) on the cached rows of every
    real model; held out only for the models it was not trained on (for the model shipped
    before the manifest's ``added`` models, those), so totals are given for those apart."""
    from ucad_cl import labeller_train as T
    from ucad_cl.labeller import LabellerModel

    model = LabellerModel(args.shipped)
    tables = real_tables(T.load_real_models(VEHICLES, frame=args.frame), args)
    facts = manifest_facts()
    print(f"\n## {args.shipped}, not retrained, on every real model (fast path)")
    print(f"{'model':44s} {'mats':>4s} | {'named':>13s} | {'hidden':>13s} | wrong (names hidden)")
    tot = {"named": Score(), "hidden": Score()}
    new = {"named": Score(), "hidden": Score()}
    for f, t in tables.items():
        res = _score_fold_model(T, model, t, tot, args.ablate)
        if facts[f]["added"]:
            for k in new:
                new[k] += res[k][0]
        _log_model(print, f, res, t, 0.0)
    print("all models (those without 'added' were trained on: not held out)")
    print_totals(tot)
    print("models the manifest marks added (held out for a model trained before them)")
    print_totals(new)


def seeds_table(args):
    """``--fast --seeds N``: one fast leave-one-model-out per recipe seed (the generated rows
    and the trees' seeds all change; seeds step by ``--members``, so no two runs share a
    generated draw), materials right and pixel-weighted, then mean and range. Compare two
    recipes by their means, or seed by seed (paired)."""
    from argparse import Namespace

    from ucad_cl import labeller_train as T

    print(f"\n## Labeller, fast leave-one-model-out at {args.seeds} training seeds (frame "
          f"{args.frame}; {args.members} members of {args.vehicles} generated vehicles + the other "
          "real models)")
    print(f"{'seed':>6s} | {'names kept':>22s} | {'names hidden':>22s}")
    tables = real_tables(T.load_real_models(VEHICLES, frame=args.frame), args)
    rows = []
    for seed in range(args.seed, args.seed + args.seeds * args.members, args.members):
        a = Namespace(**{**vars(args), "seed": seed})
        res = fast_lomo(a, tables=tables, log=None)
        rows.append([(res[k].ok, res[k].pix) for k in ("named", "hidden")])
        n = res["named"].n
        print(f"{seed:6d} | " + " | ".join(f"{ok:4d}/{n} {pix:6.1%} px" for ok, pix in rows[-1]),
              flush=True)
    r = np.array(rows, dtype=np.float64)                       # (seeds, 2, 2)
    print("  mean | " + " | ".join(f"{r[:, k, 0].mean():6.1f}   {r[:, k, 1].mean():6.1%} px"
                                   for k in range(2)))
    print(" range | " + " | ".join(f"{r[:, k, 0].min():4.0f}-{r[:, k, 0].max():<4.0f} "
                                   f"{r[:, k, 1].min():5.1%}-{r[:, k, 1].max():5.1%}"
                                   for k in range(2)))


def generated_table(args, synth, real):
    """Generated vehicles of another seed, scored through the whole path against the truth."""
    from ucad_cl import labeller_train as T
    from ucad_cl.synth import make_vehicle

    clf = T.fit_members([T.Rows.concat([s] + list(real.values())) for s in synth], args.seed)
    path = T.export_onnx(clf, Path(tempfile.mkdtemp(prefix="ucad-gen-")) / "all.onnx", {})
    test_seed = args.seed + 1_000_003
    tot = {k: Score() for k in ("lab_named", "lab_hidden", "prior_named", "prior_hidden")}
    for i in range(args.generated):
        rec = T.synth_recipe(test_seed, i)
        veh = make_vehicle(rec["seed"], rec["kind"], realism=rec["realism"])
        mesh = veh.mesh()
        views = render_views(mesh, T.make_ring_of(0))
        truth = {"names": [m.name for m in mesh.materials], "parts": veh.truth["materials"]}
        for tag, msh in (("named", mesh), ("hidden", T.hide_names(mesh))):
            tot[f"lab_{tag}"] += score_model(msh, truth, {}, views, LabellerSegmenter(path))[0]
            tot[f"prior_{tag}"] += score_model(msh, truth, {}, views, PriorSegmenter())[0]
    print(f"\n## Generated vehicles of seed run {test_seed} (never used for training), "
          f"{args.generated} vehicles, realism traits as in the training recipe")
    for k, sc in tot.items():
        print(f"  {k:14s} {sc.line()}")
    print_confusion("Confusion, labeller, generated held-out, names hidden",
                    tot["lab_hidden"].conf)


def speed_table(args):
    from ucad_cl.runtime import get_runtime

    rt = get_runtime()
    rng = np.random.default_rng(0)
    V, S, P, n_ids = 72, args.size, len(PART_NAMES), 18
    # realistic maps: blocks of materials (long runs) and part masks = material's part
    blocks = rng.integers(1, n_ids, (V, S // 8, S // 8)).astype(np.uint16)
    mat = np.kron(blocks, np.ones((8, 8), np.uint16))
    mat[:, : S // 4] = 0
    part_of = rng.integers(0, P, n_ids)
    part_of[0] = -1
    masks = np.stack([part_of[mat] == p for p in range(P)], axis=1)
    ref = numpy_histogram(mat, masks, n_ids)
    print(f"\n## IoU histogram pass: {V} views x {S}x{S} px, {P} parts, {n_ids} ids "
          f"({rt.describe()})")
    print(f"{'impl':34s} {'first call s':>12s} {'median s':>9s} {'views/s':>9s} "
          f"{'kernel s':>9s} {'exact':>6s}")
    t = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        numpy_histogram(mat, masks, n_ids)
        t.append(time.perf_counter() - t0)
    med = float(np.median(t))
    print(f"{'numpy bincount (peer)':34s} {'':>12s} {med:9.4f} {V / med:9.1f} {'':>9s} {'ref':>6s}")
    for use_local in (True, False):
        for local in args.local_sizes:
            for ppi in args.ppi:
                t0 = time.perf_counter()
                h = part_histogram(mat, masks, n_ids=n_ids, local_size=local,
                                   pixels_per_item=ppi, use_local=use_local)
                first = time.perf_counter() - t0
                t, tk = [], []
                for _ in range(args.repeats):
                    t0, st = time.perf_counter(), {}
                    part_histogram(mat, masks, n_ids=n_ids, local_size=local,
                                   pixels_per_item=ppi, use_local=use_local, stats=st)
                    t.append(time.perf_counter() - t0)
                    tk.append(st["histogram"])
                med = float(np.median(t))
                name = f"{'local' if use_local else 'global'} atomics L={local} ppi={ppi}"
                print(f"{name:34s} {first:12.3f} {med:9.4f} {V / med:9.1f} "
                      f"{float(np.median(tk)):9.4f} {str(np.array_equal(h, ref)):>6s}")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak host RSS {peak:.0f} MiB; program build times: "
          + ", ".join(f"{k[0]} {v:.2f}s" for k, v in rt.compile_seconds.items()))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--azimuth-step", type=float, default=15.0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--folds", type=lambda s: s.split(","), default=None,
                    help="score only these real model files (default: all)")
    ap.add_argument("--vehicles", type=int, default=None,
                    help="generated training vehicles (default: the training script's)")
    ap.add_argument("--seed", type=int, default=2026,
                    help="recipe seed (member k of the ensemble trains on seed + k)")
    ap.add_argument("--members", type=int, default=None,
                    help="models averaged (default: the training script's)")
    ap.add_argument("--seeds", type=int, default=1,
                    help="with --fast: repeat at this many recipe seeds (--seed, --seed + "
                         "members, ...) and print each seed's totals, their mean and range")
    ap.add_argument("--generated", type=int, default=100,
                    help="generated held-out vehicles to score (0: skip)")
    ap.add_argument("--cache", default="/tmp/ucad-labeller-cache")
    ap.add_argument("--no-prior", action="store_true", help="skip the prior segmenter's columns")
    ap.add_argument("--skip-accuracy", action="store_true")
    ap.add_argument("--frame", choices=("auto", "manifest"), default="auto",
                    help="how the real models reach the vehicle frame: the orientation stage "
                         "(auto, what the pipeline does; default) or their manifest up/front")
    ap.add_argument("--groups", choices=("repo", "model"), default="repo",
                    help="with --fast: leave out the models of one source repository together "
                         "(repo, default: the manifest's source_repo) or one model at a time")
    ap.add_argument("--train-real", choices=("all", "original"), default="all",
                    help="with --fast: real training rows from every model outside the fold "
                         "(all) or only from those the manifest does not mark 'added' (the "
                         "training set of the model shipped before them)")
    ap.add_argument("--probs", default=None, metavar="FILE.npz",
                    help="with --fast: rescore the held-out probabilities a --save-probs run "
                         "wrote with the current rules (no fitting)")
    ap.add_argument("--ablate", type=lambda s: [x for x in s.split(",") if x], default=[],
                    help="with --fast: leave out labeller rules: wheel (tyre/rim by radial "
                         "position), hidden (never-visible part from geometry)")
    ap.add_argument("--drop-cues", type=lambda s: [x for x in s.split(",") if x], default=[],
                    help="with --fast: fit and score without these cue feature groups "
                         "(labeller.CUE_GROUPS: glaze, under, trim; all): their columns zeroed")
    ap.add_argument("--save-probs", default=None, metavar="FILE.npz",
                    help="with --fast: write each model's held-out probabilities ('named:FILE', "
                         "'hidden:FILE'), to score rules on them without refitting")
    ap.add_argument("--shipped", default=None, metavar="MODEL.onnx",
                    help="with --fast: score this trained model, not retrained, on every model")
    ap.add_argument("--fast", action="store_true",
                    help="leave-one-model-out from cached feature rows, per-material argmax "
                         "(no masks, no prior columns; minutes instead of the full path)")
    ap.add_argument("--local-sizes", type=lambda s: [int(x) for x in s.split(",")],
                    default=[1, 4, 16, 64, 256])
    ap.add_argument("--ppi", type=lambda s: [int(x) for x in s.split(",")],
                    default=[64, 256, 1024])
    ap.add_argument("--skip-speed", action="store_true")
    args = ap.parse_args()
    from ucad_cl.labeller_train import DEFAULT_VEHICLES, MEMBERS
    if args.vehicles is None:
        args.vehicles = DEFAULT_VEHICLES
    if args.members is None:
        args.members = MEMBERS
    if args.members < 1:
        ap.error("--members must be >= 1")
    if not args.skip_accuracy:
        if (VEHICLES / "manifest.json").exists():
            fast_table(args) if args.fast else accuracy_table(args)
        else:
            print(f"(no vehicles at {VEHICLES}; accuracy table skipped)")
    if not args.skip_speed:
        speed_table(args)


if __name__ == "__main__":
    main()
