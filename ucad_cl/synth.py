"""Procedural vehicle library: Objaverse-like cars with one material per part instance.

``make_vehicle(seed, kind)`` builds a parametric vehicle (sedan, suv, van, truck, bus, hatchback,
pickup) out of body panels, glazing, tyres, rims, lights, plates, chrome trim and interior boxes.
Every part instance is its own node and its own glTF PBR material with a realistic name
(``paint_door_front_L``, ``glass_windshield``, ``tyre_FL``, ``rim_RR``, ``headlight_L``,
``plate_rear``, ``chrome_trim_R``, ``interior_seat_FL``...), and ``truth["materials"]`` maps
each material name to a part of :data:`ucad_cl.artifacts.PART_NAMES`.

Frames and units:

* Car frame (what a clean GLB stores): metres, +Y up, ground at y = 0, front of the car at +X,
  width along Z, the car's left side at -Z and right side at +Z (left = up x forward). The car is
  exactly mirror-symmetric across z = 0: every right part is the left one with z negated, and
  every ``_L``/``_R`` (``FL``/``FR``...) pair is listed in ``truth["symmetric_pairs"]``.
* Canonical frame (``SynthVehicle.mesh()``): the car frame moved to its bounding-box centre and
  scaled to bounding-box diagonal 1 (``ucad_cl.artifacts``). ``truth["file_to_canonical"]`` maps the
  GLB's coordinates (scene graph flattened) to it, also for the messy variants (rotated, other
  units, large offsets).
* Vertices are rounded to float32 before anything else (the GLB stores float32), so ``mesh()``
  is what a loader of a clean file gets, up to the final float64 normalisation.

Messy traits (``MESSY_TRAITS``) imitate broken real libraries; ``write_library`` gives a share of
the vehicles one each (and sometimes an extra pose trait), recorded in ``truth["messy"]``.
Orientation cases (``make_vehicle(pose=...)``, ``POSES``: one of the 24 axis-aligned rotations,
an arbitrary yaw, a tilt of up to 3 degrees) and body variants (``body=...``, ``BODIES``: a
trailer, both ends alike, two vehicles side by side); ``truth["orientation"]`` always gives the
file-frame up and front directions (and whether the body has a front).
Determinism: everything derives from ``numpy.random.default_rng(seed)``; the same seed gives the
same GLB bytes. Ties (majority part of a merged material) go to the part earlier in PART_NAMES.

Why one module of over 800 lines: its bytes are the training and test data of the labeller and
the orientation stage, and every part, trait and pose draws from seeded streams whose order is
the contract (same seed, same bytes); one file keeps that order visible, and its public surface is
``make_vehicle``, ``write_library`` and the trait tables.
"""
from __future__ import annotations

import hashlib
import itertools
import json
import math
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import trimesh  # noqa: TID253  the generator is trimesh throughout
from trimesh.visual import TextureVisuals  # noqa: TID253
from trimesh.visual.material import PBRMaterial  # noqa: TID253

from .artifacts import PART_NAMES, VEHICLE_KINDS, Material, Mesh

KINDS = VEHICLE_KINDS

#: messy traits: pose/units traits combine with others; the rest are applied alone.
POSE_TRAITS: tuple[str, ...] = ("z_up", "rotated", "units_mm", "units_cm", "units_km", "offset")
MESSY_TRAITS: tuple[str, ...] = POSE_TRAITS + (
    "merged_materials", "single_material", "missing_wheels", "many_materials", "nan_vertex",
    "empty_file", "truncated", "huge")
#: expected_reject code of the traits that make a file unusable
REJECT_OF: dict[str, str] = {"single_material": "too_few_materials", "nan_vertex": "non_finite",
                             "empty_file": "empty", "truncated": "unreadable"}
UNIT_SCALE: dict[str, float] = {"units_mm": 1000.0, "units_cm": 100.0, "units_km": 0.001}
#: orientation cases (``make_vehicle(pose=...)``): one of the 24 axis-aligned rotations, an
#: arbitrary yaw about the up axis, a small tilt (up to 3 degrees) then an arbitrary yaw
POSES: tuple[str, ...] = ("axis", "yaw", "tilt")
MAX_TILT_DEG = 3.0
#: body variants (``make_vehicle(body=...)``): a box trailer behind the vehicle, a body whose
#: two ends are mirror images (no front to find), two vehicles side by side in one file
BODIES: tuple[str, ...] = ("trailer", "symmetric_ends", "two_vehicles")
OFFSET = 1.0e5              # size of the 'offset' trait's translation, in file units
MANY_MATERIALS = 2000       # about how many materials the 'many_materials' trait makes
HUGE_TRIANGLES = 2_000_000  # default triangle count of the 'huge' trait
#: material-realism traits (``apply_realism``), applied in this order
REALISM_TRAITS: tuple[str, ...] = (
    "brake_discs", "lens_lamps", "rich_interior", "no_rims", "chassis_only", "one_paint",
    "paint_rims", "shared_black", "dark_trim", "textured_body", "varied_looks", "mtl_like",
    "opaque_glass", "dark_glass", "two_tone", "one_glass", "glass_looks", "grey_trim",
    "plain_lights", "lamp_variety", "ground_base", "axles", "light_bar", "plate_looks",
    "no_glass", "inner_shell", "mirror_glass", "meaningless_names", "misleading_names")


def make_vehicle(seed: int, kind: str | None = None, *, detail: int = 1,
                 target_triangles: int | None = None, messy: Sequence[str] = (),
                 name: str | None = None, realism: Sequence[str] = (),
                 pose: str | None = None, body: str | None = None) -> "SynthVehicle":
    """Build one vehicle. kind: one of KINDS (random from the seed when None).

    detail: resolution factor (triangles grow ~detail**2; 1 gives ~20-35k triangles).
    target_triangles: overrides detail, tessellates to about this many triangles (within ~10 %).
    messy: traits from MESSY_TRAITS to apply to the file (see module docstring).
    realism: traits from REALISM_TRAITS (how real libraries assign materials; see
    ``apply_realism``), recorded in ``truth["realism"]``.
    pose: one of POSES, the file's rotation (drawn from the seed), after the messy pose traits.
    body: one of BODIES, a body variant. ``truth["orientation"]`` gives the file-frame up and
    front directions in every case.
    """
    if pose is not None and pose not in POSES:
        raise ValueError(f"unknown pose {pose!r}; expected one of {POSES}")
    if body is not None and body not in BODIES:
        raise ValueError(f"unknown body variant {body!r}; expected one of {BODIES}")
    seed = int(seed)
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    if kind is not None and kind not in KINDS:
        raise ValueError(f"unknown vehicle kind {kind!r}; expected one of {KINDS}")
    if int(detail) < 1:
        raise ValueError(f"detail must be >= 1, got {detail}")
    bad = [t for t in messy if t not in MESSY_TRAITS]
    if bad:
        raise ValueError(f"unknown messy trait(s) {bad}; expected some of {MESSY_TRAITS}")
    bad = [t for t in realism if t not in REALISM_TRAITS]
    if bad:
        raise ValueError(f"unknown realism trait(s) {bad}; expected some of {REALISM_TRAITS}")
    if target_triangles is not None and int(target_triangles) < 1000:
        raise ValueError(f"target_triangles must be >= 1000, got {target_triangles}")
    messy = tuple(dict.fromkeys(messy))          # unique, order kept
    if "huge" in messy and target_triangles is None:
        target_triangles = HUGE_TRIANGLES
    kind_rng = np.random.default_rng([seed, 0])
    kind = kind if kind is not None else KINDS[int(kind_rng.integers(len(KINDS)))]

    def build(res: float) -> list[_Part]:
        return _build_parts(kind, np.random.default_rng([seed, 1]), res)

    res = float(detail)
    parts = build(res)
    if target_triangles is not None:                 # triangles grow ~ res**2: two corrections
        for _ in range(3):
            n = sum(len(p.faces) for p in parts)
            if abs(n - target_triangles) <= 0.08 * target_triangles:
                break
            res *= math.sqrt(target_triangles / n)
            parts = build(res)
    realism = tuple(t for t in REALISM_TRAITS if t in realism)     # fixed application order
    parts = apply_realism(parts, realism, np.random.default_rng([seed, 3]))
    if body is not None:
        parts = _body_variant(parts, body, np.random.default_rng([seed, 5]))
    v = _finish(seed, kind, name or f"{kind}_{seed:08d}", parts, messy,
                np.random.default_rng([seed, 2]), pose, np.random.default_rng([seed, 4]), body)
    v.truth["realism"] = list(realism)
    return v


def write_library(out_dir: str | Path, count: int, seed: int, *, messy_fraction: float = 0.3,
                  progress: bool = True, kinds: Sequence[str] | None = None,
                  huge_triangles: int | None = None, detail: int = 1,
                  target_triangles: int | None = None) -> list[Path]:
    """Write ``count`` vehicles as ``NAME.glb`` + ``NAME.json`` (the truth); returns the GLB paths.

    A share ``messy_fraction`` of the vehicles (every k-th, deterministically) gets one messy
    trait, cycling through the traits so that all of them occur, and every other messy vehicle
    also a random pose trait. The 'huge' trait is only used when ``huge_triangles`` is given.
    ``target_triangles`` sizes every other vehicle (e.g. 50,000 for benchmarks).
    Same arguments -> same bytes.
    """
    if count < 0:
        raise ValueError(f"count must be >= 0, got {count}")
    if not 0.0 <= messy_fraction <= 1.0:
        raise ValueError(f"messy_fraction must be in [0, 1], got {messy_fraction}")
    kinds = tuple(kinds) if kinds else KINDS
    bad = [k for k in kinds if k not in KINDS]
    if bad:
        raise ValueError(f"unknown vehicle kind(s) {bad}; expected some of {KINDS}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    traits = [t for t in MESSY_TRAITS if t != "huge" or huge_triangles]
    rng = np.random.default_rng([int(seed), 7])
    vseeds = rng.integers(0, 2**31 - 1, size=count)
    kind_idx = rng.integers(0, len(kinds), size=count)
    extra = rng.integers(0, len(POSE_TRAITS), size=count)
    n_messy = int(round(messy_fraction * count))
    messy_at = set(np.floor(np.arange(n_messy) * (count / max(n_messy, 1))).astype(int).tolist())
    paths: list[Path] = []
    it: Iterable[int] = range(count)
    if progress:
        from tqdm import tqdm
        it = tqdm(it, total=count, desc="synth", unit="car")
    k = 0
    for i in it:
        traits_i: list[str] = []
        if i in messy_at:
            traits_i.append(traits[k % len(traits)])
            if k % 2 == 1 and traits_i[0] not in REJECT_OF:
                traits_i.append(POSE_TRAITS[int(extra[i])])
            k += 1
        kind = kinds[int(kind_idx[i])]
        v = make_vehicle(int(vseeds[i]), kind, detail=detail, messy=traits_i,
                         target_triangles=huge_triangles if "huge" in traits_i else target_triangles,
                         name=f"synth_{i:05d}_{kind}")
        paths.append(v.write(out))
    return paths


def majority_part(face_counts: dict[str, int]) -> str:
    """The part with the most faces; a tie goes to the part earlier in PART_NAMES."""
    bad = [p for p in face_counts if p not in PART_NAMES]
    if bad or not face_counts:
        raise ValueError(f"face_counts must be a non-empty dict over PART_NAMES, got {face_counts}")
    return max(face_counts, key=lambda p: (face_counts[p], -PART_NAMES.index(p)))


@dataclass
class SynthVehicle:
    """A generated vehicle: the trimesh scene as written, its truth and the canonical mesh."""

    name: str
    kind: str
    seed: int
    scene: trimesh.Scene
    truth: dict
    nodes: list = field(repr=False, default_factory=list)   # list[_Part], car frame
    canonical: np.ndarray = field(repr=False, default_factory=lambda: np.eye(4))

    def mesh(self) -> Mesh:
        """The vehicle in the canonical frame, materials and node names as in the file."""
        names: list[str] = []
        mats: list[Material] = []
        index: dict[str, int] = {}
        verts, faces, fmat, fnode = [], [], [], []
        off = 0
        for ni, p in enumerate(self.nodes):
            if p.material.name not in index:
                index[p.material.name] = len(mats)
                mats.append(p.material)
            verts.append(p.vertices)
            faces.append(p.faces + off)
            off += len(p.vertices)
            fmat.append(np.full(len(p.faces), index[p.material.name], np.uint16))
            fnode.append(np.full(len(p.faces), ni, np.int32))
            names.append(p.node)
        v = np.concatenate(verts) if verts else np.zeros((0, 3))
        v = v @ self.canonical[:3, :3].T + self.canonical[:3, 3]
        f = np.concatenate(faces).astype(np.uint32) if faces else np.zeros((0, 3), np.uint32)
        fm = np.concatenate(fmat) if fmat else np.zeros(0, np.uint16)
        h = hashlib.sha256()
        for a in (v, f, fm):
            h.update(np.ascontiguousarray(a).tobytes())
        return Mesh(path=f"{self.name}.glb", sha256=h.hexdigest(), vertices=v, faces=f,
                    face_material=fm, materials=mats,
                    file_to_norm=np.array(self.truth["file_to_canonical"], dtype=np.float64),
                    face_node=np.concatenate(fnode) if fnode else np.zeros(0, np.int32),
                    node_names=names)

    def glb_bytes(self) -> bytes:
        """The file as written: trimesh's GLB, plus KHR_materials_transmission on glass.

        The 'empty_file' and 'truncated' traits return b'' and the first half of the bytes.
        """
        data = _add_transmission(self.scene.export(file_type="glb"),
                                 {p.material.name: p.material.transmission for p in self.nodes})
        if "empty_file" in self.truth["messy"]:
            return b""
        if "truncated" in self.truth["messy"]:
            return data[: len(data) // 2]
        return data

    def write(self, out_dir: str | Path) -> Path:
        """Write ``NAME.glb`` and ``NAME.json`` into out_dir; returns the GLB path."""
        out = Path(out_dir)
        path = out / f"{self.name}.glb"
        path.write_bytes(self.glb_bytes())
        (out / f"{self.name}.json").write_text(json.dumps(self.truth, indent=1, sort_keys=True))
        return path


# --------------------------------------------------------------------------------------------
# materials

class _NamedPBR(PBRMaterial):
    """PBRMaterial whose hash includes its name: trimesh's exporter merges materials with equal
    hashes, and the stock hash ignores the name (all paint panels would become one material)."""

    def __hash__(self) -> int:
        return hash((self.name, super().__hash__()))


def _q8(x: float) -> float:
    """Colours are stored as 8-bit by trimesh: quantise up front so file and truth agree."""
    return round(float(np.clip(x, 0.0, 1.0)) * 255.0) / 255.0


def _material(name: str, cls: str, paint: tuple[float, float, float]) -> Material:
    """Realistic PBR properties per material class (glass, paint, tyre, chrome...)."""
    if cls == "paint":
        return Material(name, (*paint, 1.0), "OPAQUE", 0.5, 0.3)
    if cls == "glass":
        return Material(name, (0.08, 0.1, 0.12, 0.3), "BLEND", 0.0, 0.05, transmission=0.9)
    if cls == "tyre":
        return Material(name, (0.02, 0.02, 0.02, 1.0), "OPAQUE", 0.0, 0.9)
    if cls == "rim":
        return Material(name, (0.75, 0.75, 0.78, 1.0), "OPAQUE", 1.0, 0.2)
    if cls == "chrome":
        return Material(name, (0.95, 0.95, 0.95, 1.0), "OPAQUE", 1.0, 0.05)
    if cls == "headlight":
        return Material(name, (0.9, 0.9, 0.85, 1.0), "OPAQUE", 0.0, 0.1, (1.0, 0.95, 0.8))
    if cls == "taillight":
        return Material(name, (0.6, 0.02, 0.02, 1.0), "OPAQUE", 0.0, 0.15, (0.8, 0.0, 0.0))
    if cls == "plate":
        return Material(name, (0.95, 0.95, 0.9, 1.0), "OPAQUE", 0.0, 0.5)
    if cls == "plastic":
        return Material(name, (0.03, 0.03, 0.03, 1.0), "OPAQUE", 0.0, 0.6)
    if cls == "interior":
        return Material(name, (0.18, 0.16, 0.14, 1.0), "OPAQUE", 0.0, 0.85)
    raise ValueError(f"unknown material class {cls!r}")


def _quantised(m: Material) -> Material:
    return Material(m.name, tuple(_q8(c) for c in m.base_color), m.alpha_mode, float(m.metallic),
                    float(m.roughness), tuple(float(e) for e in m.emissive),
                    float(m.transmission), False)


def _pbr(m: Material) -> _NamedPBR:
    return _NamedPBR(name=m.name, baseColorFactor=list(m.base_color),
                     metallicFactor=float(m.metallic), roughnessFactor=float(m.roughness),
                     emissiveFactor=list(m.emissive) if any(m.emissive) else None,
                     alphaMode=m.alpha_mode, doubleSided=m.alpha_mode == "BLEND")


def _add_transmission(glb: bytes, transmission: dict[str, float]) -> bytes:
    """Add KHR_materials_transmission to the materials with transmission > 0 (trimesh does not
    export it); re-pack the GLB. Deterministic: JSON keys keep trimesh's order."""
    if not any(t > 0 for t in transmission.values()):
        return glb
    (jlen,) = struct.unpack_from("<I", glb, 12)
    tree = json.loads(glb[20:20 + jlen])
    used = False
    for m in tree.get("materials", []):
        t = transmission.get(m.get("name"), 0.0)
        if t > 0:
            m.setdefault("extensions", {})["KHR_materials_transmission"] = {
                "transmissionFactor": t}
            used = True
    if not used:
        return glb
    exts = tree.setdefault("extensionsUsed", [])
    if "KHR_materials_transmission" not in exts:
        exts.append("KHR_materials_transmission")
    js = json.dumps(tree, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    rest = glb[20 + jlen:]
    total = 12 + 8 + len(js) + len(rest)
    return (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<I4s", len(js), b"JSON")
            + js + rest)


# --------------------------------------------------------------------------------------------
# geometry primitives (NumPy, vectorised; faces wound counter-clockwise seen from outside)

@dataclass
class _Part:
    node: str
    part: str
    material: Material
    vertices: np.ndarray      # (N, 3) float64 (float32-exact after _finish)
    faces: np.ndarray         # (F, 3) int64


def _lines(breaks: Sequence[float], length: float, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Grid parameters in [0, 1] through every break, cells of about ``cell`` (same unit as
    length); returns (params, segment index of each cell)."""
    b = np.asarray(breaks, dtype=np.float64)
    ts, seg = [np.zeros(1)], []
    for s in range(len(b) - 1):
        n = max(1, int(math.ceil((b[s + 1] - b[s]) * length / cell - 1e-9)))
        ts.append(b[s] + (b[s + 1] - b[s]) * np.arange(1, n + 1) / n)
        seg.append(np.full(n, s))
    t = np.concatenate(ts)
    t[0], t[-1] = b[0], b[-1]
    return t, np.concatenate(seg)


def _patch(p00, p10, p01, p11, ubreaks, vbreaks, cell, bulge=0.0, label=None, drop=None):
    """Bilinear patch split into named panels.

    Corners p00 (u=0,v=0), p10, p01, p11; normal side = (p10-p00) x (p01-p00). ubreaks/vbreaks:
    panel boundaries in [0, 1]; label(su, sv) -> name or None (dropped). bulge: outward
    displacement (same unit) at the centre, zero on the border. drop(centroids) -> bool mask of
    faces to remove (wheel arches). Returns {name: (V, F)}.
    """
    p00, p10, p01, p11 = (np.asarray(p, dtype=np.float64) for p in (p00, p10, p01, p11))
    lu = max(np.linalg.norm(p10 - p00), np.linalg.norm(p11 - p01))
    lv = max(np.linalg.norm(p01 - p00), np.linalg.norm(p11 - p10))
    us, su = _lines(ubreaks, lu, cell)
    vs, sv = _lines(vbreaks, lv, cell)
    U, V = np.meshgrid(us, vs, indexing="ij")
    P = (((1 - U) * (1 - V))[..., None] * p00 + (U * (1 - V))[..., None] * p10
         + ((1 - U) * V)[..., None] * p01 + (U * V)[..., None] * p11)
    if bulge:
        n = np.cross(p10 - p00, p01 - p00)
        n /= np.linalg.norm(n)
        P += (bulge * (1 - (2 * U - 1) ** 2) * (1 - (2 * V - 1) ** 2))[..., None] * n
    nu, nv = len(us), len(vs)
    idx = np.arange(nu * nv).reshape(nu, nv)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    F = np.stack([np.stack([a, b, c], -1), np.stack([a, c, d], -1)], 2).reshape(-1, 3)
    cu = np.repeat(np.repeat(su[:, None], nv - 1, 1), 2, axis=1).reshape(-1)
    cv = np.repeat(np.repeat(sv[None, :], nu - 1, 0), 2, axis=1).reshape(-1)
    Pf = P.reshape(-1, 3)
    keep = np.ones(len(F), bool)
    if drop is not None:
        keep &= ~drop(Pf[F].mean(axis=1))
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    label = label or (lambda i, j: "panel")
    for i in range(len(ubreaks) - 1):
        for j in range(len(vbreaks) - 1):
            name = label(i, j)
            if name is None:
                continue
            m = keep & (cu == i) & (cv == j)
            if not m.any():
                continue
            sub = _compact(Pf, F[m])
            if name in out:
                sub = _merge([out[name], sub])
            out[name] = sub
    return out


def _compact(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    used, inv = np.unique(F.reshape(-1), return_inverse=True)
    return V[used], inv.reshape(-1, 3)


def _merge(meshes: Sequence[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    vs, fs, off = [], [], 0
    for v, f in meshes:
        vs.append(v)
        fs.append(f + off)
        off += len(v)
    return np.concatenate(vs), np.concatenate(fs)


def _box(lo, hi, cell, bulge=0.0) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box [lo, hi], each face a grid of ~cell; outward winding."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    c = np.array
    faces = [  # (p00, p10, p01, p11) with (p10-p00) x (p01-p00) outward
        (c([x1, y0, z0]), c([x1, y1, z0]), c([x1, y0, z1]), c([x1, y1, z1])),   # +X
        (c([x0, y0, z0]), c([x0, y0, z1]), c([x0, y1, z0]), c([x0, y1, z1])),   # -X
        (c([x0, y1, z0]), c([x0, y1, z1]), c([x1, y1, z0]), c([x1, y1, z1])),   # +Y
        (c([x0, y0, z0]), c([x1, y0, z0]), c([x0, y0, z1]), c([x1, y0, z1])),   # -Y
        (c([x0, y0, z1]), c([x1, y0, z1]), c([x0, y1, z1]), c([x1, y1, z1])),   # +Z
        (c([x0, y0, z0]), c([x0, y1, z0]), c([x1, y0, z0]), c([x1, y1, z0])),   # -Z
    ]
    return _merge([_patch(*f, [0, 1], [0, 1], cell, bulge)["panel"] for f in faces])


def _revolve(profile: np.ndarray, segments: int, center):
    """Surface of revolution about an axis parallel to Z through ``center``.

    profile: (n, 2) points (r, a): radius and axial offset along +Z; the outside is on the right
    of the profile direction (walking outward in r faces -Z). Points with
    r == 0 (first/last only) become one pole vertex (no degenerate triangles).
    """
    prof = np.asarray(profile, dtype=np.float64)
    th = 2 * np.pi * np.arange(segments) / segments
    ct, st = np.cos(th), np.sin(th)
    verts, rings = [], []
    off = 0
    for r, a in prof:
        if r == 0.0:
            verts.append(np.array([[0.0, 0.0, a]]))
            rings.append(np.full(segments, off))
            off += 1
        else:
            verts.append(np.stack([r * ct, r * st, np.full(segments, a)], 1))
            rings.append(off + np.arange(segments))
            off += segments
    faces = []
    for i in range(len(prof) - 1):           # quad (r0, r0n, r1n, r1) -> two triangles;
        r0, r1 = rings[i], rings[i + 1]       # the one touching a pole twice is left out
        r0n, r1n = np.roll(r0, -1), np.roll(r1, -1)
        if prof[i, 0] != 0.0:
            faces.append(np.stack([r0, r0n, r1], 1))
        if prof[i + 1, 0] != 0.0:
            faces.append(np.stack([r1, r0n, r1n], 1))
    V = np.concatenate(verts)
    F = np.concatenate(faces)
    return V + np.asarray(center, dtype=np.float64), F


def _mirror(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reflect across z = 0 (exact: negation) and flip the winding."""
    return v * np.array([1.0, 1.0, -1.0]), f[:, ::-1].copy()


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
        self.parts: list[_Part] = []

    def add(self, name, part, cls, v, f, pair=False):
        """Add a part; pair=True: (v, f) is the right (+Z) instance named NAME_R / _xR, and the
        left one is its mirror image."""
        if pair:
            vl, fl = _mirror(v, f)
            left = name[:-1] + "L"
            self.parts.append(_Part(left, part, _material(left, cls, self.paint), vl, fl))
        self.parts.append(_Part(name, part, _material(name, cls, self.paint), v, f))

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
        for n, (v, f) in _patch([xr, belt, hw], [xf, belt, hw], [xr, belt, -hw], [xf, belt, -hw],
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
        for n, (v, f) in _patch([xr, clear, hw], [xf, clear, hw], [xr, belt, hw], [xf, belt, hw],
                                us, [0, 1], cell, bulge_side, side_label, arches).items():
            add(n, "body", "paint", v, f, pair=True)
        # front face (x = xf), u along z: nose | grille | nose, v along y
        zb = [0, 0.3, 0.7, 1]
        yb = [0, 0.45, 0.85, 1]

        def front_label(i, j):
            return "grille" if (i == 1 and j == 1) else "paint_nose"
        fparts = _patch([xf, clear, hw], [xf, clear, -hw], [xf, belt, hw], [xf, belt, -hw],
                        zb, yb, cell, 0.0, front_label)
        add("grille", "chrome", "plastic", *fparts["grille"])   # policy: grilles and trim = chrome
        add("paint_nose", "body", "paint", *fparts["paint_nose"])
        # rear face (x = xr): tail panel, or tailgate for pickups
        rname = "paint_tailgate" if p.get("bed") else "paint_tail_panel"
        add(rname, "body", "paint", *_patch([xr, clear, -hw], [xr, clear, hw], [xr, belt, -hw],
                                            [xr, belt, hw], [0, 1], [0, 1], cell)["panel"])
        add("underbody", "other", "plastic", *_patch([xr, clear, hw], [xr, clear, -hw],
                                                     [xf, clear, hw], [xf, clear, -hw],
                                                     [0, 1], [0, 1], cell * 2)["panel"])
        if bed_x is not None:
            yfl = clear + 0.35
            add("paint_bed_floor", "body", "paint", *_patch(
                [xr, yfl, hw - 0.05], [bed_x, yfl, hw - 0.05], [xr, yfl, -hw + 0.05],
                [bed_x, yfl, -hw + 0.05], [0, 1], [0, 1], cell)["panel"])
            add("paint_bed_front", "body", "paint", *_patch(
                [bed_x, yfl, -hw], [bed_x, yfl, hw], [bed_x, belt, -hw], [bed_x, belt, hw],
                [0, 1], [0, 1], cell)["panel"])
        if cargo_x is not None:
            add("cargo_box", "body", "paint", *_box([xr - 0.02, belt - 0.05, -hw - 0.02],
                                                    [cargo_x, p["H"], hw + 0.02], cell * 1.5))
        self.d0, self.d1 = d0, d1

    def greenhouse(self) -> None:
        """Windshield, rear window, roof, pillars and side windows."""
        p, kind, add = self.p, self.kind, self.add
        H, belt, c0, c1, t0, t1 = p["cab_H"], p["belt"], p["c0"], p["c1"], p["t0"], p["t1"]
        hw = p["W"] / 2
        cell, big = self.cell, self.big
        wc, wt = hw - (0.03 if big else 0.06), hw - (0.06 if big else 0.18)
        add("glass_windshield", "window", "glass", *_patch(
            [c1, belt, wc], [c1, belt, -wc], [t1, H, wt], [t1, H, -wt], [0, 1], [0, 1], cell)["panel"])
        back = _patch([c0, belt, -wc], [c0, belt, wc], [t0, H, -wt], [t0, H, wt], [0, 1],
                      [0, 0.12, 0.9, 1] if p["rear_glass"] else [0, 1], cell,
                      label=lambda i, j: "glass_rear" if (p["rear_glass"] and j == 1)
                      else "paint_rear_frame")
        for n, (v, f) in back.items():
            add(n, "window" if n.startswith("glass") else "body",
                "glass" if n.startswith("glass") else "paint", v, f)
        add("paint_roof", "body", "paint", *_patch(
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
        for n, (v, f) in _patch([c0, belt, wc], [c1, belt, wc], [t0, H, wt], [t1, H, wt], ubr, vbr,
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
            add(f"tyre_{tag}R", "wheel", "tyre", *_revolve(prof, seg, [ax, R, zc]), pair=True)
            add(f"rim_{tag}R", "rim", "rim", *_revolve(rim_prof, seg, [ax, R, zc]), pair=True)

    def fittings(self) -> None:
        """Lamps, bumpers, plates, chrome trim, roof rails, exhaust, mirrors."""
        p, kind, add = self.p, self.kind, self.add
        H, clear, belt, c1, t0, t1 = p["cab_H"], p["clear"], p["belt"], p["c1"], p["t0"], p["t1"]
        xf, xr, hw = p["L"] / 2, -p["L"] / 2, p["W"] / 2
        cell, seg, big = self.cell, self.seg, self.big
        d0, d1, wc, wt = self.d0, self.d1, self.wc, self.wt
        ly = (belt - 0.2, belt - 0.06) if not big else (clear + 0.35, clear + 0.55)
        add("headlight_R", "light", "headlight",
            *_box([xf - 0.04, ly[0], hw - 0.4], [xf + 0.025, ly[1], hw - 0.1], cell / 2), pair=True)
        add("taillight_R", "light", "taillight",
            *_box([xr - 0.025, ly[0], hw - 0.35], [xr + 0.04, ly[1], hw - 0.08], cell / 2), pair=True)
        by = (clear + 0.04, clear + 0.28)
        add("bumper_front", "body", "paint" if not big else "plastic",
            *_box([xf - 0.05, by[0], -hw + 0.03], [xf + 0.06, by[1], hw - 0.03], cell))
        add("bumper_rear", "body", "paint" if not big else "plastic",
            *_box([xr - 0.06, by[0], -hw + 0.03], [xr + 0.05, by[1], hw - 0.03], cell))
        py = clear + 0.16
        add("plate_front", "plate", "plate", *_box([xf + 0.06, py - 0.055, -0.26],
                                                  [xf + 0.072, py + 0.055, 0.26], cell / 2))
        add("plate_rear", "plate", "plate", *_box([xr - 0.072, py - 0.055, -0.26],
                                                 [xr - 0.06, py + 0.055, 0.26], cell / 2))
        ty = clear + 0.55 * (belt - clear)
        add("chrome_trim_R", "chrome", "chrome",
            *_box([d0, ty - 0.015, hw + 0.025], [d1, ty + 0.015, hw + 0.035], cell / 2), pair=True)
        if p.get("roof_rails"):
            add("chrome_roof_rail_R", "chrome", "chrome", *_box(
                [t0 + 0.1, H + 0.03, wt - 0.12], [t1 - 0.1, H + 0.06, wt - 0.08], cell / 2), pair=True)
        if kind in ("sedan", "suv", "pickup", "hatchback"):
            ex = np.array([[0.0, -0.12], [0.035, -0.12], [0.035, 0.0], [0.03, 0.0], [0.03, -0.1]])
            v, f = _revolve(ex, max(12, seg // 3), [0.0, 0.0, 0.0])
            v = np.stack([-v[:, 2], v[:, 1], v[:, 0]], 1) + [xr - 0.03, clear + 0.02, hw - 0.5]
            add("exhaust_R", "chrome", "chrome", v, f, pair=True)
        my = belt + 0.05
        add("paint_mirror_R", "body", "paint",
            *_box([c1 - 0.18, my, wc + 0.02], [c1 - 0.05, my + 0.12, wc + 0.2], cell / 2), pair=True)

    def interior(self) -> None:
        """Floor, dashboard and seats (visible through the glazing)."""
        p, kind, add = self.p, self.kind, self.add
        clear, belt, c0, c1 = p["clear"], p["belt"], p["c0"], p["c1"]
        cell = self.cell
        wc = self.wc
        yfl = clear + (0.35 if kind == "bus" else 0.12)
        ix0, ix1 = (c0 + 0.1, c1 - 0.1)
        add("interior_floor", "interior", "interior", *_patch(
            [ix0, yfl, wc - 0.02], [ix1, yfl, wc - 0.02], [ix0, yfl, -wc + 0.02],
            [ix1, yfl, -wc + 0.02], [0, 1], [0, 1], cell * 2)["panel"])
        add("interior_dashboard", "interior", "interior", *_box(
            [c1 - 0.55, belt - 0.3, -wc + 0.08], [c1 - 0.12, belt + 0.04, wc - 0.08], cell))

        def seat(x, z0, z1):
            cush = _box([x - 0.25, yfl, z0], [x + 0.25, yfl + 0.3, z1], cell)
            backr = _box([x - 0.32, yfl + 0.3, z0], [x - 0.2, belt + 0.35, z1], cell)
            return _merge([cush, backr])
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


def _build_parts(kind: str, r: np.random.Generator, res: float) -> list[_Part]:
    """All part instances of one vehicle, car frame (see module docstring)."""
    b = _VehicleBuilder(kind, r, res)
    for step in (b.lower_body, b.greenhouse, b.wheels, b.fittings, b.interior):
        step()
    return b.parts


def _finish(seed: int, kind: str, name: str, parts: list[_Part], messy: Sequence[str],
            r: np.random.Generator, pose: str | None = None,
            pose_rng: np.random.Generator | None = None, body: str | None = None
            ) -> SynthVehicle:
    """Round to float32, apply the messy traits, build the trimesh scene and the truth."""
    for q in parts:
        q.vertices = q.vertices.astype(np.float32).astype(np.float64)
        q.material = _quantised(q.material)
    if "missing_wheels" in messy:
        parts = [q for q in parts if q.part not in ("wheel", "rim")]
    allv = np.concatenate([q.vertices for q in parts])
    lo, hi = allv.min(axis=0), allv.max(axis=0)
    canonical = np.eye(4)
    canonical[:3, :3] /= np.linalg.norm(hi - lo)
    canonical[:3, 3] = -(lo + hi) / 2 / np.linalg.norm(hi - lo)

    # node parts (canonical geometry) vs the materials as written
    mat_part_faces: dict[str, dict[str, int]] = {}
    if "many_materials" in messy:
        body_faces = sum(len(q.faces) for q in parts if q.part == "body")
        chunk = max(2, int(math.ceil(body_faces / MANY_MATERIALS)))
        split: list[_Part] = []
        for q in parts:
            if q.part != "body":
                split.append(q)
                continue
            for k, s in enumerate(range(0, len(q.faces), chunk)):
                v, f = _compact(q.vertices, q.faces[s:s + chunk])
                nm = f"{q.node}.{k:03d}"
                m = Material(**{**q.material.__dict__, "name": nm})
                split.append(_Part(nm, q.part, m, v, f))
        parts = split
    if "merged_materials" in messy:
        groups = [("paint", lambda q: q.material.name.startswith("paint_")),
                  ("glass", lambda q: q.part == "window"),
                  ("wheels", lambda q: q.part in ("wheel", "rim")),
                  ("lights", lambda q: q.part == "light"),
                  ("trim", lambda q: q.part in ("chrome", "plate")),
                  ("interior", lambda q: q.part == "interior")]
        pick = sorted(r.choice(len(groups), size=int(r.integers(2, 5)), replace=False).tolist())
        for gi in pick:
            gname, test = groups[gi]
            members = [q for q in parts if test(q)]
            if not members:
                continue
            shared = Material(**{**members[0].material.__dict__, "name": gname})
            for q in members:
                q.material = shared
    if "single_material" in messy:
        shared = Material("Material", parts[0].material.base_color, "OPAQUE", 0.0, 0.5)
        for q in parts:
            q.material = shared
    pairs = _symmetric_pairs(parts)
    for q in parts:
        d = mat_part_faces.setdefault(q.material.name, {})
        d[q.part] = d.get(q.part, 0) + len(q.faces)
    materials = {m: majority_part(c) for m, c in mat_part_faces.items()}

    # file transform: baked (rotation, units) into vertices, 'offset' on the root node
    bake = np.eye(4)
    if "z_up" in messy:          # +Y up -> +Z up
        bake = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1.0]]) @ bake
    if "rotated" in messy:
        q = r.normal(size=4)
        q /= np.linalg.norm(q)
        rot = np.eye(4)
        rot[:3, :3] = _quat_matrix(q)
        bake = rot @ bake
    if pose is not None:
        rot = np.eye(4)
        rot[:3, :3] = _pose_rotation(pose, pose_rng)
        bake = rot @ bake
    for t, s in UNIT_SCALE.items():
        if t in messy:
            bake = np.diag([s, s, s, 1.0]) @ bake
    root = np.eye(4)
    if "offset" in messy:
        root[:3, 3] = r.uniform(-1, 1, 3) * OFFSET
    file_verts = [q.vertices @ bake[:3, :3].T + bake[:3, 3] for q in parts]
    file_verts = [v.astype(np.float32).astype(np.float64) for v in file_verts]
    if "nan_vertex" in messy:
        i = int(r.integers(len(parts)))
        file_verts[i][int(r.integers(len(file_verts[i])))] = np.nan
    file_to_canonical = canonical @ np.linalg.inv(bake) @ np.linalg.inv(root)
    nodes = parts            # mesh() is the clean car (exactly symmetric, diagonal 1)
    if "nan_vertex" in messy:
        nodes = [_Part(q.node, q.part, q.material, fv, q.faces)
                 for q, fv in zip(parts, file_verts)]

    scene = trimesh.Scene()
    scene.graph.update(frame_from=scene.graph.base_frame, frame_to=name, matrix=root)
    pbr: dict[str, _NamedPBR] = {}
    for q, fv in zip(parts, file_verts):
        if q.material.name not in pbr:
            pbr[q.material.name] = _pbr(q.material)
        tm = trimesh.Trimesh(vertices=fv, faces=q.faces, process=False, validate=False,
                             visual=TextureVisuals(material=pbr[q.material.name]))
        scene.add_geometry(tm, node_name=q.node, geom_name=q.node, parent_node_name=name)

    n_tri = int(sum(len(q.faces) for q in parts))
    reject = next((REJECT_OF[t] for t in messy if t in REJECT_OF), None)
    truth = {
        "name": name, "kind": kind, "seed": seed, "materials": materials,
        "nodes": {q.node: q.part for q in parts},
        "material_part_faces": mat_part_faces,
        "symmetric_pairs": [list(pr) for pr in pairs],
        "expected_reject": reject, "messy": list(messy),
        "file_to_canonical": file_to_canonical.tolist(), "n_triangles": n_tri,
        "frame": {"up": "+Y", "front": "+X", "left": "-Z", "unit": "m"},
        "orientation": _orientation_truth(bake, pose, body),
    }
    return SynthVehicle(name, kind, seed, scene, truth, nodes, canonical)


# --------------------------------------------------------------------------------------------
# orientation cases and body variants

def _pose_rotation(pose: str, r: np.random.Generator) -> np.ndarray:
    """3x3 rotation of a pose case: 'axis' one of the 24 signed axis permutations with
    determinant +1 (uniformly), 'yaw' a uniform angle about +Y, 'tilt' a tilt of up to
    MAX_TILT_DEG about a random horizontal axis followed by a uniform yaw."""
    if pose == "axis":
        rots = axis_rotations()
        return rots[int(r.integers(len(rots)))]
    yaw = axis_angle(np.array([0.0, 1.0, 0.0]), r.uniform(0.0, 2 * math.pi))
    if pose == "yaw":
        return yaw
    phi = r.uniform(0.0, 2 * math.pi)
    tilt = axis_angle(np.array([math.cos(phi), 0.0, math.sin(phi)]),
                       math.radians(r.uniform(-MAX_TILT_DEG, MAX_TILT_DEG)))
    return yaw @ tilt


def axis_rotations() -> list[np.ndarray]:
    """The 24 rotations that permute the axes with signs (determinant +1), in a fixed order."""
    return [m for m in (np.eye(3)[list(p)] * np.array(sg)[:, None]
                        for p in itertools.permutations(range(3))
                        for sg in itertools.product((1.0, -1.0), repeat=3))
            if np.linalg.det(m) > 0]


def axis_angle(axis, angle: float) -> np.ndarray:
    """3x3 rotation by ``angle`` radians about ``axis`` (Rodrigues; ``axis`` need not be unit)."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def _orientation_truth(bake: np.ndarray, pose: str | None, body: str | None) -> dict:
    """The car frame's up (+Y) and front (+X) as unit directions in the file frame."""
    up, front = bake[:3, 1], bake[:3, 0]
    return {"up": (up / np.linalg.norm(up)).tolist(),
            "front": (front / np.linalg.norm(front)).tolist(),
            "pose": pose or "as built", "body": body or "",
            "front_defined": body != "symmetric_ends"}


def _body_variant(parts: list[_Part], body: str, r: np.random.Generator) -> list[_Part]:
    if body == "trailer":
        return parts + _trailer(parts, r)
    if body == "symmetric_ends":
        return _symmetric_ends(parts)
    gap = r.uniform(0.3, 1.0)                                  # two_vehicles
    allv = np.concatenate([q.vertices for q in parts])
    dz = float(np.ptp(allv[:, 2])) + gap
    return parts + [_Part(f"{q.node}.2", q.part, q.material, q.vertices + [0.0, 0.0, dz],
                          q.faces) for q in parts]


def _trailer(parts: list[_Part], r: np.random.Generator) -> list[_Part]:
    """A box trailer on a drawbar behind the vehicle: as wide as the vehicle, 0.8-1.6 of
    its length, two axles at its back with the vehicle's rear wheels, red tail lamps."""
    allv = np.concatenate([q.vertices for q in parts])
    lo, hi = allv.min(axis=0), allv.max(axis=0)
    L, hw = hi[0] - lo[0], 0.5 * (hi[2] - lo[2]) * 0.95
    wheels = [q for q in parts if q.part in ("wheel", "rim") and q.node[-2:] in ("RL", "RR")]
    tyre = [q for q in wheels if q.part == "wheel"]
    R = 0.5 * float(np.ptp(tyre[0].vertices[:, 1])) if tyre else 0.4
    gap, Lt = r.uniform(1.0, 1.6), L * r.uniform(0.8, 1.6)
    x1 = lo[0] - gap
    x0 = x1 - Lt
    floor, top = 2.0 * R + 0.1, max(hi[1] * r.uniform(0.85, 1.1), 2.0 * R + 1.0)
    cell = 0.12
    out = [_Part("trailer_box", "body", _material("trailer_paint", "paint", (0.8, 0.8, 0.78)),
                 *_box([x0, floor, -hw], [x1, top, hw], cell)),
           _Part("trailer_drawbar", "other", _material("trailer_drawbar", "plastic", (0, 0, 0)),
                 *_box([x1, floor - 0.15, -0.06], [lo[0] + 0.05, floor - 0.03, 0.06], cell))]
    ax_back = x0 + 0.9 * R + 0.3
    for k, ax in enumerate((ax_back + 2.2 * R + 0.1, ax_back)):
        for q in wheels:
            cx = float(q.vertices[:, 0].mean())
            kind = "tyre" if q.part == "wheel" else "rim"
            nm = f"trailer_{kind}_{k + 1}{q.node[-1]}"
            out.append(_Part(nm, q.part, _material(nm, kind, (0, 0, 0)),
                             q.vertices + [ax - cx, 0.0, 0.0], q.faces.copy()))
    for side in (1.0, -1.0):
        nm = f"trailer_taillight_{'R' if side > 0 else 'L'}"
        z0, z1 = sorted((side * (hw - 0.35), side * (hw - 0.08)))
        out.append(_Part(nm, "light", _material(nm, "taillight", (0, 0, 0)),
                         *_box([x0 - 0.04, floor + 0.1, z0], [x0 + 0.02, floor + 0.3, z1],
                               cell / 2)))
    return out


def _symmetric_ends(parts: list[_Part]) -> list[_Part]:
    """The front half of the vehicle and its mirror image across the middle of its length
    (faces whose centroid is in the front half, mirrored in x with their winding flipped):
    both ends alike, so nothing tells the front from the back."""
    allv = np.concatenate([q.vertices for q in parts])
    mid = 0.5 * (allv[:, 0].min() + allv[:, 0].max())
    out: list[_Part] = []
    for q in parts:
        front = q.vertices[q.faces].mean(axis=1)[:, 0] >= mid
        if not front.any():
            continue
        v, f = _compact(q.vertices, q.faces[front])
        out.append(_Part(q.node, q.part, q.material, v, f))
        mv = v.copy()
        mv[:, 0] = 2.0 * mid - mv[:, 0]
        out.append(_Part(f"{q.node}_2", q.part, q.material, mv, f[:, ::-1].copy()))
    return out


def _symmetric_pairs(parts: list[_Part]) -> list[tuple[str, str]]:
    """(left, right) material pairs of mirror-image nodes: node 'X_L' / 'X_FL' / 'X_L.003'
    pairs with the same name ending in R; kept when both materials are distinct and are used by
    that node only (merged materials drop out)."""
    users: dict[str, int] = {}
    for q in parts:
        users[q.material.name] = users.get(q.material.name, 0) + 1
    by_node = {q.node: q for q in parts}
    out = set()
    for q in parts:
        head, dot, tail = q.node.partition(".")
        if not head.endswith("L"):
            continue
        other = by_node.get(head[:-1] + "R" + dot + tail)
        if other is None:
            continue
        a, b = q.material.name, other.material.name
        if a != b and users[a] == 1 and users[b] == 1:
            out.add((a, b))
    return sorted(out)


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


# --------------------------------------------------------------------------------------------
# material realism: how real libraries assign materials (traits for training and tests)

def apply_realism(parts: list[_Part], traits: Sequence[str],  # noqa: C901  one branch per trait
                  r: np.random.Generator) -> list[_Part]:
    """The vehicle's parts with the realism ``traits`` applied, in ``REALISM_TRAITS`` order.

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
    ``_mirror_glass``).
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
            black = _material("black", "plastic", (0, 0, 0))
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


def _trait_rng(r: np.random.Generator, trait: str) -> np.random.Generator:
    """A generator of its own for one realism trait: seeded from the seed of ``r`` (not its
    state) and the trait's name, so the draws of one trait do not move another's."""
    entropy = np.atleast_1d(r.bit_generator.seed_seq.entropy).tolist()   # type: ignore[attr-defined]
    return np.random.default_rng([*entropy, int.from_bytes(trait.encode()[:8], "little")])


def _opaque_glass(parts: list[_Part], r: np.random.Generator, shared) -> list[_Part]:
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


def _axles(parts: list[_Part], r: np.random.Generator) -> list[_Part]:
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
        v, f = _box([cx - t, cy - t, hi_l[2]], [cx + t, cy + t, lo_r[2]], 0.2)
        out.append(_Part(f"axle_{k}", "other", mat, v, f))
        xs.append(cx)
    if len(xs) >= 2 and np.isfinite(floor) and r.random() < 0.5:
        half = 0.5 * (min(p[0][0][2] for p in pairs) - max(p[1][1][2] for p in pairs))
        zr = float(r.uniform(0.25, 0.6)) * half
        h = float(r.uniform(0.06, 0.15))
        for side, tag in ((1.0, "R"), (-1.0, "L")):
            v, f = _box([min(xs) - 0.3, floor - h, side * zr - 0.04],
                        [max(xs) + 0.3, floor - 0.002, side * zr + 0.04], 0.3)
            out.append(_Part(f"frame_rail_{tag}", "other", mat, v, f))
    return out


def _light_bar(parts: list[_Part], r: np.random.Generator) -> list[_Part]:
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
        v, f = _box([x1 - depth - 0.02, y0, -width / 2 - 0.02], [x1 + 0.02, y0 + 0.03,
                                                                width / 2 + 0.02], 0.1)
        out.append(_Part("light_bar_base", "chrome",
                         Material("light_bar_base", (0.03, 0.03, 0.03, 1.0), "OPAQUE", 0.0, 0.6),
                         v, f))
        y0 += 0.03
    for k, c in enumerate(colours):
        z0 = -width / 2 + k * width / len(colours)
        rgb = palette[c]
        mat = Material(f"light_bar_{c}", (*rgb, alpha), "BLEND" if alpha < 1 else "OPAQUE",
                       0.0, 0.1, tuple(0.9 * x for x in rgb) if glow else (0.0, 0.0, 0.0))
        v, f = _box([x1 - depth, y0, z0], [x1, y0 + height, z0 + width / len(colours)], 0.1)
        out.append(_Part(f"light_bar_{k}", "light", mat, v, f))
    return out


def _plate_looks(parts: list[_Part], r: np.random.Generator) -> list[_Part]:
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
        out.append(_Part(q.node, "plate", mat, (q.vertices - c) * scale + c, q.faces))
    return out


def _inner_shell(parts: list[_Part], r: np.random.Generator) -> list[_Part]:
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
        out.append(_Part(f"interior_liner_{q.node[len('paint_'):]}", "interior", inner,
                         c + (q.vertices - c) * scale, q.faces[:, ::-1].copy()))
    return out


def _mirror_glass(parts: list[_Part], r: np.random.Generator) -> list[_Part]:
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
        v, f = _box([lo[0] - 0.01, lo[1] + inset, lo[2] + inset],
                    [lo[0] - 0.002, hi[1] - inset, hi[2] - inset], 0.1)
        out.append(_Part(f"mirror_glass_{q.node[-1]}", "chrome", mat, v, f))
    return out


def _bbox(q: _Part) -> tuple[np.ndarray, np.ndarray]:
    return q.vertices.min(axis=0), q.vertices.max(axis=0)


def _brake_discs(parts: list[_Part]) -> list[_Part]:
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
        v, f = _compact(q.vertices, q.faces[keep])
        out.append(_Part(q.node, q.part, q.material, v, f))
        side = 1.0 if hi[2] > 0 else -1.0
        z_in = lo[2] if side > 0 else hi[2]               # the rim's inner edge
        za, zb = z_in + side * 0.01, z_in + side * 0.035
        dv, df = _revolve(np.array([[0.0, 0.0], [0.8 * R, 0.0], [0.8 * R, 0.025], [0.0, 0.025]]),
                          32, [cx, cy, min(za, zb)])
        tag = q.node[len("rim_"):]
        out.append(_Part(f"brake_disc_{tag}", "other", disc_mat, dv, df))
        cv, cf = _box([cx - 0.12 * R, cy + 0.45 * R, min(za, zb) - 0.02],
                      [cx + 0.12 * R, cy + 0.75 * R, max(za, zb) + 0.01], 0.05)
        out.append(_Part(f"brake_calliper_{tag}", "other", cal_mat, cv, cf))
    return out


def _lens_lamps(parts: list[_Part]) -> list[_Part]:
    """Every lamp gets a clear lens box around it (1 cm larger on every side), part light."""
    out = []
    lens = Material("lamp_lens", (0.9, 0.9, 0.9, 0.25), "BLEND", 0.0, 0.05, transmission=0.9)
    for q in parts:
        out.append(q)
        if q.part == "light" and not q.node.startswith("lens_"):
            lo, hi = _bbox(q)
            v, f = _box(lo - 0.01, hi + 0.01, 0.05)
            out.append(_Part(f"lens_{q.node}", "light", lens, v, f))
    return out


def _lamp_variety(parts: list[_Part], r: np.random.Generator, shared) -> list[_Part]:
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
            out.append(_Part(q.node, "light", lens, q.vertices, q.faces))
            ilo, ihi = lo + 0.2 * size, hi - 0.2 * size
            v, f = _box(ilo, ihi, max(float(size.max()) / 3, 0.02))
            out.append(_Part(f"reflector_{q.node}", "light",
                             shared("reflector", refl), v, f))
        else:
            out.append(q)
        # indicator beside the lamp on the outer side, the lamp's depth, the lower 60 % height
        z0 = hi[2] + 0.005 if side > 0 else lo[2] - 0.005 - 0.08
        v, f = _box([lo[0], lo[1], z0], [hi[0], lo[1] + 0.6 * size[1], z0 + 0.08], 0.04)
        out.append(_Part(f"indicator_{q.node}", "light", shared("indicator", amber), v, f))
    return out


def _two_tone(parts: list[_Part], r: np.random.Generator, shared) -> list[_Part]:
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


def _ground_base(parts: list[_Part], r: np.random.Generator) -> list[_Part]:
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
        v, f = _box([cen[0] - half[0], top - thick, cen[2] - half[2]],
                    [cen[0] + half[0], top, cen[2] + half[2]], max(float(half.max()) / 6, 0.1))
    else:                                           # one-sided sheet facing up, any tessellation
        x0, x1, z0, z1 = cen[0] - half[0], cen[0] + half[0], cen[2] - half[2], cen[2] + half[2]
        v, f = _patch([x0, top, z0], [x0, top, z1], [x1, top, z0], [x1, top, z1], [0, 1], [0, 1],
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
    return list(parts) + [_Part("ground_base", "other", mat, v, f)]


def _rich_interior(parts: list[_Part], r: np.random.Generator) -> list[_Part]:
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
    v, f = _revolve(np.vstack([prof, prof[:1]]), 32, [0.0, 0.0, 0.0])
    v = np.stack([v[:, 2], v[:, 1], v[:, 0]], 1)           # axis along x: faces the driver
    f = f[:, ::-1]
    zc = 0.5 * (lo[2] + hi[2]) + 0.3 * (hi[2] - lo[2])
    v = v + [lo[0] - 0.05, hi[1] + 0.05, zc]
    wheel = Material("steering_wheel", (0.05, 0.05, 0.05, 1.0), "OPAQUE", 0.0, 0.6)
    out = list(parts) + [_Part("interior_steering_wheel", "interior", wheel, v, f)]
    panel = Material("door_panel", (0.3, 0.28, 0.25, 1.0), "OPAQUE", 0.0, 0.8)
    for side in (1.0, -1.0):
        z = side * (hi[2] + 0.03)
        pv, pf = _box([lo[0] - 1.2, lo[1] - 0.2, min(z, z + side * 0.03)],
                      [lo[0] - 0.1, hi[1], max(z, z + side * 0.03)], 0.1)
        out.append(_Part(f"interior_door_panel_{'R' if side > 0 else 'L'}", "interior", panel,
                         pv, pf))
    return out
