"""``ucad-index pose IMAGE MESH``: estimate the camera pose of a vehicle photo against a mesh.

Prints the best candidates (azimuth, elevation in degrees in the mesh's canonical frame: azimuth 0
= seen from the front, 90 = from the vehicle's left; distance in canonical units; score = the
weighted cue distance, lower is better), the front/back decision (the best twin of the best
candidate with its score gap, "close call" below ``pose.AMBIGUOUS_GAP``) and how the object was
found (the given mask, or GrabCut inside the box with the share of the box it kept); writes a
PNG: the photo's object with the best pose's outline | the render of the best pose. ``--json``
prints everything, every candidate's camera (K, world-to-camera) included.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

DESCRIPTION = """\
Find the camera pose of a vehicle photo against a mesh (or every mesh of a catalogue).

The vehicle is given by --box (GrabCut then finds the vehicle inside it) or --mask (exact).
Its background is replaced by the renders' grey, the photo is turned so the vehicle sits on
the optical axis, and views of MESH are scored by appearance-invariant cues (gradient
orientations, silhouette, edges, colour regions), coarse to fine. Front/back and left/right:
the best pose is compared with its twins (mirror -a, opposite a+180, front-back 180-a); the
best twin is printed second with its score gap.

Azimuths are in the mesh's canonical frame (azimuth 0 looks at the vehicle's front, 90 at its
left side, elevation > 0 from above), so answers are comparable across meshes.

examples:
  ucad-index pose street.jpg car.glb --box 120 80 460 300
  ucad-index pose street.jpg car.glb --mask street_mask.png --json > pose.json
  ucad-index pose street.jpg --box 120 80 460 300 --catalog cat/

A vehicle cut by the photo's edge (its box touches the edge) is also tried as going on past
the edge (by 10, 25 and 50 % of what shows), and posed so when that matches the mesh's views
better; the line "the vehicle touches the photo's edge" says by how much (--as-shown: never).
"""


def register(sub) -> None:
    import argparse

    p = sub.add_parser("pose", help="estimate the pose of a vehicle photo against a mesh",
                       description=DESCRIPTION,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("image", type=Path, help="reference photo (PNG/JPEG, RGB)")
    p.add_argument("mesh", type=Path, nargs="?", default=None,
                   help="vehicle model (glb/gltf/obj) to match; omit with --catalog")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--box", type=float, nargs=4, metavar=("X0", "Y0", "X1", "Y1"),
                   help="object box in pixels (x1, y1 exclusive), e.g. from a detector")
    g.add_argument("--mask", type=Path, help="object mask image, same size (object: at least "
                   "half its largest value)")
    p.add_argument("--top", type=int, default=5, help="candidates to print (default 5)")
    p.add_argument("--step", type=float, default=10.0, help="coarse azimuth step, degrees")
    p.add_argument("--elevations", type=float, nargs="+", default=[0.0, 15.0, 30.0],
                   help="coarse ring elevations, degrees")
    p.add_argument("--no-refine", action="store_true", help="coarse ring only")
    p.add_argument("--method", choices=("robust", "legacy"), default="robust",
                   help="robust (default) or legacy: the search before issue 12 (HOG of the box "
                        "crop with its background), for comparison")
    p.add_argument("--onnx", type=Path, default=None,
                   help="use this ONNX image encoder (e.g. DINOv2, see docs/POSE.md) for the "
                        "feature cue instead of the built-in HOG")
    p.add_argument("--fov", type=float, default=None, metavar="DEG",
                   help="the photo's field of view over the narrower side, in degrees, when "
                        "known (default: 45 assumed; with MESH only)")
    p.add_argument("--as-shown", action="store_true",
                   help="a vehicle cut by the photo's edge: pose it as the photo shows it only "
                        "(default: also as going on past the edge, whichever matches the "
                        "stored or rendered views better)")
    p.add_argument("--json", action="store_true",
                   help="print JSON: object, decision and every candidate with K and w2c")
    p.add_argument("--out", type=Path, default=None,
                   help="side-by-side PNG (default: IMAGE stem + '_pose.png' next to it)")
    p.add_argument("--catalog", type=Path, default=None, metavar="PATH",
                   help="search every stored view of every accepted mesh of this catalogue "
                        "(built-in features) instead of rendering one MESH")
    from .render import add_orientation_args
    add_orientation_args(p)
    p.set_defaults(func=run, late_positional="mesh")


def run(args) -> int:
    import cv2

    from ..features import HogExtractor, OnnxExtractor
    from ..ingest import IngestError, load_mesh_isolated
    from ..pose import LEGACY, ROBUST, estimate_pose

    if (args.catalog is None) == (args.mesh is None):
        print("give either MESH or --catalog PATH", file=sys.stderr)
        return 2
    if args.top < 1:
        print(f"--top {args.top}: must be >= 1", file=sys.stderr)
        return 2
    if args.catalog is not None and args.onnx is not None:
        print("--onnx cannot be used with --catalog: the catalogue stores the built-in HOG "
              "features", file=sys.stderr)
        return 2
    if args.catalog is not None and args.fov is not None:
        print("--fov cannot be used with --catalog: it lists the stored views' own cameras",
              file=sys.stderr)
        return 2
    image, mask = _read_inputs(args)
    if image is None:
        return 2
    if args.catalog is not None:
        return run_catalog(args, image, mask)
    from .render import orientation_from_args
    try:
        mode, overrides = orientation_from_args(args)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:
        mesh = load_mesh_isolated(args.mesh, orientation=mode, overrides=overrides)
    except IngestError as exc:
        print(str(exc), file=sys.stderr)
        return 1
    try:
        extractor = OnnxExtractor(args.onnx) if args.onnx else HogExtractor()
    except ValueError as exc:
        print(str(exc), file=sys.stderr)
        return 2
    method = LEGACY if args.method == "legacy" else ROBUST
    try:
        est = estimate_pose(image, mesh, box=args.box, mask=mask, extractor=extractor,
                            azimuth_step=args.step, elevations=args.elevations,
                            top=args.top, refine=not args.no_refine, method=method,
                            fov=args.fov, past_edge=not args.as_shown)
    except ValueError as exc:
        print(f"{args.image}: {exc}", file=sys.stderr)
        return 2
    out = args.out or args.image.with_name(args.image.stem + "_pose.png")
    cv2.imwrite(str(out), side_by_side(image, est.object.mask, mesh, est.best)[:, :, ::-1])
    if args.json:
        print(json.dumps(estimate_json(est, args.image, args.mesh, out), indent=1))
        return 0
    print(f"{'rank':>4s} {'azimuth':>8s} {'elev':>6s} {'dist':>6s} {'score':>7s} {'gap':>7s}  note")
    for i, c in enumerate(est.candidates):
        note = (f"{c.twin} twin " if c.flipped else "") + ("refined" if c.refined else "coarse")
        print(f"{i + 1:4d} {c.azimuth:8.1f} {c.elevation:6.1f} {c.distance:6.3f} "
              f"{c.score:7.4f} {c.gap:7.4f}  {note}")
    print(object_line(est.object))
    if any(est.past_edge):
        print(past_edge_line(est.past_edge, "posed"))
    runner = est.runner_up
    if runner is not None:
        verdict = "close call" if est.ambiguous else "clear"
        print(f"front/back/sides: {verdict}: best twin is the {runner.twin} view "
              f"(azimuth {runner.azimuth:.1f}), score gap {runner.gap:.4f}")
    print(f"wrote {out}")
    return 0


def object_line(obj) -> str:
    x0, y0, x1, y1 = obj.box
    if obj.source == "mask":
        return f"object: the given mask ({int(obj.mask.sum())} pixels)"
    if obj.source == "box":
        return (f"object: the whole box ({x0} {y0} {x1} {y1}); GrabCut kept only "
                f"{obj.kept * 100:.0f} % of it, too little to trust")
    return (f"object: {obj.source} kept {obj.kept * 100:.0f} % of the box "
            f"({x0} {y0} {x1} {y1})")


def past_edge_line(past_edge, how: str) -> str:
    return (f"the vehicle touches the photo's edge: {how} as going on past it by "
            "{} / {} / {} / {} px (left / top / right / bottom)".format(*past_edge))


def estimate_json(est, image_path, mesh_path, png) -> dict:
    """A JSON-ready dict of a PoseEstimate (angles in degrees, canonical frame)."""
    o = est.object
    return {
        "image": str(image_path), "mesh": str(mesh_path), "png": str(png),
        "conventions": "azimuth/elevation degrees in the mesh's canonical frame (azimuth 0 = "
                       "front, counter-clockwise seen from +Y); distance in canonical units "
                       "(bbox diagonal 1); K (3x3) and w2c (4x4, canonical -> OpenCV camera) "
                       "of the photo",
        "object": {"source": o.source, "box": list(o.box), "kept": round(o.kept, 4),
                   "pixels": int(o.mask.sum())},
        "ambiguous": bool(est.ambiguous),
        "past_edge": [int(v) for v in est.past_edge],
        "candidates": [candidate_json(c, i + 1) for i, c in enumerate(est.candidates)],
    }


def candidate_json(c, rank: int) -> dict:
    return {"rank": rank, "azimuth": c.azimuth, "elevation": c.elevation,
            "distance": c.distance, "score": c.score, "gap": c.gap, "refined": c.refined,
            "flipped": c.flipped, "twin": c.twin, "view": c.view,
            "cues": {k: float(v) for k, v in c.cues.items()},
            "K": None if c.K is None else c.K.tolist(),
            "w2c": None if c.w2c is None else c.w2c.tolist()}


def run_catalog(args, image, mask) -> int:
    """Nearest stored views across the whole catalogue (the features the build stored), the
    rows read as the fit reads them (``fit.catalog_rows``: the search index's rows nearest to
    the photo in projection when the catalogue is large, else every row) and ranked exactly;
    the cameras are read for the listed rows only."""
    import cv2
    import numpy as np

    from ..cameras import camera_distance
    from ..features import HogExtractor
    from ..fit import catalog_rows
    from ..ingest import IngestError, load_mesh
    from ..foreground import PhotoWindow, mask_box, past_the_edge
    from ..pose import PoseCandidate, query_features
    from ..search import search_catalog

    from .common import open_reader

    reader = open_reader(args.catalog)
    if reader is None:
        return 2
    legacy = args.method == "legacy"
    window = PhotoWindow.around(image.shape[:2], args.box, mask)   # a large photo: its window
    img, box, obj_mask = ((image, args.box, mask) if window is None
                          else window.cut(image, args.box, mask))
    with reader as r:
        try:
            query, seen = query_features(img, HogExtractor(), box=box, mask=obj_mask,
                                         isolate=not legacy)
            obj = seen if window is None else window.photo_object(seen, image.shape[:2])
        except ValueError as exc:
            print(f"{args.image}: {exc}", file=sys.stderr)
            return 2

        def nearest(q):
            """The stored rows nearest to features ``q``, best first, and the notes."""
            metas, db, mesh_of, view_of, notes = catalog_rows(r, q)
            zeros = np.zeros(len(db))               # angles are read for the listed rows only
            return metas, search_catalog(q, db, mesh_of, view_of, zeros, zeros,
                                         top=min(args.top, len(db))), notes

        try:
            metas, matches, notes = nearest(query)
            grown = None                # a vehicle cut by the photo's edge: also as going on
            for hyp in ([] if legacy or args.as_shown else past_the_edge(img, seen)):
                q2, _ = query_features(hyp.image, HogExtractor(), mask=hyp.obj.mask)
                metas2, m2, _ = nearest(q2)         # past it (ties: as seen, then growth order)
                if m2[0].score < matches[0].score:
                    metas, matches, grown = metas2, m2, hyp
        except ValueError as exc:
            print(f"{args.catalog}: {exc}", file=sys.stderr)
            return 2
        for note in notes:
            print(f"note: {note}", file=sys.stderr)
        cameras: dict[int, dict] = {}
        for mt in matches:
            if mt.mesh not in cameras:
                cameras[mt.mesh] = {v.index: v for v in r.views(metas[mt.mesh].sha256)}
    x0, y0, x1, y1 = mask_box(obj.mask)
    q_side = max(x1 - x0, y1 - y0) / min(obj.mask.shape)
    past_edge = (0, 0, 0, 0)
    if grown is not None:               # the whole assumed vehicle's size, in the photo
        def longer(m):
            bx0, by0, bx1, by1 = mask_box(m)
            return max(bx1 - bx0, by1 - by0)
        q_side *= longer(grown.obj.mask) / longer(seen.mask)
        past_edge = grown.margins() if window is None else window.photo_lengths(grown.margins())
    rows = []                # (match, its camera, the camera's distance, the photo's estimate)
    for mt in matches:
        v = cameras[mt.mesh][mt.view]
        K = np.asarray(v.K, np.float64)
        dist = camera_distance(v.w2c)
        side = float(v.stats.get("box_side", np.nan)) / min(K[:2, 2] * 2)
        rows.append((mt, v, dist, dist * side / q_side if q_side > 0 else float("nan")))
    best, best_cam, best_dist, _ = rows[0]
    out = args.out or args.image.with_name(args.image.stem + "_pose.png")
    if args.json:
        print(json.dumps({
            "image": str(args.image), "catalog": str(args.catalog),
            "object": {"source": obj.source, "box": list(obj.box), "kept": round(obj.kept, 4)},
            "past_edge": list(past_edge),
            "conventions": "azimuth/elevation degrees in each mesh's canonical frame (azimuth 0 "
                           "= front); K and w2c: the stored view's render camera",
            "candidates": [{"rank": i + 1, "mesh": str(metas[mt.mesh].source),
                            "sha256": metas[mt.mesh].sha256, "view": mt.view,
                            "azimuth": v.azimuth, "elevation": v.elevation, "distance": d,
                            "score": mt.score, "K": np.asarray(v.K).tolist(),
                            "w2c": np.asarray(v.w2c).tolist()}
                           for i, (mt, v, _, d) in enumerate(rows)]},
            indent=1))
    else:
        print(f"{'rank':>4s} {'azimuth':>8s} {'elev':>6s} {'dist':>6s} {'score':>7s}  mesh (view)")
        for i, (mt, v, _, d) in enumerate(rows):
            print(f"{i + 1:4d} {v.azimuth:8.1f} {v.elevation:6.1f} {d:6.3f} {mt.score:7.4f}  "
                  f"{metas[mt.mesh].source} ({mt.view})")
        print(object_line(obj))
        if any(past_edge):
            print(past_edge_line(past_edge, "matched"))
    try:                          # in the frame the catalogue stored (its cameras are in it)
        from ..orient import in_frame
        mesh = in_frame(load_mesh(metas[best.mesh].source, orientation=None),
                        metas[best.mesh].file_to_norm)
    except (IngestError, ValueError) as exc:
        print(f"(no side-by-side PNG: {exc})", file=sys.stderr)
        return 0
    cand = PoseCandidate(best_cam.azimuth, best_cam.elevation, best_dist, best.score, best.view)
    cv2.imwrite(str(out), side_by_side(image, obj.mask, mesh, cand)[:, :, ::-1])
    if not args.json:
        print(f"wrote {out}")
    return 0


def _read_inputs(args):
    """(RGB image, mask or None), or (None, None) after printing why: the photo and the mask
    read as ``fit`` reads them (``common.read_image``: EXIF orientation applied, grayscale and
    16-bit converted; a missing, corrupt or over-large file refused before it is decoded)."""
    from .common import read_image, read_mask

    try:
        image = read_image(args.image)
    except ValueError as exc:
        print(f"{args.image}: {exc}", file=sys.stderr)
        return None, None
    mask = None
    if args.mask is not None:
        try:
            mask = read_mask(args.mask, image.shape[:2])
        except ValueError as exc:
            print(f"{args.image}: {exc}", file=sys.stderr)
            return None, None
    return image, mask


def side_by_side(image, mask, mesh, cand, size: int = 256):
    """(size, 2*size, 3) uint8: the photo around the object with the outline (green) of the
    candidate's silhouette when it has a camera for the photo | the render of ``cand``, both
    cropped by the pose features' rule. The outline is rendered at the tile's own size (the
    photo's camera mapped onto the crop), not at the photo's: a 12-megapixel photo's outline
    used to be a full-size render."""
    import cv2
    import numpy as np

    from ..cameras import make_ring, single_camera
    from ..features import crop_square, crop_window, square_windows
    from ..foreground import RENDER_BACKGROUND
    from ..render import render_views
    from ..shade import shade_views

    top, left, side = square_windows(np.asarray(mask, bool)[None])[0]
    ref = crop_window(np.ascontiguousarray(image), (top, left, side), size)
    if cand.K is not None and cand.w2c is not None:
        s = size / side            # photo pixel coordinates -> the tile's: (x - left) * s
        to_tile = np.array([[s, 0.0, -left * s], [0.0, s, -top * s], [0.0, 0.0, 1.0]])
        ring = single_camera(to_tile @ np.asarray(cand.K, np.float64), cand.w2c, size, size,
                             azimuth=cand.azimuth, elevation=cand.elevation,
                             distance=cand.distance)
        sil = np.isfinite(render_views(mesh, ring).depth[0]).astype(np.uint8)
        contours, _ = cv2.findContours(sil, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        ref = ref.copy()
        cv2.drawContours(ref, contours, -1, (0, 255, 0), 1)
    ring = make_ring(azimuths=[cand.azimuth], elevations=[cand.elevation], size=size)
    views = render_views(mesh, ring)
    rend = shade_views(mesh, views, background=RENDER_BACKGROUND)
    crop, _ = crop_square(rend, np.isfinite(views.depth), size)
    return np.concatenate([ref, crop[0]], axis=1)
