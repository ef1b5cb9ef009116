"""Material realism: how real libraries assign materials (``apply_realism``, one branch per
trait of ``REALISM_TRAITS``), each trait drawing from its own seeded stream.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ..artifacts import PART_NAMES, Material
from .materials import make_material
from .shapes import Part, box, compact, patch, revolve

# --------------------------------------------------------------------------------------------
# material realism: how real libraries assign materials (traits for training and tests)

def apply_realism(parts: list[Part], traits: Sequence[str],  # noqa: C901  one branch per trait
                  r: np.random.Generator) -> list[Part]:
    """The vehicle's parts with the realism ``traits`` applied in the order given
    (``make_vehicle``: the body-shape traits ``SHAPE_TRAITS`` first, then ``REALISM_TRAITS``).

    Geometry traits: ``brake_discs`` (rims become rings with a grey disc and a red calliper
    behind them: part other), ``lens_lamps`` (every lamp enclosed in a clear lens box, part
    light: the lamp is seen only through the lens), ``rich_interior`` (steering wheel, door
    panels, seats in two leathers), ``no_rims`` (the rim faces take the tyre's material: wheels
    without separate rims), ``chassis_only`` (no wheels and no interior).
    Material traits: ``one_paint`` (every paint panel shares one paint material),
    ``paint_rims`` (the rims share the body paint), ``shared_black`` (tyres, grille, underbody
    and plastic bumpers share one black), ``dark_trim`` (grille, bumpers, mirror housings and
    side trim in one dark plastic: part chrome, the trim policy), ``textured_body`` (body, lamps,
    plates, trim and grille are one textured material, 40 % of the time the tyres and rims too,
    as texture-atlas models do; glass and interior stay separate),
    ``varied_looks`` (every material's colour pulled up to 60 % toward a random colour, metallic
    and roughness moved by up to 0.35), ``mtl_like`` (OBJ/MTL materials: metallic 0, roughness 1,
    no emission, no transmission),
    ``opaque_glass`` (glass is opaque: light blue, or a blue, blue-grey or grey of any
    lightness, one colour for all windows or one each; ``_opaque_glass``),
    ``dark_glass`` (glass is opaque and dark: black, grey or a dark tint, one random colour),
    ``two_tone`` (a group of body panels, the roof and pillars, the lower panels or every other
    panel, in a second paint far from the first: part body), ``one_glass`` (every window shares one glass material: the whole
    glasshouse, as most real libraries build it), ``glass_looks`` (the glass looks as real
    libraries make it: see-through by alpha only (0.1-0.7, alpha mode BLEND or OPAQUE, no
    transmission) or opaque, light or dark grey or tinted, any metallic and roughness),
    ``grey_trim`` (grille, bumpers, mirror housings and side trim in one grey material,
    lightness and gloss drawn at random: part chrome, the trim policy), ``plain_lights`` (lamps without emission),
    ``lamp_variety`` (lamps as real libraries build them: an amber indicator beside every lamp,
    tail lamps behind a tinted red see-through lens with a grey reflector inside, headlamps as a
    clear lens over a chrome-like reflector; all part light), ``ground_base`` (the vehicle stands
    on a ground plane, plinth or cloth up to 3 times its size: part other, and the file's
    bounding box is the base's), ``axles`` (a rod joins the two wheels of every axle and, on
    half of the vehicles, two frame rails run between the first and last axle: part other,
    dark metal or plastic, as simulator and game models build their undercarriage),
    ``light_bar`` (an emergency light bar across the roof, in one or two of blue, red and
    amber, sometimes see-through or glowing: part light), ``plate_looks`` (plates as real
    libraries paint them: white, yellow, black or dark grey, plain or textured, any gloss, US
    or EU proportions, sometimes no front plate), ``no_glass`` (no window at all, as many game
    models are built: the interior is seen directly), ``inner_shell`` (the cabin's roof,
    pillars and doors lined inside in an interior material: ``_inner_shell``),
    ``mirror_glass`` (a reflective glass on the back of each door mirror: part chrome,
    ``_mirror_glass``), ``plastic_trim`` (game-kit trim: one neutral grey plastic on the
    grille, tall bumpers, mirrors, side trim and sill cladding, on trucks the chassis sides,
    sometimes the underbody: ``_plastic_trim``), ``cargo_paint`` (a truck's cargo box or a
    pickup's bed in a second paint, neutral or coloured, sometimes under a canvas cover:
    ``_cargo_paint``).
    Shape traits: ``cartoon`` (cartoon proportions: the body 12-28 % shorter and 10-30 %
    taller, the wheels 15-45 % bigger, standing on the ground: ``_cartoon``), ``wedge`` (a
    wedge body: every non-wheel part's height scaled from 1 - k at the nose to 1 + k at the
    tail, k 8-20 %); both on streams of their own.
    ``opaque_glass`` and the traits from ``axles`` on draw from their own random streams
    (``_trait_rng``), so adding or changing one changes no other trait's draws.
    Name traits: ``meaningless_names`` (materials become ``Material.001``..., nodes
    ``Object_1``...), ``misleading_names`` (some materials named after another part).
    The truth of a shared material is its majority part (``majority_part``)."""
    parts = list(parts)
    mats: dict[tuple[str, str], Material] = {}
    t = ""

    def shared(name: str, like: Material, **kw) -> Material:
        """One material object per (trait, name): parts given it share it."""
        if (t, name) not in mats:
            mats[(t, name)] = Material(**{**like.__dict__, "name": name, **kw})
        return mats[(t, name)]

    def is_(q, *prefixes):
        return q.node.startswith(prefixes)

    for t in traits:
        if t == "brake_discs":
            parts = _brake_discs(parts)
        elif t == "lens_lamps":
            parts = _lens_lamps(parts)
        elif t == "rich_interior":
            parts = _rich_interior(parts, r)
        elif t == "no_rims":
            tyres = {q.node[len("tyre_"):]: q for q in parts if is_(q, "tyre_")}
            for q in parts:
                if is_(q, "rim_") and q.node[len("rim_"):] in tyres:
                    q.material = tyres[q.node[len("rim_"):]].material
                    q.part = "wheel"
        elif t == "chassis_only":
            parts = [q for q in parts if q.part not in ("wheel", "rim", "interior")
                     and not is_(q, "brake_", "calliper_")]
        elif t == "one_paint":
            paint = next((q.material for q in parts if q.material.name.startswith("paint_")),
                         None)
            for q in parts:
                if paint is not None and q.material.name.startswith("paint_"):
                    q.material = shared("paint", paint)
        elif t == "paint_rims":
            paint = next((q.material for q in parts if q.part == "body"
                          and q.material.name.startswith("paint")), None)
            for q in parts:
                if paint is not None and is_(q, "rim_") and q.part == "rim":
                    q.material = shared(paint.name if paint.name == "paint" else "paint_body",
                                        paint)
                elif paint is not None and paint.name != "paint" and q.material is paint:
                    q.material = shared("paint_body", paint)
        elif t == "shared_black":
            black = make_material("black", "plastic", (0, 0, 0))
            for q in parts:
                if (is_(q, "tyre_", "grille", "underbody")
                        or (is_(q, "bumper_") and q.material.metallic < 0.5)):
                    q.material = shared("black", black)
        elif t == "dark_trim":
            trim = Material("trim_dark", (0.04, 0.04, 0.045, 1.0), "OPAQUE", 0.0, 0.55)
            for q in parts:
                if is_(q, "grille", "bumper_", "paint_mirror_", "chrome_trim_"):
                    q.material = shared("trim_dark", trim)
                    q.part = "chrome"
        elif t == "textured_body":
            tex = Material("body_tex", (1.0, 1.0, 1.0, 1.0), "OPAQUE", 0.0, 0.5,
                           has_texture=True)
            atlas = ("body", "light", "plate", "chrome") + (("wheel", "rim") if r.random() < 0.4
                                                           else ())
            for q in parts:
                if q.part in atlas or is_(q, "grille"):
                    q.material = shared("body_tex", tex)
        elif t == "varied_looks":
            for q in parts:
                m = q.material
                if ("varied_looks", m.name) not in mats:
                    k = float(r.uniform(0.0, 0.6))
                    rgb = (1 - k) * np.asarray(m.base_color[:3]) + k * r.uniform(0, 1, 3)
                    jm, jr = r.uniform(-0.35, 0.35, 2)
                    shared(m.name, m, base_color=(*(float(x) for x in rgb), m.base_color[3]),
                           metallic=float(np.clip(m.metallic + jm, 0, 1)),
                           roughness=float(np.clip(m.roughness + jr, 0.02, 1)))
                q.material = mats[("varied_looks", m.name)]
        elif t == "mtl_like":
            for q in parts:
                m = q.material
                q.material = shared(m.name, m, metallic=0.0, roughness=1.0,
                                    emissive=(0.0, 0.0, 0.0), transmission=0.0)
        elif t == "opaque_glass":
            parts = _opaque_glass(parts, _trait_rng(r, t), shared)
        elif t == "dark_glass":
            rgb = r.uniform(0.0, 0.12) + r.uniform(0.0, 0.1, 3)
            for q in parts:
                if q.part == "window":
                    q.material = shared(q.material.name, q.material,
                                        base_color=(*(float(x) for x in rgb), 1.0),
                                        alpha_mode="OPAQUE", transmission=0.0,
                                        metallic=float(r.uniform(0.0, 0.3)),
                                        roughness=float(r.uniform(0.05, 0.5)))
        elif t == "two_tone":
            parts = _two_tone(parts, r, shared)
        elif t == "grey_trim":
            g = float(r.uniform(0.05, 0.7))
            trim = Material("trim_grey", (g, g, g * float(r.uniform(0.95, 1.05)), 1.0), "OPAQUE",
                            float(r.choice([0.0, 1.0, r.uniform(0, 1)])),
                            float(r.choice([1.0, r.uniform(0.2, 1)])))
            for q in parts:
                if is_(q, "grille", "bumper_", "paint_mirror_", "chrome_trim_"):
                    q.material = shared("trim_grey", trim)
                    q.part = "chrome"
        elif t == "one_glass":
            glass = next((q.material for q in parts if q.part == "window"), None)
            for q in parts:
                if glass is not None and q.part == "window":
                    q.material = shared("glass", glass)
        elif t == "glass_looks":
            grey = float(r.choice([r.uniform(0.0, 0.2), r.uniform(0.5, 0.95)]))
            rgb = np.clip(grey + r.uniform(-0.08, 0.08, 3), 0, 1)
            alpha = float(r.uniform(0.1, 0.7)) if r.random() < 0.7 else 1.0
            mode = "BLEND" if alpha < 1 and r.random() < 0.6 else "OPAQUE"
            looks = dict(base_color=(*(float(x) for x in rgb), alpha), alpha_mode=mode,
                         transmission=0.0, metallic=float(r.choice([0.0, 1.0, r.uniform(0, 1)])),
                         roughness=float(r.choice([0.0, 1.0, r.uniform(0, 1)])))
            for q in parts:
                if q.part == "window":
                    q.material = shared(q.material.name, q.material, **looks)
        elif t == "plain_lights":
            for q in parts:
                if q.part == "light" and max(q.material.emissive) > 0:
                    q.material = shared(q.material.name, q.material, emissive=(0.0, 0.0, 0.0))
        elif t == "lamp_variety":
            parts = _lamp_variety(parts, r, shared)
        elif t == "ground_base":
            parts = _ground_base(parts, r)
        elif t == "axles":
            parts = _axles(parts, _trait_rng(r, t))
        elif t == "light_bar":
            parts = _light_bar(parts, _trait_rng(r, t))
        elif t == "plate_looks":
            parts = _plate_looks(parts, _trait_rng(r, t))
        elif t == "no_glass":
            parts = [q for q in parts if q.part != "window"]
        elif t == "inner_shell":
            parts = _inner_shell(parts, _trait_rng(r, t))
        elif t == "mirror_glass":
            parts = _mirror_glass(parts, _trait_rng(r, t))
        elif t == "cartoon":
            parts = _cartoon(parts, _trait_rng(r, t))
        elif t == "wedge":
            parts = _wedge(parts, _trait_rng(r, t))
        elif t == "plastic_trim":
            parts = _plastic_trim(parts, _trait_rng(r, t))
        elif t == "cargo_paint":
            parts = _cargo_paint(parts, _trait_rng(r, t))
        elif t == "meaningless_names":
            renamed: dict[str, str] = {}
            for k, q in enumerate(parts):
                nm = renamed.setdefault(q.material.name, f"Material.{len(renamed) + 1:03d}")
                q.material = shared(nm, q.material)
                q.node = f"Object_{k + 1}"
        elif t == "misleading_names":
            words = {"window": "glass", "light": "lamp", "wheel": "tire", "rim": "rim",
                     "chrome": "chrome", "body": "body", "interior": "interior",
                     "plate": "plate", "other": "part"}
            names = sorted({q.material.name for q in parts})
            lie = set(np.asarray(names)[r.random(len(names)) < 0.25].tolist()) if names else set()
            for q in parts:
                nm = q.material.name
                if nm in lie:
                    wrong = [p for p in PART_NAMES if p != q.part]
                    k = int(np.random.default_rng(list(nm.encode())).integers(len(wrong)))
                    q.material = shared(f"{words[wrong[k]]}_{nm}", q.material)
    return parts


_WHEEL_NODES = ("tyre_", "rim_", "brake_", "calliper_")


def _cartoon(parts: list[Part], r: np.random.Generator) -> list[Part]:
    """Cartoon proportions, as toy and stylised models have them: x scaled by sx (0.72-0.88),
    y by sy (1.1-1.3) about the ground (y = 0); each wheel (tyre, rim, brake parts: nodes
    ending in its tag such as ``FL``) scaled by k (1.15-1.45) in x and y about its ground
    contact, which moves with the body; axle rods keep joining the wheel centres."""
    sx, sy = float(r.uniform(0.72, 0.88)), float(r.uniform(1.1, 1.3))
    k = float(r.uniform(1.15, 1.45))
    tyres = {q.node[len("tyre_"):]: _bbox(q) for q in parts if q.node.startswith("tyre_")}
    out = []
    for q in parts:
        v = np.array(q.vertices, np.float64)
        tag = q.node.split("_", 1)[1] if q.node.startswith(_WHEEL_NODES) else None
        if tag in tyres:
            lo, hi = tyres[tag]
            cx, gy = 0.5 * (lo[0] + hi[0]), lo[1]
            v[:, 0] = cx * sx + (v[:, 0] - cx) * k
            v[:, 1] = gy + (v[:, 1] - gy) * k
        elif q.node.startswith("axle_"):
            v[:, 0] = v[:, 0] * sx
            v[:, 1] = v[:, 1] * k
        else:
            v[:, 0] *= sx
            v[:, 1] *= sy
        out.append(Part(q.node, q.part, q.material, v, q.faces))
    return out


def _wedge(parts: list[Part], r: np.random.Generator) -> list[Part]:
    """A wedge body (nose low, tail high): every part but the wheels and axle rods has its
    height above the ground scaled by 1 - k * x / (L / 2) (k 0.08-0.2; x from the middle of
    the length L, positive to the front)."""
    k = float(r.uniform(0.08, 0.2))
    lo = min(float(q.vertices[:, 0].min()) for q in parts)
    hi = max(float(q.vertices[:, 0].max()) for q in parts)
    mid, half = 0.5 * (lo + hi), max(0.5 * (hi - lo), 1e-9)
    out = []
    for q in parts:
        v = np.array(q.vertices, np.float64)
        if not q.node.startswith(_WHEEL_NODES + ("axle_",)):
            v[:, 1] *= 1.0 - k * (v[:, 0] - mid) / half
        out.append(Part(q.node, q.part, q.material, v, q.faces))
    return out


def _trait_rng(r: np.random.Generator, trait: str) -> np.random.Generator:
    """A generator of its own for one realism trait: seeded from the seed of ``r`` (not its
    state) and the trait's name, so the draws of one trait do not move another's."""
    entropy = np.atleast_1d(r.bit_generator.seed_seq.entropy).tolist()   # type: ignore[attr-defined]
    return np.random.default_rng([*entropy, int.from_bytes(trait.encode()[:8], "little")])


def _opaque_glass(parts: list[Part], r: np.random.Generator, shared) -> list[Part]:
    """Opaque windows as simulator and game models paint them: one colour for all windows, or
    (half of the vehicles) one per window material with a left/right pair alike; each colour is
    the light blue of the first recipe half of the time, else a blue, blue-grey or grey of
    lightness 0.2-0.9. The windows keep their materials and their gloss."""
    each = r.random() < 0.5

    def look() -> dict:
        if r.random() < 0.5:
            return dict(base_color=(0.55, 0.7, 0.85, 1.0))
        light, blue = float(r.uniform(0.2, 0.9)), float(r.uniform(0.0, 0.25))
        rgb = np.clip([light - blue, light - 0.4 * blue, light + 0.3 * blue], 0.0, 1.0)
        return dict(base_color=(*(float(x) for x in rgb), 1.0))

    common = look()
    looks: dict[str, dict] = {}
    for q in parts:
        if q.part == "window":
            pair = q.material.name.removesuffix("_L").removesuffix("_R")   # a pair alike
            if pair not in looks:
                looks[pair] = look() if each else common
            q.material = shared(q.material.name, q.material, alpha_mode="OPAQUE",
                                transmission=0.0, **looks[pair])
    return parts


def _axles(parts: list[Part], r: np.random.Generator) -> list[Part]:
    """A rod (a thin box) between the two wheels of every axle, from one tyre's inner face to
    the other's, at the wheel centre or just under the floor when the floor is lower (so it can
    be seen between the wheels, as in game and simulator models), and on half of the vehicles
    two frame rails under the floor between the first and the last axle: one material, dark
    grey or black metal or plastic, part ``other``."""
    tyres = {q.node: _bbox(q) for q in parts if q.node.startswith("tyre_")}
    pairs = [(tyres[n], tyres[n[:-1] + "L"]) for n in sorted(tyres)
             if n.endswith("R") and n[:-1] + "L" in tyres]
    if not pairs:
        return parts
    floor = min((_bbox(q)[0][1] for q in parts if q.node == "underbody"), default=np.inf)
    g = float(r.uniform(0.02, 0.35))
    mat = Material("axle" if r.random() < 0.5 else "chassis_frame",
                   (g, g, g * float(r.uniform(0.95, 1.1)), 1.0), "OPAQUE",
                   float(r.choice([0.0, 1.0, r.uniform(0, 1)])), float(r.uniform(0.3, 1.0)))
    out = list(parts)
    xs = []
    for k, ((lo_r, hi_r), (_lo_l, hi_l)) in enumerate(pairs):
        cx = 0.5 * (lo_r[0] + hi_r[0])
        t = float(r.uniform(0.06, 0.16)) * (hi_r[1] - lo_r[1]) / 2
        cy = min(0.5 * (lo_r[1] + hi_r[1]), floor - 1.2 * t)
        v, f = box([cx - t, cy - t, hi_l[2]], [cx + t, cy + t, lo_r[2]], 0.2)
        out.append(Part(f"axle_{k}", "other", mat, v, f))
        xs.append(cx)
    if len(xs) >= 2 and np.isfinite(floor) and r.random() < 0.5:
        half = 0.5 * (min(p[0][0][2] for p in pairs) - max(p[1][1][2] for p in pairs))
        zr = float(r.uniform(0.25, 0.6)) * half
        h = float(r.uniform(0.06, 0.15))
        for side, tag in ((1.0, "R"), (-1.0, "L")):
            v, f = box([min(xs) - 0.3, floor - h, side * zr - 0.04],
                        [max(xs) + 0.3, floor - 0.002, side * zr + 0.04], 0.3)
            out.append(Part(f"frame_rail_{tag}", "other", mat, v, f))
    return out


def _light_bar(parts: list[Part], r: np.random.Generator) -> list[Part]:
    """An emergency light bar across the front of the roof: 60-95 % of the roof's width, in one
    colour or two halves (blue, red, amber), opaque or see-through, glowing or not; part
    ``light``, on a black base (part ``chrome``, the trim policy) half of the time."""
    roof = next((q for q in parts if q.node == "paint_roof"), None)
    if roof is None:
        return parts
    lo, hi = _bbox(roof)
    width = (hi[2] - lo[2]) * float(r.uniform(0.6, 0.95))
    depth, height = float(r.uniform(0.18, 0.32)), float(r.uniform(0.07, 0.16))
    x1 = hi[0] - float(r.uniform(0.05, 0.4)) * (hi[0] - lo[0])
    palette = {"blue": (0.1, 0.2, 0.95), "red": (0.95, 0.05, 0.05), "amber": (1.0, 0.55, 0.0)}
    picks = list(r.choice(list(palette), size=2, replace=False))
    colours = picks[:1] if r.random() < 0.4 else picks
    alpha = float(r.uniform(0.4, 0.9)) if r.random() < 0.4 else 1.0
    glow = r.random() < 0.5
    out = list(parts)
    y0 = hi[1]
    if r.random() < 0.5:
        v, f = box([x1 - depth - 0.02, y0, -width / 2 - 0.02], [x1 + 0.02, y0 + 0.03,
                                                                width / 2 + 0.02], 0.1)
        out.append(Part("light_bar_base", "chrome",
                         Material("light_bar_base", (0.03, 0.03, 0.03, 1.0), "OPAQUE", 0.0, 0.6),
                         v, f))
        y0 += 0.03
    for k, c in enumerate(colours):
        z0 = -width / 2 + k * width / len(colours)
        rgb = palette[c]
        mat = Material(f"light_bar_{c}", (*rgb, alpha), "BLEND" if alpha < 1 else "OPAQUE",
                       0.0, 0.1, tuple(0.9 * x for x in rgb) if glow else (0.0, 0.0, 0.0))
        v, f = box([x1 - depth, y0, z0], [x1, y0 + height, z0 + width / len(colours)], 0.1)
        out.append(Part(f"light_bar_{k}", "light", mat, v, f))
    return out


def _plate_looks(parts: list[Part], r: np.random.Generator) -> list[Part]:
    """Number plates as real libraries make them: one material for both, white, yellow, black
    or dark grey (an untextured export), textured a third of the time, any gloss; US (about
    2:1) or EU (about 4.7:1) proportions; no front plate a quarter of the time."""
    look = int(r.integers(4))
    rgb = [(0.92, 0.92, 0.88), (0.95, 0.8, 0.1), (0.03, 0.03, 0.03),
           tuple(float(x) for x in np.full(3, r.uniform(0.1, 0.35)))][look]
    mat = Material("plate", (*rgb, 1.0), "OPAQUE", float(r.choice([0.0, r.uniform(0, 1)])),
                   float(r.uniform(0.1, 1.0)), has_texture=bool(r.random() < 0.33))
    us = r.random() < 0.5
    drop_front = r.random() < 0.25
    out = []
    for q in parts:
        if not q.node.startswith("plate_"):
            out.append(q)
            continue
        if drop_front and q.node == "plate_front":
            continue
        lo, hi = _bbox(q)
        c = 0.5 * (lo + hi)
        scale = np.array([1.0, 1.4, 0.6]) if us else np.array([1.0, 1.0, 1.0])
        out.append(Part(q.node, "plate", mat, (q.vertices - c) * scale + c, q.faces))
    return out


def _inner_shell(parts: list[Part], r: np.random.Generator) -> list[Part]:
    """The cabin lined inside as real models line it (head liner, pillar trims, door cards):
    the roof, pillar, door, sill and side panels shrunk toward the body's centre by 2-6 cm on
    each axis and turned inside out, in an interior material, the interior's own half of the
    time, else a liner of its own (black, grey or beige). Part ``interior``, so the interior
    reaches the roof and the body's sides and is seen through every window. Nothing is added
    to a vehicle without an interior."""
    cabin = ("paint_roof", "paint_pillar", "paint_door", "paint_window_sill", "paint_side",
             "paint_rear_frame", "paint_roof_rail")
    inner = next((q.material for q in parts if q.part == "interior"), None)
    panels = [q for q in parts if q.part == "body" and q.node.startswith(cabin)]
    if inner is None or not panels:
        return parts
    if r.random() >= 0.5:
        tone = [(0.03, 0.03, 0.03), (0.15, 0.15, 0.16), (0.45, 0.45, 0.45), (0.6, 0.52, 0.4)]
        rgb = np.clip(np.asarray(tone[int(r.integers(len(tone)))]) * r.uniform(0.8, 1.2, 3),
                      0.0, 1.0)
        inner = Material("interior_liner", (*(float(x) for x in rgb), 1.0), "OPAQUE",
                         float(r.uniform(0.0, 0.2)), float(r.uniform(0.5, 1.0)))
    body = np.concatenate([q.vertices for q in parts if q.part == "body"])
    lo, hi = body.min(axis=0), body.max(axis=0)
    c, half = 0.5 * (lo + hi), np.maximum(0.5 * (hi - lo), 0.2)
    scale = 1.0 - float(r.uniform(0.02, 0.06)) / half
    out = list(parts)
    for q in panels:
        out.append(Part(f"interior_liner_{q.node[len('paint_'):]}", "interior", inner,
                         c + (q.vertices - c) * scale, q.faces[:, ::-1].copy()))
    return out


def _mirror_glass(parts: list[Part], r: np.random.Generator) -> list[Part]:
    """A reflective glass behind the rear face of each door mirror housing (a plate 8 mm thick,
    2 mm off the housing, inset 1-2 cm from its edges): metallic, glossy, light grey or
    faintly cyan; part ``chrome`` (the label policy for mirror glass, docs/CONVENTIONS.md)."""
    grey = float(r.uniform(0.55, 0.95))
    mat = Material("mirror_glass", (grey - float(r.uniform(0.0, 0.1)), grey, grey, 1.0),
                   "OPAQUE", float(r.choice([1.0, r.uniform(0.5, 1.0)])),
                   float(r.uniform(0.0, 0.25)))
    inset = float(r.uniform(0.01, 0.02))
    out = list(parts)
    for q in parts:
        if not q.node.startswith("paint_mirror_"):
            continue
        lo, hi = _bbox(q)
        v, f = box([lo[0] - 0.01, lo[1] + inset, lo[2] + inset],
                    [lo[0] - 0.002, hi[1] - inset, hi[2] - inset], 0.1)
        out.append(Part(f"mirror_glass_{q.node[-1]}", "chrome", mat, v, f))
    return out


def _plastic_trim(parts: list[Part], r: np.random.Generator) -> list[Part]:
    """Trim as low-poly game kits build it: one neutral grey plastic (linear grey 0.04-0.3,
    any metallic, roughness 0.4-1) on the grille, the bumpers (made 40-75 % of the height
    from their bottom to the belt line tall, kept below the lamps), the mirror housings, the
    side trim and a cladding strip 10-25 cm tall along each sill between the wheel arches;
    on a truck also the side panels under the cargo box (the chassis' sides), and on 40 % of
    the vehicles the underbody. Part ``chrome`` (the trim policy), the underbody ``other``:
    the material's truth is its majority part (``majority_part``)."""
    g = float(r.uniform(0.04, 0.3))
    mat = Material("plastic", (g, g, g * float(r.uniform(0.97, 1.05)), 1.0), "OPAQUE",
                   float(r.choice([0.0, 1.0, r.uniform(0, 1)])), float(r.uniform(0.4, 1.0)))
    tall, clad, under = float(r.uniform(0.4, 0.75)), float(r.uniform(0.1, 0.25)), r.random() < 0.4
    truck = any(q.node == "cargo_box" for q in parts)
    nodes = {q.node: q for q in parts}
    sides = [q for q in parts if q.node.startswith(("paint_door", "paint_fender"))]
    belt = max((_bbox(q)[1][1] for q in sides), default=None)
    lamp = min((_bbox(q)[0][1] for q in parts if q.node.startswith("headlight_")),
               default=np.inf)
    out = []
    for q in parts:
        if q.node.startswith(("grille", "paint_mirror_", "chrome_trim_")) or (
                truck and q.node.startswith("paint_side_")):
            out.append(Part(q.node, "chrome", mat, q.vertices, q.faces))
        elif q.node.startswith("bumper_") and belt is not None:
            lo, hi = _bbox(q)
            top = max(min(lo[1] + tall * (belt - lo[1]), lamp - 0.02), hi[1])
            v = np.array(q.vertices, np.float64)
            v[:, 1] = lo[1] + (v[:, 1] - lo[1]) * (top - lo[1]) / max(hi[1] - lo[1], 1e-9)
            out.append(Part(q.node, "chrome", mat, v, q.faces))
        elif q.node == "underbody" and under:
            out.append(Part(q.node, "other", mat, q.vertices, q.faces))
        else:
            out.append(q)
    floor, bumper = nodes.get("underbody"), nodes.get("bumper_front")
    if floor is None or bumper is None:
        return out
    lo, hi = _bbox(floor)
    hw = float(_bbox(bumper)[1][2]) + 0.03
    arches = sorted((float(a[0][0] + a[1][0]) / 2, float(a[1][1] - a[0][1]) / 2)
                    for a in (_bbox(q) for q in parts if q.node.startswith("tyre_")))
    edges = [float(lo[0]) + 0.05]
    for cx, rad in arches:
        edges += [cx - rad - 0.06, cx + rad + 0.06]
    edges.append(float(hi[0]) - 0.05)
    for k in range(0, len(edges) - 1, 2):
        a, b = edges[k], edges[k + 1]
        if b - a < 0.15:
            continue
        v, f = box([a, lo[1] - 0.01, hw - 0.01], [b, lo[1] + clad, hw + 0.025], 0.15)
        out.append(Part(f"cladding_{k // 2}_R", "chrome", mat, v, f))
        out.append(Part(f"cladding_{k // 2}_L", "chrome", mat,
                        v * [1.0, 1.0, -1.0], f[:, ::-1].copy()))
    return out


def _cargo_paint(parts: list[Part], r: np.random.Generator) -> list[Part]:
    """A second paint on the load space, as cargo trucks and pickups are painted: a truck's
    cargo box, or a pickup's bed (sides, floor, front wall, tailgate), in one material of its
    own: half of the time a neutral (white, grey or silver, grey 0.25-0.95, metallic a third
    of the time), else a colour at least 0.35 from the first paint (RGB, any channel). On half
    of the trucks the box's upper 30-70 % is a canvas cover (bulging 3 cm) of a third, dull
    colour (khaki, olive, grey or a random one). Part ``body``; a vehicle without a load space is
    unchanged."""
    load = ("cargo_box", "paint_bed_", "paint_tailgate")
    if not any(q.node.startswith(load) for q in parts):
        return parts
    paint = next((q.material for q in parts if q.part == "body"
                  and q.material.name.startswith("paint")), None)
    first = np.asarray(paint.base_color[:3]) if paint is not None else np.full(3, 0.5)
    if r.random() < 0.5:
        rgb = np.clip(r.uniform(0.25, 0.95) * (1.0 + r.uniform(-0.04, 0.04, 3)), 0.0, 1.0)
        metal = float(r.uniform(0.5, 1.0)) if r.random() < 1 / 3 else 0.0
    else:
        for _ in range(8):
            rgb = r.uniform(0, 1, 3)
            if np.abs(rgb - first).max() > 0.35:
                break
        metal = float(r.choice([0.0, r.uniform(0, 1)]))
    mat = Material("paint_cargo", (*(float(x) for x in rgb), 1.0), "OPAQUE", metal,
                   float(r.uniform(0.3, 1.0)))
    dull = [(0.45, 0.4, 0.25), (0.22, 0.27, 0.13), (0.33, 0.33, 0.31),
            tuple(float(x) for x in r.uniform(0.1, 0.5, 3))][int(r.integers(4))]
    cover = Material("cargo_cover", (*dull, 1.0), "OPAQUE", 0.0, float(r.uniform(0.8, 1.0)))
    split = float(r.uniform(0.3, 0.7)) if r.random() < 0.5 else None
    out = []
    for q in parts:
        if not q.node.startswith(load):
            out.append(q)
        elif q.node == "cargo_box" and split is not None:
            lo, hi = _bbox(q)
            y = float(hi[1] - split * (hi[1] - lo[1]))
            out.append(Part(q.node, "body", mat, *box(lo, [hi[0], y, hi[2]], 0.15)))
            out.append(Part("cargo_cover", "body", cover, *box([lo[0], y, lo[2]], hi, 0.15,
                                                                0.03)))
        else:
            out.append(Part(q.node, "body", mat, q.vertices, q.faces))
    return out


def _bbox(q: Part) -> tuple[np.ndarray, np.ndarray]:
    return q.vertices.min(axis=0), q.vertices.max(axis=0)


def _brake_discs(parts: list[Part]) -> list[Part]:
    """Rims become rings (their faces nearer than 55 % of the rim radius to the axle are
    dropped); a grey disc and a red calliper sit behind each, part ``other``."""
    out = []
    disc_mat = Material("brake_disc", (0.35, 0.35, 0.36, 1.0), "OPAQUE", 1.0, 0.45)
    cal_mat = Material("brake_calliper", (0.6, 0.05, 0.04, 1.0), "OPAQUE", 0.0, 0.4)
    for q in parts:
        if not (q.node.startswith("rim_") and q.part == "rim"):
            out.append(q)
            continue
        lo, hi = _bbox(q)
        cx, cy = 0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1])
        R = 0.5 * (hi[1] - lo[1])
        cen = q.vertices[q.faces].mean(axis=1)
        keep = np.hypot(cen[:, 0] - cx, cen[:, 1] - cy) >= 0.55 * R
        v, f = compact(q.vertices, q.faces[keep])
        out.append(Part(q.node, q.part, q.material, v, f))
        side = 1.0 if hi[2] > 0 else -1.0
        z_in = lo[2] if side > 0 else hi[2]               # the rim's inner edge
        za, zb = z_in + side * 0.01, z_in + side * 0.035
        dv, df = revolve(np.array([[0.0, 0.0], [0.8 * R, 0.0], [0.8 * R, 0.025], [0.0, 0.025]]),
                          32, [cx, cy, min(za, zb)])
        tag = q.node[len("rim_"):]
        out.append(Part(f"brake_disc_{tag}", "other", disc_mat, dv, df))
        cv, cf = box([cx - 0.12 * R, cy + 0.45 * R, min(za, zb) - 0.02],
                      [cx + 0.12 * R, cy + 0.75 * R, max(za, zb) + 0.01], 0.05)
        out.append(Part(f"brake_calliper_{tag}", "other", cal_mat, cv, cf))
    return out


def _lens_lamps(parts: list[Part]) -> list[Part]:
    """Every lamp gets a clear lens box around it (1 cm larger on every side), part light."""
    out = []
    lens = Material("lamp_lens", (0.9, 0.9, 0.9, 0.25), "BLEND", 0.0, 0.05, transmission=0.9)
    for q in parts:
        out.append(q)
        if q.part == "light" and not q.node.startswith("lens_"):
            lo, hi = _bbox(q)
            v, f = box(lo - 0.01, hi + 0.01, 0.05)
            out.append(Part(f"lens_{q.node}", "light", lens, v, f))
    return out


def _lamp_variety(parts: list[Part], r: np.random.Generator, shared) -> list[Part]:
    """Indicators, tinted lenses and reflectors on the head and tail lamps (``apply_realism``).
    ``shared(name, like, **changes)`` gives one material per name (lamps of a kind share it)."""
    amber = Material("indicator", (0.95, 0.45, 0.04, 1.0), "OPAQUE", 0.0, 0.2,
                     (0.9, 0.4, 0.0) if r.random() < 0.5 else (0.0, 0.0, 0.0))
    red_lens = r.random() < 0.6
    clear_head = r.random() < 0.6
    refl = Material("reflector", (0.8, 0.8, 0.82, 1.0), "OPAQUE", 1.0, 0.1)
    out = []
    for q in parts:
        head, tail = q.node.startswith("headlight_"), q.node.startswith("taillight_")
        if not (q.part == "light" and (head or tail)):
            out.append(q)
            continue
        lo, hi = _bbox(q)
        side = 1.0 if hi[2] + lo[2] > 0 else -1.0
        size = hi - lo
        if (tail and red_lens) or (head and clear_head):
            lens = (shared("taillight_glass", q.material, base_color=(0.7, 0.04, 0.03, 0.45),
                           alpha_mode="BLEND", transmission=0.6, metallic=0.0, roughness=0.05)
                    if tail else
                    shared("headlight_glass", q.material, base_color=(0.92, 0.92, 0.95, 0.25),
                           alpha_mode="BLEND", transmission=0.9, metallic=0.0, roughness=0.05,
                           emissive=(0.0, 0.0, 0.0)))
            out.append(Part(q.node, "light", lens, q.vertices, q.faces))
            ilo, ihi = lo + 0.2 * size, hi - 0.2 * size
            v, f = box(ilo, ihi, max(float(size.max()) / 3, 0.02))
            out.append(Part(f"reflector_{q.node}", "light",
                             shared("reflector", refl), v, f))
        else:
            out.append(q)
        # indicator beside the lamp on the outer side, the lamp's depth, the lower 60 % height
        z0 = hi[2] + 0.005 if side > 0 else lo[2] - 0.005 - 0.08
        v, f = box([lo[0], lo[1], z0], [hi[0], lo[1] + 0.6 * size[1], z0 + 0.08], 0.04)
        out.append(Part(f"indicator_{q.node}", "light", shared("indicator", amber), v, f))
    return out


def _two_tone(parts: list[Part], r: np.random.Generator, shared) -> list[Part]:
    """A second paint on a group of body panels (``apply_realism``): the roof and pillars, the
    panels below the belt line, or every other panel; its colour differs from the first paint
    in lightness or hue (a random colour at least 0.35 away in RGB)."""
    paint = [q for q in parts if q.part == "body" and q.material.name.startswith("paint")]
    if not paint:
        return parts
    first = np.asarray(paint[0].material.base_color[:3])
    for _ in range(8):
        rgb = r.uniform(0, 1, 3)
        if np.abs(rgb - first).max() > 0.35:
            break
    mode = int(r.integers(3))
    lo = np.min([_bbox(q)[0] for q in parts], axis=0)
    hi = np.max([_bbox(q)[1] for q in parts], axis=0)
    belt = lo[1] + 0.45 * (hi[1] - lo[1])
    for k, q in enumerate(paint):
        pick = (("roof" in q.node or "pillar" in q.node or "rail" in q.node) if mode == 0
                else bool(_bbox(q)[1][1] < belt + 0.02 * (hi[1] - lo[1])) if mode == 1
                else k % 2 == 1)
        if pick:
            q.material = shared("paint_second", q.material,
                                base_color=(*(float(x) for x in rgb), 1.0))
    return parts


def _ground_base(parts: list[Part], r: np.random.Generator) -> list[Part]:
    """A base under the vehicle (``apply_realism``): a ground plane or a sagging cloth (one
    upward-facing sheet, coarse or finely tessellated) or a low plinth (a box), 1.2-3 times the
    vehicle's length and width, top just below the tyres; textured half of the time."""
    lo = np.min([_bbox(q)[0] for q in parts], axis=0)
    hi = np.max([_bbox(q)[1] for q in parts], axis=0)
    size = hi - lo
    cen = 0.5 * (lo + hi)
    kx, kz = r.uniform(1.2, 3.0, 2)
    half = np.array([0.5 * kx * size[0], 0.0, 0.5 * max(kz * size[2], 1.1 * size[0] * 0.5)])
    style = int(r.integers(3))                      # 0 plane, 1 plinth, 2 cloth
    thick = float(r.uniform(0.05, 0.3)) * size[1]    # the plinth's height (drawn for every style)
    top = lo[1] - 0.002
    if style == 1:
        v, f = box([cen[0] - half[0], top - thick, cen[2] - half[2]],
                    [cen[0] + half[0], top, cen[2] + half[2]], max(float(half.max()) / 6, 0.1))
    else:                                           # one-sided sheet facing up, any tessellation
        x0, x1, z0, z1 = cen[0] - half[0], cen[0] + half[0], cen[2] - half[2], cen[2] + half[2]
        v, f = patch([x0, top, z0], [x0, top, z1], [x1, top, z0], [x1, top, z1], [0, 1], [0, 1],
                      float(half.max()) / float(r.uniform(6.0, 40.0)))["panel"]
    if style == 2:                                  # cloth: edges hang down to 1.2 x the height
        d = np.maximum(np.abs(v[:, 0] - cen[0]) / half[0], np.abs(v[:, 2] - cen[2]) / half[2])
        v = v.copy()
        v[:, 1] -= np.clip(d - 0.6, 0, None) / 0.4 * 1.2 * size[1]
    g = float(r.uniform(0.1, 0.9))
    tint = np.clip(g + r.uniform(-0.1, 0.1, 3), 0, 1)
    mat = Material("ground" if style == 0 else ("base" if style == 1 else "fabric"),
                   (*(float(x) for x in tint), 1.0), "OPAQUE", 0.0, float(r.uniform(0.5, 1.0)),
                   has_texture=bool(r.random() < 0.5))
    return list(parts) + [Part("ground_base", "other", mat, v, f)]


def _rich_interior(parts: list[Part], r: np.random.Generator) -> list[Part]:
    """Steering wheel (a torus facing forward), door panels and a second leather for seats."""
    seats = [q for q in parts if q.node.startswith("interior_seat")]
    dash = next((q for q in parts if q.node == "interior_dashboard"), None)
    if dash is None:
        return parts
    leather = Material("leather_seats", tuple(float(x) for x in r.uniform(0.05, 0.5, 3))
                       + (1.0,), "OPAQUE", 0.0, 0.7)
    for q in seats:
        q.material = leather
    lo, hi = _bbox(dash)
    ring_r, tube = 0.17, 0.02
    th = np.linspace(0, 2 * np.pi, 13)[:-1]
    prof = np.stack([ring_r + tube * np.cos(th), tube * np.sin(th)], 1)
    v, f = revolve(np.vstack([prof, prof[:1]]), 32, [0.0, 0.0, 0.0])
    v = np.stack([v[:, 2], v[:, 1], v[:, 0]], 1)           # axis along x: faces the driver
    f = f[:, ::-1]
    zc = 0.5 * (lo[2] + hi[2]) + 0.3 * (hi[2] - lo[2])
    v = v + [lo[0] - 0.05, hi[1] + 0.05, zc]
    wheel = Material("steering_wheel", (0.05, 0.05, 0.05, 1.0), "OPAQUE", 0.0, 0.6)
    out = list(parts) + [Part("interior_steering_wheel", "interior", wheel, v, f)]
    panel = Material("door_panel", (0.3, 0.28, 0.25, 1.0), "OPAQUE", 0.0, 0.8)
    for side in (1.0, -1.0):
        z = side * (hi[2] + 0.03)
        pv, pf = box([lo[0] - 1.2, lo[1] - 0.2, min(z, z + side * 0.03)],
                      [lo[0] - 0.1, hi[1], max(z, z + side * 0.03)], 0.1)
        out.append(Part(f"interior_door_panel_{'R' if side > 0 else 'L'}", "interior", panel,
                         pv, pf))
    return out
