"""Helpers the commands share (the catalogue commands ``status``/``show``/``export`` and ``parts
--catalog``; ``fit`` and ``pose`` for their photos and masks); not a sub-command itself (no
``register``)."""
from __future__ import annotations

import sys
from pathlib import Path

MAX_PIXELS = 50_000_000     # larger photos (and masks) are refused before they are decoded


def open_reader(path):
    """A CatalogReader for ``path``, or None after printing why it cannot be opened."""
    from ucad_catalog._db import CatalogError
    from ucad_catalog.reader import CatalogReader
    try:
        return CatalogReader(path)
    except CatalogError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return None


def vehicle_mask(values):
    """(H, W) bool of a mask image's values ((H, W) or (H, W, C), any integer type; the
    channels' largest): the pixels at least half the image's largest value, so 0/1 and 0/255
    masks, a segmenter's soft matte and a JPEG-saved mask's faint noise all give the vehicle
    (``> 0`` took a JPEG mask's noise for vehicle); an all-zero image gives none."""
    import numpy as np

    v = np.asarray(values)
    if v.ndim == 3:
        v = v.max(axis=2)
    top = int(v.max()) if v.size else 0
    return v >= max(1, (top + 1) // 2)


def read_image(path):
    """(H, W, 3) uint8 RGB of a photo or mask file as a viewer shows it (a JPEG's EXIF
    orientation applied, as image viewers do: a phone photo's box is drawn on the turned
    image): grayscale and 16-bit images converted, alpha dropped; ValueError for a missing,
    corrupt or huge file (over ``MAX_PIXELS``, refused from its header before decoding)."""
    import cv2
    import numpy as np
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise ValueError("no such file")
    try:
        with Image.open(path) as im:
            w, h = im.size
    except Image.DecompressionBombError:
        raise ValueError(f"the image is larger than {MAX_PIXELS // 1_000_000} megapixels; "
                         "scale it down first") from None
    except (UnidentifiedImageError, OSError, ValueError):
        raise ValueError("cannot read the image (corrupt or not an image)") from None
    if w * h > MAX_PIXELS:
        raise ValueError(f"the image is {w}x{h}: larger than {MAX_PIXELS // 1_000_000} "
                         "megapixels; scale it down first")
    img = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)   # not UNCHANGED:
    #                                                          it ignores the EXIF orientation
    if img is None or img.size == 0:
        raise ValueError("cannot read the image (corrupt or not an image)")
    if img.dtype == np.uint16:
        img = ((img.astype(np.uint32) + 128) // 257).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise ValueError(f"unsupported pixel type {img.dtype}")
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    elif img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    else:
        raise ValueError(f"unsupported channel count {img.shape[2]}")
    return np.ascontiguousarray(img)


def read_mask(path, shape):
    """(H, W) bool of a mask image the photo's size (``vehicle_mask``); ValueError naming the
    mask file when it cannot be read or is another size (callers prefix the photo's path)."""
    try:
        img = read_image(path)
    except ValueError as exc:
        raise ValueError(f"mask {path}: {exc}") from None
    if img.shape[:2] != tuple(shape):
        raise ValueError(f"mask {path} is {img.shape[1]}x{img.shape[0]}, the photo "
                         f"{shape[1]}x{shape[0]}")
    return vehicle_mask(img)


def match_meshes(reader, key: str) -> list:
    """Catalogued meshes that ``key`` names (``CatalogReader.find``: id, id prefix of >= 8 hex
    digits, path in any spelling, file name)."""
    return reader.find(key)


def format_rows(rows, indent: str = "") -> str:
    """Material -> part rows (anything with name, part, score, iou, view, decision, pixels:
    a fresh ``MaterialPart`` or a catalogue ``PartRow``) as an aligned text table. ``prob`` is
    the labeller's probability of the part (``-`` without a labeller: the score of self-painted
    masks is 1.00 by construction and says nothing); ``split`` lists a shared material's parts
    per component group with their area shares."""
    lines = [f"{indent}{'material':32s} {'part':9s} {'prob':>5s} {'score':>5s} {'iou':>5s} "
             f"{'view':>4s} {'decision':15s} {'pixels':>8s}  split"]
    for r in rows:
        prob, split = _prob_split(r)
        p = f"{prob:5.2f}" if prob is not None else f"{'-':>5s}"
        sp = " ".join(f"{g['part']}:{g['area_share']:.2f}" for g in split or [])
        lines.append(f"{indent}{r.name[:32]:32s} {r.part:9s} {p} {r.score:5.2f} {r.iou:5.2f} "
                     f"{r.view:4d} {r.decision:15s} {r.pixels:8d}  {sp}".rstrip())
    return "\n".join(lines)


def label_confidence(r) -> float:
    """How sure the recorded label of a catalogue row is, in [0, 1]: 0 for an unseen material,
    else the labeller's probability of its part (``props['prob']``), else its score (segmenters
    without a labeller); a curator's override is 1."""
    if r.decision == "override":
        return 1.0
    if r.part == "unseen":
        return 0.0
    prob = (r.props or {}).get("prob")
    return float(prob) if prob is not None else float(r.score)


def format_low_confidence(sha256: str, rows, n: int, indent: str = "") -> str:
    """The ``n`` materials whose labels are least sure (``label_confidence`` ascending; ties:
    more visible pixels first, then material index), curators' overrides left out, each with a
    line for ``build --labels-file`` that a person edits to the right part (the material by
    name, or ``#index`` when its name is shared or reads as an index; PART stands for the part
    of an unseen material, which the file refuses until it is edited)."""
    import shlex

    names = [r.name for r in rows]

    def key(r) -> str:
        plain = names.count(r.name) == 1 and not (r.name[:1] == "#" and r.name[1:].isdigit())
        return shlex.quote(r.name) if plain else f"#{r.index}"

    todo = sorted((r for r in rows if r.decision != "override"),
                  key=lambda r: (label_confidence(r), -r.pixels, r.index))[:max(n, 0)]
    lines = [f"{indent}lowest label confidence first ({len(todo)} of {len(rows)} materials; "
             "fix one with a --labels-file line):",
             f"{indent}  {'conf':>5s} {'material':32s} {'part':9s} {'pixels':>8s}  "
             "labels-file line"]
    for r in todo:
        lines.append(f"{indent}  {label_confidence(r):5.2f} {r.name[:32]:32s} {r.part:9s} "
                     f"{r.pixels:8d}  {sha256} {key(r)} {'PART' if r.part == 'unseen' else r.part}")
    return "\n".join(lines)


def _prob_split(r):
    """(prob, split) of a ``MaterialPart`` (fields) or a catalogue row (its ``props``)."""
    if hasattr(r, "prob"):
        return r.prob, r.split
    props = getattr(r, "props", None) or {}
    return props.get("prob"), props.get("split")
