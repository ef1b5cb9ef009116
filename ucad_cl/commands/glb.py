"""``ucad-index export-glb ID|--all --catalog CAT --out DIR``: part-labelled GLBs for glTF tools."""
from __future__ import annotations

import sys
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser(
        "export-glb", help="write catalogued models back as GLB with each material's part",
        description="Write each chosen accepted mesh as DIR/NAME.glb (glTF 2.0 binary) for "
                    "Blender, three.js or any glTF viewer: the model's triangles (re-read from "
                    "the source file under the recorded library folder; refused when the file "
                    "moved or changed since it was catalogued), one primitive per material, and "
                    "in every material's extras.ucad its part, score and decision. "
                    "--part-materials replaces each labelled material with UrbanCAD's "
                    "part-level physically based prior (car paint with clear coat, glass with "
                    "KHR_materials_transmission, tyre rubber, alloy rims, chrome, lamp lenses "
                    "with emission, plate, interior; ucad_catalog/parts.py); --transfer-from "
                    "copies another catalogued model's material of each part (material "
                    "transfer). Textures and UVs are not carried. Exit status 1 if any mesh "
                    "could not be written.")
    p.add_argument("ids", nargs="*", metavar="ID",
                   help="mesh id or id prefix (>= 8 hex digits), path or file name")
    p.add_argument("--all", action="store_true", help="every accepted mesh of the catalogue")
    p.add_argument("--catalog", required=True, type=Path, metavar="PATH")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder")
    p.add_argument("--frame", choices=["file", "canonical"], default="file",
                   help="file: the source's own coordinates (default); canonical: +Y up, "
                        "centred, bounding-box diagonal 1")
    p.add_argument("--part-materials", action="store_true",
                   help="give every labelled material its part's physically based prior")
    p.add_argument("--transfer-from", metavar="ID", default=None,
                   help="take each part's material from this catalogued model")
    p.set_defaults(func=run)


def run(args) -> int:
    from ucad_catalog import CatalogError

    from ..jobs import content_sha256
    from ..glb import donor_materials, write_glb
    from ..ingest import IngestError, load_mesh
    from .common import open_reader

    if bool(args.ids) == bool(args.all):
        print("error: give mesh IDs or --all (not both)", file=sys.stderr)
        return 2
    reader = open_reader(args.catalog)
    if reader is None:
        return 2
    with reader as r:
        try:
            metas = r.meshes() if args.all else [r.mesh(k) for k in args.ids]
            donor = (donor_materials(r.parts(r.mesh(args.transfer_from).sha256))
                     if args.transfer_from else None)
        except CatalogError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        names = _file_names(metas)
        failed = 0
        for m, name in zip(metas, names):
            try:
                if m.state != "accepted":
                    raise ValueError(f"rejected ({m.reason}: {m.detail}); it has no part table")
                src = m.source
                if not src.is_file():
                    raise ValueError(f"the source file is not at {src} (library folder recorded "
                                     f"as {m.library_root or 'unknown'}); it moved or was "
                                     "deleted")
                if content_sha256(src) != m.sha256:
                    raise ValueError(f"{src} changed since it was catalogued (its content hash "
                                     "differs); rebuild the catalogue first")
                mesh = load_mesh(src)
                out = write_glb(args.out / name, mesh, r.parts(m.sha256), frame=args.frame,
                                part_materials=args.part_materials, donor=donor,
                                mesh_id=m.sha256)
                print(f"ok    {m.sha256[:12]} {m.path} -> {out}")
            except (ValueError, OSError, IngestError, CatalogError) as exc:
                failed += 1
                print(f"FAIL  {m.sha256[:12]} {m.path}: {exc}", file=sys.stderr)
    print(f"{len(metas) - failed} written, {failed} failed; outputs in {args.out}")
    return 1 if failed else 0


def _file_names(metas) -> list[str]:
    """NAME.glb per mesh; names that would collide get the id's first 8 digits."""
    stems = [Path(m.path).stem for m in metas]
    return [f"{s}.glb" if stems.count(s) == 1 else f"{s}-{m.sha256[:8]}.glb"
            for s, m in zip(stems, metas)]
