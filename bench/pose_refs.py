"""Reference photos for the pose benchmark, made independently of the pose descriptor.

A reference is one vehicle rendered with ``ucad_cl.render`` + ``ucad_cl.shade`` at a random pose
(azimuth anywhere in [0, 360), elevation 0-30 deg, field of view 30-60 deg over the narrower image
side, the vehicle at a random scale and image position: the camera is turned away from the
vehicle's centre, so it is seen off-axis as in a photo), with one random colour per part, a random
light (direction, ambient, specular, shininess), a random white balance, rendered at twice the
size and reduced (antialiased edges, unlike the single-sample renders pose search compares with),
composited over one of several kinds of clutter with a soft contact shadow on the ground under
the vehicle, lit unevenly (a smooth random illumination field over the vehicle), then blurred a
little, given Gaussian pixel noise and JPEG-compressed.

Truth: the azimuth/elevation of the camera centre seen from the vehicle's centre (the pose
conventions of ``ucad_cl.cameras``), the exact object mask (pixels at least half covered by the
vehicle, from the depth map) and a detector-like box (the mask's box, each side moved by up to
``box_jitter`` of the box size).

Clutter kinds (``CLUTTER``): ``blocks`` (random filled rectangles, discs and lines over a
gradient), ``stripes`` (periodic bands at a random angle and period), ``smooth`` (low-frequency
coloured noise), ``hf`` (per-pixel coloured noise, partly blurred), ``vehicles`` (other vehicles'
renders, random colours and poses, behind the target), ``road`` (a composed street: sky, building
facades with windows, horizon from the camera elevation, asphalt, lane markings towards a
vanishing point, kerb).

Real models are put into the canonical vehicle frame (+Y up, front +X, right +Z) from the
manifest's ``up``/``front`` truth (``canonical_from_manifest``), not by the orientation stage, so
the pose figures do not depend on that stage's errors.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ucad_cl.artifacts import CameraRing, Mesh
from ucad_cl.cameras import camera_position
from ucad_cl.render import render_views
from ucad_cl.shade import shade_views

CLUTTER = ("blocks", "stripes", "smooth", "hf", "vehicles", "road")
#: left out of the benchmark: several vehicles in one file (no single front), a ground cloth
#: that sets the bounding box (the car is 2 % of it), a byte-level twin of another model
EXCLUDED_REAL = {"godot_truck_town_vehicles.glb": "several vehicles in one file",
                 "toy_car/ToyCar.gltf": "bounding box set by a ground cloth",
                 "ferrari_458_nodraco.glb": "same model as ferrari_458.glb"}


@dataclass
class Reference:
    image: np.ndarray           # (H, W, 3) uint8 RGB
    mask: np.ndarray            # (H, W) bool, exact object mask
    box: tuple                  # (x0, y0, x1, y1) detector-like box, pixels, x1/y1 exclusive
    azimuth: float              # truth, degrees in [0, 360)
    elevation: float
    fov: float                  # of the narrower image side, degrees
    clutter: str
    vehicle: str


# ----------------------------------------------------------------------------- vehicles

def axis_vector(axis: str) -> np.ndarray:
    """'+Y' / '-Z' ... -> unit vector."""
    v = np.zeros(3)
    v["XYZ".index(axis[1].upper())] = -1.0 if axis[0] == "-" else 1.0
    return v


def canonical_from_manifest(mesh: Mesh, up: str, front: str) -> Mesh:
    """``mesh`` turned into the canonical vehicle frame (+Y up, front +X, right +Z) from the
    manifest's file-frame ``up``/``front`` axes, re-centred and scaled to bbox diagonal 1.

    The rotation the loader already applied (the linear part of ``file_to_norm`` over its scale;
    identity before the orientation stage) is undone first, so the result is the same either way.
    """
    u, f = axis_vector(up), axis_vector(front)
    truth = np.stack([f, u, np.cross(f, u)])            # rows: front -> +X, up -> +Y, right -> +Z
    lin = np.asarray(mesh.file_to_norm, np.float64)[:3, :3]
    scale = abs(np.linalg.det(lin)) ** (1.0 / 3.0)
    loaded = lin / scale
    rot = truth @ loaded.T
    v = np.asarray(mesh.vertices, np.float64) @ rot.T
    lo, hi = v.min(0), v.max(0)
    centre, diag = (lo + hi) / 2.0, float(np.linalg.norm(hi - lo))
    v = (v - centre) / diag
    step = np.eye(4)
    step[:3, :3] = rot / diag
    step[:3, 3] = -centre / diag
    return Mesh(path=mesh.path, sha256=mesh.sha256, vertices=v, faces=mesh.faces,
                face_material=mesh.face_material, materials=mesh.materials,
                file_to_norm=step @ mesh.file_to_norm, face_node=mesh.face_node,
                node_names=mesh.node_names, report=mesh.report)


def real_vehicles(base: Path, names=None):
    """[(name, canonical mesh, material -> part)] of the manifest's models (minus EXCLUDED_REAL)."""
    from ucad_cl.ingest import load_mesh

    man = json.loads((base / "manifest.json").read_text())
    out = []
    for e in man["models"]:
        if e["file"] in EXCLUDED_REAL or (names is not None and e["file"] not in names):
            continue
        mesh = canonical_from_manifest(load_mesh(base / e["file"]), e["up"], e["front"])
        out.append((e["file"], mesh, dict(e["materials"])))
    return out


def synth_vehicles(seeds):
    """[(name, mesh, material -> part)] of generated vehicles (already canonical: front +X)."""
    from ucad_cl.synth import make_vehicle

    out = []
    for s in seeds:
        v = make_vehicle(int(s))
        out.append((f"synth:{s}:{v.kind}", v.mesh(), dict(v.truth["materials"])))
    return out


# ----------------------------------------------------------------------------- cameras

def photo_camera(az, el, fov, width, height, fill, off_x, off_y) -> CameraRing:
    """One upright camera (its x axis level, as a photographer holds it) at (az, el) from the
    vehicle centre, at the distance where the bounding sphere (radius 0.5) spans ``fill`` of the
    narrower half field of view, aimed away from the vehicle's centre by a heading and a tilt of
    ``off_x``, ``off_y`` (fractions of the room left on each side, -1..1)."""
    half = np.radians(fov) / 2.0
    f = 0.5 * min(width, height) / np.tan(half)
    K = np.array([[f, 0, width / 2.0], [0, f, height / 2.0], [0, 0, 1.0]])
    alpha = fill * half                                     # angular radius of the sphere
    dist = 0.5 / np.sin(alpha)
    half_x = np.arctan(0.5 * width / f)
    half_y = np.arctan(0.5 * height / f)
    pos = camera_position(az, el, dist)
    to = -pos / np.linalg.norm(pos)
    heading = np.arctan2(to[2], to[0]) + off_x * max(half_x - alpha, 0.0) * 0.9
    tilt = np.arcsin(to[1]) + off_y * max(half_y - alpha, 0.0) * 0.9
    fwd = np.array([np.cos(tilt) * np.cos(heading), np.sin(tilt), np.cos(tilt) * np.sin(heading)])
    right = np.cross(fwd, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    R = np.stack([right, np.cross(fwd, right), fwd])
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ pos
    return CameraRing(K=K, w2c=w2c[None], width=width, height=height,
                      azimuth=np.array([az]), elevation=np.array([el]), distance=float(dist),
                      near=0.01 * dist)


def scaled(ring: CameraRing, k: int) -> CameraRing:
    """The same camera with k times the pixels (pixel centres conventions kept)."""
    K = ring.K.copy()
    K[:2] *= k
    return CameraRing(K=K, w2c=ring.w2c, width=ring.width * k, height=ring.height * k,
                      azimuth=ring.azimuth, elevation=ring.elevation, distance=ring.distance,
                      near=ring.near)


# ----------------------------------------------------------------------------- appearance

def part_colours(rng, mesh: Mesh, parts: dict) -> np.ndarray:
    """(n_materials, 3) linear RGB: one random colour per part (a material without a part in
    ``parts`` gets its own)."""
    keys = [parts.get(m.name, "mat:" + m.name) for m in mesh.materials]
    n = max(len(keys), int(np.max(np.asarray(mesh.face_material, np.int64), initial=-1)) + 1)
    keys += [f"mat#{i}" for i in range(len(keys), n)]
    palette = {k: rng.uniform(0.0, 1.0, 3) ** 2.2 for k in sorted(set(keys))}
    return np.array([palette[k] for k in keys])


def random_light(rng) -> dict:
    return dict(light_dir=(rng.uniform(-1, 1), rng.uniform(-1, 0.3), -rng.uniform(0.2, 1.0)),
                ambient=rng.uniform(0.1, 0.5), specular=rng.uniform(0.0, 0.6),
                shininess=float(rng.choice([8.0, 16.0, 32.0, 64.0])))


def render_photo(mesh, parts, ring, rng, background=None, ss: int = 2, shadow: bool = True):
    """(image (H, W, 3) uint8, coverage (H, W) float in [0, 1]) of ``mesh`` from ``ring``'s one
    camera at ``ss`` x the size, area-reduced, unevenly lit, over ``background`` ((H, W, 3) uint8,
    None: black) darkened by a contact shadow under the vehicle (``shadow``)."""
    big = scaled(ring, ss)
    views = render_views(mesh, big)
    img = shade_views(mesh, views, colors=part_colours(rng, mesh, parts), **random_light(rng))[0]
    cov = np.isfinite(views.depth[0]).astype(np.float32)
    size = (ring.width, ring.height)
    img = cv2.resize(img, size, interpolation=cv2.INTER_AREA).astype(np.float32)
    cov = cv2.resize(cov, size, interpolation=cv2.INTER_AREA)
    field = rng.uniform(0.6, 1.4, (3, 3)).astype(np.float32)
    img *= cv2.resize(field, size, interpolation=cv2.INTER_CUBIC)[..., None]
    if background is not None:
        bg = background.astype(np.float32)
        if shadow:
            bg *= 1.0 - rng.uniform(0.3, 0.7) * _shadow(mesh, ring, rng)[..., None]
        img = img * cov[..., None] + bg * (1 - cov[..., None])
    return np.clip(img + 0.5, 0, 255).astype(np.uint8), cov


def _shadow(mesh, ring, rng) -> np.ndarray:
    """(H, W) float in [0, 1]: a soft shadow of the vehicle's footprint on the ground plane (the
    bounding box's bottom rectangle, grown a little), projected into the image."""
    v = np.asarray(mesh.vertices)
    lo, hi = v.min(0), v.max(0)
    grow = rng.uniform(1.0, 1.25)
    cx, cz = (lo[0] + hi[0]) / 2, (lo[2] + hi[2]) / 2
    hx, hz = (hi[0] - lo[0]) / 2 * grow, (hi[2] - lo[2]) / 2 * grow
    corners = np.array([[cx - hx, lo[1], cz - hz], [cx + hx, lo[1], cz - hz],
                        [cx + hx, lo[1], cz + hz], [cx - hx, lo[1], cz + hz]])
    cam = corners @ ring.w2c[0, :3, :3].T + ring.w2c[0, :3, 3]
    out = np.zeros((ring.height, ring.width), np.float32)
    if np.any(cam[:, 2] <= ring.near):
        return out
    pix = cam @ ring.K.T
    pts = (pix[:, :2] / pix[:, 2:3] * 16).round().astype(np.int32)     # 4 fractional bits
    cv2.fillPoly(out, [pts], 1.0, lineType=cv2.LINE_AA, shift=4)
    k = 2 * int(max(ring.width, ring.height) * 0.02) + 1
    return cv2.GaussianBlur(out, (k, k), 0)


# ----------------------------------------------------------------------------- clutter

def clutter(kind: str, rng, H: int, W: int, *, elevation: float = 15.0, fov: float = 45.0,
            others=()) -> np.ndarray:
    """(H, W, 3) uint8 background of ``kind`` (see CLUTTER). ``others``: [(mesh, parts)] for
    the 'vehicles' kind."""
    if kind == "blocks":
        img = _gradient(rng, H, W)
        for _ in range(rng.integers(8, 20)):
            col = tuple(int(x) for x in rng.integers(0, 256, 3))
            p = (int(rng.integers(0, W)), int(rng.integers(0, H)))
            q = (int(rng.integers(0, W)), int(rng.integers(0, H)))
            shape = rng.integers(3)
            if shape == 0:
                cv2.rectangle(img, p, q, col, -1)
            elif shape == 1:
                cv2.circle(img, p, int(rng.integers(4, H // 3)), col, -1)
            else:
                cv2.line(img, p, q, col, int(rng.integers(1, 6)))
        return img
    if kind == "stripes":
        yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
        ang = rng.uniform(0, np.pi)
        period = rng.uniform(4, 40)
        t = (np.cos(ang) * xx + np.sin(ang) * yy) / period
        wave = (np.sin(2 * np.pi * t) > rng.uniform(-0.5, 0.5)).astype(np.float32)
        c0, c1 = rng.integers(0, 256, 3), rng.integers(0, 256, 3)
        return (c0 + (c1 - c0) * wave[..., None]).astype(np.uint8)
    if kind == "smooth":
        small = rng.uniform(0, 255, (rng.integers(3, 9), rng.integers(3, 9), 3)).astype(np.float32)
        return np.clip(cv2.resize(small, (W, H), interpolation=cv2.INTER_CUBIC), 0, 255
                       ).astype(np.uint8)
    if kind == "hf":
        img = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        k = int(rng.choice([1, 3]))
        return cv2.GaussianBlur(img, (k, k), 0) if k > 1 else img
    if kind == "vehicles":
        img = _gradient(rng, H, W)
        for mesh, parts in others:
            ring = photo_camera(rng.uniform(0, 360), rng.uniform(0, 30), fov, W, H,
                                rng.uniform(0.3, 0.9), rng.uniform(-1, 1), rng.uniform(-1, 1))
            img, _ = render_photo(mesh, parts, ring, rng, background=img, ss=1)
        return img
    if kind == "road":
        return _road(rng, H, W, elevation, fov)
    raise ValueError(f"unknown clutter kind {kind!r}")


def _gradient(rng, H, W) -> np.ndarray:
    c0, c1 = rng.integers(0, 256, 3), rng.integers(0, 256, 3)
    ang = rng.uniform(0, 2 * np.pi)
    yy, xx = np.mgrid[0:H, 0:W]
    t = (np.cos(ang) * xx / W + np.sin(ang) * yy / H + 1) / 2
    return np.ascontiguousarray((c0 + (c1 - c0) * t[..., None]).astype(np.uint8))


def _road(rng, H, W, elevation, fov) -> np.ndarray:
    """A street: sky, facades with windows above the horizon, asphalt with lane markings."""
    f = 0.5 * min(H, W) / np.tan(np.radians(fov) / 2)
    horizon = int(H / 2 - f * np.tan(np.radians(elevation)) + rng.uniform(-0.1, 0.1) * H)
    img = np.empty((H, W, 3), np.uint8)
    sky0, sky1 = rng.integers(150, 256, 3), rng.integers(60, 200, 3)
    t = np.linspace(0, 1, H)[:, None, None]
    img[:] = (sky1 + (sky0 - sky1) * t).astype(np.uint8)
    # facades: boxes standing on the horizon, with a grid of windows
    x = int(rng.integers(-W // 4, 0))
    while x < W:
        w = int(rng.integers(W // 8, W // 3))
        top = horizon - int(rng.integers(H // 8, H // 2 + 1))
        col = tuple(int(c) for c in rng.integers(40, 230, 3))
        cv2.rectangle(img, (x, top), (x + w, horizon), col, -1)
        win = tuple(int(c) for c in rng.integers(0, 256, 3))
        ws, hs = int(rng.integers(6, 16)), int(rng.integers(8, 20))
        for yy in range(top + 4, horizon - hs, hs + 6):
            for xx in range(x + 4, x + w - ws, ws + 6):
                cv2.rectangle(img, (xx, yy), (xx + ws, yy + hs), win, -1)
        x += w + int(rng.integers(0, W // 10))
    # asphalt below the horizon, textured, lane markings towards a vanishing point
    g0 = max(horizon, 0)
    if g0 < H:
        grey = int(rng.integers(50, 130))
        tex = rng.normal(grey, 10, (H - g0, W, 1)).clip(0, 255)
        img[g0:] = np.repeat(tex, 3, axis=2).astype(np.uint8)
        vx = int(rng.uniform(0.2, 0.8) * W)
        for k in range(-3, 4):
            x1 = int(vx + k * W * rng.uniform(0.3, 0.6))
            colour = (230, 230, 230) if k else (220, 190, 40)
            for s in np.linspace(0, 1, 12)[:-1]:
                if rng.uniform() < 0.6:
                    p = (int(vx + (x1 - vx) * s), int(horizon + (H - horizon) * s))
                    q = (int(vx + (x1 - vx) * (s + 0.05)), int(horizon + (H - horizon) * (s + 0.05)))
                    cv2.line(img, p, q, colour, max(1, int(1 + 6 * s)))
        kerb = int(horizon + (H - horizon) * rng.uniform(0.05, 0.2))
        cv2.line(img, (0, kerb), (W, kerb + int(rng.integers(-20, 20))), (200, 200, 200), 3)
    return img


# ----------------------------------------------------------------------------- references

def make_reference(mesh, parts, rng, *, kind: str, name: str = "", others=(),
                   size=(320, 240), box_jitter: float = 0.05) -> Reference:
    """One reference photo of ``mesh`` (see the module docstring)."""
    W, H = size
    az, el, fov = rng.uniform(0, 360), rng.uniform(0, 30), rng.uniform(30, 60)
    ring = photo_camera(az, el, fov, W, H, rng.uniform(0.35, 0.95), rng.uniform(-1, 1),
                        rng.uniform(-1, 1))
    bg = clutter(kind, rng, H, W, elevation=el, fov=fov, others=others)
    img, cov = render_photo(mesh, parts, ring, rng, background=bg)
    sigma = rng.uniform(0.0, 1.0)
    if sigma > 0.3:
        img = cv2.GaussianBlur(img, (0, 0), sigma)
    gain = rng.uniform(0.8, 1.2, 3)
    noise = rng.uniform(2, 8)
    img = np.clip(img * gain + rng.normal(0, noise, img.shape), 0, 255).astype(np.uint8)
    ok, jpg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(40, 96))])
    img = np.ascontiguousarray(cv2.imdecode(jpg, cv2.IMREAD_UNCHANGED))
    mask = cov >= 0.5
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    x0, x1, y0, y1 = cols[0], cols[-1] + 1, rows[0], rows[-1] + 1
    bw, bh = x1 - x0, y1 - y0
    j = rng.uniform(-box_jitter, box_jitter, 4) * np.array([bw, bh, bw, bh])
    box = (float(np.clip(x0 + j[0], 0, W)), float(np.clip(y0 + j[1], 0, H)),
           float(np.clip(x1 + j[2], 0, W)), float(np.clip(y1 + j[3], 0, H)))
    return Reference(image=img, mask=mask, box=box, azimuth=float(az), elevation=float(el),
                     fov=float(fov), clutter=kind, vehicle=name)


def make_references(vehicles, per_vehicle: int, seed: int, *, size=(320, 240)) -> list:
    """``per_vehicle`` references of each vehicle; clutter kinds in turn; 'vehicles' clutter
    draws 1-3 of the other vehicles in the list."""
    rng = np.random.default_rng(seed)
    out = []
    k = 0
    for i, (name, mesh, parts) in enumerate(vehicles):
        for _ in range(per_vehicle):
            kind = CLUTTER[k % len(CLUTTER)]
            k += 1
            others = []
            if kind == "vehicles" and len(vehicles) > 1:
                pick = rng.choice([j for j in range(len(vehicles)) if j != i],
                                  size=min(int(rng.integers(1, 4)), len(vehicles) - 1),
                                  replace=False)
                others = [(vehicles[j][1], vehicles[j][2]) for j in pick]
            out.append(make_reference(mesh, parts, rng, kind=kind, name=name, others=others,
                                      size=size))
    return out
