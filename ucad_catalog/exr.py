"""The per-mesh view stack: one multi-part OpenEXR file, one part per view (format version 2).

Every part ``view_VVV`` (scanline, ZIP compressed) has the display window of the whole H x W
image and a *data window* that is the bounding box of the object's pixels in that view (1 x 1 at
the top-left corner, holding background, when the view is empty). Pixels outside the data window
are background. (Version 1 stored the whole image; at 256 px the object's box is ~28 % of a view
on average, and OpenEXR's write cost grows with the pixels stored: 150 -> ~50 ms per mesh of
72 views.) Three channels:

=======  =====  =====================================================================
channel  type   meaning
=======  =====  =====================================================================
``tri``  UINT   triangle (face) index after ingest; 0xFFFFFFFF = background
``mat``  UINT   material id = material index + 1; 0 = background
``Z``    FLOAT  linear camera-space depth z in canonical units; +inf = background
=======  =====  =====================================================================

and these header attributes (all parts, unless noted):

* ``ucad:K`` (m33d): intrinsics, OpenCV convention, pixel (i, j) centred at (j + 0.5, i + 0.5);
* ``ucad:w2c`` (m44d): world-to-camera, world = the canonical frame, camera x right, y down,
  z forward; ``worldToCamera`` (m44f, the standard EXR attribute) holds the same matrix;
* ``ucad:fileToNorm`` (m44d): file frame -> canonical frame, so file-frame rays are recoverable;
* ``ucad:view`` (int), ``ucad:azimuth`` / ``ucad:elevation`` (float, degrees),
  ``ucad:distance`` / ``ucad:near`` (float, canonical units);
* ``dataWindow`` / ``displayWindow`` (box2i, standard): the stored box and the whole image;
* ``ucad:formatVersion`` (int), ``ucad:meshSha256`` (string), ``ucad:conventions`` (string);
* part 0 only: ``ucad:materials`` (string, JSON list of material names, index = id - 1).

The ray of pixel (i, j) in the canonical frame: origin ``-R^T t``, direction
``R^T K^-1 (j + 0.5, i + 0.5, 1)`` with ``w2c = [R t; 0 1]``; the surface point is
``origin + direction * Z / (direction . R[2])``. See ``read_viewset_exr`` and docs/FORMATS.md.
This module imports no OpenCL.
"""
from __future__ import annotations

import json
import os
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .views import CameraRing, ViewSet, nonzero_box

FORMAT_VERSION = 2
BACKGROUND = {"tri": np.uint32(0xFFFFFFFF), "mat": np.uint32(0), "Z": np.float32(np.inf)}
CONVENTIONS = ("canonical frame: right-handed, +Y up, front +X, right side +Z, bbox centred "
               "(z on the mirror plane when symmetric), bbox diagonal 1; "
               "camera: OpenCV (x right, y down, z forward), pixel (i,j) centre at (j+0.5,i+0.5); "
               "azimuth 0 looks from +X (the front view), counter-clockwise seen from +Y; "
               "mat = material index + 1 (0 background), tri = face index (0xFFFFFFFF background), "
               "Z = linear camera depth (+inf background)")


def write_viewset_exr(path, views, mesh=None, *, material_names=None, file_to_norm=None,
                      mesh_sha256: str | None = None) -> Path:
    """Write ``views`` (a ViewSet) to ``path`` atomically (temporary name, then rename).

    Encoded here, not by OpenEXR's writer (``_encode``): the same multi-part scanline file, its
    headers byte for byte those OpenEXR writes for these attributes (tests/test_exr.py), ZIP
    chunks deflated by libdeflate (the ``deflate`` package; OpenEXR's own deflater) at
    ``DEFLATE_LEVEL``. Any OpenEXR reader decodes them. Not ISA-L, used until stop 40 and ~0.045
    s a 144-view mesh faster: its level 1 gave the same chunk different (valid) streams in
    different processes, ~1 mesh in 100-200 builds (docs/FORMATS.md); libdeflate's output
    depends on its input and version only."""
    cams = views.cameras
    names = material_names if material_names is not None else (
        [m.name for m in mesh.materials] if mesh is not None else [])
    f2n = np.asarray(file_to_norm if file_to_norm is not None else (
        mesh.file_to_norm if mesh is not None else np.eye(4)), np.float64)
    sha = mesh_sha256 or (mesh.sha256 if mesh is not None else "")
    H, W = views.mat_id.shape[1:]
    parts = []
    for v in range(views.n_views):
        # the object's box (material id > 0); an empty view stores its top-left pixel
        y0, y1, x0, x1 = nonzero_box(views.mat_id[v]) or (0, 1, 0, 1)
        attrs = {
            "dataWindow": _box2i(x0, y0, x1 - 1, y1 - 1),
            "displayWindow": _box2i(0, 0, W - 1, H - 1),
            "name": _string(f"view_{v:03d}"),
            "ucad:formatVersion": _int(FORMAT_VERSION),
            "ucad:K": ("m33d", np.asarray(cams.K, "<f8").tobytes()),
            "ucad:w2c": ("m44d", np.asarray(cams.w2c[v], "<f8").tobytes()),
            "worldToCamera": ("m44f", np.asarray(cams.w2c[v], "<f4").tobytes()),
            "ucad:fileToNorm": ("m44d", np.asarray(f2n, "<f8").tobytes()),
            "ucad:view": _int(v),
            "ucad:azimuth": _float(cams.azimuth[v]),
            "ucad:elevation": _float(cams.elevation[v]),
            "ucad:distance": _float(cams.distance),
            "ucad:near": _float(cams.near),
            "ucad:meshSha256": _string(sha),
            "ucad:conventions": _string(CONVENTIONS),
        }
        if v == 0:
            attrs["ucad:materials"] = _string(json.dumps(list(names), ensure_ascii=False))
        box = (slice(y0, y1), slice(x0, x1))
        lines = np.empty((y1 - y0, 3, x1 - x0), "<u4")     # channels in name order: Z, mat, tri
        lines[:, 0] = np.asarray(views.depth[v][box], "<f4").view("<u4")
        lines[:, 1] = views.mat_id[v][box]
        lines[:, 2] = views.tri_id[v][box]
        parts.append((attrs, y0, lines))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.writelines(_encode(parts))
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


# -- the writer: OpenEXR 2's multi-part scanline layout (openexr.com, "OpenEXR File Layout").
# Magic, version 2 with the multi-part flag; per part a header (attributes sorted by name:
# name, type, size, value), an empty header ending the list; per part its chunk offsets
# (uint64, absolute); the chunks (part, first line, packed size, data). A ZIP chunk holds 16
# lines, each line its channels' values in channel-name order; its data is zlib of the bytes
# split into even and odd halves, each byte then replaced by (b[i] - b[i-1] + 128) mod 256,
# or the plain bytes when that is not smaller (as OpenEXR does; ``_unzip`` undoes it).
_CHANNELS = (("Z", 2), ("mat", 0), ("tri", 0))          # name, pixel type (2 FLOAT, 0 UINT)
_ZIP, _ZIP_LINES, _MULTIPART = 3, 16, 0x1000
DEFLATE_LEVEL = 1    # libdeflate's level for ZIP chunks: 1-4 took the same time on view stacks


def _encode(parts: list[tuple[dict, int, np.ndarray]]) -> list[bytes | bytearray]:
    """The file's bytes for [(attributes, first line, (h, 3, w) uint32 lines)], as the pieces
    to write in turn (not joined: a 144-view stack is ~10 MB)."""
    try:
        import deflate
    except ImportError:                                  # pragma: no cover - a broken install
        raise RuntimeError("writing view stacks needs the deflate package (libdeflate; pip "
                           "install deflate)") from None
    chlist = b"".join(n.encode() + b"\0" + struct.pack("<iB3xii", t, 0, 1, 1)
                      for n, t in _CHANNELS) + b"\0"
    common = {"channels": ("chlist", chlist), "compression": ("compression", bytes([_ZIP])),
              "lineOrder": ("lineOrder", b"\0"), "pixelAspectRatio": _float(1.0),
              "screenWindowCenter": ("v2f", struct.pack("<2f", 0, 0)),
              "screenWindowWidth": _float(1.0), "type": _string("scanlineimage")}
    headers, chunks = [], []
    for attrs, _, lines in parts:
        packed: list[bytes | bytearray] = [deflate.zlib_compress(pre, DEFLATE_LEVEL)
                                           for pre in _zip_ready(lines)]
        flat = lines.reshape(len(lines), -1)
        for k, data in enumerate(packed):           # not smaller: the plain bytes
            plain = flat[k * _ZIP_LINES:(k + 1) * _ZIP_LINES]
            if len(data) >= plain.nbytes:
                packed[k] = plain.tobytes()
        chunks.append(packed)
        a = {**common, **attrs, "chunkCount": _int(len(packed))}
        headers.append(b"".join(k.encode() + b"\0" + t.encode() + b"\0"
                                + struct.pack("<i", len(val)) + val
                                for k, (t, val) in sorted(a.items())) + b"\0")
    head = _MAGIC + struct.pack("<I", 2 | _MULTIPART) + b"".join(headers) + b"\0"
    at = len(head) + 8 * sum(len(c) for c in chunks)
    offsets: list[int] = []
    body: list[bytes | bytearray] = []
    for p, ((_, y0, _), cs) in enumerate(zip(parts, chunks)):
        for k, data in enumerate(cs):
            offsets.append(at)
            body += (struct.pack("<3i", p, y0 + k * _ZIP_LINES, len(data)), data)
            at += 12 + len(data)
    return [head, np.asarray(offsets, "<u8").tobytes(), *body]


def _zip_ready(lines: np.ndarray) -> list[np.ndarray]:
    """Each chunk's bytes interleaved and predicted (OpenEXR's ZIP preprocessing), the full
    chunks in one NumPy pass. The lines' bytes read as little-endian uint16 pairs: a chunk's
    even bytes are the pairs' low bytes, its odd bytes their high bytes (contiguous casts,
    ~1.5x faster than gathering every other byte)."""
    h = len(lines)
    x = np.ascontiguousarray(lines, "<u4").reshape(h, -1).view("<u2")
    full = h // _ZIP_LINES
    out: list[np.ndarray] = []
    for block in ([x[:full * _ZIP_LINES].reshape(full, -1)] if full else []) + (
            [x[full * _ZIP_LINES:].reshape(1, -1)] if h % _ZIP_LINES else []):
        n, m = block.shape
        t = np.empty((n, 2 * m), np.uint8)
        np.copyto(t[:, :m], block, casting="unsafe")        # low bytes (mod 256)
        np.copyto(t[:, m:], block >> 8, casting="unsafe")   # high bytes
        d = np.empty_like(t)
        d[:, 0] = t[:, 0]
        np.subtract(t[:, 1:], t[:, :-1], out=d[:, 1:])      # wraps mod 256, as OpenEXR's
        d[:, 1:] += 128                                     # predictor (b[i] - b[i-1] + 128)
        out.extend(d)
    return out


def _int(x) -> tuple[str, bytes]:
    return "int", struct.pack("<i", int(x))


def _float(x) -> tuple[str, bytes]:
    return "float", struct.pack("<f", float(x))


def _string(s: str) -> tuple[str, bytes]:
    return "string", s.encode()


def _box2i(x0, y0, x1, y1) -> tuple[str, bytes]:
    return "box2i", struct.pack("<4i", x0, y0, x1, y1)


def _full_image(part, name: str, dtype) -> np.ndarray:
    """A channel of ``part`` placed in its display window, background outside the data window."""
    (dx0, dy0), (dx1, dy1) = (np.asarray(c) for c in part.header["displayWindow"])
    (x0, y0), (x1, y1) = (np.asarray(c) for c in part.header["dataWindow"])
    out = np.full((int(dy1 - dy0) + 1, int(dx1 - dx0) + 1), BACKGROUND[name], dtype)
    out[y0 - dy0:y1 - dy0 + 1, x0 - dx0:x1 - dx0 + 1] = part.channels[name].pixels
    return out


def read_viewset_exr(path):
    """Read a view stack back: ``(ViewSet, meta)`` with meta keys ``materials``,
    ``file_to_norm``, ``mesh_sha256``, ``format_version``. Raises ValueError naming the file."""
    import OpenEXR

    path = Path(path)
    try:
        f = OpenEXR.File(str(path))
    except Exception as exc:
        raise ValueError(f"{path}: not a readable OpenEXR view stack ({exc})") from exc
    parts = f.parts
    if not parts or "ucad:w2c" not in parts[0].header:
        raise ValueError(f"{path}: OpenEXR file without ucad view headers")
    h0 = parts[0].header
    try:
        tri = np.stack([_full_image(p, "tri", np.uint32) for p in parts])
        mat = np.stack([_full_image(p, "mat", np.uint16) for p in parts])
        depth = np.stack([_full_image(p, "Z", np.float32) for p in parts])
    except (KeyError, ValueError) as exc:
        raise ValueError(f"{path}: view stack parts lack channel or window data ({exc})") from exc
    ring = CameraRing(
        K=np.asarray(h0["ucad:K"], np.float64),
        w2c=np.stack([np.asarray(p.header["ucad:w2c"], np.float64) for p in parts]),
        width=int(tri.shape[2]), height=int(tri.shape[1]),
        azimuth=np.array([p.header["ucad:azimuth"] for p in parts], np.float64),
        elevation=np.array([p.header["ucad:elevation"] for p in parts], np.float64),
        distance=float(h0["ucad:distance"]), near=float(h0["ucad:near"]))
    meta = {
        "materials": json.loads(h0.get("ucad:materials", "[]")),
        "file_to_norm": np.asarray(h0["ucad:fileToNorm"], np.float64),
        "mesh_sha256": h0.get("ucad:meshSha256", ""),
        "format_version": int(h0.get("ucad:formatVersion", 0)),
    }
    return ViewSet(cameras=ring, tri_id=tri, mat_id=mat, depth=depth), meta


# ----------------------------------------------------------------------------- one view at a time
#
# ``read_viewset_exr`` decodes every part (OpenEXR's Python API reads a whole file: ~30 ms for
# 72 views at 256 px). A consumer usually wants one view, so ``ViewStackFile`` reads and parses
# the headers once (names, windows, channels, compression, chunk offsets; no pixels: ~0.9 ms for
# 144 views, against ~2-7 ms to read a whole 5-10 MB stack), then reads and decodes only the
# chunks of the part asked for, straight from the file with NumPy and zlib. It handles the
# scanline compressions this package writes (ZIP, 16 lines a chunk) plus NONE and ZIPS; any other
# file (tiled, deep, another compression) is read through OpenEXR instead, with the same result.

_MAGIC = b"\x76\x2f\x31\x01"
_PIXEL_BYTES = {0: 4, 1: 2, 2: 4}                       # UINT, HALF, FLOAT
_PIXEL_DTYPE: dict[int, np.dtype] = {0: np.dtype("<u4"), 1: np.dtype("<f2"), 2: np.dtype("<f4")}
_LINES_PER_CHUNK = {0: 1, 2: 1, 3: 16}                 # NONE, ZIPS, ZIP
_HEAD_BYTES = 1 << 18       # the first read of a view stack (72 views' headers: ~117 KB); doubled
                            # until the headers and offset tables parse
_OUT_DTYPE = {"tri": np.uint32, "mat": np.uint16, "Z": np.float32}


class ViewStackFile:
    """Random access to the views of one view-stack EXR: ``read(view, channels)``.

    Opening reads the file's headers and chunk offset tables only (``_HEAD_BYTES`` at a time);
    ``read`` reads the byte range of that part's chunks (each chunk ends where the next chunk of
    the file starts) and returns
    ``{channel: (H, W) array}`` for the requested channels of one part, background outside its
    data window (tri uint32, mat uint16, Z float32, as ``read_viewset_exr``). ValueError naming
    the file for anything that is not a readable view stack.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        try:
            with open(self.path, "rb") as f:
                self._size = os.fstat(f.fileno()).st_size
                head = f.read(_HEAD_BYTES)
                while True:                            # read on until the headers parse
                    try:
                        self.parts, self._multipart = _parse_headers(head)
                        break
                    except (IndexError, ValueError, UnicodeDecodeError, struct.error) as exc:
                        more = f.read(len(head))
                        if not more:
                            raise ValueError(f"{self.path}: not a readable OpenEXR view stack "
                                             f"({exc})") from None
                        head += more
        except OSError as exc:
            raise ValueError(f"{self.path}: cannot read the view stack ({exc})") from None
        # a chunk ends where the next one starts, the last at the end of the file (``_decode``
        # clamps every range to the file, so offsets past its end read short and are refused)
        self._starts = np.unique(np.concatenate([p["offsets"] for p in self.parts]))
        self._ends = np.append(self._starts[1:], self._size)
        self._fallback: Any = None                  # OpenEXR parts, when the fast path cannot
        self._inflate = _inflater()                 # decided once a stack, not once a chunk

    @property
    def n_views(self) -> int:
        return len(self.parts)

    def read(self, view: int, channels=("tri", "mat", "Z")) -> dict[str, np.ndarray]:
        if not 0 <= view < len(self.parts):
            raise ValueError(f"{self.path}: no view {view} (the stack has {len(self.parts)})")
        part = self.parts[view]
        missing = [c for c in channels if c not in part["channels"]]
        if missing:
            raise ValueError(f"{self.path}: view {view} has no channel(s) {missing}")
        if part["compression"] not in _LINES_PER_CHUNK or part.get("type", "scanlineimage") \
                != "scanlineimage":
            return self._read_with_openexr(view, channels)
        try:
            return self._decode(view, part, channels)
        except OSError as exc:
            raise ValueError(f"{self.path}: view {view}: cannot read ({exc})") from None
        except (ValueError, IndexError, zlib.error, struct.error) as exc:
            raise ValueError(f"{self.path}: view {view}: corrupt chunk data ({exc})") from None

    # -- internals
    def _decode(self, view: int, part: dict, channels) -> dict[str, np.ndarray]:
        (x0, y0, x1, y1), (dx0, dy0, dx1, dy1) = part["dataWindow"], part["displayWindow"]
        W, n_rows = x1 - x0 + 1, y1 - y0 + 1
        chans = part["channels"]                       # name -> (type, byte offset in a line)
        line_bytes = sum(_PIXEL_BYTES[t] for t, _ in chans.values()) * W
        rows = np.empty((n_rows, line_bytes), np.uint8)
        lines = _LINES_PER_CHUNK[part["compression"]]
        offsets = part["offsets"]
        if offsets.size == 0:
            raise ValueError("the part has no chunks")
        first = int(offsets.min())
        last = min(int(self._ends[np.searchsorted(self._starts, offsets.max())]), self._size)
        with open(self.path, "rb") as f:              # the part's chunks, in one read
            f.seek(first)
            data = f.read(max(0, last - first))
        for pos in offsets:
            at = int(pos) - first
            if self._multipart:
                if int.from_bytes(data[at:at + 4], "little") != view:
                    raise ValueError(f"chunk at byte {at + first} belongs to another part")
                at += 4
            y = int.from_bytes(data[at:at + 4], "little", signed=True)
            size = int.from_bytes(data[at + 4:at + 8], "little")
            raw = data[at + 8:at + 8 + size]
            r0 = y - y0
            n = min(lines, n_rows - r0)
            if r0 < 0 or n <= 0 or len(raw) != size:
                raise ValueError(f"chunk at byte {at + first} is outside the data window or "
                                 f"truncated")
            want = n * line_bytes
            block = (np.frombuffer(raw, np.uint8) if size == want or part["compression"] == 0
                     else _unzip(raw, want, self._inflate))
            rows[r0:r0 + n] = block.reshape(n, line_bytes)
        out = {}
        H_full, W_full = dy1 - dy0 + 1, dx1 - dx0 + 1
        for name in channels:
            ptype, offset = chans[name]
            pix = np.ascontiguousarray(rows[:, offset * W:(offset + _PIXEL_BYTES[ptype]) * W])
            vals = pix.view(_PIXEL_DTYPE[ptype]).reshape(n_rows, W)
            img = np.full((H_full, W_full), BACKGROUND.get(name, 0),
                          _OUT_DTYPE.get(name, _PIXEL_DTYPE[ptype]))
            img[y0 - dy0:y1 - dy0 + 1, x0 - dx0:x1 - dx0 + 1] = vals
            out[name] = img
        return out

    def _read_with_openexr(self, view: int, channels) -> dict[str, np.ndarray]:
        import OpenEXR

        if self._fallback is None:
            self._fallback = OpenEXR.File(str(self.path), separate_channels=True).parts
        p = self._fallback[view]
        return {c: _full_image(p, c, _OUT_DTYPE.get(c, np.float32)) for c in channels}


def _unzip(raw: bytes, size: int, inflate: Callable[[bytes, int], bytes | bytearray]
           ) -> np.ndarray:
    """OpenEXR's ZIP/ZIPS chunk: zlib (``inflate``, from ``_inflater``), then undo the byte
    predictor and the two-half interleave."""
    t = np.frombuffer(inflate(raw, size), np.uint8)
    if t.size != size:
        raise ValueError(f"chunk inflates to {t.size} bytes, expected {size}")
    d = t - np.uint8(128)                              # wraps mod 256, as the encoder's + 128
    d[0] = t[0]
    d = np.cumsum(d, dtype=np.uint32).astype(np.uint8)  # mod 256 either way; NumPy's uint32
    #                                                     running sum is ~2.7x its uint8 one
    out = np.empty(size, np.uint8)
    half = (size + 1) // 2
    out[0::2], out[1::2] = d[:half], d[half:]
    return out


def _inflater() -> Callable[[bytes, int], bytes | bytearray]:
    """How a zlib stream of ``size`` bytes is inflated: by libdeflate (the ``deflate`` package,
    the writer's; ~2x zlib's speed) when it is installed, else by zlib. The same bytes either
    way; a stream that is corrupt or not ``size`` bytes long raises ValueError (libdeflate) or
    zlib.error / gives a short result (zlib), which ``ViewStackFile.read`` reports. Looked up
    once a stack: a failed import costs ~50 us, about as much as inflating a chunk."""
    try:
        import deflate
    except ImportError:                                  # the reader alone: zlib
        return lambda raw, size: zlib.decompress(raw, bufsize=size)

    def inflate(raw: bytes, size: int) -> bytearray:
        try:
            return deflate.zlib_decompress(raw, size)
        except deflate.DeflateError as exc:
            raise ValueError(f"chunk does not inflate to {size} bytes (libdeflate: {exc})") \
                from None

    return inflate


def _parse_headers(data: bytes) -> tuple[list[dict], bool]:
    """Per part: compression, type, windows, channels {name: (type, offset in pixel units)},
    chunk offsets; and whether the file is multi-part. Only what reading pixels needs."""
    if data[:4] != _MAGIC:
        raise ValueError("bad magic number")
    flags = int.from_bytes(data[4:8], "little")
    multipart, tiled, deep = bool(flags & 0x1000), bool(flags & 0x200), bool(flags & 0x800)
    pos, parts = 8, []
    chlists: dict[bytes, dict[str, tuple[int, int]]] = {}
    while True:
        first, pos, layout = _parse_header(data, pos, chlists)
        batch = [first]
        if multipart and data[pos] != 0:                # the next headers alike, at once
            alike, pos = _repeated_headers(data, pos, layout, chlists)
            batch += alike
        for part in batch:
            if tiled and not multipart:
                part["type"] = "tiledimage"
            if deep:
                part.setdefault("type", "deepscanline")
        parts += batch
        if not multipart or data[pos] == 0:
            break
    if multipart:
        pos += 1                                       # the empty header ending the list
    for part in parts:
        (x0, y0, x1, y1) = part["dataWindow"]
        if "chunkCount" in part:
            n = part["chunkCount"]
        else:
            lines = _LINES_PER_CHUNK.get(part["compression"], 16)
            n = (y1 - y0 + lines) // lines
        part["offsets"] = np.frombuffer(data, "<u8", count=n, offset=pos).copy()
        pos += 8 * n
    return parts, multipart


def _parse_header(data: bytes, pos: int, chlists: dict[bytes, dict[str, tuple[int, int]]]
                  ) -> tuple[dict, int, _Layout]:
    """One part's header from byte ``pos``, walked attribute by attribute: (what
    ``_parse_headers`` keeps, the byte after it, its layout: the headers after it that repeat
    it byte for byte but for the values, as a view stack's do, ``_repeated_headers`` reads at
    once). ``chlists`` maps channel-list bytes already parsed in this file to their result."""
    part, start, fixed, wanted = {"compression": 0}, pos, [], []
    find = data.index
    while data[pos] != 0:
        end = find(b"\0", pos)
        name = data[pos:end]
        tend = find(b"\0", end + 1)
        size = _I32(data, tend + 1)[0]
        if size < 0:                                   # (else the walk could loop forever)
            raise ValueError(f"attribute {name!r} has a negative size")
        v = tend + 5
        fixed.append(np.arange(pos - start, v - start))
        if name in _WANTED:
            _store(part, name, data[v:v + size], chlists)
            wanted.append((name, v - start, size))
        pos = v + size
    fixed.append(np.array([pos - start]))              # the terminating 0
    skeleton = np.concatenate(fixed)
    layout = _Layout(pos + 1 - start, skeleton,
                     np.frombuffer(data, np.uint8, count=pos + 1 - start, offset=start)[skeleton],
                     tuple(wanted))
    return _checked(part), pos + 1, layout


def _repeated_headers(data: bytes, pos: int, layout: _Layout,
                      chlists: dict[bytes, dict[str, tuple[int, int]]]) -> tuple[list[dict], int]:
    """The run of headers from byte ``pos`` on that have ``layout`` (``_parse_header``'s),
    compared all at once: (their parts, the byte after the run). The run ends at the first
    header that differs, at the end of the header list (its terminating 0 never matches a
    layout, which starts with a name) or where ``data`` ends; the caller reads on from there.
    A view stack of 144 views opens in ~0.9 ms, ~2 ms with its headers compared one at a time
    (a retrieval over 1,003 meshes opens ~40)."""
    n = (len(data) - pos) // layout.length
    if n < 1:
        return [], pos
    rows = np.frombuffer(data, np.uint8, count=n * layout.length, offset=pos).reshape(
        n, layout.length)
    same = (rows[:, layout.skeleton] == layout.expected).all(axis=1)
    k = n if same.all() else int(same.argmin())
    parts = []
    for at in range(pos, pos + k * layout.length, layout.length):
        part: dict = {"compression": 0}
        for name, v, size in layout.wanted:
            _store(part, name, data[at + v:at + v + size], chlists)
        parts.append(_checked(part))
    return parts, pos + k * layout.length


@dataclass(frozen=True)
class _Layout:
    """A header's layout: its length in bytes (terminator included); the offsets of its bytes
    that are not attribute values (names, types, sizes, terminators) and those bytes; and
    (name, value offset, size) of the attributes ``_store`` keeps."""

    length: int
    skeleton: np.ndarray
    expected: np.ndarray
    wanted: tuple


def _store(part: dict, name: bytes, value: bytes, chlists: dict) -> None:
    """Keep one wanted attribute's value in ``part``."""
    if name in (b"dataWindow", b"displayWindow"):
        part[name.decode()] = struct.unpack_from("<4i", value)
    elif name == b"compression":
        part["compression"] = value[0]
    elif name == b"chunkCount":
        part["chunkCount"] = int.from_bytes(value[:4], "little")
    elif name == b"type":
        part["type"] = value.decode()
    else:
        if value not in chlists:
            chlists[value] = _parse_chlist(value)
        part["channels"] = chlists[value]


def _checked(part: dict) -> dict:
    if "dataWindow" not in part or "channels" not in part:
        raise ValueError("a part has no dataWindow or channels")
    part.setdefault("displayWindow", part["dataWindow"])
    return part


_I32 = struct.Struct("<i").unpack_from
_WANTED = frozenset((b"dataWindow", b"displayWindow", b"compression", b"chunkCount", b"type",
                     b"channels"))


def _parse_chlist(value: bytes) -> dict[str, tuple[int, int]]:
    """{name: (pixel type, offset in units of pixels-bytes within one line, per pixel)}."""
    out, pos, offset = {}, 0, 0
    while value[pos] != 0:
        end = value.index(b"\0", pos)
        name = value[pos:end].decode()
        ptype = int.from_bytes(value[end + 1:end + 5], "little")
        xs = int.from_bytes(value[end + 9:end + 13], "little")
        ys = int.from_bytes(value[end + 13:end + 17], "little")
        if ptype not in _PIXEL_BYTES or (xs, ys) != (1, 1):
            raise ValueError(f"channel {name!r}: unsupported pixel type or subsampling")
        out[name] = (ptype, offset)
        offset += _PIXEL_BYTES[ptype]
        pos = end + 17
    return out
