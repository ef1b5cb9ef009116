"""``ucad-index fit PHOTO (--box X0 Y0 X1 Y1 | --mask MASK) --catalog CAT [--mesh MESH] --out DIR``:
fit the part materials of a catalogued vehicle to a photo (``ucad_cl.fit``; docs/FIT.md).

Writes DIR/<stem>.json (mesh, pose, lighting, parts, materials, candidates, retrieval_margin,
seconds; a note when retrieval is uncertain),
DIR/<stem>.glb (the model with every material replaced by its part's fitted material; not
written when the mesh file moved) and DIR/<stem>.png (photo | fitted render | part masks over
the photo | error map). ``--photos LIST.csv`` (columns path,x0,y0,x1,y1[,mesh], or a header
naming path, the box or a mask column, and mesh: ``read_list``; paths relative to the list's
folder) fits many photos with a progress bar. Bad input: one line on stderr, exit
status 2 (1 when some photos of a list failed).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path


DESCRIPTION = """\
Fit each part's material of a catalogued vehicle to a photo of it: the model and pose are
found in the catalogue (or MESH is given), the part masks come from the render at that pose
inside the photo's vehicle, and a light model (sky, sun, clear-coat reflection) is estimated
jointly with one base colour per part; metallic, roughness, clear coat and transmission stay
the part prior's (ucad_catalog/parts.py). See docs/FIT.md.

examples:
  ucad-index fit street.jpg --box 120 80 460 300 --catalog cat --out fits
  ucad-index fit street.jpg --mask car.png --catalog cat --mesh 3f2a9c01 --out fits
  ucad-index fit --photos photos.csv --catalog cat --out fits

The photo list: one photo a line, path,x0,y0,x1,y1[,mesh]; or with a header line naming the
columns, e.g. "path,mask,mesh" for vehicle masks from a segmenter (paths relative to the list).
A mask finds the right mesh more often than a box (GrabCut's mask errors cost retrieval:
docs/FIT.md, "The object mask's share of retrieval"). When the next retrieved mesh scores
nearly as well as the answer (the JSON's retrieval_margin), a note says retrieval is uncertain:
look at the candidates the output lists, or give MESH (docs/FIT.md, "How sure retrieval is").

Boxes and masks are in the photo as a viewer shows it (a JPEG's EXIF orientation applied). A
phone-sized photo is fine: it is analysed in a window around the box, and the pose (K, w2c)
comes back in the photo's pixels.
"""


def register(sub) -> None:
    import argparse

    p = sub.add_parser("fit", help="fit a catalogued vehicle's part materials to a photo",
                       description=DESCRIPTION,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("photo", type=Path, nargs="?", default=None,
                   help="reference photo (PNG/JPEG; grayscale and 16-bit are converted)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--box", type=float, nargs=4, metavar=("X0", "Y0", "X1", "Y1"),
                   help="vehicle box in pixels (x1, y1 exclusive); GrabCut finds the vehicle")
    g.add_argument("--mask", type=Path, help="vehicle mask image, same size (vehicle: at least "
                   "half its largest value)")
    p.add_argument("--photos", type=Path, default=None, metavar="LIST.csv",
                   help="fit every row of this CSV (path,x0,y0,x1,y1[,mesh]; or a header "
                        "naming the columns, e.g. path,mask,mesh)")
    p.add_argument("--catalog", required=True, type=Path, metavar="CAT")
    p.add_argument("--mesh", default=None, metavar="MESH",
                   help="the catalogued mesh (id, id prefix, path or file name); default: "
                        "retrieval over the whole catalogue")
    p.add_argument("--segmenter", default=None, metavar="onnx:MODEL:CONFIG.json",
                   help="part masks from this ONNX image segmenter instead of the render")
    p.add_argument("--vgg", default=None, metavar="onnx:MODEL:CONFIG.json",
                   help="add the paper's l_vgg (masked Gram matrices of this ONNX feature "
                        "extractor's maps, e.g. a VGG-16 you export; none ships) to the "
                        "objective; config: input_size [H, W], mean, std, outputs, "
                        "layer_weights, weight (docs/FIT.md, 'The VGG term')")
    p.add_argument("--fov", type=float, default=None, metavar="DEG",
                   help="the photos' field of view over the narrower side, in degrees, when "
                        "known (a long lens: small, a close-up with a wide lens: large); "
                        "default: 45 assumed")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder")
    p.set_defaults(func=run)


def run(args) -> int:
    from ucad_catalog import CatalogError
    from ucad_catalog.reader import CatalogReader

    if (args.photo is None) == (args.photos is None):
        print("error: give PHOTO (with --box or --mask) or --photos LIST.csv", file=sys.stderr)
        return 2
    if args.photo is not None and args.box is None and args.mask is None:
        print("error: give --box X0 Y0 X1 Y1 or --mask MASK.png", file=sys.stderr)
        return 2
    options = {}
    for flag, spec in (("--segmenter", args.segmenter), ("--vgg", args.vgg)):
        try:
            options[flag] = _onnx_option(flag, spec)
        except (ValueError, OSError) as exc:
            print(f"error: {flag} {spec}: {exc}", file=sys.stderr)
            return 2
    segmenter, vgg = options["--segmenter"], options["--vgg"]
    try:
        reader = CatalogReader(args.catalog)
    except CatalogError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    with reader:
        if args.photo is not None:
            loader = _loader_for(args.mesh, getattr(args, "mesh_reader", None))
            try:
                res, out = fit_one(reader, args.photo, args.box, args.mask, args.mesh,
                                   args.out, segmenter, loader, args.fov, vgg)
            except ValueError as exc:
                print(f"{args.photo}: {exc}", file=sys.stderr)
                return 2
            finally:
                if loader is not None:
                    loader.close()
            report(res, out)
            return 0
        return run_list(reader, args, segmenter, vgg)


def _onnx_option(flag: str, spec: str | None):
    """What an ``onnx:MODEL:CONFIG.json`` option names (None without it): the photo segmenter
    of ``--segmenter``, the feature extractor of ``--vgg``; ValueError / OSError naming the
    file. (Imported here: a lone call reads its mesh ahead before importing the fit.)"""
    if not spec:
        return None
    if flag == "--segmenter":
        from ..fit import OnnxPhotoSegmenter
        return OnnxPhotoSegmenter.from_spec(spec)
    from ..vgg import OnnxFeatures
    return OnnxFeatures.from_spec(spec)


def _loader_for(mesh_key, child=None):
    """The ``ingest.MeshLoader`` of one photo: on ``child``, the reader's child the CLI started
    first thing (``cli._mesh_reader_ahead``), when there is one; else, with ``--mesh``, an
    isolated one started now, so that ``fit_one`` can have the mesh read while this process
    imports the fit, reads the photo and finds the object (the fit's ``load`` step then finds it
    read; docs/FIT.md); None without either (the fit starts its own beside retrieval) or when
    no process can be had (the fit then reads the mesh in this process)."""
    if mesh_key is None and child is None:
        return None
    from ..ingest import MeshLoader

    try:
        return MeshLoader(child=child)
    except OSError:
        return None


def _read_ahead(reader, mesh_key, mesh_loader) -> None:
    """Start reading the mesh ``mesh_key`` names in ``mesh_loader``'s child, when the
    catalogue has it accepted and its file is there (anything else is the fit's to report)."""
    from ucad_catalog import CatalogError

    if mesh_key is None or mesh_loader is None or not mesh_loader.isolated:
        return
    try:
        meta = reader.mesh(str(mesh_key))
    except CatalogError:
        return
    if meta.state == "accepted" and meta.source.is_file():
        mesh_loader.prefetch(meta.source)


def run_list(reader, args, segmenter, vgg=None) -> int:
    from tqdm import tqdm

    try:
        jobs = read_list(args.photos)
    except (ValueError, OSError) as exc:
        print(f"{args.photos}: {exc}", file=sys.stderr)
        return 2
    from ..fit import retrieval_uncertain
    from ..ingest import MeshLoader

    failed = unsure = 0
    with MeshLoader(child=getattr(args, "mesh_reader", None)) as mesh_loader:   # one child
        for path, box, mask, mesh in tqdm(jobs, unit="photo", desc="fit", disable=None):
            try:
                res, out = fit_one(reader, path, box, mask, mesh or args.mesh, args.out,
                                   segmenter, mesh_loader, args.fov, vgg)
                m = res.retrieval_margin
                flag = retrieval_uncertain(m)
                unsure += flag
                tqdm.write(f"ok    {path} -> {out}.json ({res.mesh_path})"
                           + (f"  retrieval uncertain (margin {m:.1%})" if flag else ""))
            except ValueError as exc:
                failed += 1
                tqdm.write(f"FAIL  {path}: {exc}", file=sys.stderr)
    print(f"{len(jobs) - failed} fitted, {failed} failed; outputs in {args.out}"
          + (f"; retrieval uncertain for {unsure} (check their candidates, or give the mesh)"
             if unsure else ""))
    return 1 if failed else 0


LIST_COLUMNS = ("path", "x0", "y0", "x1", "y1", "mask", "mesh")


def read_list(path: Path) -> list:
    """[(photo path, box or None, mask path or None, mesh or None)] of a photo list (CSV).

    Without a header: columns path,x0,y0,x1,y1[,mesh]. With a header (first cell ``path``),
    columns by name, any of ``LIST_COLUMNS`` in any order: each row gives the box (x0..x1) or
    a ``mask`` image (``common.vehicle_mask``), not both; an empty ``mesh`` means retrieval. Paths
    are relative to the list's folder. ValueError naming the line for a malformed row."""
    import csv

    def where(p: str) -> Path:
        q = Path(p.strip())
        return q if q.is_absolute() else path.parent / q

    rows = []
    names = ["path", "x0", "y0", "x1", "y1", "mesh"]
    with open(path, newline="", encoding="utf-8-sig") as f:     # a spreadsheet's BOM dropped
        for k, row in enumerate(csv.reader(f)):
            if not row or row[0].strip().startswith("#"):
                continue
            if k == 0 and row[0].strip().lower() == "path":
                names = [c.strip().lower() for c in row]
                unknown = [c for c in names if c not in LIST_COLUMNS]
                if unknown or len(set(names)) != len(names):
                    raise ValueError(f"line 1: columns must be distinct names among "
                                     f"{','.join(LIST_COLUMNS)}; got {','.join(names)}")
                if "mask" not in names and not {"x0", "y0", "x1", "y1"} <= set(names):
                    raise ValueError("line 1: give the box columns x0,y0,x1,y1 or a mask "
                                     "column")
                continue
            if names[-1] == "mesh" and len(row) == len(names) - 1:
                row = row + [""]                    # the optional last mesh column left out
            if len(row) != len(names):
                raise ValueError(f"line {k + 1}: expected {','.join(names)}, got {len(row)} "
                                 "columns")
            cell = {n: v.strip() for n, v in zip(names, row)}
            corners = [cell.get(n, "") for n in ("x0", "y0", "x1", "y1")]
            box = mask = None
            if any(corners):
                try:
                    box = [float(v) for v in corners]
                except ValueError:
                    raise ValueError(f"line {k + 1}: the box must be 4 numbers") from None
            if cell.get("mask"):
                mask = where(cell["mask"])
            if (box is None) == (mask is None):
                raise ValueError(f"line {k + 1}: give the box (x0,y0,x1,y1) or a mask, "
                                 + ("not both" if box is not None else "neither is given"))
            rows.append((where(cell["path"]), box, mask, cell.get("mesh") or None))
    if not rows:
        raise ValueError("no photo listed")
    return rows


def fit_one(reader, photo: Path, box, mask_path, mesh, out_dir: Path, segmenter, mesh_loader=None,
            fov: float | None = None, vgg=None):
    """Fit one photo and write its three outputs; ValueError with one line on bad input.
    ``mesh_loader``: an ``ingest.MeshLoader`` kept over a list of photos, or started for this
    photo's given mesh (else the fit starts one); a given mesh is read ahead in its child;
    ``fov``: the photo's field of view and ``vgg``: the l_vgg feature extractor (``fit_photo``)."""
    _read_ahead(reader, mesh, mesh_loader)
    from ..fit import fit_photo
    from .common import read_image, read_mask

    image = read_image(photo)
    mask = read_mask(mask_path, image.shape[:2]) if mask_path is not None else None
    res = fit_photo(image, box=box, mask=mask, catalog=reader, mesh=mesh, segmenter=segmenter,
                    mesh_loader=mesh_loader, fov=fov, vgg=vgg)
    try:
        out = write_outputs(res, out_dir, photo.stem)
    except OSError as exc:
        raise ValueError(f"cannot write the outputs to {out_dir}: {exc.strerror or exc}"
                         ) from None
    return res, out


UNCERTAIN_BAND = (170, 20, 20)   # the overview's band for an uncertain retrieval (RGB)


def write_outputs(res, out_dir: Path, stem: str) -> Path:
    """DIR/<stem>.json, .png and (with the mesh) .glb; returns DIR/<stem>."""
    import cv2

    from ..glb import write_glb

    out_dir.mkdir(parents=True, exist_ok=True)
    base = out_dir / stem
    doc = res.to_json()
    glb = None
    if res.mesh is not None:
        glb = write_glb(base.with_suffix(".glb"), res.mesh, res.part_rows,
                        mesh_id=res.mesh_id, fitted=doc["parts"])
    doc["glb"] = str(glb) if glb else None
    base.with_suffix(".json").write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    cv2.imwrite(str(base.with_suffix(".png")), overview(res)[:, :, ::-1])
    return base


def overview(res, height: int = 256):
    """(h, 4w, 3) uint8 RGB: photo | fitted render | part masks over the photo | error map
    (|photo - render| in 8-bit sRGB levels, x4, inside the vehicle), in the working frame; when
    retrieval was uncertain (``fit.retrieval_uncertain``) a red band across its top says so."""
    import cv2
    import numpy as np

    from ..fit import retrieval_uncertain
    from ..segment import material_colors

    im = res.images
    photo, render = im.photo, im.render
    parts = photo.copy()
    cols = material_colors(16)
    sel = im.part_map >= 0
    parts[sel] = (0.4 * photo[sel] + 0.6 * cols[im.part_map[sel] + 1]).astype(np.uint8)
    err = np.abs(photo.astype(np.int32) - render.astype(np.int32)).max(axis=2)
    emap = cv2.applyColorMap(np.clip(err * 4, 0, 255).astype(np.uint8), cv2.COLORMAP_JET)
    emap = emap[:, :, ::-1].copy()
    emap[~im.object] = 0
    row = np.concatenate([photo, render, parts, emap], axis=1)
    h, w = row.shape[:2]
    if h > height:
        row = cv2.resize(row, (int(round(w * height / h)), height),
                         interpolation=cv2.INTER_AREA)
    row = np.ascontiguousarray(row)
    m = res.retrieval_margin
    if retrieval_uncertain(m):
        band = max(12, row.shape[0] // 14)
        row[:band] = UNCERTAIN_BAND
        cv2.putText(row, f"retrieval uncertain (margin {m:.1%}): check the candidates",
                    (4, band - max(3, band // 4)), cv2.FONT_HERSHEY_SIMPLEX, band / 32,
                    (255, 255, 255), 1, cv2.LINE_AA)
    return row


def report(res, out: Path) -> None:
    print(f"mesh {res.mesh_id[:12]} {res.mesh_path}")
    print(f"pose azimuth {res.pose.azimuth:.1f} elevation {res.pose.elevation:.1f} "
          f"({res.pose.source})")
    for c in res.candidates[1:]:
        print(f"  next: {c.mesh_id[:12]} {Path(c.mesh_path).name} view {c.view} "
              f"score {c.score:.4f}")
    for note in res.notes:
        print(f"note: {note}")
    doc = res.to_json()
    for p, f in doc["parts"].items():
        extra = f"  ({f['reason']})" if f.get("reason") else ""
        print(f"  {p:9s} {f['color_srgb']} {f['status']:8s} {f['pixels']:7d} px{extra}")
    if res.vgg is not None:
        v = res.vgg
        print(f"l_vgg ({v.model}, weight {v.weight:g}): {v.vgg_before:.4g} -> {v.vgg_after:.4g}, "
              f"objective {v.loss_before:.4g} -> {v.loss_after:.4g} ({v.jacobians} Jacobians, "
              f"{v.images} model runs, {v.seconds:.2f} s)")
    print(f"seconds: {sum(res.seconds.values()):.2f} "
          + " ".join(f"{k} {v:.2f}" for k, v in res.seconds.items()))
    print(f"wrote {out}.json, {out}.png" + (f", {out}.glb" if res.mesh is not None else ""))
