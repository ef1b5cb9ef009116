"""Training data and fitting for the learned labeller (``ucad_cl.labeller``).

Training-only: needs the ``[train]`` extra (scikit-learn, onnx). ``scripts/train_labeller.py``
is the command line; ``bench/parts.py`` uses the same functions for its leave-one-model-out folds.

Data recipe (``synth_recipe``): vehicle i of a run with seed S is generated from seed
``hash(S, i)`` with a kind drawn from all kinds, each realism trait of ``REALISM_PROB`` drawn
independently with its probability (``synth.REALISM_TRAITS``), names kept or hidden (half of the
vehicles: every material renamed ``m0, m1, ...`` and every node ``n0, ...``), and one camera ring
of ``RINGS`` (the build's default ring, the bench's, and two others), so the model sees the
rings it will be used with. Labels are the generator's truth (majority part of each material).
Optional real models (a folder with ``manifest.json``, brought into the vehicle frame by the
manifest's ``up``/``front``) add their materials (rendered with the rings ``REAL_RINGS``) with
weight ``REAL_WEIGHT`` per material; a bench fold leaves the scored model out of them.

Model: ``MEMBERS`` scikit-learn ``HistGradientBoostingClassifier``s (``MODEL_PARAMS``, fixed
seeds, no early stopping, so the same data gives the same trees), member k fitted on the generated
vehicles of seed ``seed + k`` plus the same real rows, its trees seeded ``seed + k``; their
probabilities are averaged (``Ensemble``): one generated draw moved the real models' scores by
3-5 materials, and the average of three draws is steadier than any one of them. Exported by
``tree_ensemble_onnx`` to one ``TreeEnsembleClassifier`` (ONNX-ML) per member, whose
probabilities (softmax of the summed leaf values) the graph averages, then adds the names.
"""
from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .artifacts import PART_NAMES, Mesh
from .cameras import make_ring
from .ingest import load_mesh
from .labeller import FEATURE_NAMES, material_table
from .render import render_views
from .synth import KINDS, REALISM_TRAITS, make_vehicle

RINGS: tuple[tuple[float, tuple[float, ...], int], ...] = (
    (5.0, (15.0,), 256),          # the build's default ring
    (15.0, (15.0, 45.0), 128),    # bench/parts.py's ring
    (10.0, (15.0,), 192),
    (20.0, (10.0, 35.0), 128),
)
REALISM_PROB: dict[str, float] = {
    "brake_discs": 0.3, "lens_lamps": 0.4, "rich_interior": 0.5, "no_rims": 0.2,
    "chassis_only": 0.12, "one_paint": 0.75, "paint_rims": 0.15, "shared_black": 0.25,
    "dark_trim": 0.4, "textured_body": 0.12, "varied_looks": 0.5, "mtl_like": 0.25,
    "opaque_glass": 0.15, "dark_glass": 0.12, "two_tone": 0.25,
    "one_glass": 0.6, "glass_looks": 0.5, "grey_trim": 0.3,
    "plain_lights": 0.35, "lamp_variety": 0.4, "ground_base": 0.15,
    "axles": 0.3, "light_bar": 0.12, "plate_looks": 0.5, "no_glass": 0.1,
    "inner_shell": 0.25, "mirror_glass": 0.3,
    "plastic_trim": 0.0, "cargo_paint": 0.0,    # not drawn: at 0.2 and 0.5 they did not help
    "meaningless_names": 0.2, "misleading_names": 0.1,
}
#: traits added after the recipe's first version, each drawn from a stream of its own (so the
#: kind, names, ring and earlier traits of every vehicle stay as they were)
LATER_TRAITS: tuple[str, ...] = ("axles", "light_bar", "plate_looks", "no_glass", "inner_shell",
                                 "mirror_glass", "plastic_trim", "cargo_paint")
REAL_RINGS = (0,)          # rings whose renders of each real model give training rows
DEFAULT_VEHICLES = 1000    # generated training vehicles of the shipped model
DEFAULT_SEED = 2026
MEMBERS = 3                # models averaged; member k trains on the generated vehicles of seed + k
HIDE_NAMES = 0.5           # share of generated vehicles with names hidden
REAL_WEIGHT = 24.0         # weight of a real model's material row (a generated one weighs 1)
MODEL_PARAMS = dict(max_iter=150, learning_rate=0.1, max_leaf_nodes=15, min_samples_leaf=10,
                    l2_regularization=1.0, max_features=0.5, early_stopping=False)


@dataclass
class Rows:
    """Training rows: X (N, D) float32, y (N,) part index, w (N,) weight, group (N,) source."""

    X: np.ndarray
    y: np.ndarray
    w: np.ndarray
    group: np.ndarray

    @staticmethod
    def concat(items: list["Rows"]) -> "Rows":
        items = [r for r in items if r.X.shape[0]]
        if not items:
            return Rows(np.zeros((0, len(FEATURE_NAMES)), np.float32), np.zeros(0, np.int64),
                        np.zeros(0), np.zeros(0, object))
        return Rows(*(np.concatenate([getattr(r, k) for r in items])
                      for k in ("X", "y", "w", "group")))


def member_seeds(seed: int, members: int = MEMBERS) -> list[int]:
    """Generated-data and tree seeds of the ensemble members of a run with ``seed``."""
    return [int(seed) + k for k in range(int(members))]


def vehicle_seed(seed: int, i: int) -> int:
    """Generator seed of vehicle i of a run with ``seed`` (sha256, so runs do not overlap)."""
    return int.from_bytes(hashlib.sha256(f"labeller:{seed}:{i}".encode()).digest()[:4], "little")


def synth_recipe(seed: int, i: int) -> dict:
    """Kind, realism traits, names and ring of generated vehicle i (see the module docstring)."""

    vs = vehicle_seed(seed, i)
    r = np.random.default_rng([vs, 11])
    traits = [t for t in REALISM_TRAITS if t not in LATER_TRAITS and r.random() < REALISM_PROB[t]]
    traits += [t for k, t in enumerate(LATER_TRAITS)
               if np.random.default_rng([vs, 12, k]).random() < REALISM_PROB[t]]
    return {"seed": vs, "kind": KINDS[int(r.integers(len(KINDS)))], "realism": traits,
            "hide_names": bool(r.random() < HIDE_NAMES),
            "ring": int(r.integers(len(RINGS)))}


def hide_names(mesh: Mesh) -> Mesh:
    """The mesh with materials renamed m0, m1, ... and nodes n0, n1, ... (names hidden)."""
    return replace(mesh, materials=[replace(m, name=f"m{i}") for i, m in enumerate(mesh.materials)],
                   node_names=[f"n{i}" for i in range(len(mesh.node_names))])


def make_ring_of(index: int):

    step, elev, size = RINGS[index]
    return make_ring(azimuth_step=step, elevations=elev, size=size)


def synth_rows(count: int, seed: int, *, start: int = 0, progress=None) -> Rows:
    """Feature rows of generated vehicles ``start .. start + count - 1`` of run ``seed``."""

    out = []
    for i in range(start, start + count):
        rec = synth_recipe(seed, i)
        veh = make_vehicle(rec["seed"], rec["kind"], realism=rec["realism"])
        mesh = veh.mesh()
        truth = veh.truth["materials"]
        y = np.array([PART_NAMES.index(truth[m.name]) for m in mesh.materials])
        views = render_views(mesh, make_ring_of(rec["ring"]))
        X = material_table(hide_names(mesh) if rec["hide_names"] else mesh, views).X
        out.append(Rows(X, y, np.ones(len(y)), np.array([f"synth:{i}"] * len(y), object)))
        if progress:
            progress(i - start + 1, count)
    return Rows.concat(out)


# ---------------------------------------------------------------------------------------------
# real models (a folder with manifest.json)
# ---------------------------------------------------------------------------------------------
AXES = {"+X": (1, 0, 0), "-X": (-1, 0, 0), "+Y": (0, 1, 0), "-Y": (0, -1, 0),
        "+Z": (0, 0, 1), "-Z": (0, 0, -1)}


def manifest_rotation(up: str, front: str) -> np.ndarray:
    """3x3 rotation taking the file's ``up``/``front`` axes to the vehicle frame's +Y/+X (right
    = front x up -> +Z)."""
    u, f = np.array(AXES[up], float), np.array(AXES[front], float)
    return np.stack([f, u, np.cross(f, u)])


@dataclass
class RealModel:
    """One real model in the vehicle frame with its truth (material name -> part) and the
    acceptable alternatives (material name -> parts)."""

    file: str
    mesh: Mesh
    truth: dict
    alternatives: dict


def load_real_models(folder: str | Path, *, skip=("ferrari_458.glb",),
                     frame: str = "manifest") -> list[RealModel]:
    """The manifest's models (``skip``: duplicates) in the vehicle frame. ``frame``:
    ``"manifest"`` rotates them by their manifest ``up``/``front`` (models without a front keep
    the file's horizontal axes); ``"auto"`` lets the orientation stage estimate the frame, as
    the pipeline does for a file nobody labelled (``load_mesh(orientation="auto")``)."""

    if frame not in ("manifest", "auto"):
        raise ValueError(f"frame must be 'manifest' or 'auto', not {frame!r}")
    folder = Path(folder)
    manifest = json.loads((folder / "manifest.json").read_text(encoding="utf-8"))
    out = []
    for m in manifest["models"]:
        if m["file"] in skip:
            continue
        if frame == "auto":
            mesh = load_mesh(folder / m["file"], orientation="auto")
        else:
            mesh = load_mesh(folder / m["file"], orientation=None)    # the manifest orients it
            up, front = m.get("up") or "+Y", m.get("front")
            if front is None:
                front = "+X" if up[1] != "X" else "+Z"
            R = manifest_rotation(up, front)
            mesh = replace(mesh, vertices=np.asarray(mesh.vertices) @ R.T)
        out.append(RealModel(m["file"], mesh, dict(m["materials"]),
                             dict(m.get("ambiguous_alternatives", {}))))
    return out


def real_rows(models: list[RealModel], rings: tuple[int, ...] = REAL_RINGS) -> dict[str, Rows]:
    """{file: rows} of every real model: one row per material and ring of ``rings`` (indices
    into ``RINGS``), names kept, weight ``REAL_WEIGHT / len(rings)``; materials missing from the
    manifest are left out. (The trees never see names; the named rows also give the names'
    reliability, ``name_weights``.)"""

    out = {}
    for rm in models:
        keep = [i for i, m in enumerate(rm.mesh.materials) if m.name in rm.truth]
        y = np.array([PART_NAMES.index(rm.truth[rm.mesh.materials[i].name]) for i in keep],
                     np.int64)
        Xs = [material_table(rm.mesh, render_views(rm.mesh, make_ring_of(k))).X[keep]
              for k in rings]
        n = len(rings) * len(keep)
        out[rm.file] = Rows(np.concatenate(Xs), np.tile(y, len(rings)),
                            np.full(n, REAL_WEIGHT / len(rings)),
                            np.array([f"real:{rm.file}"] * n, object))
    return out


# ---------------------------------------------------------------------------------------------
# fitting and export
# ---------------------------------------------------------------------------------------------
def name_columns() -> tuple[np.ndarray, np.ndarray]:
    """Indices of the material-name and node-name columns of ``FEATURE_NAMES`` (PART_NAMES order)."""

    col = {n: i for i, n in enumerate(FEATURE_NAMES)}
    return (np.array([col[f"name_{p}"] for p in PART_NAMES]),
            np.array([col[f"node_{p}"] for p in PART_NAMES]))


def without_names(X: np.ndarray) -> np.ndarray:
    """X with the name and node-name columns zeroed (what the trees are fitted on)."""
    X = np.array(X, np.float32, copy=True)
    a, b = name_columns()
    X[:, a] = 0
    X[:, b] = 0
    return X


def name_weights(rows: Rows) -> tuple[float, float]:
    """(w_name, w_node): log likelihood ratios of the names, from how often a name that says a
    part is right in ``rows`` (the real rows when there are any: generated names are cleaner
    than real ones). A name right with rate r among P parts gets w = log(r (P - 1) / (1 - r))
    (naive Bayes with the other parts equally likely), clipped to [0, 8]; a node name counts
    when over half of the material's area is on nodes naming one part."""
    real = np.array([str(g).startswith("real:") for g in rows.group])
    sel = real if real.any() else np.ones(len(rows.y), bool)
    X, y, w = rows.X[sel], rows.y[sel], rows.w[sel]
    P = len(PART_NAMES)
    out = []
    for cols, thr in zip(name_columns(), (0.5, 0.5)):
        v = X[:, cols]
        fires = v.max(axis=1) > thr
        if not fires.any():
            out.append(0.0)
            continue
        right = float(np.sum(w[fires] * (v[fires].argmax(axis=1) == y[fires])) / np.sum(w[fires]))
        r = min(max(right, 1.0 / P), 0.995)
        out.append(float(np.clip(np.log(r * (P - 1) / (1 - r)), 0.0, 8.0)))
    return out[0], out[1]


def fit(rows: Rows, seed: int, *, max_iter: int | None = None):
    """A fitted ``HistGradientBoostingClassifier`` (``MODEL_PARAMS``, ``random_state=seed``) on
    the rows without their name columns (``without_names``), with ``name_weights`` attached as
    ``clf.name_weights_``. Every part index appears in the classes (a part absent from the data
    gets one zero-weight row), so the model's probability columns are ``PART_NAMES``."""
    from sklearn.ensemble import HistGradientBoostingClassifier

    X, y, w = without_names(rows.X), rows.y, rows.w
    missing = [p for p in range(len(PART_NAMES)) if p not in set(y.tolist())]
    if missing:
        X = np.concatenate([X, np.zeros((len(missing), X.shape[1]), X.dtype)])
        y = np.concatenate([y, missing])
        w = np.concatenate([w, np.full(len(missing), 1e-6)])
    params = dict(MODEL_PARAMS)
    if max_iter is not None:
        params["max_iter"] = int(max_iter)
    clf = HistGradientBoostingClassifier(random_state=int(seed), **params)
    # one OpenMP thread: on a shared 2-core machine two spinning threads measured 3x slower,
    # and the trees do not depend on the thread count
    from threadpoolctl import threadpool_limits
    with threadpool_limits(1):
        clf.fit(X, y, sample_weight=w)
    clf.name_weights_ = name_weights(rows)
    return clf


class Ensemble:
    """Fitted members (``fit``) whose tree probabilities are averaged (arithmetic mean, float64);
    the names enter once, after the average (``predict``), with the first member's
    ``name_weights`` (measured on the real rows, the same for every member; on member 0's
    generated rows when there are no real rows)."""

    def __init__(self, members: list):
        if not members:
            raise ValueError("an ensemble needs at least one member")
        self.members = list(members)
        self.name_weights_ = members[0].name_weights_

    def predict_proba(self, X: np.ndarray) -> np.ndarray:
        return np.mean([m.predict_proba(X) for m in self.members], axis=0)


def fit_members(rows: list[Rows], seed: int, *, max_iter: int | None = None) -> Ensemble:
    """An ``Ensemble`` of ``fit(rows[k], seed + k)`` (``member_seeds``)."""
    return Ensemble([fit(r, s, max_iter=max_iter)
                     for r, s in zip(rows, member_seeds(seed, len(rows)))])


def predict(clf, X: np.ndarray) -> np.ndarray:
    """(N, P) probabilities of the whole labeller in NumPy (the reference for the ONNX graph):
    softmax(log p_trees(X without names) + w_name * name one-hot + w_node * node shares), with
    p_trees the members' mean for an ``Ensemble``."""
    a, b = name_columns()
    X = np.asarray(X, np.float32)
    p = clf.predict_proba(without_names(X))
    wn, wd = clf.name_weights_
    z = (np.log(np.maximum(p.astype(np.float32), np.float32(1e-9)))
         + np.float32(wn) * X[:, a] + np.float32(wd) * X[:, b]).astype(np.float64)
    z = np.exp(z - z.max(axis=1, keepdims=True))
    return z / z.sum(axis=1, keepdims=True)


def export_onnx(clf, path: str | Path, record: dict, check: np.ndarray | None = None) -> Path:
    """Write the model as ONNX (``tree_ensemble_onnx``) and ``record`` (plus the feature and
    class names) as JSON beside it; returns the ONNX path. ``check`` rows (float32) are stored
    with scikit-learn's probabilities for them, a reference any runtime must reproduce."""

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(tree_ensemble_onnx(clf, len(FEATURE_NAMES)).SerializeToString())
    full = {**record, "features": list(FEATURE_NAMES), "classes": list(PART_NAMES),
            "onnx_bytes": path.stat().st_size}
    if check is not None and len(check):
        check = np.asarray(check, np.float32)
        full["check"] = {"X": check.tolist(),
                         "prob": np.round(predict(clf, check), 6).tolist()}
    full["name_weights"] = {"name": round(clf.name_weights_[0], 6),
                            "node": round(clf.name_weights_[1], 6)}
    path.with_suffix(".json").write_text(json.dumps(full, indent=1, sort_keys=True) + "\n",
                                         encoding="utf-8")
    return path


def tree_ensemble_onnx(clf, n_features: int):
    """A fitted multi-class ``HistGradientBoostingClassifier`` (from ``fit``) or an ``Ensemble``
    of them as an ONNX graph: input ``features`` (N, D) float32; the name columns zeroed, one
    ONNX-ML ``TreeEnsembleClassifier`` per member (opset ai.onnx.ml 3; softmax of baseline +
    leaves), their ``Mean``, then the names added as in ``predict``; outputs ``label`` (N,) int64
    and ``probabilities`` (N, C).

    Written here rather than with skl2onnx (whose converter fails on this scikit-learn). Exact:
    a split ``x <= t`` (t float64) becomes ``x <= t32`` with t32 the largest float32 <= t, the
    same test for every float32 x; the features have no NaN (no missing-value branches)."""
    from onnx import TensorProto, helper

    members = getattr(clf, "members", [clf])
    K = len(members[0].classes_)
    ops = [_trees_node(m, K, f"tree_prob_{j}" if len(members) > 1 else "tree_prob")
           for j, m in enumerate(members)]
    if len(members) > 1:
        ops.append(helper.make_node("Mean", [f"tree_prob_{j}" for j in range(len(members))],
                                    ["tree_prob"]))
    # names: the trees see the features with the name columns zeroed; the names enter as
    # log-likelihood ratios: softmax(log p_trees + w_name * name one-hot + w_node * node shares)
    a, b = name_columns()
    keep = np.ones(n_features, np.float32)
    keep[a] = 0
    keep[b] = 0
    wn, wd = getattr(clf, "name_weights_", (0.0, 0.0))
    wname = np.zeros((n_features, K), np.float32)
    wname[a, np.arange(K)] = wn
    wname[b, np.arange(K)] = wd
    init = [helper.make_tensor("keep", TensorProto.FLOAT, [n_features], keep.tolist()),
            helper.make_tensor("w_names", TensorProto.FLOAT, [n_features, K],
                               wname.ravel().tolist()),
            helper.make_tensor("eps", TensorProto.FLOAT, [], [1e-9])]
    nodes_ = [helper.make_node("Mul", ["features", "keep"], ["trees_in"]), *ops,
              helper.make_node("Max", ["tree_prob", "eps"], ["tree_prob_safe"]),
              helper.make_node("Log", ["tree_prob_safe"], ["tree_logp"]),
              helper.make_node("MatMul", ["features", "w_names"], ["name_logit"]),
              helper.make_node("Add", ["tree_logp", "name_logit"], ["logit"]),
              helper.make_node("Softmax", ["logit"], ["probabilities"], axis=1),
              helper.make_node("ArgMax", ["probabilities"], ["label"], axis=1, keepdims=0)]
    graph = helper.make_graph(
        nodes_, "ucad_labeller",
        [helper.make_tensor_value_info("features", TensorProto.FLOAT, [None, n_features])],
        [helper.make_tensor_value_info("label", TensorProto.INT64, [None]),
         helper.make_tensor_value_info("probabilities", TensorProto.FLOAT, [None, K])],
        initializer=init)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17),
                                                    helper.make_opsetid("ai.onnx.ml", 3)],
                              producer_name="ucad_cl.labeller_train")
    model.ir_version = 8
    return model


def _trees_node(clf, K: int, out: str):
    """One member's ``TreeEnsembleClassifier`` node: input ``trees_in``, probabilities ``out``."""
    from onnx import helper

    if len(clf.classes_) != K or K < 3 or list(clf.classes_) != list(range(K)):
        raise ValueError("expected multi-class models with classes 0..K-1")
    nodes = {k: [] for k in ("treeids", "nodeids", "featureids", "values", "modes",
                             "truenodeids", "falsenodeids", "missing")}
    cls = {k: [] for k in ("treeids", "nodeids", "ids", "weights")}
    tree = 0
    for it in clf._predictors:
        for k, pred in enumerate(it):
            nd = pred.nodes
            if nd["is_categorical"].any():
                raise ValueError("categorical splits are not supported")
            for i, n in enumerate(nd):
                nodes["treeids"].append(tree)
                nodes["nodeids"].append(i)
                if n["is_leaf"]:
                    nodes["featureids"].append(0)
                    nodes["values"].append(0.0)
                    nodes["modes"].append("LEAF")
                    nodes["truenodeids"].append(0)
                    nodes["falsenodeids"].append(0)
                    cls["treeids"].append(tree)
                    cls["nodeids"].append(i)
                    cls["ids"].append(k)
                    cls["weights"].append(float(n["value"]))
                else:
                    t = float(n["num_threshold"])
                    t32 = np.float32(t)
                    if float(t32) > t:
                        t32 = np.nextafter(t32, np.float32(-np.inf))
                    nodes["featureids"].append(int(n["feature_idx"]))
                    nodes["values"].append(float(t32))
                    nodes["modes"].append("BRANCH_LEQ")
                    nodes["truenodeids"].append(int(n["left"]))
                    nodes["falsenodeids"].append(int(n["right"]))
                nodes["missing"].append(int(bool(n["missing_go_to_left"])) if not n["is_leaf"]
                                        else 0)
            tree += 1
    return helper.make_node(
        "TreeEnsembleClassifier", ["trees_in"], [out + "_label", out],
        domain="ai.onnx.ml",
        nodes_treeids=nodes["treeids"], nodes_nodeids=nodes["nodeids"],
        nodes_featureids=nodes["featureids"],
        nodes_values=np.asarray(nodes["values"], np.float32).tolist(),
        nodes_modes=nodes["modes"], nodes_truenodeids=nodes["truenodeids"],
        nodes_falsenodeids=nodes["falsenodeids"],
        nodes_missing_value_tracks_true=nodes["missing"],
        class_treeids=cls["treeids"], class_nodeids=cls["nodeids"], class_ids=cls["ids"],
        class_weights=np.asarray(cls["weights"], np.float32).tolist(),
        classlabels_int64s=list(range(K)), post_transform="SOFTMAX",
        base_values=np.asarray(clf._baseline_prediction, np.float32).ravel().tolist())


def accuracy(clf, rows: Rows) -> float:
    """Share of rows whose argmax part (``predict``) is the label (unweighted)."""
    if rows.X.shape[0] == 0:
        return float("nan")
    return float(np.mean(predict(clf, rows.X).argmax(axis=1) == rows.y))


def train(out: str | Path, *, vehicles: int, seed: int, real: str | Path | None = None,
          leave_out: tuple[str, ...] = (), test_vehicles: int = 0, max_iter: int | None = None,
          members: int = MEMBERS, log=print) -> dict:
    """The whole recipe: for each of ``members`` members (``member_seeds``), generate
    ``vehicles`` training vehicles of its seed (+ the real models except ``leave_out``, the same
    for every member), fit them (``fit_members``), score on ``test_vehicles`` generated vehicles
    of another seed (never used for training), export to ``out`` (.onnx + .json). Returns the
    JSON record."""
    t0 = time.perf_counter()
    real_list: list[Rows] = []
    n_real = 0
    if real is not None:
        models = [m for m in load_real_models(real) if m.file not in leave_out]
        n_real = len(models)
        real_list = list(real_rows(models).values())
    per_member = [Rows.concat([synth_rows(vehicles, s)] + real_list)
                  for s in member_seeds(seed, members)]
    data = Rows.concat(per_member)
    t_data = time.perf_counter() - t0
    clf = fit_members(per_member, seed, max_iter=max_iter)
    t_fit = time.perf_counter() - t0 - t_data
    record = {
        "recipe": {"vehicles": vehicles, "seed": seed, "members": members,
                   "member_seeds": member_seeds(seed, members), "realism_prob": REALISM_PROB,
                   "hide_names": HIDE_NAMES, "rings": [list(map(str, r)) for r in RINGS],
                   "real_models": n_real, "real_weight": REAL_WEIGHT,
                   "leave_out": list(leave_out), "model": "HistGradientBoostingClassifier",
                   "params": {**MODEL_PARAMS, **({"max_iter": max_iter} if max_iter else {})}},
        "rows": int(data.X.shape[0]),
        "metrics": {"train_material_accuracy": round(accuracy(clf, data), 4)},
        "seconds": {"data": round(t_data, 1), "fit": round(t_fit, 1)},
    }
    if test_vehicles:
        test = synth_rows(test_vehicles, seed + 1_000_003)
        record["metrics"]["heldout_generated_material_accuracy"] = round(accuracy(clf, test), 4)
        record["metrics"]["heldout_generated"] = {"vehicles": test_vehicles,
                                                  "seed": seed + 1_000_003, "rows": len(test.y)}
    first = [int(np.flatnonzero(data.y == p)[0]) for p in range(len(PART_NAMES))
             if (data.y == p).any()]
    export_onnx(clf, out, record, check=data.X[first])
    log(f"labeller: {data.X.shape[0]} rows, fit {t_fit:.0f} s, metrics {record['metrics']}")
    return record
