"""The kernel ABI: every constant and parameter struct that host code and OpenCL kernels share.

Constants reach the kernels as ``-D`` options: ``Runtime.program`` adds ``defines()`` to every
build, and the kernels refuse to compile without them (``common.h``), so a value lives here only.
Each parameter struct's NumPy dtype below mirrors a C struct of ``ucad_cl/kernels`` field for
field (same names, order and types); ``tests/test_abi.py`` compiles a probe on every test device
and checks size, offsets and field sizes, so a field added on one side only fails there.

Units: pixels, counts and bytes unless a comment says otherwise.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ucad_catalog.views import BACKGROUND_MAT, BACKGROUND_TRI

from .artifacts import PartMasks

# ---- constants (name in the kernels = name here) -------------------------------------------------
BG_TRI = int(BACKGROUND_TRI)     # triangle id of background pixels (the catalogue's)
BG_MAT = int(BACKGROUND_MAT)     # material id of background pixels; faces have material + 1
BIG_PIXELS = 1024                # raster parallel path: boxes above this go to raster_big
MAX_BINS = 36                    # HOG orientation bins, at most (per-cell histogram array)
K_MAX = 64                       # search: k of one top-k, at most (per-work-item arrays)
SRGB_BUCKETS = 65536             # shade: buckets of the linear -> sRGB start-level table
MAX_PARTS = PartMasks.MAX_PARTS  # parts: part masks are uint16 bit sets

CONSTANTS = {"UCAD_BG_TRI": f"{BG_TRI:#x}u", "UCAD_BG_MAT": f"{BG_MAT}u",
             "BIG_PIXELS": BIG_PIXELS, "MAX_BINS": MAX_BINS, "KMAX": K_MAX,
             "SRGB_BUCKETS": SRGB_BUCKETS, "MAX_PARTS": MAX_PARTS}


def defines() -> tuple[str, ...]:
    """The ``-D`` build options that give every kernel the constants above."""
    return tuple(f"-D{name}={value}" for name, value in CONSTANTS.items())


# ---- parameter structs (passed by value to kernels) ----------------------------------------------
RASTER_PARAMS = np.dtype([("width", np.int32), ("height", np.int32), ("n_faces", np.int32),
                          ("n_views", np.int32), ("near", np.float32),
                          ("big_capacity", np.uint32)])
SHADE_PARAMS = np.dtype([("kinv", np.float32, 9), ("light", np.float32, 3),
                         ("ambient", np.float32), ("specular", np.float32),
                         ("shininess", np.float32), ("width", np.int32), ("height", np.int32),
                         ("n_views", np.int32), ("int_shininess", np.int32),
                         ("bg", np.uint8, 3), ("pad", np.uint8)])
PART_HIST_PARAMS = np.dtype([("n_pixels", np.uint32), ("n_views", np.uint32),
                             ("n_ids", np.uint32), ("n_parts", np.uint32),
                             ("pixels_per_item", np.uint32), ("pad", np.uint32)])
CANNY_PARAMS = np.dtype([("width", np.int32), ("height", np.int32), ("n_images", np.int32),
                         ("channels", np.int32), ("low", np.int32), ("high", np.int32),
                         ("l2", np.int32), ("pad", np.int32)])
HOG_PARAMS = np.dtype([
    ("size", np.int32), ("cell", np.int32), ("n_cells", np.int32), ("bins", np.int32),
    ("is_signed", np.int32), ("n_blocks", np.int32), ("d_hog", np.int32), ("d_sil", np.int32),
    ("eps", np.float32), ("clip", np.float32), ("sil_weight", np.float32),
    ("min_grad", np.float32)])
DIST_PARAMS = np.dtype([("n_queries", np.int32), ("n_rows", np.int32), ("dim16", np.int32),
                        ("q_stride", np.int32), ("dist_stride", np.int32)])
TOPK_PARAMS = np.dtype([("n_queries", np.int32), ("n_rows", np.int32), ("dist_stride", np.int32),
                        ("chunk", np.int32), ("n_chunks", np.int32), ("k", np.int32)])
MERGE_PARAMS = np.dtype([("n_queries", np.int32), ("n_cand", np.int32), ("k", np.int32)])
GATHER_PARAMS = np.dtype([("n_queries", np.int32), ("dim16", np.int32), ("n_cand", np.int32)])


@dataclass(frozen=True)
class Struct:
    """One parameter struct: the kernel file (program) that declares it, its C name, its dtype."""

    program: str
    c_name: str
    dtype: np.dtype


STRUCTS = (
    Struct("raster_parallel", "raster_params", RASTER_PARAMS),
    Struct("raster_serial", "raster_params", RASTER_PARAMS),
    Struct("shade", "shade_params", SHADE_PARAMS),
    Struct("parts", "part_hist_params", PART_HIST_PARAMS),
    Struct("canny", "canny_params", CANNY_PARAMS),
    Struct("features", "hog_params", HOG_PARAMS),
    Struct("search", "dist_params", DIST_PARAMS),
    Struct("search", "topk_params", TOPK_PARAMS),
    Struct("search", "merge_params", MERGE_PARAMS),
    Struct("search", "gather_params", GATHER_PARAMS),
)
