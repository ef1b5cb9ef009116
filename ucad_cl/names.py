"""Part priors from material names: the keyword table (many languages) and ``name_prior``.

Used by the prior segmenter (``segment``), the learned labeller's name features (``labeller``)
and classification's leftover rule (``classify_parts(priors=name_priors(mesh))``).
"""
from __future__ import annotations

import re

from .artifacts import Mesh

# ---------------------------------------------------------------------------------------------
# Keyword lists, checked in this order (the earliest match in the name wins, see ``name_prior``;
# equal positions go to the earlier group). Matching is case-insensitive on the
# name with separators (_ - . space digits) turned into word breaks; Latin keywords must start a
# word, except those marked "~" (German compounds: Windschutzscheibe) and non-Latin ones, which
# match anywhere. Mirrors and door handles are trim (part chrome), the labelling policy of the
# real test models (docs/CONVENTIONS.md).
NAME_KEYWORDS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("interior", ("interior", "seat", "~sitz", "siège", "siege", "asiento", "sedile", "dashboard",
                  "dash", "leather", "leder", "cuir", "cuero", "pelle", "carpet", "teppich",
                  "steering", "lenkrad", "volant", "fabric", "cloth", "wood",
                  "innen", "intérieur", "interieur", "シート", "内装", "座椅", "内饰", "салон",
                  "сиден")),
    ("plate", ("plate", "number", "licen", "~kennzeichen", "nummernschild", "plaque",
               "immatriculation",
               "matrícula", "matricula", "targa", "ナンバー", "牌照", "车牌", "номер")),
    ("light", ("light", "lamp", "headlight", "taillight", "~scheinwerfer", "licht", "~leuchte",
               "phare", "feu", "faro", "luz", "luce", "fanale", "projector", "signal", "indicator",
               "blinker", "led", "lens", "ライト", "ランプ", "灯", "фар", "фонар")),
    ("chrome", ("chrome", "chrom", "cromo", "trim", "grill", "grille", "kühlergrill", "calandre",
                "parrilla", "griglia", "bumper", "stoßstange", "mirror", "miroir", "~spiegel",
                "espejo", "specchio", "retrovisor", "rétroviseur", "handle", "~knob", "poignée",
                "クローム", "ミラー", "镀铬", "后视镜", "хром", "зеркал")),
    ("rim", ("rim", "~felge", "jante", "llanta", "cerchio", "hub", "ホイール", "轮毂", "диск")),
    ("wheel", ("tyre", "tire", "wheel", "~reifen", "pneu", "neumático", "neumatico",
               "gomma", "pneumatico", "rubber", "gummi", "タイヤ", "车轮", "轮胎", "шин", "колес")),
    ("window", ("glass", "window", "windshield", "windscreen", "~scheibe", "glas", "fenster",
                "vitre", "verre", "ventana", "vidrio", "cristal", "vetro", "finestrino", "ガラス",
                "窓", "玻璃", "车窗", "стекл", "окн")),
    ("body", ("paint", "body", "~karosserie", "lack", "carrosserie", "peinture", "carrocería",
              "carroceria", "pintura", "carrozzeria", "vernice", "ボディ", "塗装", "车身", "车漆",
              "кузов", "краск")),
)


def _name_pattern() -> re.Pattern:
    """One regex for every keyword of ``NAME_KEYWORDS`` (see ``name_prior``): the alternatives in
    group order, one named group per part, so a search finds the earliest position any keyword
    matches and, at that position, the earliest group."""
    groups = []
    for rank, (_part, words) in enumerate(NAME_KEYWORDS):
        alts = [re.escape(kw[1:]) if kw.startswith("~")
                else "(?<![a-z])" + re.escape(kw) if kw.isascii() else re.escape(kw)
                for kw in words]
        groups.append(f"(?P<g{rank}>" + "|".join(alts) + ")")
    return re.compile("|".join(groups))


_NAME_RE = _name_pattern()
_CAMEL_RE = re.compile(r"([a-z])([A-Z])")
_SEP_RE = re.compile(r"[\s_\-.:/\\0-9()\[\]]+")


def name_prior(name: str) -> str | None:
    """Part named by a material name, or None.

    Every keyword of ``NAME_KEYWORDS`` found in the name is a candidate; the one that starts
    earliest in the name wins (names put the part first: ``paint_window_sill`` is paint,
    ``Taillight_Glass`` a light), equal positions go to the earlier group of ``NAME_KEYWORDS``.
    One precompiled regex (``_NAME_RE``), a few microseconds per name.
    """
    spaced = _CAMEL_RE.sub(r"\1 \2", name).lower()                   # camelCase -> camel case
    spaced = " " + _SEP_RE.sub(" ", spaced) + " "
    hit = _NAME_RE.search(spaced)
    if hit is None:
        return None
    return NAME_KEYWORDS[int(hit.lastgroup[1:])][0]


def name_priors(mesh: Mesh) -> dict[int, str]:
    """{material index: part} for the materials whose names say their part (``name_prior``);
    classification uses them for leftovers instead of merging those into the body."""
    return {m: p for m, mat in enumerate(mesh.materials) if (p := name_prior(mat.name)) is not None}
