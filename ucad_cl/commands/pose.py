"""``ucad-index pose IMAGE MESH``: estimate the camera pose of a vehicle photo against a mesh.

Prints the best candidates (azimuth, elevation in degrees, distance in canonical units, score =
squared feature distance, lower is better; a ``flipped`` candidate is the best one ~180 deg away)
and writes a side-by-side PNG: the reference crop | the best render, both at the same size.
"""
from __future__ import annotations

import sys
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("pose", help="estimate the pose of a vehicle photo against a mesh",
                       description="Crop the vehicle (--box or --mask), compare its features with "
                                   "renders of MESH on a camera ring, refine around the best "
                                   "views and print the best candidates.")
    p.add_argument("image", type=Path, help="reference photo (PNG/JPEG, RGB)")
    p.add_argument("mesh", type=Path, nargs="?", default=None,
                   help="vehicle model (glb/gltf/obj) to match; omit with --catalog")
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
    p.add_argument("--catalog", type=Path, default=None, metavar="PATH",
                   help="search every stored view of every accepted mesh of this catalogue "
                        "(built-in features) instead of rendering one MESH")
    p.set_defaults(func=run, late_positional="mesh")


def run(args) -> int:
    import cv2
    import numpy as np

    from ..features import HogExtractor, OnnxExtractor, crop_square
    from ..ingest import IngestError, load_mesh
    from ..pose import estimate_pose

    if (args.catalog is None) == (args.mesh is None):
        print("give either MESH or --catalog PATH", file=sys.stderr)
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
    if args.catalog is not None:
        return run_catalog(args, image, mask)
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


def run_catalog(args, image, mask) -> int:
    """Nearest stored views across the whole catalogue (the features the build stored)."""
    import cv2
    import numpy as np

    from ucad_catalog._db import CatalogError

    from ..features import HogExtractor, crop_square
    from ..ingest import IngestError, load_mesh
    from ..pose import PoseCandidate, _box_side, reference_mask, search_catalog

    from .common import open_reader

    reader = open_reader(args.catalog)
    if reader is None:
        return 2
    with reader as r:
        metas = r.meshes()
        feats, mesh_ids, views, az, el, sides, dist = [], [], [], [], [], [], []
        for k, m in enumerate(metas):
            try:
                f = r.features(m.sha256)
            except (CatalogError, KeyError):
                continue                      # built with --no-features
            rec = r.record(m.sha256)
            for v in rec["views"]:
                w2c = np.asarray(v["w2c"], np.float64)
                dist.append(float(np.linalg.norm(w2c[:3, :3].T @ w2c[:3, 3])))
                sides.append(float(v["stats"].get("box_side", np.nan))
                             / min(np.asarray(v["K"])[:2, 2] * 2))
                az.append(v["azimuth"])
                el.append(v["elevation"])
                views.append(v["index"])
                mesh_ids.append(k)
            feats.append(f)
    if not feats:
        print(f"{args.catalog}: no accepted mesh with stored features", file=sys.stderr)
        return 2
    try:
        qmask = reference_mask(image, box=args.box, mask=mask)
    except ValueError as exc:
        print(f"{args.image}: {exc}", file=sys.stderr)
        return 2
    query = HogExtractor().extract(image[None], qmask[None]).feats[0]
    db = np.concatenate(feats)
    top = min(args.top, len(db))
    matches = search_catalog(query, db, np.asarray(mesh_ids), np.asarray(views),
                             np.asarray(az), np.asarray(el), top=top)
    q_side = _box_side(qmask) / min(qmask.shape)
    print(f"{'rank':>4s} {'azimuth':>8s} {'elev':>6s} {'dist':>6s} {'score':>7s}  mesh (view)")
    for i, mt in enumerate(matches):
        d = dist[mt.row] * sides[mt.row] / q_side if q_side > 0 else float("nan")
        print(f"{i + 1:4d} {mt.azimuth:8.1f} {mt.elevation:6.1f} {d:6.3f} {mt.score:7.4f}  "
              f"{metas[mt.mesh].source} ({mt.view})")
    best = matches[0]
    try:
        mesh = load_mesh(metas[best.mesh].source)
    except IngestError as exc:
        print(f"(no side-by-side PNG: {exc})", file=sys.stderr)
        return 0
    cand = PoseCandidate(best.azimuth, best.elevation, dist[best.row], best.score, best.view)
    out = args.out or args.image.with_name(args.image.stem + "_pose.png")
    cv2.imwrite(str(out), side_by_side(image, mask, args.box, mesh, cand, crop_square)[:, :, ::-1])
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
