"""Materials of the generated vehicles: PBR materials with their names kept through trimesh's
GLB export (``NamedPBR``), quantised colours, and glass transmission added to the GLB.
"""
from __future__ import annotations

import json
import struct

import numpy as np
from trimesh.visual.material import PBRMaterial  # noqa: TID253

from ..artifacts import Material

# --------------------------------------------------------------------------------------------
# materials

class NamedPBR(PBRMaterial):
    """PBRMaterial whose hash includes its name: trimesh's exporter merges materials with equal
    hashes, and the stock hash ignores the name (all paint panels would become one material)."""

    def __hash__(self) -> int:
        return hash((self.name, super().__hash__()))


def _q8(x: float) -> float:
    """Colours are stored as 8-bit by trimesh: quantise up front so file and truth agree."""
    return round(float(np.clip(x, 0.0, 1.0)) * 255.0) / 255.0


def make_material(name: str, cls: str, paint: tuple[float, float, float]) -> Material:
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


def quantised(m: Material) -> Material:
    return Material(m.name, tuple(_q8(c) for c in m.base_color), m.alpha_mode, float(m.metallic),
                    float(m.roughness), tuple(float(e) for e in m.emissive),
                    float(m.transmission), False)


def pbr_material(m: Material) -> NamedPBR:
    return NamedPBR(name=m.name, baseColorFactor=list(m.base_color),
                     metallicFactor=float(m.metallic), roughnessFactor=float(m.roughness),
                     emissiveFactor=list(m.emissive) if any(m.emissive) else None,
                     alphaMode=m.alpha_mode, doubleSided=m.alpha_mode == "BLEND")


def add_transmission(glb: bytes, transmission: dict[str, float]) -> bytes:
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
