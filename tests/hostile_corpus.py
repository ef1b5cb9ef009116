"""A corpus of hostile files (and a few good vehicles dressed up oddly), generated on the fly.

``write_corpus(folder)`` writes every case into ``folder`` (one library) and returns the cases:
``Case(name, path, expect, group)`` where ``expect`` is ``"accepted"`` or the reason code the
build must record. Used by ``tests/test_hostile.py`` and ``bench/hostile.py``. Small files only
(the largest is a few MB; "huge" files are sparse or declare sizes they do not have).

Groups (for the per-class figures): ``good`` (good vehicles, some with odd but valid traits),
``structure`` (broken containers, JSON, headers, indices), ``budget`` (declared counts or sizes
over a budget), ``reference`` (URIs and mtllib pointing where they must not), ``filesystem``
(FIFOs, symlink loops, devices, odd names), ``numeric`` (NaN, overflowing scales), ``filter``
(valid files the catalogue's criteria reject).
"""
from __future__ import annotations

import json
import os
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

GOOD_SEEDS = (3, 4, 5)          # synth vehicles written as they are


@dataclass
class Case:
    name: str
    path: Path
    expect: str                 # "accepted" or a reason code
    group: str


# ----------------------------------------------------------------------------- GLB helpers

def pack_glb(gltf: dict | bytes, binary: bytes = b"") -> bytes:
    """A GLB container: JSON chunk (a dict, or raw bytes for broken JSON) + optional BIN chunk."""
    text = gltf if isinstance(gltf, bytes) else json.dumps(gltf, allow_nan=True).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    chunks = struct.pack("<II", len(text), 0x4E4F534A) + text
    if binary:
        chunks += struct.pack("<II", len(binary), 0x004E4942) + binary
    return b"glTF" + struct.pack("<II", 2, 12 + len(chunks)) + chunks


def unpack_glb(data: bytes) -> tuple[dict, bytes]:
    n = struct.unpack_from("<I", data, 12)[0]
    gltf = json.loads(data[20:20 + n])
    rest = data[20 + n:]
    return gltf, (rest[8:8 + struct.unpack_from("<I", rest, 0)[0]] if rest else b"")


def box_gltf(n_materials: int = 2, scale: float = 1.0) -> tuple[dict, bytes]:
    """A unit box (12 triangles) whose faces use ``n_materials`` materials: (gltf, bin)."""
    v = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], np.float32) * scale
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tri = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], np.uint32)
    groups = np.array_split(np.arange(len(tri)), n_materials)
    binary = v.tobytes()
    gltf = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
            "nodes": [{"mesh": 0}], "materials": [], "accessors": [], "bufferViews": [],
            "buffers": [], "meshes": [{"primitives": []}]}
    gltf["bufferViews"].append({"buffer": 0, "byteOffset": 0, "byteLength": len(binary)})
    gltf["accessors"].append({"bufferView": 0, "componentType": 5126, "count": 8, "type": "VEC3",
                              "min": v.min(0).tolist(), "max": v.max(0).tolist()})
    for k, g in enumerate(groups):
        idx = tri[g].tobytes()
        gltf["bufferViews"].append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(idx)})
        gltf["accessors"].append({"bufferView": len(gltf["bufferViews"]) - 1,
                                  "componentType": 5125, "count": int(g.size * 3), "type": "SCALAR"})
        binary += idx
        gltf["materials"].append({"name": f"paint_{k}", "pbrMetallicRoughness": {
            "baseColorFactor": [0.2 + 0.3 * k % 1, 0.4, 0.6, 1.0]}})
        gltf["meshes"][0]["primitives"].append({"attributes": {"POSITION": 0},
                                                "indices": len(gltf["accessors"]) - 1,
                                                "material": k})
    gltf["buffers"].append({"byteLength": len(binary)})
    return gltf, binary


def vehicle_glb(seed: int) -> bytes:
    from ucad_cl.synth import make_vehicle
    return make_vehicle(seed, "sedan").glb_bytes()


def wrapped(data: bytes, **root) -> bytes:
    """The vehicle GLB ``data`` with one new root node (``root``: scale, translation...) above
    the scene's root nodes."""
    gltf, binary = unpack_glb(data)
    scene = gltf["scenes"][gltf.get("scene", 0)]
    gltf["nodes"].append({"name": "hostile_root", "children": scene["nodes"], **root})
    scene["nodes"] = [len(gltf["nodes"]) - 1]
    return pack_glb(gltf, binary)


def gltf_text(gltf: dict) -> bytes:
    return json.dumps(gltf, allow_nan=True).encode()


def data_uri(binary: bytes) -> str:
    import base64
    return "data:application/octet-stream;base64," + base64.b64encode(binary).decode()


# ----------------------------------------------------------------------------- other formats

def stl_binary(tris: np.ndarray, count: int | None = None) -> bytes:
    tris = np.asarray(tris, np.float32).reshape(-1, 3, 3)
    rec = np.zeros(len(tris), [("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
    rec["v"] = tris
    return b"\0" * 80 + struct.pack("<I", len(tris) if count is None else count) + rec.tobytes()


def box_triangles(scale: float = 1.0) -> np.ndarray:
    gltf, binary = box_gltf(1)
    v = np.frombuffer(binary[:96], np.float32).reshape(8, 3).astype(np.float64) * scale
    idx = np.frombuffer(binary[96:], np.uint32).reshape(-1, 3)
    return v[idx]


def obj_text(materials: bool = True, tag: str = "") -> str:
    """A box in OBJ with two materials (red, blue); ``tag`` (a comment) makes the bytes unique."""
    lines = [f"# {tag}"] + (["mtllib car.mtl"] if materials else [])
    v = [(x, y, z) for x in (0, 1) for y in (0, 1) for z in (0, 1)]
    lines += [f"v {x} {y} {z}" for x, y, z in v]
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    for k, q in enumerate(quads):
        lines.append(f"usemtl {'red' if k % 2 else 'blue'}")
        lines.append("f " + " ".join(str(i + 1) for i in q))
    return "\n".join(lines) + "\n"


MTL = "newmtl red\nKd 1 0 0\nnewmtl blue\nKd 0 0 1\n"


# ----------------------------------------------------------------------------- the corpus

def write_corpus(folder: str | os.PathLike, *, good: bool = True) -> list[Case]:
    """Write every case into ``folder`` (created); returns the cases in a fixed order.
    ``good=False`` leaves out the synth vehicles (for ingest-only checks)."""
    root = Path(folder)
    root.mkdir(parents=True, exist_ok=True)
    cases: list[Case] = []

    def add(name, expect, group, data: bytes | str | None = None, sub: str = "") -> Path:
        d = root / sub if sub else root
        d.mkdir(parents=True, exist_ok=True)
        path = d / name
        if data is not None:
            path.write_bytes(data.encode() if isinstance(data, str) else data)
        cases.append(Case(name if not sub else f"{sub}/{name}", path, expect, group))
        return path

    box, box_bin = box_gltf(2)

    # ---- good vehicles, plain and oddly dressed (all must be accepted)
    if good:
        for s in GOOD_SEEDS:
            add(f"good_{s}.glb", "accepted", "good", vehicle_glb(s))
        base = vehicle_glb(7)
        add("good_scale_1e200.glb", "accepted", "good", wrapped(base, scale=[1e200] * 3))
        add("good_scale_1e-200.glb", "accepted", "good", wrapped(vehicle_glb(8), scale=[1e-200] * 3))
        add("good_far_offset.glb", "accepted", "good",
            wrapped(vehicle_glb(9), translation=[1e9, -1e9, 1e9]))
        g, b = unpack_glb(vehicle_glb(10))
        for k, m in enumerate(g["materials"]):
            m["name"] = m.get("name", "") + ("\ud800" if k % 2 else "")      # lone surrogates
            if k % 3 == 0:
                m["alphaMode"] = ["not", "a", "string"]
                m.setdefault("pbrMetallicRoughness", {})["baseColorFactor"] = "red"
                m["emissiveFactor"] = [1e400, 0]
        add("good_odd_materials.glb", "accepted", "good", pack_glb(g, b))
        name = os.fsdecode(b"good_latin1_\xe9\xff.glb")        # not UTF-8: a surrogate-escaped str
        add(name, "accepted", "good", vehicle_glb(11))
        # the same bytes as good_3.glb seen as STL: its own identity, rejected as an STL
        add("copy_of_good_3.stl", "unreadable", "structure", vehicle_glb(GOOD_SEEDS[0]))

    # ---- GLB / glTF structure
    add("glb_bad_magic.glb", "unreadable", "structure", b"GLTF" + b"\0" * 40)
    add("glb_truncated.glb", "unreadable", "structure", pack_glb(box, box_bin)[:-20])
    data = bytearray(pack_glb(box, box_bin))
    struct.pack_into("<I", data, 12, 1 << 30)
    add("glb_json_chunk_too_long.glb", "unreadable", "structure", bytes(data))
    add("glb_invalid_json.glb", "unreadable", "structure", pack_glb(b'{"asset": {', box_bin))
    add("glb_json_list.glb", "unreadable", "structure", pack_glb(b"[1, 2, 3]"))
    add("glb_json_nested_deep.glb", "unreadable", "structure",
        pack_glb(b'{"a": ' + b"[" * 200_000 + b"]" * 200_000 + b"}"))
    add("gltf_buffers_int.gltf", "unreadable", "structure", gltf_text({**box, "buffers": 5}))
    add("gltf_uri_int.gltf", "unreadable", "structure",
        gltf_text({**box, "buffers": [{"uri": 5, "byteLength": 4}]}))
    g = json.loads(json.dumps(box))
    g["meshes"][0]["primitives"][0]["indices"] = 999
    add("glb_index_out_of_range.glb", "unreadable", "structure", pack_glb(g, box_bin))
    g = json.loads(json.dumps(box))
    g["meshes"][0]["primitives"][0]["mode"] = "triangles"
    add("glb_mode_string.glb", "unreadable", "structure", pack_glb(g, box_bin))
    g = json.loads(json.dumps(box))
    g["nodes"] = [{"mesh": 0, "children": [1]}, {"children": [0]}]
    add("glb_node_cycle.glb", "unreadable", "structure", pack_glb(g, box_bin))
    g = json.loads(json.dumps(box))
    g["nodes"] = [{"children": [2]}, {"children": [2]}, {"mesh": 0}]
    g["scenes"] = [{"nodes": [0, 1]}]
    add("glb_two_parents.glb", "unreadable", "structure", pack_glb(g, box_bin))
    g = json.loads(json.dumps(box))
    g["scene"] = 7
    add("glb_scene_index_bad.glb", "unreadable", "structure", pack_glb(g, box_bin))
    g = json.loads(json.dumps(box))
    g["bufferViews"][0]["byteOffset"] = 1 << 20
    add("glb_bufferview_outside_buffer.glb", "unreadable", "structure", pack_glb(g, box_bin))
    g = json.loads(json.dumps(box))
    g["buffers"][0]["uri"] = "data:application/octet-stream,%00%01"
    add("gltf_data_uri_not_base64.gltf", "unreadable", "structure", gltf_text(g))
    g = json.loads(json.dumps(box))
    g["buffers"][0]["uri"] = "data:application/octet-stream;base64,@@@not base64@@@"
    add("gltf_data_uri_bad_base64.gltf", "unreadable", "structure", gltf_text(g))
    g = json.loads(json.dumps(box))            # Draco as exporters write it: accessors have no
    for p in g["meshes"][0]["primitives"]:      # data of their own, the draco buffer is garbage
        p["extensions"] = {"KHR_draco_mesh_compression": {"bufferView": 0,
                                                          "attributes": {"POSITION": 0}}}
    for a in g["accessors"]:
        a.pop("bufferView")
    g["extensionsUsed"] = ["KHR_draco_mesh_compression"]
    add("glb_draco_garbage.glb", "unsupported_compression", "structure", pack_glb(g, box_bin))
    g = json.loads(json.dumps(box))
    g["extensionsRequired"] = g["extensionsUsed"] = ["EXT_meshopt_compression"]
    add("glb_meshopt.glb", "unsupported_compression", "structure", pack_glb(g, box_bin))
    add("glb_empty_object.glb", "empty", "structure", pack_glb({"asset": {"version": "2.0"}}))
    g = json.loads(json.dumps(box))
    for p in g["meshes"][0]["primitives"]:
        p["mode"] = 0                                                     # points only
    add("glb_points_only.glb", "empty", "structure", pack_glb(g, box_bin))

    # ---- budgets (declared counts and sizes; the files themselves are small)
    g = json.loads(json.dumps(box))
    g["buffers"][0]["byteLength"] = 1 << 40
    add("glb_buffer_bytelength_1TiB.glb", "too_large", "budget", pack_glb(g, box_bin))
    g = json.loads(json.dumps(box))
    g["accessors"][0]["count"] = 1_000_000_000
    add("glb_accessor_count_1e9.glb", "too_large", "budget", pack_glb(g, box_bin))
    # 5,000 materials sharing one 3,000-vertex position accessor (15M vertices once flattened)
    n_vert = 3000
    pos = np.random.default_rng(0).random((n_vert, 3), np.float32)
    idx = np.arange(n_vert, dtype=np.uint32)
    binary = pos.tobytes() + idx.tobytes()
    g = {"asset": {"version": "2.0"}, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
         "buffers": [{"byteLength": len(binary)}],
         "bufferViews": [{"buffer": 0, "byteLength": pos.nbytes},
                         {"buffer": 0, "byteOffset": pos.nbytes, "byteLength": idx.nbytes}],
         "accessors": [{"bufferView": 0, "componentType": 5126, "count": n_vert, "type": "VEC3",
                        "min": [0, 0, 0], "max": [1, 1, 1]},
                       {"bufferView": 1, "componentType": 5125, "count": n_vert,
                        "type": "SCALAR"}],
         "materials": [{"name": f"m{k}"} for k in range(5000)],
         "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "material": k}
                                    for k in range(5000)]}]}
    add("glb_5000_materials_shared_accessor.glb", "too_large", "budget", pack_glb(g, binary))
    # one 12k-triangle mesh instanced on 400 nodes (4.8M triangles drawn)
    n_tri = 12_000
    pos = np.random.default_rng(1).random((n_tri * 3, 3), np.float32)
    binary = pos.tobytes()
    g = {"asset": {"version": "2.0"}, "scenes": [{"nodes": list(range(400))}],
         "nodes": [{"mesh": 0, "translation": [k * 1.5, 0, 0]} for k in range(400)],
         "buffers": [{"byteLength": len(binary)}],
         "bufferViews": [{"buffer": 0, "byteLength": len(binary)}],
         "accessors": [{"bufferView": 0, "componentType": 5126, "count": n_tri * 3,
                        "type": "VEC3", "min": [0, 0, 0], "max": [1, 1, 1]}],
         "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}]}
    add("glb_instancing_bomb_400.glb", "too_large", "budget", pack_glb(g, binary))
    g = json.loads(json.dumps(box))
    g["nodes"] = [{"children": [k + 1]} for k in range(1000)] + [{"mesh": 0}]
    add("glb_nested_1000_deep.glb", "too_large", "budget", pack_glb(g, box_bin))
    g = json.loads(json.dumps(box))
    g["nodes"] = [{"mesh": 0} for _ in range(100_001)]
    g["scenes"] = [{"nodes": list(range(100_001))}]
    add("glb_100k_instances.glb", "too_large", "budget", pack_glb(g, box_bin))
    g = json.loads(json.dumps(box))
    g["materials"] = [{"name": "m"}] * 70_000
    add("glb_70000_materials.glb", "too_large", "budget", pack_glb(g, box_bin))
    big = add("glb_sparse_2GiB.glb", "too_large", "budget")
    with open(big, "wb") as f:                                  # sparse: no disk used
        f.truncate(2 << 30)
    g = json.loads(json.dumps(box))
    g["buffers"][0]["uri"] = "data:application/octet-stream;base64,AAAA"
    g["buffers"][0]["byteLength"] = 1 << 40                    # a "bomb" declared in a data: URI
    add("gltf_data_uri_declares_1TiB.gltf", "too_large", "budget", gltf_text(g))

    # ---- references (external buffers, MTL files, textures)
    def ref_gltf(name, uri, expect, sub=""):
        g = json.loads(json.dumps(box))
        g["buffers"][0]["uri"] = uri
        return add(name, expect, "reference", gltf_text(g), sub=sub)

    ref_gltf("gltf_uri_dev_zero.gltf", "/dev/zero", "unsafe_reference")
    ref_gltf("gltf_uri_etc_passwd.gltf", "../../../../../../etc/passwd", "unsafe_reference")
    ref_gltf("gltf_uri_absolute.gltf", "/etc/hostname", "unsafe_reference")
    ref_gltf("gltf_uri_percent_escape.gltf", "%2e%2e/%2e%2e/%2e%2e/etc/passwd", "unsafe_reference")
    ref_gltf("gltf_uri_url.gltf", "https://example.com/box.bin", "unsafe_reference")
    ref_gltf("gltf_uri_file_url.gltf", "file:///etc/passwd", "unsafe_reference")
    ref_gltf("gltf_uri_missing.gltf", "nowhere.bin", "missing_reference")
    sub = "fifo_buffer"
    p = ref_gltf("gltf_uri_fifo.gltf", "pipe.bin", "unsafe_reference", sub=sub)
    os.mkfifo(p.parent / "pipe.bin")
    sub = "symlink_buffer"
    p = ref_gltf("gltf_uri_symlink_out.gltf", "box.bin", "unsafe_reference", sub=sub)
    os.symlink("/dev/zero", p.parent / "box.bin")
    sub = "dir_buffer"
    p = ref_gltf("gltf_uri_directory.gltf", "adir", "unsafe_reference", sub=sub)
    (p.parent / "adir").mkdir()
    sub = "good_gltf"
    g = json.loads(json.dumps(box))
    g["buffers"][0]["uri"] = "box.bin"
    (root / sub).mkdir()
    (root / sub / "box.bin").write_bytes(box_bin)
    add("box_external_buffer.gltf", "accepted", "good", gltf_text(g), sub=sub)
    # OBJ: materials survive a missing or refused MTL (named after usemtl, a note), textures are
    # never read from outside the folder, a FIFO mtllib is not opened
    sub = "obj_missing_mtl"
    add("missing_mtl.obj", "accepted", "reference", obj_text(tag=sub), sub=sub)
    sub = "obj_mtl_escape"
    add("mtl_escape.obj", "accepted", "reference",
        obj_text(tag=sub).replace("mtllib car.mtl", "mtllib ../../../../etc/passwd"), sub=sub)
    sub = "obj_mtl_fifo"
    p = add("mtl_fifo.obj", "accepted", "reference", obj_text(tag=sub), sub=sub)
    os.mkfifo(p.parent / "car.mtl")
    sub = "obj_texture_dev_zero"
    p = add("texture_dev_zero.obj", "accepted", "reference", obj_text(tag=sub), sub=sub)
    (p.parent / "car.mtl").write_text(MTL.replace("Kd 1 0 0", "Kd 1 0 0\nmap_Kd /dev/zero")
                                      .replace("Kd 0 0 1", "Kd 0 0 1\nmap_Kd zero.png"))
    os.symlink("/dev/zero", p.parent / "zero.png")

    # ---- OBJ / STL / PLY / OFF structure and numbers
    add("obj_index_out_of_range.obj", "unreadable", "structure",
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 99999\nf 1 2 3\n")
    add("obj_random_text.obj", "empty", "structure", "lorem ipsum dolor sit amet\n" * 50)
    add("obj_random_bytes.obj", "empty", "structure",
        np.random.default_rng(2).integers(0, 256, 4096, np.uint8).tobytes())
    add("obj_nan_vertex.obj", "non_finite", "numeric",
        obj_text(False).replace("v 0 0 0", "v nan 0 0"))
    add("stl_random_bytes.stl", "unreadable", "structure",
        np.random.default_rng(3).integers(0, 256, 1000, np.uint8).tobytes())
    add("stl_count_1e9.stl", "unreadable", "structure", stl_binary(box_triangles(), 10 ** 9))
    add("stl_ascii_no_facets.stl", "empty", "structure", "solid nothing\nendsolid nothing\n")
    tris = box_triangles()
    tris[0, 0, 0] = np.nan
    add("stl_nan.stl", "non_finite", "numeric", stl_binary(tris))
    add("stl_one_material.stl", "too_few_materials", "filter", stl_binary(box_triangles()))
    add("stl_scale_1e30.stl", "too_few_materials", "numeric", stl_binary(box_triangles(1e30)))
    add("stl_scale_1e-30.stl", "too_few_materials", "numeric", stl_binary(box_triangles(1e-30)))
    add("ply_vertex_count_2e9.ply", "too_large", "budget",
        "ply\nformat ascii 1.0\nelement vertex 2000000000\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n")
    add("ply_no_end_header.ply", "unreadable", "structure", "ply\nformat ascii 1.0\n" + "x\n" * 10)
    add("ply_binary_truncated.ply", "unreadable", "structure",
        b"ply\nformat binary_little_endian 1.0\nelement vertex 100\nproperty float x\n"
        b"property float y\nproperty float z\nelement face 10\n"
        b"property list uchar int vertex_indices\nend_header\n" + b"\0" * 30)
    add("ply_count_not_integer.ply", "unreadable", "structure",
        "ply\nformat ascii 1.0\nelement vertex many\nproperty float x\nend_header\n")
    add("off_count_huge.off", "too_large", "budget", "OFF\n3 900000000 0\n0 0 0\n1 0 0\n0 1 0\n")
    add("off_garbage.off", "unreadable", "structure", "this is not an OFF file\n1 2 3\n")
    add("off_truncated.off", "unreadable", "structure", "OFF\n100 10 0\n0 0 0\n1 1 1\n")

    # ---- file-system oddities
    os.mkfifo(add("fifo.glb", "not_a_file", "filesystem"))
    os.symlink("loop.glb", add("loop.glb", "not_a_file", "filesystem"))
    os.symlink("no_such_target.glb", add("dangling.glb", "not_a_file", "filesystem"))
    os.symlink("/dev/zero", add("dev_zero.glb", "not_a_file", "filesystem"))
    os.symlink("/dev/urandom", add("dev_urandom.stl", "not_a_file", "filesystem"))
    add("empty.glb", "empty", "filesystem", b"")
    add("empty.obj", "empty", "filesystem", b"")
    g = json.loads(json.dumps(box))                 # a good box 1,000 folders deep (deeper than
    g["materials"][0]["name"] = "deep_paint"        # a recursive walk, pathlib's mkdir included,
    deep = root                                     # can go)
    for _ in range(1000):
        deep = deep / "d"
        deep.mkdir(exist_ok=True)
    add("deep_box.glb", "accepted", "filesystem", pack_glb(g, box_bin),
        sub=str(deep.relative_to(root)))
    return cases


def remove_deep(folder: str | os.PathLike) -> None:
    """Delete the corpus' 1,000-deep folder chain (``folder/d/d/...``) bottom-up, without
    recursion: ``shutil.rmtree`` (and so pytest's and tempfile's cleanup) recurses per level and
    fails on it."""
    top = Path(folder) / "d"
    chain = []
    d = top
    while d.is_dir() and not d.is_symlink():
        chain.append(d)
        d = d / "d"
    for d in reversed(chain):
        for entry in os.scandir(d):
            if entry.is_dir(follow_symlinks=False):
                os.rmdir(entry.path)
            else:
                os.unlink(entry.path)
        os.rmdir(d)


def png_header_only(path: Path, w: int, h: int) -> None:
    """A PNG whose header claims w x h and that holds no pixel data (a decompression bomb's
    shape: readers must refuse it from the header, not try to decode it)."""
    def chunk(kind, data):
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IEND", b""))
