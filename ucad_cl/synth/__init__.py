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

Layout (a package by concern; its bytes are the training and test data of the labeller and the
orientation stage, so every split keeps the seeded streams' order): this file holds the public
functions, the trait tables and ``_finish`` (messy traits, pose, scene and truth); ``builder``
the parametric vehicle of each kind; ``shapes`` the geometry primitives and ``Part``;
``materials`` the PBR materials and the GLB's transmission; ``poses`` the orientation cases and
body variants; ``realism`` the material-realism traits. Submodules never import this file.
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import trimesh  # noqa: TID253  the generator is trimesh throughout
from trimesh.visual import TextureVisuals  # noqa: TID253

from ..artifacts import PART_NAMES, VEHICLE_KINDS, Material, Mesh
from .builder import build_parts
from .materials import NamedPBR, add_transmission, pbr_material, quantised
from .poses import (MAX_TILT_DEG, axis_angle, axis_rotations, body_variant, orientation_truth,
                    pose_rotation, quat_matrix, symmetric_pairs)
from .realism import apply_realism
from .shapes import Part, compact

__all__ = ["BODIES", "HUGE_TRIANGLES", "KINDS", "MANY_MATERIALS", "MAX_TILT_DEG", "MESSY_TRAITS",
           "OFFSET", "POSES", "POSE_TRAITS", "REALISM_TRAITS", "REJECT_OF", "SHAPE_TRAITS",
           "UNIT_SCALE",
           "SynthVehicle", "apply_realism", "axis_angle", "axis_rotations", "majority_part",
           "make_vehicle", "write_library"]

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
    "no_glass", "inner_shell", "mirror_glass", "plastic_trim", "cargo_paint",
    "meaningless_names", "misleading_names")
#: body-shape traits (``apply_realism`` too, before the material traits): cartoon proportions
#: and wedge bodies, as low-poly and stylised models have them. Kept apart from
#: REALISM_TRAITS, whose draws make the labeller's training data
SHAPE_TRAITS: tuple[str, ...] = ("cartoon", "wedge")


def make_vehicle(seed: int, kind: str | None = None, *, detail: int = 1,
                 target_triangles: int | None = None, messy: Sequence[str] = (),
                 name: str | None = None, realism: Sequence[str] = (),
                 pose: str | None = None, body: str | None = None) -> "SynthVehicle":
    """Build one vehicle. kind: one of KINDS (random from the seed when None).

    detail: resolution factor (triangles grow ~detail**2; 1 gives ~20-35k triangles).
    target_triangles: overrides detail, tessellates to about this many triangles (within ~10 %).
    messy: traits from MESSY_TRAITS to apply to the file (see module docstring).
    realism: traits from REALISM_TRAITS (how real libraries assign materials; see
    ``apply_realism``) and SHAPE_TRAITS (body shapes), recorded in ``truth["realism"]``.
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
    bad = [t for t in realism if t not in REALISM_TRAITS + SHAPE_TRAITS]
    if bad:
        raise ValueError(f"unknown realism trait(s) {bad}; expected some of "
                         f"{REALISM_TRAITS + SHAPE_TRAITS}")
    if target_triangles is not None and int(target_triangles) < 1000:
        raise ValueError(f"target_triangles must be >= 1000, got {target_triangles}")
    messy = tuple(dict.fromkeys(messy))          # unique, order kept
    if "huge" in messy and target_triangles is None:
        target_triangles = HUGE_TRIANGLES
    kind_rng = np.random.default_rng([seed, 0])
    kind = kind if kind is not None else KINDS[int(kind_rng.integers(len(KINDS)))]

    def build(res: float) -> list[Part]:
        return build_parts(kind, np.random.default_rng([seed, 1]), res)

    res = float(detail)
    parts = build(res)
    if target_triangles is not None:                 # triangles grow ~ res**2: two corrections
        for _ in range(3):
            n = sum(len(p.faces) for p in parts)
            if abs(n - target_triangles) <= 0.08 * target_triangles:
                break
            res *= math.sqrt(target_triangles / n)
            parts = build(res)
    realism = tuple(t for t in SHAPE_TRAITS + REALISM_TRAITS if t in realism)   # fixed order
    parts = apply_realism(parts, realism, np.random.default_rng([seed, 3]))
    if body is not None:
        parts = body_variant(parts, body, np.random.default_rng([seed, 5]))
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
    nodes: list = field(repr=False, default_factory=list)   # list[Part], car frame
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
        data = add_transmission(self.scene.export(file_type="glb"),
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


def _finish(seed: int, kind: str, name: str, parts: list[Part], messy: Sequence[str],
            r: np.random.Generator, pose: str | None = None,
            pose_rng: np.random.Generator | None = None, body: str | None = None
            ) -> SynthVehicle:
    """Round to float32, apply the messy traits, build the trimesh scene and the truth."""
    for q in parts:
        q.vertices = q.vertices.astype(np.float32).astype(np.float64)
        q.material = quantised(q.material)
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
        split: list[Part] = []
        for q in parts:
            if q.part != "body":
                split.append(q)
                continue
            for k, s in enumerate(range(0, len(q.faces), chunk)):
                v, f = compact(q.vertices, q.faces[s:s + chunk])
                nm = f"{q.node}.{k:03d}"
                m = Material(**{**q.material.__dict__, "name": nm})
                split.append(Part(nm, q.part, m, v, f))
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
    pairs = symmetric_pairs(parts)
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
        rot[:3, :3] = quat_matrix(q)
        bake = rot @ bake
    if pose is not None:
        rot = np.eye(4)
        rot[:3, :3] = pose_rotation(pose, pose_rng)
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
        nodes = [Part(q.node, q.part, q.material, fv, q.faces)
                 for q, fv in zip(parts, file_verts)]

    scene = trimesh.Scene()
    scene.graph.update(frame_from=scene.graph.base_frame, frame_to=name, matrix=root)
    pbr: dict[str, NamedPBR] = {}
    for q, fv in zip(parts, file_verts):
        if q.material.name not in pbr:
            pbr[q.material.name] = pbr_material(q.material)
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
        "orientation": orientation_truth(bake, pose, body),
    }
    return SynthVehicle(name, kind, seed, scene, truth, nodes, canonical)
