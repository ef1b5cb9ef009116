"""``ucad-index render MESH... --out DIR``: 360-degree material-index views of meshes."""
from __future__ import annotations

import os
import sys
from pathlib import Path


def add_camera_args(p, elevations=(15.0,), elevations_help: str = "") -> None:
    """Camera-ring options shared by the commands that render (``elevations``: the default
    rings, with ``elevations_help`` said after them)."""
    g = p.add_argument_group("cameras")
    g.add_argument("--azimuth-step", type=float, default=5.0, metavar="DEG",
                   help="azimuth step in degrees; M = 360/step views per elevation (default 5 -> 72)")
    g.add_argument("--elevations", type=float, nargs="+", default=list(elevations),
                   metavar="DEG", help="camera elevations in degrees (default "
                   f"{' '.join(f'{e:g}' for e in elevations)}){elevations_help}")
    g.add_argument("--fov", type=float, default=40.0, metavar="DEG",
                   help="field of view in degrees (default 40); the distance is fitted to it")
    g.add_argument("--size", type=int, default=256, metavar="PX",
                   help="image width and height in pixels (default 256)")


def add_orientation_args(p) -> None:
    """Orientation options shared by the commands that load meshes."""
    g = p.add_argument_group(
        "orientation", "Meshes are turned into the canonical vehicle frame (+Y up, front +X, "
        "right side +Z; azimuth 0 = the front view) when loaded.")
    g.add_argument("--orientation", default="auto", metavar="MODE",
                   help="auto (default: estimate up and front from wheels, symmetry, glazing, "
                        "lamps, names...), file (trust the file: +Y up, no rotation), or "
                        "UP,FRONT: the file's up and front axes, e.g. +Z,-Y for a Z-up file "
                        "whose nose points to -Y (write --orientation=-Z,+X when UP starts "
                        "with '-')")
    g.add_argument("--orientation-file", type=Path, default=None, metavar="FILE",
                   help="per-mesh overrides: JSON {\"PATH or SHA256\": \"+Z,-Y\"} or text lines "
                        "'PATH_OR_SHA256 UP FRONT' (paths relative to FILE); they win over "
                        "--orientation for the meshes they name")


def orientation_from_args(args):
    """(mode, overrides or None) from --orientation / --orientation-file; ValueError names
    the problem."""
    from ..orient import OrientationOverrides, parse_mode

    mode = parse_mode(args.orientation)
    overrides = None
    if getattr(args, "orientation_file", None) is not None:
        overrides = OrientationOverrides.read(args.orientation_file)
    return mode, overrides


def describe_orientation(o) -> str:
    """One line: how a mesh was oriented (an Orientation or its ``as_dict()`` record)."""
    if o is None:
        return "orientation: none recorded"
    d = o if isinstance(o, dict) else o.as_dict()
    if not d:
        return "orientation: none recorded"
    import numpy as np

    from ..orient import axis_label

    R = np.asarray(d["rotation"], np.float64)
    exact = bool(np.all(np.isin(R, (-1.0, 0.0, 1.0))))
    up = axis_label(R[1]) if exact else np.array2string(R[1], precision=3)
    front = axis_label(R[0]) if exact else np.array2string(R[0], precision=3)
    text = f"orientation {d['source']}: file up {up}, front {front}"
    if d["source"] == "auto":
        text += (f" (confidence up {d['up_confidence']:.2f}, front "
                 f"{d['front_confidence']:.2f}{', UNCERTAIN' if d.get('uncertain') else ''})")
    if d.get("flags"):
        text += f" flags: {', '.join(d['flags'])}"
    return text


def ring_from_args(args):
    from ..cameras import make_ring
    return make_ring(azimuth_step=args.azimuth_step, elevations=args.elevations,
                     fov_deg=args.fov, size=args.size)


def output_stems(meshes) -> list[str]:
    """The output name of each input mesh (its file name without the suffix); ValueError naming
    the inputs when two would write the same outputs (one output folder holds one name once)."""
    stems = [Path(m).name.rsplit(".", 1)[0] for m in meshes]
    seen: dict[str, str] = {}
    clashes = []
    for m, s in zip(meshes, stems):
        if s in seen and os.path.abspath(seen[s]) != os.path.abspath(m):
            clashes.append(f"{seen[s]} and {m} -> {s}.*")
        seen.setdefault(s, m)
    if clashes:
        raise ValueError("two inputs would write the same outputs (" + "; ".join(clashes[:5])
                         + "); nothing was written: rename one, or run them with separate --out "
                         "folders")
    return stems


def register(sub) -> None:
    p = sub.add_parser(
        "render", help="render material-index / triangle-id / depth views of meshes",
        description="Render 360-degree views of each MESH (GLB, glTF, OBJ+MTL, PLY, OFF, STL) with "
                    "the OpenCL rasterizer. Writes, per mesh, DIR/NAME.views.exr (multi-part OpenEXR: "
                    "UINT tri and mat ids, FLOAT depth, cameras in the headers; see docs/FORMATS.md) "
                    "and DIR/NAME.sheet.png (contact sheet, a fixed colour per material). NAME is the "
                    "file name without its suffix; two inputs with the same NAME are refused "
                    "before anything is written. Exit status 1 if any mesh failed, 2 for a usage "
                    "error, 0 otherwise.")
    p.add_argument("meshes", nargs="+", metavar="MESH", help="mesh files")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder")
    add_camera_args(p)
    add_orientation_args(p)
    p.add_argument("--no-sheet", action="store_true",
                   help="skip the PNG contact sheets (they start at the front view, azimuth 0)")
    p.add_argument("--edges", action="store_true",
                   help="also write ControlNet conditioning images: Canny edges of the material "
                        "maps, white on black, DIR/NAME.edges/NAME_VVV.png")
    p.set_defaults(func=run)


def run(args) -> int:
    from tqdm import tqdm

    from ucad_catalog.exr import write_viewset_exr

    from ..system import printable
    from ..ingest import IngestError, describe_exception, load_mesh_isolated
    from ..render import render_views
    from ..sheets import material_sheet, write_png

    try:
        stems = dict(zip(args.meshes, output_stems(args.meshes)))
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    ring = ring_from_args(args)
    try:
        mode, overrides = orientation_from_args(args)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    from ..runtime import get_runtime
    get_runtime()           # no usable OpenCL device: one line (cli.main), not one per file
    args.out.mkdir(parents=True, exist_ok=True)
    failed = 0
    bar = tqdm(args.meshes, unit="mesh", desc="render", disable=None)
    for path in bar:
        stem = stems[path]
        try:
            mesh = load_mesh_isolated(path, orientation=mode, overrides=overrides)
            views = render_views(mesh, ring)
            write_viewset_exr(args.out / f"{stem}.views.exr", views, mesh)
            if args.edges:
                from ..edges import material_edges, write_conditioning_pngs
                write_conditioning_pngs(material_edges(views), args.out / f"{stem}.edges", stem)
            if not args.no_sheet:
                write_png(args.out / f"{stem}.sheet.png",
                          material_sheet(views, [m.name for m in mesh.materials]))
            bar.write(f"ok    {printable(path)}: {mesh.n_faces} triangles, {len(mesh.materials)} materials, "
                      f"{views.n_views} views -> {args.out / (stem + '.views.exr')}; "
                      f"{describe_orientation(mesh.orientation)}")
        except IngestError as exc:                  # every file gets its line, none stops us
            failed += 1
            bar.write(f"FAIL  {printable(str(exc))}", file=sys.stderr)
        except MemoryError:
            failed += 1
            bar.write(f"FAIL  {printable(path)}: out of memory [too_large]", file=sys.stderr)
        except Exception as exc:                    # noqa: BLE001 - reported per file
            failed += 1
            bar.write(f"FAIL  {printable(path)}: {describe_exception(exc)}", file=sys.stderr)
    print(f"{len(args.meshes) - failed} rendered, {failed} failed; outputs in {args.out}")
    return 1 if failed else 0
