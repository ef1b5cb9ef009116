"""The parametric vehicle: dimensions per kind (metres, x from rear to front), the parts of the
body, glazing, wheels, lights, plates, trim and interior (``VehicleBuilder``), and
``finish``: the messy traits, the pose and the scene written as GLB with its truth.
"""
from __future__ import annotations

import numpy as np

from .materials import make_material
from .shapes import Part, box, merge, mirror, patch, revolve

# --------------------------------------------------------------------------------------------
# the vehicle

def _kind_params(kind: str, r: np.random.Generator) -> dict:
    """Dimensions in metres. x: rear -L/2 .. front +L/2. Greenhouse bottom [c0, c1] at the belt
    line, top [t0, t1] at roof height H; ``axles``: x of the axles, front first."""
    u = r.uniform
    if kind == "sedan":
        L, W, H = u(4.4, 4.9), u(1.75, 1.85), u(1.40, 1.48)
        p = dict(R=u(0.31, 0.34), tw=0.22, clear=0.16, belt=u(0.9, 1.0))
        p.update(c1=L / 2 - u(1.4, 1.6), c0=-L / 2 + u(0.95, 1.1))
        p.update(t1=p["c1"] - 0.75, t0=p["c0"] + 0.55, windows=2, doors=2, rear_glass=True)
        p["axles"] = [L / 2 - 0.9, -L / 2 + 1.0]
    elif kind == "hatchback":
        L, W, H = u(3.9, 4.2), u(1.7, 1.8), u(1.44, 1.52)
        p = dict(R=u(0.29, 0.32), tw=0.2, clear=0.15, belt=u(0.88, 0.95))
        p.update(c1=L / 2 - u(1.1, 1.25), c0=-L / 2 + 0.22)
        doors = int(r.integers(1, 3))
        p.update(t1=p["c1"] - 0.7, t0=p["c0"] + 0.3, windows=doors, doors=doors, rear_glass=True)
        p["axles"] = [L / 2 - 0.8, -L / 2 + 0.7]
    elif kind == "suv":
        L, W, H = u(4.5, 4.9), u(1.85, 1.95), u(1.7, 1.8)
        p = dict(R=u(0.36, 0.39), tw=0.25, clear=0.22, belt=u(1.05, 1.12))
        p.update(c1=L / 2 - u(1.3, 1.4), c0=-L / 2 + 0.2)
        p.update(t1=p["c1"] - 0.65, t0=p["c0"] + 0.15, windows=3, doors=2, rear_glass=True,
                 roof_rails=True)
        p["axles"] = [L / 2 - 0.95, -L / 2 + 1.0]
    elif kind == "van":
        L, W, H = u(4.9, 5.3), u(1.95, 2.0), u(2.0, 2.3)
        p = dict(R=u(0.33, 0.35), tw=0.22, clear=0.18, belt=u(1.0, 1.08))
        p.update(c1=L / 2 - u(0.75, 0.85), c0=-L / 2 + 0.03)
        p.update(t1=p["c1"] - 0.7, t0=p["c0"] + 0.05, windows=3, doors=2, rear_glass=True)
        p["axles"] = [L / 2 - 0.9, -L / 2 + 1.0]
    elif kind == "pickup":
        L, W, H = u(5.2, 5.6), u(1.9, 2.0), u(1.8, 1.9)
        p = dict(R=u(0.37, 0.4), tw=0.26, clear=0.25, belt=u(1.12, 1.18))
        crew = bool(r.integers(0, 2))
        p.update(c1=L / 2 - u(1.45, 1.55))
        p.update(c0=p["c1"] - (2.3 if crew else 1.5))
        p.update(t1=p["c1"] - 0.6, t0=p["c0"] + 0.1, windows=2 if crew else 1,
                 doors=2 if crew else 1, rear_glass=True, bed=True)
        p["axles"] = [L / 2 - 1.0, -L / 2 + 1.2]
    elif kind == "truck":
        L, W, H = u(6.5, 8.5), u(2.35, 2.5), u(3.0, 3.4)
        p = dict(R=u(0.48, 0.52), tw=0.3, clear=0.35, belt=u(1.35, 1.45))
        p.update(c1=L / 2 - 0.15, c0=L / 2 - 2.1)
        p.update(t1=p["c1"] - 0.2, t0=p["c0"], windows=1, doors=1, rear_glass=False,
                 cargo=True, cab_H=u(2.6, 2.8))
        p["axles"] = [L / 2 - 1.2, -L / 2 + 2.9, -L / 2 + 1.6]
    elif kind == "bus":
        L, W, H = u(10.5, 12.5), 2.5, u(3.0, 3.2)
        p = dict(R=u(0.48, 0.52), tw=0.3, clear=0.3, belt=u(1.15, 1.25))
        p.update(c1=L / 2 - 0.05, c0=-L / 2 + 0.05)
        p.update(t1=p["c1"] - 0.15, t0=p["c0"] + 0.05, windows=int(r.integers(6, 10)), doors=1,
                 rear_glass=True)
        p["axles"] = [L / 2 - 2.5, -L / 2 + 3.0]
    else:  # pragma: no cover - checked by make_vehicle
        raise ValueError(kind)
    p.update(kind=kind, L=L, W=W, H=H)
    p.setdefault("cab_H", H)
    return p


class _VehicleBuilder:
    """Builds the part instances of one vehicle in the car frame (see module docstring), one
    named builder per group of parts, all from the proportions of ``_kind_params``. The
    builders run in a fixed order (the order of parts, hence of materials, is part of the
    output); ``d0``/``d1`` (door span) and ``wc``/``wt`` (glazing half-widths) are shared."""

    def __init__(self, kind: str, r: np.random.Generator, res: float):
        self.kind, self.res = kind, res
        self.p = p = _kind_params(kind, r)
        self.cell = 0.08 * max(1.0, p["L"] / 4.6) ** 0.5 / res
        self.seg = max(12, int(round(48 * res)))
        self.paint = tuple(r.uniform(0.05, 0.9, 3))
        self.big = kind in ("truck", "bus", "van")
        self.parts: list[Part] = []

    def add(self, name, part, cls, v, f, pair=False):
        """Add a part; pair=True: (v, f) is the right (+Z) instance named NAME_R / _xR, and the
        left one is its mirror image."""
        if pair:
            vl, fl = mirror(v, f)
            left = name[:-1] + "L"
            self.parts.append(Part(left, part, make_material(left, cls, self.paint), vl, fl))
        self.parts.append(Part(name, part, make_material(name, cls, self.paint), v, f))

    def lower_body(self) -> None:
        """Belt-line top, side panels (doors, fenders), nose, grille, tail, underbody, bed or
        cargo box."""
        p, kind, add = self.p, self.kind, self.add
        L, R, clear, belt, c0, c1 = p["L"], p["R"], p["clear"], p["belt"], p["c0"], p["c1"]
        xf, xr, hw = L / 2, -L / 2, p["W"] / 2
        cell, big = self.cell, self.big
        bulge_side = 0.01 if big else 0.03
        arch = [(ax, R + 0.04) for ax in p["axles"]]

        def arches(cen):
            d = np.zeros(len(cen), bool)
            for ax, rad in arch:
                d |= (cen[:, 0] - ax) ** 2 + (cen[:, 1] - R) ** 2 < rad ** 2
            return d

        bed_x = c0 - 0.05 if p.get("bed") else None
        cargo_x = c0 - 0.1 if p.get("cargo") else None
        # top (y = belt), u along x from rear to front: trunk | cabin (open) | hood
        xb = [xr]
        for x in sorted([min(max(c0, xr), xf), min(max(c1, xr), xf), xf]):
            if x - xb[-1] > 1e-6:
                xb.append(x)
        ub = [(x - xr) / L for x in xb]

        def top_label(i, j):
            x_mid = xr + 0.5 * (ub[i] + ub[i + 1]) * L
            if x_mid > c1:
                return "paint_hood"
            if x_mid < c0:
                if p.get("bed") or p.get("cargo"):
                    return None
                return "paint_trunk" if kind == "sedan" else "paint_rear_deck"
            return None
        for n, (v, f) in patch([xr, belt, hw], [xf, belt, hw], [xr, belt, -hw], [xf, belt, -hw],
                                ub, [0, 1], cell, 0.0 if big else 0.04, top_label).items():
            add(n, "body", "paint", v, f)
        # sides (right side z = +hw; left mirrored): quarter | doors | fender
        d0, d1 = (c0 + 0.05, min(c1 + 0.25, xf - 0.3)) if kind != "bus" else (c1 - 1.6, c1 - 0.4)
        if kind == "truck":
            d0, d1 = c0 + 0.1, c1 - 0.35
        nd = p["doors"]
        xs = [xr, d0] + [d0 + (d1 - d0) * k / nd for k in range(1, nd)] + [d1, xf]
        if bed_x is not None:
            xs = sorted(xs + [bed_x])
        us = [(x - xr) / L for x in xs]
        door_names = (["paint_door_R"] if nd == 1 else ["paint_door_rear_R", "paint_door_front_R"])
        rear_name = "paint_side_R" if big else "paint_quarter_R"

        def side_label(i, j):
            x_mid = xr + 0.5 * (us[i] + us[i + 1]) * L
            if bed_x is not None and x_mid < bed_x:
                return "paint_bed_side_R"
            if x_mid < d0:
                return rear_name
            if x_mid > d1:
                return "paint_fender_R"
            return door_names[min(nd - 1, int((x_mid - d0) / (d1 - d0) * nd))]
        for n, (v, f) in patch([xr, clear, hw], [xf, clear, hw], [xr, belt, hw], [xf, belt, hw],
                                us, [0, 1], cell, bulge_side, side_label, arches).items():
            add(n, "body", "paint", v, f, pair=True)
        # front face (x = xf), u along z: nose | grille | nose, v along y
        zb = [0, 0.3, 0.7, 1]
        yb = [0, 0.45, 0.85, 1]

        def front_label(i, j):
            return "grille" if (i == 1 and j == 1) else "paint_nose"
        fparts = patch([xf, clear, hw], [xf, clear, -hw], [xf, belt, hw], [xf, belt, -hw],
                        zb, yb, cell, 0.0, front_label)
        add("grille", "chrome", "plastic", *fparts["grille"])   # policy: grilles and trim = chrome
        add("paint_nose", "body", "paint", *fparts["paint_nose"])
        # rear face (x = xr): tail panel, or tailgate for pickups
        rname = "paint_tailgate" if p.get("bed") else "paint_tail_panel"
        add(rname, "body", "paint", *patch([xr, clear, -hw], [xr, clear, hw], [xr, belt, -hw],
                                            [xr, belt, hw], [0, 1], [0, 1], cell)["panel"])
        add("underbody", "other", "plastic", *patch([xr, clear, hw], [xr, clear, -hw],
                                                     [xf, clear, hw], [xf, clear, -hw],
                                                     [0, 1], [0, 1], cell * 2)["panel"])
        if bed_x is not None:
            yfl = clear + 0.35
            add("paint_bed_floor", "body", "paint", *patch(
                [xr, yfl, hw - 0.05], [bed_x, yfl, hw - 0.05], [xr, yfl, -hw + 0.05],
                [bed_x, yfl, -hw + 0.05], [0, 1], [0, 1], cell)["panel"])
            add("paint_bed_front", "body", "paint", *patch(
                [bed_x, yfl, -hw], [bed_x, yfl, hw], [bed_x, belt, -hw], [bed_x, belt, hw],
                [0, 1], [0, 1], cell)["panel"])
        if cargo_x is not None:
            add("cargo_box", "body", "paint", *box([xr - 0.02, belt - 0.05, -hw - 0.02],
                                                    [cargo_x, p["H"], hw + 0.02], cell * 1.5))
        self.d0, self.d1 = d0, d1

    def greenhouse(self) -> None:
        """Windshield, rear window, roof, pillars and side windows."""
        p, kind, add = self.p, self.kind, self.add
        H, belt, c0, c1, t0, t1 = p["cab_H"], p["belt"], p["c0"], p["c1"], p["t0"], p["t1"]
        hw = p["W"] / 2
        cell, big = self.cell, self.big
        wc, wt = hw - (0.03 if big else 0.06), hw - (0.06 if big else 0.18)
        add("glass_windshield", "window", "glass", *patch(
            [c1, belt, wc], [c1, belt, -wc], [t1, H, wt], [t1, H, -wt], [0, 1], [0, 1], cell)["panel"])
        back = patch([c0, belt, -wc], [c0, belt, wc], [t0, H, -wt], [t0, H, wt], [0, 1],
                      [0, 0.12, 0.9, 1] if p["rear_glass"] else [0, 1], cell,
                      label=lambda i, j: "glass_rear" if (p["rear_glass"] and j == 1)
                      else "paint_rear_frame")
        for n, (v, f) in back.items():
            add(n, "window" if n.startswith("glass") else "body",
                "glass" if n.startswith("glass") else "paint", v, f)
        add("paint_roof", "body", "paint", *patch(
            [t0, H, wt], [t1, H, wt], [t0, H, -wt], [t1, H, -wt], [0, 1], [0, 1], cell,
            0.015 if big else 0.03)["panel"])
        nw = p["windows"]
        pil = 0.04 if big else 0.06                       # pillar width, fraction of the side
        a_w = 0.02 if big else 0.12                       # A pillar, fraction
        c_w = 0.04 if big else (0.15 if kind == "sedan" else 0.1)
        inner = np.linspace(c_w, 1 - a_w, nw + 1)
        ubr = [0.0, c_w]
        for k in range(1, nw):
            ubr += [inner[k] - pil / 2, inner[k] + pil / 2]
        ubr += [1 - a_w, 1.0]
        vbr = [0.0, 0.06, 0.88, 1.0]
        win_names = (["glass_side_R"] if nw == 1 else
                     ["glass_side_rear_R", "glass_side_front_R"] if nw == 2 else
                     [f"glass_side_{k + 1}_R" for k in range(nw)])

        def gh_label(i, j):
            if j == 0:
                return "paint_window_sill_R"
            if j == 2:
                return "paint_roof_rail_R"
            if i == 0:
                return "paint_pillar_C_R"
            if i == len(ubr) - 2:
                return "paint_pillar_A_R"
            if i % 2 == 1:
                return win_names[(i - 1) // 2]
            return f"paint_pillar_B{i // 2}_R" if nw > 2 else "paint_pillar_B_R"
        for n, (v, f) in patch([c0, belt, wc], [c1, belt, wc], [t0, H, wt], [t1, H, wt], ubr, vbr,
                                cell, 0.0, gh_label).items():
            glass = n.startswith("glass")
            add(n, "window" if glass else "body", "glass" if glass else "paint", v, f, pair=True)
        self.wc, self.wt = wc, wt

    def wheels(self) -> None:
        """Tyres (closed rounded profile) and rims (dished disc, inset 1.5 cm) on every axle."""
        p, add = self.p, self.add
        R, tw = p["R"], p["tw"]
        hw = p["W"] / 2
        seg = self.seg
        res = self.res
        nar = max(2, int(round(3 * res)))
        zc = hw - tw / 2 + 0.02
        rr, cr = 0.62 * R, 0.05
        arc = np.linspace(0, np.pi / 2, nar + 1)
        prof = np.concatenate([
            [[rr, -tw / 2]],
            np.stack([R - cr + cr * np.sin(arc), -tw / 2 + cr - cr * np.cos(arc)], 1),
            np.stack([R - cr + cr * np.cos(arc), tw / 2 - cr + cr * np.sin(arc)], 1),
            [[rr, tw / 2], [rr, -tw / 2]]])
        prof = prof[np.r_[True, np.any(np.abs(np.diff(prof, axis=0)) > 1e-12, axis=1)]]
        af = tw / 2 - 0.015
        rim_prof = np.array([[rr, af - 0.12], [rr, af], [0.85 * rr, af - 0.012],
                             [0.3 * rr, af - 0.004], [0.2 * rr, af - 0.03], [0.0, af - 0.03]])
        axle_tags = ["F", "R", "R2"]
        for ai, ax in enumerate(p["axles"]):
            tag = axle_tags[ai]
            add(f"tyre_{tag}R", "wheel", "tyre", *revolve(prof, seg, [ax, R, zc]), pair=True)
            add(f"rim_{tag}R", "rim", "rim", *revolve(rim_prof, seg, [ax, R, zc]), pair=True)

    def fittings(self) -> None:
        """Lamps, bumpers, plates, chrome trim, roof rails, exhaust, mirrors."""
        p, kind, add = self.p, self.kind, self.add
        H, clear, belt, c1, t0, t1 = p["cab_H"], p["clear"], p["belt"], p["c1"], p["t0"], p["t1"]
        xf, xr, hw = p["L"] / 2, -p["L"] / 2, p["W"] / 2
        cell, seg, big = self.cell, self.seg, self.big
        d0, d1, wc, wt = self.d0, self.d1, self.wc, self.wt
        ly = (belt - 0.2, belt - 0.06) if not big else (clear + 0.35, clear + 0.55)
        add("headlight_R", "light", "headlight",
            *box([xf - 0.04, ly[0], hw - 0.4], [xf + 0.025, ly[1], hw - 0.1], cell / 2), pair=True)
        add("taillight_R", "light", "taillight",
            *box([xr - 0.025, ly[0], hw - 0.35], [xr + 0.04, ly[1], hw - 0.08], cell / 2), pair=True)
        by = (clear + 0.04, clear + 0.28)
        add("bumper_front", "body", "paint" if not big else "plastic",
            *box([xf - 0.05, by[0], -hw + 0.03], [xf + 0.06, by[1], hw - 0.03], cell))
        add("bumper_rear", "body", "paint" if not big else "plastic",
            *box([xr - 0.06, by[0], -hw + 0.03], [xr + 0.05, by[1], hw - 0.03], cell))
        py = clear + 0.16
        add("plate_front", "plate", "plate", *box([xf + 0.06, py - 0.055, -0.26],
                                                  [xf + 0.072, py + 0.055, 0.26], cell / 2))
        add("plate_rear", "plate", "plate", *box([xr - 0.072, py - 0.055, -0.26],
                                                 [xr - 0.06, py + 0.055, 0.26], cell / 2))
        ty = clear + 0.55 * (belt - clear)
        add("chrome_trim_R", "chrome", "chrome",
            *box([d0, ty - 0.015, hw + 0.025], [d1, ty + 0.015, hw + 0.035], cell / 2), pair=True)
        if p.get("roof_rails"):
            add("chrome_roof_rail_R", "chrome", "chrome", *box(
                [t0 + 0.1, H + 0.03, wt - 0.12], [t1 - 0.1, H + 0.06, wt - 0.08], cell / 2), pair=True)
        if kind in ("sedan", "suv", "pickup", "hatchback"):
            ex = np.array([[0.0, -0.12], [0.035, -0.12], [0.035, 0.0], [0.03, 0.0], [0.03, -0.1]])
            v, f = revolve(ex, max(12, seg // 3), [0.0, 0.0, 0.0])
            v = np.stack([-v[:, 2], v[:, 1], v[:, 0]], 1) + [xr - 0.03, clear + 0.02, hw - 0.5]
            add("exhaust_R", "chrome", "chrome", v, f, pair=True)
        my = belt + 0.05
        add("paint_mirror_R", "body", "paint",
            *box([c1 - 0.18, my, wc + 0.02], [c1 - 0.05, my + 0.12, wc + 0.2], cell / 2), pair=True)

    def interior(self) -> None:
        """Floor, dashboard and seats (visible through the glazing)."""
        p, kind, add = self.p, self.kind, self.add
        clear, belt, c0, c1 = p["clear"], p["belt"], p["c0"], p["c1"]
        cell = self.cell
        wc = self.wc
        yfl = clear + (0.35 if kind == "bus" else 0.12)
        ix0, ix1 = (c0 + 0.1, c1 - 0.1)
        add("interior_floor", "interior", "interior", *patch(
            [ix0, yfl, wc - 0.02], [ix1, yfl, wc - 0.02], [ix0, yfl, -wc + 0.02],
            [ix1, yfl, -wc + 0.02], [0, 1], [0, 1], cell * 2)["panel"])
        add("interior_dashboard", "interior", "interior", *box(
            [c1 - 0.55, belt - 0.3, -wc + 0.08], [c1 - 0.12, belt + 0.04, wc - 0.08], cell))

        def seat(x, z0, z1):
            cush = box([x - 0.25, yfl, z0], [x + 0.25, yfl + 0.3, z1], cell)
            backr = box([x - 0.32, yfl + 0.3, z0], [x - 0.2, belt + 0.35, z1], cell)
            return merge([cush, backr])
        row0 = c1 - 1.0
        rows = [row0 - 0.85 * k for k in range(14) if row0 - 0.85 * k - 0.32 > c0 - 0.35]
        for k, x in enumerate(rows):
            if k == 0:
                add("interior_seat_FR", "interior", "interior", *seat(x, 0.12, min(0.65, wc - 0.1)),
                    pair=True)
            elif kind in ("bus", "van"):
                add(f"interior_seat_{k}_R", "interior", "interior",
                    *seat(x, 0.12, min(0.65, wc - 0.1)), pair=True)
            elif k == 1:
                add("interior_seat_rear", "interior", "interior", *seat(x, -wc + 0.15, wc - 0.15))


def build_parts(kind: str, r: np.random.Generator, res: float) -> list[Part]:
    """All part instances of one vehicle, car frame (see module docstring)."""
    b = _VehicleBuilder(kind, r, res)
    for step in (b.lower_body, b.greenhouse, b.wheels, b.fittings, b.interior):
        step()
    return b.parts
