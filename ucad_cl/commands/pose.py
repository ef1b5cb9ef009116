"""``ucad-index pose IMAGE MESH``: estimate the camera pose of a vehicle photo against a mesh.

Prints the best candidates (azimuth, elevation in degrees, distance in canonical units, score =
squared feature distance, lower is better; a ``flipped`` candidate is the best one ~180 deg away)
and writes a side-by-side PNG: the reference crop | the best render, both at the same size.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("pose", help="estimate the pose of a vehicle photo against a mesh",
                       description="Crop the vehicle (--box or --mask), compare its features with "
                                   "renders of MESH on a camera ring, refine around the best "
                                   "views and print the best candidates.")
    p.add_argument("image", type=Path, help="reference photo (PNG/JPEG, RGB)")
    p.add_argument("mesh", type=Path, help="vehicle model (glb/gltf/obj) to match")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--box", type=float, nargs=4, metavar=("X0", "Y0", "X1", "Y1"),
                   help="object box in pixels (x1, y1 exclusive)")
    g.add_argument("--mask", type=Path, help="object mask image (non-zero = object)")
    p.add_argument("--top", type=int, default=5, help="candidates to print (default 5)")
    p.add_argument("--step", type=float, default=10.0, help="coarse azimuth step, degrees")
    p.add_argument("--elevations", type=float, nargs="+", default=[0.0, 15.0, 30.0],
                   help="coarse ring elevations, degrees")
    p.add_argument("--no-refine", action="store_true", help="coarse ring only")
    p.add_argument("--onnx", type=Path, default=None,
                   help="use this ONNX image encoder instead of the built-in HOG features")
    p.add_argument("--out", type=Path, default=None,
                   help="side-by-side PNG (default: IMAGE stem + '_pose.png' next to it)")
    # Hook for the lead: --catalog PATH will search stored ring features of many meshes with
    # ucad_cl.pose.search_catalog (then MESH becomes optional).
    p.add_argument("--catalog", type=Path, default=None, help=argparse.SUPPRESS)
    p.set_defaults(func=run)


def run(args) -> int:
    import cv2
    import numpy as np

    from ..features import HogExtractor, OnnxExtractor, crop_square
    from ..ingest import IngestError, load_mesh
    from ..pose import estimate_pose

    if args.catalog is not None:
        print("--catalog is not wired yet: give MESH", file=sys.stderr)
        return 2
    bgr = cv2.imread(str(args.image), cv2.IMREAD_COLOR)
    if bgr is None:
        print(f"{args.image}: cannot read the image", file=sys.stderr)
        return 2
    image = np.ascontiguousarray(bgr[:, :, ::-1])
    mask = None
    if args.mask is not None:
        m = cv2.imread(str(args.mask), cv2.IMREAD_GRAYSCALE)
        if m is None:
            print(f"{args.mask}: cannot read the mask", file=sys.stderr)
            return 2
        mask = m > 0
    try:
        mesh = load_mesh(args.mesh)
    except IngestError as exc:
        print(str(exc), file=sys.stderr)
        return 1
    extractor = OnnxExtractor(args.onnx) if args.onnx else HogExtractor()
    try:
        cands = estimate_pose(image, mesh, box=args.box, mask=mask, extractor=extractor,
                              azimuth_step=args.step, elevations=args.elevations,
                              top=args.top, refine=not args.no_refine)
    except ValueError as exc:
        print(f"{args.image}: {exc}", file=sys.stderr)
        return 2
    print(f"{'rank':>4s} {'azimuth':>8s} {'elev':>6s} {'dist':>6s} {'score':>7s}  note")
    for i, c in enumerate(cands):
        note = ("flipped " if c.flipped else "") + ("refined" if c.refined else "coarse")
        print(f"{i + 1:4d} {c.azimuth:8.1f} {c.elevation:6.1f} {c.distance:6.3f} "
              f"{c.score:7.4f}  {note}")
    out = args.out or args.image.with_name(args.image.stem + "_pose.png")
    side = side_by_side(image, mask, args.box, mesh, cands[0], crop_square)
    cv2.imwrite(str(out), side[:, :, ::-1])
    print(f"wrote {out}")
    return 0


def side_by_side(image, mask, box, mesh, cand, crop_square, size: int = 256):
    """(size, 2*size, 3) uint8: reference crop | render of ``cand``, same crop rule."""
    import numpy as np

    from ..cameras import make_ring
    from ..pose import RENDER_BACKGROUND, reference_mask
    from ..render import render_views
    from ..shade import shade_views

    qmask = reference_mask(image, box=box, mask=mask)
    ref, _ = crop_square(image[None], qmask[None], size)
    ring = make_ring(azimuths=[cand.azimuth], elevations=[cand.elevation], size=size)
    views = render_views(mesh, ring)
    rend = shade_views(mesh, views, background=RENDER_BACKGROUND)
    crop, _ = crop_square(rend, np.isfinite(views.depth), size)
    return np.concatenate([ref[0], crop[0]], axis=1)
