"""``ucad-index demo``: the main job on an embedded default (a generated sample library)."""
from __future__ import annotations

from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser(
        "demo", help="generate a sample vehicle library and build its catalogue (the README's first command)",
        description="Generate a sample library of procedural vehicles (with messy cases: odd units, "
                    "orientations, offsets, one-material and broken files), build the part-labelled "
                    "catalogue from it, and write contact sheets to look at. Everything goes under OUT.")
    p.add_argument("--out", type=Path, default=Path("sample-catalog"), metavar="DIR",
                   help="output folder (default ./sample-catalog)")
    p.add_argument("--count", type=int, default=24, help="vehicles to generate (default 24)")
    p.add_argument("--seed", type=int, default=0, help="generator seed (default 0)")
    p.add_argument("--workers", type=int, default=1, help="build worker processes (default 1)")
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np

    from ucad_catalog.exr import read_viewset_exr
    from ucad_catalog.reader import CatalogReader

    from ..build import BuildOptions, build
    from ..cameras import label_ring
    from ..sheets import material_sheet, write_png
    from ..synth import write_library
    from .build import print_summary

    lib, cat, sheets = args.out / "library", args.out / "catalog", args.out / "sheets"
    print(f"1/4 generating {args.count} vehicles into {lib}")
    # 0.55 of 24 vehicles = 13 messy ones: every messy trait once (odd units, orientations,
    # offsets, merged or thousands of materials, missing wheels, one-material, NaN, empty, truncated)
    write_library(lib, args.count, seed=args.seed, messy_fraction=0.55)
    print(f"2/4 building the catalogue {cat} (72 views x 256 px per mesh)")
    summary = build(lib, cat, BuildOptions())
    print_summary(summary, cat)
    print(f"3/4 contact sheets in {sheets}")
    sheets.mkdir(parents=True, exist_ok=True)
    with CatalogReader(cat) as r:
        accepted = r.meshes()
        for m in accepted[:4]:
            stem = Path(m.path).stem
            views, meta = read_viewset_exr(r.artifact_path(m.sha256, "views.exr"))
            ring = label_ring(views.cameras).stop
            views = views.select(np.arange(0, ring, max(1, ring // 12)))   # the label ring
            write_png(sheets / f"{stem}.materials.png", material_sheet(views, meta["materials"]))
            (sheets / f"{stem}.parts.png").write_bytes(r.artifact_path(m.sha256, "parts.png").read_bytes())
        rejected = r.meshes(state="rejected")
        fitted = demo_fit(r, accepted, args.out / "fit") if accepted else None
    print(f"\nlook at: {sheets}/*.png (views by material and by part),")
    if fitted is not None:
        print(f"         {fitted}.png (a photo-like reference | the fitted model | part masks | "
              "error),")
    print(f"         ucad-index status --catalog {cat}")
    if accepted:
        print(f"         ucad-index show {accepted[0].id[:12]} --catalog {cat}")
    for m in rejected:
        print(f"rejected {Path(m.path).name}: {m.reason}")
    return 0


DEMO_COLORS = {"body": (0.55, 0.05, 0.04), "wheel": (0.03, 0.03, 0.03),
               "rim": (0.65, 0.65, 0.65), "plate": (0.8, 0.8, 0.78),
               "interior": (0.12, 0.12, 0.12)}


def demo_fit(reader, accepted, out: Path):
    """4/4: a photo-like reference (``ucad_cl.refphoto``: Embree, clutter, noise, JPEG) of the
    first accepted vehicle in DEMO_COLORS, fitted from its box with that mesh given
    (``ucad-index fit --mesh``); returns DIR/<stem> of the outputs, or None when it fails."""
    import cv2

    from ..fit import fit_photo
    from ..ingest import IngestError, load_mesh
    from ..orient import in_frame
    from ..refphoto import render_reference
    from .fit import report, write_outputs

    m = accepted[0]
    print(f"4/4 fitting a photo-like reference of {Path(m.path).name} (colours the demo picks)")
    try:
        mesh = in_frame(load_mesh(m.source, orientation=None), m.file_to_norm)
        rows = sorted(reader.parts(m.sha256), key=lambda r: r.index)
        ref = render_reference(mesh, [r.part for r in rows], DEMO_COLORS, azimuth=35.0,
                               elevation=12.0, seed=7, background="clutter")
        out.mkdir(parents=True, exist_ok=True)
        photo = out / "reference.jpg"
        cv2.imwrite(str(photo), ref.image[:, :, ::-1])
        res = fit_photo(ref.image, box=ref.box, catalog=reader, mesh=m.sha256)
    except (IngestError, ValueError) as exc:
        print(f"   fit skipped: {exc}")
        return None
    base = write_outputs(res, out, "reference")
    print(f"   ucad-index fit {photo} --box {' '.join(map(str, ref.box))} --catalog "
          f"{reader.root} --mesh {m.sha256[:12]} --out {out}")
    report(res, base)
    return base
