"""Name cues: material and node names (front/rear, head/tail, roof, floor, wheel, lamp, glass in
several languages), lamp colours and glass materials, as the up and front cues read them.
"""
from __future__ import annotations

import re
from typing import Sequence

import numpy as np

from ..artifacts import Mesh, node_stem
from .geometry import N_SAMPLES, Samples

# ----------------------------------------------------------------------------- names

class _Keywords:
    """A test on a name's words (``_words``): an ASCII keyword starts one of its words, a
    non-ASCII one appears anywhere in it (CJK has no spaces), or one of its words is one of
    ``tokens``. Words starting with one of ``exclude`` are dropped first (``headrest`` is
    not a head lamp). ``many`` applies it to many names, each distinct word tested once."""

    def __init__(self, words: Sequence[str], tokens: Sequence[str] = (),
                 exclude: Sequence[str] = ()):
        self.rx = re.compile(r"(?<![a-z])(?:" + "|".join(re.escape(w) for w in words
                                                         if w.isascii()) + ")")
        self.other = [w for w in words if not w.isascii()]
        self.tok = frozenset(tokens)
        self.excl = tuple(exclude)
        self.prefixes = tuple(w for w in words if w.isascii())

    def many(self, names: Sequence[tuple[str, ...]]) -> np.ndarray:
        """(N,) bool: the test on each of ``names`` (their words, as ``_words`` gives them),
        word by word (a keyword or token has no space, so a match lies in one word), each
        distinct word tested once."""
        out = np.zeros(len(names), bool)
        hit: dict[str, bool] = {}
        for i, ws in enumerate(names):
            for w in ws:
                h = hit.get(w)
                if h is None:
                    h = hit[w] = self._word(w)
                if h:
                    out[i] = True
                    break
        return out

    def _word(self, w: str) -> bool:
        """The test on one word (letters only): an ASCII word can only match a keyword at its
        start (``rx`` needs no letter a-z before it)."""
        if w.startswith(self.excl):
            return False
        if w.isascii():
            return w.startswith(self.prefixes) or w in self.tok
        return (self.rx.search(w) is not None or w in self.tok
                or any(k in w for k in self.other))


_CAMEL = re.compile(r"([a-z])([A-Z])")
_WORD = re.compile(r"[^\W\d_]+")


def _words(name: str) -> tuple[str, ...]:
    """Lower-case words of a name: camelCase split; digits and punctuation separate words."""
    return tuple(w.lower() for w in _WORD.findall(_CAMEL.sub(r"\1 \2", str(name))))


_NOT_DIRECTION = ("headrest", "headliner", "headlining", "backrest", "background", "rearview",
                  "backplate", "backface", "backside", "headphone")
IS_FRONT = _Keywords(
    ("front", "head", "hood", "bonnet", "windshield", "windscreen", "grill", "nose", "avant",
     "phare", "capot", "vorn", "vorder", "scheinwerfer", "motorhaube", "frontscheibe",
     "delanter", "faro", "capo", "parabris", "anterior", "cofano", "передн", "фара", "капот",
     "前", "フロント", "ヘッド", "ボンネット"), ("f", "fl", "fr", "av", "fwd"), _NOT_DIRECTION)
IS_REAR = _Keywords(
    ("rear", "back", "tail", "brake", "trunk", "boot", "exhaust", "muffler", "reverse",
     "arriere", "arrière", "coffre", "hinten", "heck", "rück", "rueck", "kofferraum",
     "auspuff", "traser", "malet", "posterior", "bagagli", "задн", "багаж", "后", "後",
     "テール", "ブレーキ", "マフラー"), ("rl", "rr", "bl", "br", "ar", "bk"), _NOT_DIRECTION)
_IS_LAMP = _Keywords(
    ("light", "lamp", "lens", "blinker", "indicator", "signal", "licht", "leuchte", "phare",
     "feu", "faro", "luz", "luce", "fanale", "projector", "led", "brakelight", "taillight",
     "headlight", "ライト", "ランプ", "灯", "燈", "фар", "фонар"))
_IS_GLASS = _Keywords(
    ("glass", "window", "windshield", "windscreen", "glazing", "scheibe", "glas", "fenster",
     "vitre", "verre", "ventana", "vidrio", "cristal", "vetro", "finestrin", "стекл", "окн",
     "ガラス", "窓", "玻璃", "车窗"))
IS_ROOF = _Keywords(("roof", "top", "dach", "toit", "techo", "tetto", "крыш", "ルーフ",
                             "车顶"))
IS_FLOOR = _Keywords(
    ("floor", "underbody", "under", "bottom", "chassis", "dessous", "boden", "unterboden",
     "piso", "suelo", "pavimento", "fondo", "днище", "床", "底"), ("sol",))
IS_WHEEL = _Keywords(
    ("tyre", "tire", "wheel", "reifen", "pneu", "neumatic", "neumátic", "rueda", "ruota",
     "roue", "gomma", "колес", "шин", "タイヤ", "ホイール", "轮", "輪"), ("rad",),
    ("steering", "lenkrad", "volant", "spare", "wheelhouse", "wheelwell"))


class Names:
    """The names of a mesh's materials and nodes, pass-independent (made once per mesh and
    shared by the cascade's passes): ``groupings`` (per-face labels (F,) and the names), each
    distinct name split into words once and tested against a keyword set once, the kind of
    every material (``kinds``) and the node groups ``overlapping_vehicles`` weighs."""

    def __init__(self, mesh: Mesh):
        self.mesh = mesh
        fm = np.asarray(mesh.face_material)                 # labels as stored (no copy)
        self.groupings = [(fm, [m.name for m in mesh.materials])]
        if mesh.face_node is not None and len(mesh.node_names):
            fn = np.asarray(mesh.face_node)
            if fn.size and fn.min() >= 0 and fn.max() < len(mesh.node_names):
                # without trimesh's random '_xxxxxx' suffix (its hex letters would be
                # words such as 'f' or 'bb': a names cue that changed from run to run)
                self.groupings.append((fn, [node_stem(n) for n in mesh.node_names]))
        # same[g]: the first grouping with the same labels and as many groups (one node per
        # material is common): its per-group sums are grouping g's, computed once
        self.same = [next(h for h in range(g + 1) if h == g or (
            len(self.groupings[h][1]) == len(names) and np.array_equal(self.groupings[h][0], lab)))
            for g, (lab, names) in enumerate(self.groupings)]
        self._words: dict[str, tuple[str, ...]] = {}
        self._tests: dict = {}
        self._kinds: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._node_groups: tuple | None = None
        self._sorted: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}

    def words(self, name: str) -> tuple[str, ...]:
        if name not in self._words:
            self._words[name] = _words(name)
        return self._words[name]

    def matching(self, match: _Keywords, g: int) -> np.ndarray:
        """(K,) bool: the names of grouping ``g`` that ``match`` (remembered)."""
        key = (match, g)
        if key not in self._tests:
            names = self.groupings[g][1]
            h = next(h for h in range(g + 1) if h == g or self.groupings[h][1] == names)
            self._tests[key] = (self.matching(match, h) if h < g
                                else match.many([self.words(n) for n in names]))
        return self._tests[key]

    def _by_group(self, g: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(faces sorted by their group in grouping ``g`` (stable), where each non-empty
        group starts in that order, its number of faces, those groups' labels); once per
        mesh."""
        if g not in self._sorted:
            lab = self.groupings[g][0]
            order = np.argsort(lab, kind="stable")
            starts = np.flatnonzero(np.r_[True, np.diff(lab[order]) != 0]) if lab.size else order
            self._sorted[g] = (order, starts, np.diff(np.append(starts, order.size)),
                               lab[order[starts]])
        return self._sorted[g]

    def sums(self, g: int, weights: np.ndarray) -> np.ndarray:
        """(K,) per-face ``weights`` summed over each group of grouping ``g``, group by group
        in face order (``np.add.reduceat`` over the faces sorted by group: several times
        faster than ``np.bincount`` with weights)."""
        order, starts, _, present = self._by_group(g)
        out = np.zeros(len(self.groupings[g][1]))
        if starts.size:
            out[present] = np.add.reduceat(weights[order], starts)
        return out

    def sums_on(self, g: int, groups: np.ndarray, weight) -> np.ndarray:
        """(len(groups),) ``sums(g, w)[groups]`` for a per-face w that is ``weight(faces)``
        on the faces of those groups (ascending; weight: a function of face indices),
        computed on those faces only (the same values in the same order per group)."""
        order, starts, size, present = self._by_group(g)
        out = np.zeros(len(groups))
        if present.size == 0:
            return out
        k = np.minimum(np.searchsorted(present, groups), present.size - 1)
        has = present[k] == groups                        # groups with faces
        s, lens = starts[k[has]], size[k[has]]
        if lens.size:
            first = np.cumsum(lens) - lens
            faces = order[np.repeat(s - first, lens) + np.arange(int(lens.sum()))]
            out[has] = np.add.reduceat(weight(faces), first)
        return out

    def kinds(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(glass (M,) bool, lamp (M,) bool, lamp colour (M,) int8) of every material."""
        if self._kinds is None:
            self._kinds = _material_kinds(self.mesh.materials, self.words)
        return self._kinds

    def node_groups(self) -> tuple[np.ndarray, int, np.ndarray] | None:
        """Node groups by stem (trimesh's suffix dropped): (group of each face (F,), K, (K,)
        bool: at least 4 faces and 2 materials), or None with under 2 groups or no nodes."""
        if self._node_groups is None:
            self._node_groups = (None,)
            if len(self.groupings) >= 2:
                node_of_face, stems = self.groupings[1]           # already node_stem
                stem_ids = {st: k for k, st in enumerate(dict.fromkeys(stems))}
                if len(stem_ids) == len(stems) and self.same[1] == 0:
                    pass                         # one node per material: one material each
                elif len(stem_ids) >= 2:
                    K = len(stem_ids)
                    group = np.array([stem_ids[st] for st in stems])[node_of_face]
                    fm = self.groupings[0][0]                     # material of each face
                    # counts per group in one pass each: faces, distinct materials
                    M = max(len(self.mesh.materials), 1)
                    if K * M <= 4_000_000:
                        n_mat = (np.bincount(group * M + fm, minlength=K * M) > 0).reshape(
                            K, M).sum(axis=1)
                    else:
                        n_mat = np.bincount(np.unique(group * M + fm) // M, minlength=K)
                    self._node_groups = (group, K, (np.bincount(group, minlength=K) >= 4)
                                         & (n_mat >= 2))
        return None if self._node_groups[0] is None else self._node_groups


class NameTable:
    """Materials and nodes as named groups of faces (``groupings`` of ``Names``) with their
    surface share in this pass, and of samples (the material of each sample). Faces weigh
    twice their area (``area``, ``total_area``): shares and means are ratios, the factor
    cancels exactly."""

    def __init__(self, names: Names, S: Samples):
        mesh = names.mesh
        self.names, self.mesh, self.groupings = names, mesh, names.groupings
        self.material_of_sample = np.asarray(mesh.face_material)[S.face].astype(np.intp)
        self.area = S.face_area2
        self.total_area = total = max(float(self.area.sum()), 1e-300)
        share: list[np.ndarray] = []                              # surface share of each group
        for g in range(len(self.groupings)):
            share.append(share[names.same[g]] if names.same[g] < g else
                         names.sums(g, self.area) / total)
        self.share = share
        self._means: dict = {}   # (grouping, groups, id(value)) -> (value kept alive, means)
        glass, lamp, colour = names.kinds()
        with_surface = share[0] > 0                               # the rest: not any kind
        self.glass, self.lamp = glass & with_surface, lamp & with_surface
        self.colour = np.where(with_surface, colour, 0).astype(np.int8)

    def matches(self, match, g: int) -> np.ndarray:
        """(K,) bool: the names of grouping ``g`` (with surface) that ``match``."""
        return self.names.matching(match, g) & (self.share[g] > 0)

    def means_on(self, g: int, groups: np.ndarray, value) -> np.ndarray:
        """(len(groups),) area-weighted mean over each of the groups ``groups`` (ascending) of
        grouping g of a per-face v that is ``value(faces)`` on their faces (value: a function
        of the face indices), computed on those faces only (group by group in face order,
        the same sums as ``Names.sums`` over all faces)."""
        tot = np.maximum(self.share[g][groups] * self.total_area, 1e-300)
        return self.names.sums_on(g, groups, lambda f: self.area[f] * value(f)) / tot

    def votes(self, match, value: np.ndarray) -> list[tuple[float, float]]:
        """(weight, area-weighted mean of the per-face ``value``) of the groups whose name
        matches; weight = sqrt of the group's surface share x N_SAMPLES, at most 50 (a big
        panel is one vote, not many). The means are remembered (a grouping with another's
        labels asks for the same ones)."""
        out = []
        for g in range(len(self.groupings)):
            hit = np.flatnonzero(self.matches(match, g))
            if hit.size:
                w = np.sqrt(np.minimum(self.share[g][hit] * N_SAMPLES, 50.0))
                h = self.names.same[g]
                key = (h, hit.tobytes(), id(value))
                if key not in self._means:
                    self._means[key] = (value, self.means_on(h, hit, lambda f: value[f]))
                out.extend(zip(w.tolist(), self._means[key][1].tolist()))
        return out


def vote(votes: list[tuple[float, float]]) -> float:
    """Weighted signed votes [(weight, value in [-1, 1])] -> agreement in [-1, 1]; few or
    weak votes give less than full agreement (a prior weight of 2 on zero)."""
    if not votes:
        return 0.0
    w = np.array([v[0] for v in votes])
    x = np.clip(np.array([v[1] for v in votes]), -1.0, 1.0)
    return float(np.clip(2.0 * (w * x).sum() / (w.sum() + 2.0), -1.0, 1.0))


def _is_glass(mat, lamp_name: bool, glass_name: bool) -> bool:
    """Window glass: clear (transmission, or blended and see-through) or named so
    (``glass_name``: a glass word in its name); lamp covers (``lamp_name``: a lamp word in
    the name) are not windows."""
    if lamp_name:
        return False
    clear = mat.transmission > 0.05 or (mat.alpha_mode == "BLEND" and mat.base_color[3] < 0.9)
    return bool(clear or glass_name)


def _lamp_colour(mat, lamp_name: bool) -> int:
    """-1 a red lamp, +1 a white / yellow / amber lamp, 0 not a lamp or unknown colour (a
    lamp: a lamp word in the name (``lamp_name``) or emission; its colour: emissive, else
    base colour)."""
    glowing = max(mat.emissive) > 0.1
    if not (glowing or lamp_name) or (mat.has_texture and not glowing):
        return 0
    r, g, b = (float(c) for c in (mat.emissive if glowing else mat.base_color[:3]))
    if r > 0.25 and g < 0.45 * r and b < 0.45 * r:
        return -1
    if r > 0.4 and g > 0.35 * r and (b > 0.5 * r or g > 0.6 * r):
        return 1
    return 0


def _material_kinds(mats: Sequence, words) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(glass (M,) bool, lamp (M,) bool, lamp colour (M,) int8) of materials ``mats``
    (``words``: a name -> its words)."""
    M = len(mats)
    glass, lamp, colour = np.zeros(M, bool), np.zeros(M, bool), np.zeros(M, np.int8)
    ws = [words(mat.name) for mat in mats]
    lamp_name, glass_name = _IS_LAMP.many(ws).tolist(), _IS_GLASS.many(ws).tolist()
    for i, mat in enumerate(mats):
        glass[i] = _is_glass(mat, lamp_name[i], glass_name[i])
        lamp[i] = lamp_name[i] or max(mat.emissive) > 0.1
        colour[i] = _lamp_colour(mat, lamp_name[i])
    return glass, lamp, colour
