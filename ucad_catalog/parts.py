"""The part vocabulary and UrbanCAD's part-level material prior, as plain data (no OpenCL).

``PART_NAMES``: the parts a material can be labelled with (``'unseen'`` is used for materials no
view shows). ``PART_MATERIALS``: a physically based material per part, as glTF 2.0 material
fields (metallic-roughness model, linear RGB, Khronos extensions), used by
``ucad-index export-glb --part-materials``. The numbers are generic priors for a road vehicle,
not measurements of any model:

=========  =================  =============================================================
part       material           glTF fields
=========  =================  =============================================================
body       car paint          source base colour kept (the paint colour is the model's),
                              metallic 0.5, roughness 0.35, KHR_materials_clearcoat 1 / 0.03
window     glass              base (0.9, 0.92, 0.92), metallic 0, roughness 0.05,
                              KHR_materials_transmission 0.95, KHR_materials_ior 1.5
wheel      tyre rubber        base (0.025, 0.025, 0.025), metallic 0, roughness 0.9
rim        alloy              base (0.91, 0.92, 0.92) (aluminium F0), metallic 1, roughness 0.25
light      lamp lens          base white, metallic 0, roughness 0.05, transmission 0.5, ior 1.5,
                              emissive = source base colour scaled to max 1 (red rear lamps stay
                              red; white when the source is grey or black)
chrome     chrome             base (0.549, 0.556, 0.554) (chromium F0), metallic 1, roughness 0.05
plate      licence plate      base (0.9, 0.9, 0.88), metallic 0.2, roughness 0.35
interior   interior trim      base (0.1, 0.1, 0.1), metallic 0, roughness 0.75
other      (source kept)      the source material unchanged
=========  =================  =============================================================
"""
from __future__ import annotations

PART_NAMES: tuple[str, ...] = (
    "body", "window", "wheel", "rim", "light", "chrome", "plate", "interior", "other",
)
UNSEEN = "unseen"

# glTF material fields per part; "keep_source_color" / "emissive_from_source" are the two rules
# that take the source material's base colour (see the module docstring)
PART_MATERIALS: dict[str, dict] = {
    "body": {"label": "car paint", "keep_source_color": True,
             "pbrMetallicRoughness": {"metallicFactor": 0.5, "roughnessFactor": 0.35},
             "extensions": {"KHR_materials_clearcoat": {"clearcoatFactor": 1.0,
                                                        "clearcoatRoughnessFactor": 0.03}}},
    "window": {"label": "glass",
               "pbrMetallicRoughness": {"baseColorFactor": [0.9, 0.92, 0.92, 1.0],
                                        "metallicFactor": 0.0, "roughnessFactor": 0.05},
               "extensions": {"KHR_materials_transmission": {"transmissionFactor": 0.95},
                              "KHR_materials_ior": {"ior": 1.5}}},
    "wheel": {"label": "tyre rubber",
              "pbrMetallicRoughness": {"baseColorFactor": [0.025, 0.025, 0.025, 1.0],
                                       "metallicFactor": 0.0, "roughnessFactor": 0.9}},
    "rim": {"label": "alloy",
            "pbrMetallicRoughness": {"baseColorFactor": [0.91, 0.92, 0.92, 1.0],
                                     "metallicFactor": 1.0, "roughnessFactor": 0.25}},
    "light": {"label": "lamp lens", "emissive_from_source": True,
              "pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0],
                                       "metallicFactor": 0.0, "roughnessFactor": 0.05},
              "extensions": {"KHR_materials_transmission": {"transmissionFactor": 0.5},
                             "KHR_materials_ior": {"ior": 1.5}}},
    "chrome": {"label": "chrome",
               "pbrMetallicRoughness": {"baseColorFactor": [0.549, 0.556, 0.554, 1.0],
                                        "metallicFactor": 1.0, "roughnessFactor": 0.05}},
    "plate": {"label": "licence plate",
              "pbrMetallicRoughness": {"baseColorFactor": [0.9, 0.9, 0.88, 1.0],
                                       "metallicFactor": 0.2, "roughnessFactor": 0.35}},
    "interior": {"label": "interior trim",
                 "pbrMetallicRoughness": {"baseColorFactor": [0.1, 0.1, 0.1, 1.0],
                                          "metallicFactor": 0.0, "roughnessFactor": 0.75}},
}
