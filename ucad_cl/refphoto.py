"""Photo-like reference images of a vehicle with known part colours, light and camera.

``render_reference(mesh, part_of_material, part_colors, azimuth=..., elevation=..., light=...,
seed=...) -> Reference`` ray-casts the mesh with Embree (``embreex``), independently of the
project's OpenCL rasterizer and shader, and returns the 8-bit sRGB photo together with its truth:
the vehicle's foreground mask, a part map, the camera (``K``, ``w2c``) and the base colour of
every part. ``draw_light(rng)`` and ``draw_car_colors(rng)`` draw a plausible daylight and a
plausible set of part colours (body colours at real car-colour frequencies). Used by the fit's
tests and demo and by ``bench/fit.py``.

Conventions and units:

* Frames and cameras as docs/CONVENTIONS.md: ``mesh`` is in the canonical vehicle frame (+Y up,
  nose +X, bounding-box diagonal 1); OpenCV camera (x right, y down, z forward), pixel (i, j)
  centred at (j + 0.5, i + 0.5). ``azimuth``/``elevation``/``distance`` are those of the camera
  centre seen from the vehicle's centre (the pose convention); the camera is held level (its x
  axis horizontal) and turned away from the vehicle's centre by ``offset`` (fractions -1..1 of
  the room left in the frame, x then y), so the vehicle sits off-centre and is seen obliquely.
  ``fov`` is the field of view over the narrower image side (degrees), ``fill`` the share of the
  narrower half-field the bounding sphere (radius 0.5) spans, which sets the distance.
* Colours are linear RGB (sRGB primaries, D65). Light quantities are radiances in one unit: a
  white Lambertian surface (albedo 1) under a uniform sky of radiance L returns L. The photo's
  linear value is ``exposure * gains * radiance`` (``RefLight.exposure``; ``gains`` the camera's
  white balance: per channel, the luminance of the irradiance of a surface facing up over its
  channel, so a grey surface facing up is neutral, as a camera's auto white balance makes the
  light's average colour neutral; times ``exp(N(0, white_balance_error))`` per channel, an
  imperfect balance; the background image is not balanced again), then noise, clipping to
  [0, 1], the sRGB curve, 8 bits and JPEG.
* Truth: ``mask`` and ``part_map`` come from one ray through each pixel centre (as the
  rasterizer samples); the colour image averages ``samples`` x ``samples`` rays per pixel
  (antialiased edges). ``part_map`` holds the index into ``PART_NAMES`` of the first surface hit
  (glass included; a material whose part is not in ``PART_NAMES``, e.g. ``unseen``, counts as
  ``other``), -1 on background.

Shading (all per sample; normals: each corner takes its area-weighted vertex normal when that stays
within 35 deg of the face normal, else the face normal, interpolated at the hit; two-sided):

* Light: a sky whose radiance goes from ``sky_horizon`` (at the horizon) to ``sky_zenith`` as
  sqrt(y) of the direction, optionally buildings on the horizon (``skyline``: seen in sharp
  reflections; the irradiance ignores them), a uniform ``ground`` radiance below the horizon,
  and a sun (direction
  ``sun_dir`` toward the sun, ``sun_color`` = the radiance a white Lambertian surface facing it
  returns from the sun alone). Sky irradiance of a normal n: mix(ground, sky mean,
  (1 + n_y) / 2) (exact for a sky and ground each uniform), times the share of
  ``ao_rays`` cosine-distributed rays that leave the vehicle (occlusion: wheel arches, cabin);
  the sun is blocked by a shadow ray.
* Materials: the part prior of ``ucad_catalog.parts.PART_MATERIALS`` (metallic, roughness, clear
  coat, transmission), with the base colour from ``part_colors`` when given, else the prior's
  (body, ``other``: the source material's). Base layer: a dielectric share ``1 - metallic``
  (diffuse ``(1 - Fd) c`` plus a specular ``Fd``, Schlick's ``Fd = 0.04 + 0.96 (1 - n.v)^5``) and
  a metallic share (specular ``c + (1 - c)(1 - n.v)^5``), the specular reflecting the sky blurred
  by the roughness and a normalised Blinn-Phong sun highlight. Clear coat (body): a layer of
  Fresnel ``0.04 + 0.96 (1 - n.v)^5`` and roughness 0.03 over the base; under it the base meets
  the coat's resin (index ~1.5), not air, so its dielectric reflection and both grazing rises are
  dropped (a black paint reflects ~4 %, not the 6 % of glTF's layering). Glass (``window``, or a
  see-through source material): Fresnel reflection of the sky plus the surface behind it (a
  second ray that ignores glass) times
  ``transmission`` and the glass tint. Lamps are shaded as glossy dielectrics of their colour
  (daylight, lamps off). Energy: with every albedo 1 and a uniform sky, every opaque pixel is
  the sky's radiance (the white furnace test in tests/test_refphoto.py).
* Ground: the background gets the vehicle's sun shadow on the ground plane under its lowest
  point (cast within 1.5 units of the centre), darkened by the sun's share of the light.
* Background: ``plain`` (flat mid grey, sRGB 128) or ``clutter`` (a street or random shapes,
  gradients, stripes and textures, drawn from ``seed``).
* Noise: Gaussian with variance ``noise^2 (0.2 + 0.8 x / 0.18)`` at linear value x (read + shot
  noise; ``noise`` is the standard deviation at mid grey), before quantisation; JPEG through
  Pillow at ``jpeg_quality`` (None: none).

Deterministic: the same arguments and ``seed`` give the same bytes on a machine (one NumPy
generator drawn in a fixed order; Embree returns the nearest hit and its BVH builders are
deterministic; another CPU's Embree kernels may round a hit distance differently). Between
exactly coincident faces Embree's choice need not be the rasterizer's lower-index rule: the truth
maps agree with the rasterizer on >= 99 % of pixels, not on every one (tests/test_refphoto.py).
"""
from __future__ import annotations

import io
from dataclasses import dataclass, field, replace
from typing import Mapping, Sequence

import numpy as np
from PIL import Image

from ucad_catalog.parts import PART_MATERIALS, PART_NAMES

from .artifacts import Mesh
from .cameras import camera_position
from .colorimetry import lab_to_linear, linear_to_srgb8, srgb8_to_linear
from .labeller import see_through

#: published frequencies of new-car body colours (fractions; see ``draw_car_colors``)
CAR_COLOR_FREQUENCIES: dict[str, float] = {
    "white": 0.35, "black": 0.19, "grey": 0.17, "silver": 0.10, "blue": 0.08, "red": 0.07,
    "brown": 0.02, "green": 0.01, "yellow": 0.01,
}
#: each body colour family as CIELAB (L, a, b) centre and the +- spread drawn around it
_FAMILY_LAB: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "white": ((93.0, -0.5, 1.5), (3.0, 1.0, 2.5)),
    "black": ((14.0, 0.0, -0.5), (5.0, 1.0, 1.5)),
    "grey": ((45.0, -0.5, -1.5), (12.0, 1.0, 2.0)),
    "silver": ((72.0, -0.5, -1.0), (6.0, 1.0, 2.0)),
    "blue": ((32.0, 5.0, -38.0), (10.0, 6.0, 12.0)),
    "red": ((40.0, 58.0, 38.0), (6.0, 8.0, 8.0)),
    "brown": ((42.0, 12.0, 22.0), (12.0, 5.0, 8.0)),
    "green": ((40.0, -30.0, 12.0), (10.0, 10.0, 8.0)),
    "yellow": ((80.0, 8.0, 80.0), (6.0, 10.0, 10.0)),
}
_PART_INDEX = {p: i for i, p in enumerate(PART_NAMES)}
_OTHER = _PART_INDEX["other"]
_SMOOTH_COS = float(np.cos(np.radians(35.0)))
_EPS = 1e-4                     # ray offset off a surface, canonical units (diagonal 1)


@dataclass(frozen=True)
class RefLight:
    """Daylight of a reference (linear RGB radiances, see the module docstring)."""
    sun_dir: tuple[float, float, float] = (0.4, 0.8, 0.45)     # toward the sun, canonical frame
    sun_color: tuple[float, float, float] = (1.0, 0.97, 0.92)
    sky_zenith: tuple[float, float, float] = (0.25, 0.32, 0.45)
    sky_horizon: tuple[float, float, float] = (0.45, 0.48, 0.52)
    ground: tuple[float, float, float] = (0.12, 0.11, 0.10)
    exposure: float = 0.8
    ao_rays: int = 4            # occlusion rays per sample (0: no occlusion)
    # buildings on the horizon, seen in reflections: one (height in degrees, r, g, b radiance)
    # per equal azimuth sector, sector k from k * 360 / len degrees (the camera azimuth
    # convention, canonical frame); () none
    skyline: tuple = ()


@dataclass
class Reference:
    """A photo-like reference and its truth (see the module docstring)."""
    image: np.ndarray           # (H, W, 3) uint8 sRGB
    box: tuple[int, int, int, int]   # (x0, y0, x1, y1) of the mask, pixels, x1/y1 exclusive
    mask: np.ndarray            # (H, W) bool, the vehicle's pixels
    part_map: np.ndarray        # (H, W) int16, index into PART_NAMES, -1 background
    K: np.ndarray               # (3, 3)
    w2c: np.ndarray             # (4, 4) canonical -> OpenCV camera
    azimuth: float              # of the camera centre seen from the vehicle centre, degrees
    elevation: float
    distance: float             # canonical units
    fov: float                  # over the narrower image side, degrees
    colors: dict[str, tuple[float, float, float]]   # part -> base colour (linear RGB) of the
    #                                                 parts of PART_MATERIALS the mesh has
    material_colors: np.ndarray  # (M, 3) base colour of every material (linear RGB)
    light: RefLight
    seed: int
    meta: dict = field(default_factory=dict)   # white_balance: the channel gains applied


def render_reference(mesh: Mesh, part_of_material: Sequence[str],
                     part_colors: Mapping[str, Sequence[float]], *, azimuth: float,
                     elevation: float, size: tuple[int, int] = (360, 480), fov: float = 45.0,
                     fill: float = 0.6, offset: tuple[float, float] = (0.0, 0.0),
                     light: RefLight | None = None, seed: int = 0, background: str = "clutter",
                     noise: float = 0.01, jpeg_quality: int | None = 90,
                     samples: int = 2, white_balance_error: float = 0.0) -> Reference:
    """A photo-like reference of ``mesh`` (canonical frame), ``part_of_material[m]`` the part of
    material m, ``part_colors`` base colours (linear RGB) of the parts that get one; ``size`` is
    (height, width). See the module docstring for every convention."""
    H, W = int(size[0]), int(size[1])
    light = light or RefLight()
    _check_args(mesh, part_of_material, part_colors, H, W, fov, fill, samples, background,
                noise, jpeg_quality, white_balance_error)
    rng = np.random.default_rng(seed)
    K, w2c, dist = photo_camera(azimuth, elevation, W, H, fov=fov, fill=fill, offset=offset)
    mats = _materials(mesh, part_of_material, part_colors)
    tracer = _Tracer(mesh, mats.glass)

    # truth: one ray per pixel centre
    o, d_centre = _rays(K, w2c, W, H, 1)
    near = 0.01 * dist
    tri, _, _, _ = tracer.first(o, d_centre, near, w2c)
    mask = (tri >= 0).reshape(H, W)
    part_map = np.where(tri >= 0, mats.part_index[mesh.face_material[np.maximum(tri, 0)]], -1)
    part_map = part_map.reshape(H, W).astype(np.int16)

    bg = _background(background, rng, H, W, elevation, fov)              # (H, W, 3) linear
    o, d = _rays(K, w2c, W, H, samples)                                   # (H*W*s*s, 3)
    pix = np.repeat(np.arange(H * W), samples * samples)
    radiance, hit = _shade_samples(tracer, mesh, mats, light, rng, o, d, near, w2c,
                                   bg.reshape(-1, 3)[pix] / light.exposure)
    ground = _ground_shadow(tracer, mesh, light, o, d[~hit])
    radiance[~hit] *= ground[:, None]
    gains = white_balance(light) * np.exp(rng.normal(0.0, white_balance_error, 3))
    radiance[hit] *= gains
    lin = light.exposure * radiance.reshape(H * W, samples * samples, 3).mean(axis=1)
    lin = lin.reshape(H, W, 3)
    if noise > 0:
        var = noise * noise * (0.2 + 0.8 * np.maximum(lin, 0.0) / 0.18)
        lin = lin + rng.standard_normal(lin.shape) * np.sqrt(var)
    image = linear_to_srgb8(np.clip(lin, 0.0, 1.0))
    if jpeg_quality is not None:
        image = _jpeg(image, int(jpeg_quality))
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    box = ((int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1) if rows.size
           else (0, 0, 0, 0))
    colors = {p: tuple(float(x) for x in c) for p, c in sorted(mats.part_color.items())}
    return Reference(image=image, box=box, mask=mask, part_map=part_map, K=K, w2c=w2c,
                     azimuth=float(azimuth) % 360.0, elevation=float(elevation),
                     distance=float(dist), fov=float(fov), colors=colors,
                     material_colors=mats.color.copy(), light=light, seed=int(seed),
                     meta={"white_balance": [float(g) for g in gains]})


def draw_car_colors(rng: np.random.Generator) -> dict[str, tuple[float, float, float]]:
    """Base colours (linear RGB) of a plausible car: ``body`` from a colour family drawn at the
    frequencies of ``CAR_COLOR_FREQUENCIES``, then spread in CIELAB around the family's centre;
    ``wheel`` (tyre black), ``rim`` (silver alloy, or dark / black painted one time in four),
    ``interior`` (black, grey or beige), ``plate`` (white, or the yellow of a UK rear plate one
    time in ten).

    Frequencies: approximate global shares of new cars by colour from Axalta's Global
    Automotive Color Popularity Report 2022 (white 35 %, black 19 %, grey 17 %, silver 10 %,
    blue 8 %, red 7 %; the remaining 4 % split here as brown/beige 2 %, green 1 %,
    yellow/orange/gold 1 %). The Lab centres are typical solid and metallic paints (not
    measurements of any one paint)."""
    names = list(CAR_COLOR_FREQUENCIES)
    p = np.array([CAR_COLOR_FREQUENCIES[n] for n in names])
    family = names[int(rng.choice(len(names), p=p / p.sum()))]
    centre, spread = _FAMILY_LAB[family]
    lab = np.asarray(centre) + rng.uniform(-1.0, 1.0, 3) * np.asarray(spread)
    body = np.clip(lab_to_linear(lab), 0.003, 0.9)
    tyre = np.full(3, rng.uniform(0.02, 0.04))
    rim = (np.full(3, rng.uniform(0.5, 0.8)) if rng.uniform() >= 0.25
           else np.full(3, rng.uniform(0.02, 0.08)))
    interior = [np.array([0.03, 0.03, 0.03]), np.array([0.12, 0.12, 0.12]),
                np.array([0.35, 0.28, 0.2])][int(rng.integers(3))] * rng.uniform(0.8, 1.2)
    plate = (np.array([0.8, 0.8, 0.78]) if rng.uniform() >= 0.1
             else np.array([0.85, 0.62, 0.02]))
    out = {"body": body, "wheel": tyre, "rim": rim, "interior": interior, "plate": plate}
    return {k: (float(v[0]), float(v[1]), float(v[2])) for k, v in out.items()}


def draw_light(rng: np.random.Generator, *, sun: bool = True,
               skyline: bool = False) -> RefLight:
    """A plausible daylight: sun 15-65 deg above the horizon at any heading with a warm-to-white
    colour and a strength of 1-3 times the sky's (or no sun: overcast), a blue-to-grey sky, a
    grey-brown ground, and the exposure that maps a white surface facing the sun (facing up
    without sun) to 0.85-1.0 after the white balance (a well-exposed photo: highlights and
    glints clip, diffuse whites do not). ``skyline``: 24 sectors of buildings 0-25 deg high
    (a third of them gaps), 0.25-0.9 of the horizon's radiance with a random tint, drawn after
    everything else (the other draws do not change)."""
    h, e = rng.uniform(0.0, 2.0 * np.pi), np.radians(rng.uniform(15.0, 65.0))
    sun_dir = (float(np.cos(e) * np.cos(h)), float(np.sin(e)), float(np.cos(e) * np.sin(h)))
    blue = rng.uniform(0.0, 1.0)                                  # 0: overcast grey, 1: blue
    zenith = np.array([0.30, 0.33, 0.36]) * (1 - blue) + np.array([0.18, 0.27, 0.45]) * blue
    zenith = zenith * rng.uniform(0.8, 1.2)
    horizon = zenith * 0.5 + np.array([0.22, 0.23, 0.24]) * rng.uniform(0.9, 1.3)
    ground = np.array([0.11, 0.10, 0.09]) * rng.uniform(0.6, 1.6)
    warm = rng.uniform(0.0, 1.0)
    sun_col = (np.array([1.0, 0.98, 0.95]) * (1 - warm) + np.array([1.0, 0.86, 0.7]) * warm)
    sky_mean = horizon + 0.8 * (zenith - horizon)
    sun_col = sun_col * float(sky_mean.mean()) * rng.uniform(1.0, 3.0) / np.sin(e) if sun \
        else np.zeros(3)
    t = lambda v: (float(v[0]), float(v[1]), float(v[2]))
    out = RefLight(sun_dir=sun_dir, sun_color=t(sun_col), sky_zenith=t(zenith),
                   sky_horizon=t(horizon), ground=t(ground))
    brightest = white_balance(out) * (sky_mean + sun_col)
    out = replace(out, exposure=float(rng.uniform(0.85, 1.0) / float(brightest.max())))
    if skyline:
        n = 24
        height = np.where(rng.uniform(size=n) < 1.0 / 3.0, 0.0, rng.uniform(3.0, 25.0, n))
        col = horizon[None, :] * rng.uniform(0.25, 0.9, (n, 1)) * rng.uniform(0.85, 1.15, (n, 3))
        out = replace(out, skyline=tuple((float(hh), *(float(x) for x in c))
                                         for hh, c in zip(height, col)))
    return out


def white_balance(light: RefLight) -> np.ndarray:
    """(3,) channel gains that make a grey surface facing up neutral under ``light``: the
    luminance (Rec. 709) of its irradiance (sky, ground and sun) over each channel."""
    E = _irradiance(light, np.array([[0.0, 1.0, 0.0]]))[0]
    E = E + np.asarray(light.sun_color, np.float64) * max(_unit(light.sun_dir)[1], 0.0)
    E = np.maximum(E, 1e-9)
    return float(np.dot([0.2126, 0.7152, 0.0722], E)) / E


def photo_camera(azimuth: float, elevation: float, width: int, height: int, *,
                 fov: float = 45.0, fill: float = 0.6,
                 offset: tuple[float, float] = (0.0, 0.0)) -> tuple[np.ndarray, np.ndarray, float]:
    """(K, w2c, distance) of a level camera at (azimuth, elevation) from the vehicle's centre,
    at the distance where the bounding sphere spans ``fill`` of the narrower half-field, turned
    by ``offset`` (x, y in -1..1) of the room left on each side (see the module docstring)."""
    half = np.radians(fov) / 2.0
    f = 0.5 * min(width, height) / np.tan(half)
    K = np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
    alpha = fill * half
    dist = 0.5 / np.sin(alpha)
    room_x = max(np.arctan(0.5 * width / f) - alpha, 0.0) * 0.9
    room_y = max(np.arctan(0.5 * height / f) - alpha, 0.0) * 0.9
    pos = camera_position(azimuth, elevation, dist)
    to = -pos / np.linalg.norm(pos)
    heading = np.arctan2(to[2], to[0]) + float(offset[0]) * room_x
    tilt = np.arcsin(np.clip(to[1], -1.0, 1.0)) - float(offset[1]) * room_y
    fwd = np.array([np.cos(tilt) * np.cos(heading), np.sin(tilt), np.cos(tilt) * np.sin(heading)])
    right = np.cross(fwd, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    R = np.stack([right, np.cross(fwd, right), fwd])
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ pos
    return K, w2c, float(dist)


# ----------------------------------------------------------------------------- materials

@dataclass
class _Materials:
    color: np.ndarray           # (M, 3) linear base colour
    metallic: np.ndarray        # (M,)
    roughness: np.ndarray       # (M,)
    clearcoat: np.ndarray       # (M,) 0 / 1
    transmission: np.ndarray    # (M,) glass only
    glass: np.ndarray           # (M,) bool
    part_index: np.ndarray      # (M,) int16 into PART_NAMES
    part_color: dict            # part -> base colour used


def _materials(mesh: Mesh, part_of_material: Sequence[str],
               part_colors: Mapping[str, Sequence[float]]) -> _Materials:
    M = len(mesh.materials)
    out = _Materials(color=np.zeros((M, 3)), metallic=np.zeros(M), roughness=np.ones(M),
                     clearcoat=np.zeros(M), transmission=np.zeros(M), glass=np.zeros(M, bool),
                     part_index=np.full(M, _OTHER, np.int16), part_color={})
    clear = see_through(mesh)
    for m, mat in enumerate(mesh.materials):
        part = part_of_material[m]
        prior = PART_MATERIALS.get(part)
        out.part_index[m] = _PART_INDEX.get(part, _OTHER)
        if prior is None:                                   # other / unseen: the source's
            out.color[m] = mat.base_color[:3]
            out.metallic[m], out.roughness[m] = mat.metallic, mat.roughness
        else:
            pbr = prior["pbrMetallicRoughness"]
            ext = prior.get("extensions", {})
            base = pbr.get("baseColorFactor", mat.base_color)[:3]
            if prior.get("emissive_from_source"):           # a lamp: its own colour, lamps off
                src = np.asarray(mat.base_color[:3], np.float64)
                base = src / src.max() if src.max() > 0.05 else np.ones(3)
            out.color[m] = part_colors.get(part, base)
            out.metallic[m] = pbr["metallicFactor"]
            out.roughness[m] = pbr["roughnessFactor"]
            out.clearcoat[m] = ext.get("KHR_materials_clearcoat", {}).get("clearcoatFactor", 0.0)
            if part == "window":
                out.transmission[m] = ext["KHR_materials_transmission"]["transmissionFactor"]
        if part == "window" or (clear[m] and part not in ("light",)):
            out.glass[m] = True
            out.transmission[m] = max(out.transmission[m], 1.0 - float(mat.base_color[3]), 0.5)
        if prior is not None:              # other / unseen: one colour per material, no truth
            out.part_color.setdefault(part, out.color[m].copy())
    out.color = np.clip(out.color, 0.0, 1.0)
    return out


def _check_args(mesh, part_of_material, part_colors, H, W, fov, fill, samples, background,
                noise, jpeg_quality, white_balance_error) -> None:
    if len(part_of_material) != len(mesh.materials):
        raise ValueError(f"{mesh.path}: part_of_material has {len(part_of_material)} entries "
                         f"for {len(mesh.materials)} materials")
    for p, c in part_colors.items():
        if p not in _PART_INDEX:
            raise ValueError(f"part_colors: unknown part {p!r} (parts: {', '.join(PART_NAMES)})")
        c = np.asarray(c, np.float64)
        if c.shape != (3,) or not np.all(np.isfinite(c)) or c.min() < 0 or c.max() > 1:
            raise ValueError(f"part_colors[{p!r}] must be 3 linear values in [0, 1], got {c}")
    if not (8 <= H <= 4096 and 8 <= W <= 4096):
        raise ValueError(f"size {H}x{W} outside 8..4096")
    if not (5.0 <= fov <= 120.0 and 0.05 <= fill <= 1.0):
        raise ValueError(f"fov={fov} must be in [5, 120] and fill={fill} in [0.05, 1]")
    if samples not in (1, 2, 3, 4):
        raise ValueError(f"samples={samples} must be 1..4")
    if background not in ("clutter", "plain"):
        raise ValueError(f"background={background!r} must be 'clutter' or 'plain'")
    if not white_balance_error >= 0:
        raise ValueError(f"white_balance_error={white_balance_error} must be >= 0")
    if noise < 0 or (jpeg_quality is not None and not 1 <= jpeg_quality <= 100):
        raise ValueError(f"noise={noise} must be >= 0, jpeg_quality={jpeg_quality} in 1..100")


# ----------------------------------------------------------------------------- ray casting

class _Tracer:
    """Two Embree scenes of one mesh: every face, and the faces that are not glass."""

    def __init__(self, mesh: Mesh, glass: np.ndarray):
        from embreex import rtcore_scene as rtcs
        from embreex.mesh_construction import TriangleMesh

        V = np.asarray(mesh.vertices, np.float64)
        F = np.asarray(mesh.faces, np.int64)
        self.all = rtcs.EmbreeScene()
        TriangleMesh(self.all, np.ascontiguousarray(V[F], dtype=np.float32))
        self.opaque_faces = np.flatnonzero(~glass[mesh.face_material])
        self.opaque = rtcs.EmbreeScene()
        if self.opaque_faces.size:
            TriangleMesh(self.opaque, np.ascontiguousarray(V[F[self.opaque_faces]], np.float32))
        fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        vn = np.zeros_like(V)
        for k in range(3):
            np.add.at(vn, F[:, k], fn)
        ln = np.linalg.norm(fn, axis=1, keepdims=True)
        self.face_n = np.divide(fn, ln, out=np.zeros_like(fn), where=ln > 0)
        lv = np.linalg.norm(vn, axis=1, keepdims=True)
        self.vert_n = np.divide(vn, lv, out=np.zeros_like(vn), where=lv > 0)
        self.V, self.F = V, F

    def first(self, o, d, near, w2c, opaque: bool = False):
        """(face (N,) int64 -1 = miss, t (N,), u (N,), v (N,)) of rays from ``o`` along unit
        ``d``, starting on the camera's near plane (as the rasterizer clips)."""
        fwd = w2c[2, :3]
        cos = np.maximum(d @ fwd, 1e-6)
        return self.cast(o + d * (near / cos)[:, None], d, opaque, offset=near / cos)

    def cast(self, o, d, opaque: bool = False, offset=None):
        o = np.broadcast_to(o, d.shape)
        scene = self.opaque if opaque else self.all
        if opaque and self.opaque_faces.size == 0:
            n = d.shape[0]
            return np.full(n, -1, np.int64), np.full(n, np.inf), np.zeros(n), np.zeros(n)
        res = scene.run(np.ascontiguousarray(o, np.float32), np.ascontiguousarray(d, np.float32),
                        output=1)
        tri = np.asarray(res["primID"]).astype(np.int64)
        if opaque:
            tri = np.where(tri >= 0, self.opaque_faces[np.maximum(tri, 0)], -1)
        t = np.asarray(res["tfar"], np.float64) + (0.0 if offset is None else offset)
        return tri, t, np.asarray(res["u"], np.float64), np.asarray(res["v"], np.float64)

    def blocked(self, o, d) -> np.ndarray:
        """(N,) bool: the rays from ``o`` along ``d`` hit an opaque face."""
        if self.opaque_faces.size == 0 or d.shape[0] == 0:
            return np.zeros(d.shape[0], bool)
        res = self.opaque.run(np.ascontiguousarray(o, np.float32),
                              np.ascontiguousarray(d, np.float32), query="OCCLUDED")
        return np.asarray(res) != -1

    def normals(self, tri, u, v, d):
        """(N, 3) shading normals at the hits, facing the viewer (against ``d``), and the face
        normals (also facing the viewer) for ray offsets. A corner takes its vertex normal when
        that is within 35 deg of the face normal (either winding), else the face normal; the
        corners are interpolated at the hit (so a box stays flat and a curved panel is smooth)."""
        fn = self.face_n[tri]
        cn = self.vert_n[self.F[tri]]                                  # (N, 3, 3)
        dot = (cn * fn[:, None, :]).sum(axis=2)
        cn = np.where((np.abs(dot) >= _SMOOTH_COS)[..., None], cn * np.sign(dot)[..., None],
                      fn[:, None, :])
        w = np.stack([1.0 - u - v, u, v], axis=1)
        sn = (cn * w[:, :, None]).sum(axis=1)
        ln = np.linalg.norm(sn, axis=1, keepdims=True)
        sn = np.divide(sn, ln, out=fn.copy(), where=ln > 0)
        flip = np.where((fn * d).sum(axis=1) > 0, -1.0, 1.0)[:, None]
        fn, sn = fn * flip, sn * flip
        # a shading normal turned away from the viewer falls back to the face normal
        sn = np.where(((sn * d).sum(axis=1) < 0)[:, None], sn, fn)
        return sn, fn


def _rays(K, w2c, W, H, s):
    """Camera centre and unit directions through s x s sub-pixel centres of every pixel,
    pixel-major (the s*s samples of pixel (i, j) are consecutive); s = 1: the pixel centres."""
    sub = (np.arange(s) + 0.5) / s
    u = (np.arange(W)[:, None] + sub[None, :]).reshape(1, W, 1, s)      # x, per (j, sx)
    v = (np.arange(H)[:, None] + sub[None, :]).reshape(H, 1, s, 1)      # y, per (i, sy)
    Ki = np.linalg.inv(K)
    cam = [Ki[r, 0] * u + Ki[r, 1] * v + Ki[r, 2] for r in range(3)]     # K^-1 (u, v, 1)
    R, t = w2c[:3, :3], w2c[:3, 3]
    d = np.empty((H, W, s, s, 3))
    for c in range(3):                                                   # R^T K^-1 (u, v, 1)
        d[..., c] = cam[0] * R[0, c] + cam[1] * R[1, c] + cam[2] * R[2, c]
    d = d.reshape(-1, 3)
    d /= np.sqrt(np.einsum("ij,ij->i", d, d))[:, None]
    return -R.T @ t, d


# ----------------------------------------------------------------------------- shading

def _sky(light: RefLight, dirs: np.ndarray) -> np.ndarray:
    """(N, 3) radiance of the environment (no sun) in directions ``dirs``."""
    z, h, g = (np.asarray(x, np.float64) for x in (light.sky_zenith, light.sky_horizon,
                                                   light.ground))
    y = dirs[:, 1:2]
    sky = h + (z - h) * np.sqrt(np.clip(y, 0.0, 1.0))
    if light.skyline:
        table = np.asarray(light.skyline, np.float64)                   # (S, 4)
        az = np.degrees(np.arctan2(-dirs[:, 2], dirs[:, 0])) % 360.0
        k = np.minimum((az * len(table) / 360.0).astype(np.int64), len(table) - 1)
        elev = np.degrees(np.arcsin(np.clip(y[:, 0], -1.0, 1.0)))
        building = (elev < table[k, 0])[:, None]
        sky = np.where(building, table[k, 1:], sky)
    return np.where(y >= 0, sky, g)


def _irradiance(light: RefLight, n: np.ndarray) -> np.ndarray:
    """(N, 3) sky + ground irradiance of normals ``n`` over pi (radiance units)."""
    z, h, g = (np.asarray(x, np.float64) for x in (light.sky_zenith, light.sky_horizon,
                                                   light.ground))
    mean = h + 0.8 * (z - h)                        # 2 * integral of L(y) y dy over [0, 1]
    share = (1.0 + n[:, 1:2]) / 2.0
    return g + (mean - g) * share


def _env(light: RefLight, r: np.ndarray, rough: np.ndarray) -> np.ndarray:
    """Sky reflected in mirror direction ``r``, blurred toward the irradiance by roughness."""
    w = np.clip(2.0 * rough, 0.0, 1.0)[:, None]
    return (1.0 - w) * _sky(light, r) + w * _irradiance(light, r)


def _sun_spec(light_dir, n, v, rough, ndl) -> np.ndarray:
    """(N,) normalised Blinn-Phong sun highlight (times n.l), exponent from roughness."""
    h = light_dir[None, :] + v
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)
    a = np.maximum(rough, 0.05) ** 2
    s = 2.0 / a - 2.0
    ndh = np.clip((n * h).sum(axis=1), 0.0, 1.0)
    return (s + 2.0) / 8.0 * ndh ** s * ndl


def _shade_samples(tracer: _Tracer, mesh: Mesh, mats: _Materials, light: RefLight, rng, o, d,
                   near, w2c, bg_radiance):
    """(N, 3) radiance of every ray and (N,) bool hit; misses take ``bg_radiance``."""
    tri, t, u, v = tracer.first(o, d, near, w2c)
    hit = tri >= 0
    out = np.array(bg_radiance, np.float64, copy=True)
    idx = np.flatnonzero(hit)
    if idx.size == 0:
        return out, hit
    dh = d[idx]
    p = o[None, :] + dh * t[idx, None]
    ftri = tri[idx]
    mat = mesh.face_material[ftri].astype(np.int64)
    n, fn = tracer.normals(ftri, u[idx], v[idx], dh)
    rad = _surface(tracer, mats, light, rng, p, dh, n, fn, mat)
    glass = mats.glass[mat]
    if glass.any():
        g = np.flatnonzero(glass)
        btri, bt, bu, bv = tracer.first(o, dh[g], near, w2c, opaque=True)
        behind = bg_radiance[idx[g]].copy()
        bh = np.flatnonzero(btri >= 0)
        if bh.size:
            bd = dh[g][bh]
            bp = o[None, :] + bd * bt[bh, None]
            bn, bfn = tracer.normals(btri[bh], bu[bh], bv[bh], bd)
            bmat = mesh.face_material[btri[bh]].astype(np.int64)
            behind[bh] = _surface(tracer, mats, light, rng, bp, bd, bn, bfn, bmat)
        vv = -dh[g]
        ndv = np.clip((n[g] * vv).sum(axis=1), 1e-4, 1.0)
        F = (0.04 + 0.96 * (1.0 - ndv) ** 5)[:, None]
        r = 2.0 * ndv[:, None] * n[g] - vv
        refl = _env(light, r, mats.roughness[mat[g]])
        ldir = _unit(light.sun_dir)
        ndl = np.clip(n[g] @ ldir, 0.0, 1.0)
        lit = ~tracer.blocked(p[g] + fn[g] * _EPS, np.broadcast_to(ldir, (g.size, 3)))
        refl = refl + (np.asarray(light.sun_color) * (_sun_spec(
            ldir, n[g], vv, mats.roughness[mat[g]], ndl) * lit)[:, None])
        trans = (mats.transmission[mat[g]][:, None] * mats.color[mat[g]])
        rad[g] = F * refl + (1.0 - F) * trans * behind
    out[idx] = rad
    return out, hit


def _surface(tracer: _Tracer, mats: _Materials, light: RefLight, rng, p, d, n, fn, mat):
    """(N, 3) radiance of opaque surfaces (glass is finished by the caller)."""
    N = p.shape[0]
    c = mats.color[mat]
    metal = mats.metallic[mat][:, None]
    rough = mats.roughness[mat]
    v = -d
    ndv = np.clip((n * v).sum(axis=1), 1e-4, 1.0)
    x5 = ((1.0 - ndv) ** 5)[:, None]
    r = 2.0 * ndv[:, None] * n - v
    ldir = _unit(light.sun_dir)
    sun = np.asarray(light.sun_color, np.float64)
    start = p + fn * _EPS
    ndl = np.clip(n @ ldir, 0.0, 1.0) * (np.clip(fn @ ldir, 0.0, 1.0) > 0)
    lit = np.zeros(N, bool)
    need = ndl > 0
    if sun.max() > 0 and need.any():
        lit[need] = ~tracer.blocked(start[need], np.broadcast_to(ldir, (int(need.sum()), 3)))
    sunlit = ndl * lit
    vis = _sky_visibility(tracer, light, rng, start, n, fn)[:, None]
    E = _irradiance(light, n) * vis
    cc = mats.clearcoat[mat][:, None]
    # base layer: a dielectric share (F0 0.04) and a metallic share (F0 = c); under a clear coat
    # the base meets the coat's resin, not air: no dielectric reflection and no grazing rise
    rise = x5 * (1.0 - cc)
    F0d = 0.04 * (1.0 - cc)
    Fd = F0d + (1.0 - F0d) * rise
    F = (1.0 - metal) * Fd + metal * (c + (1.0 - c) * rise)
    kd = (1.0 - metal) * (1.0 - Fd)
    base = (kd * c * (E + sun * sunlit[:, None])
            + F * (_env(light, r, rough) * vis + sun * _sun_spec(ldir, n, v, rough,
                                                                 sunlit)[:, None]))
    Fc = cc * (0.04 + 0.96 * x5)
    coat = _env(light, r, np.full(N, 0.03)) * vis + sun * _sun_spec(
        ldir, n, v, np.full(N, 0.03), sunlit)[:, None]
    return (1.0 - Fc) * base + Fc * coat


def _sky_visibility(tracer: _Tracer, light: RefLight, rng, start, n, fn) -> np.ndarray:
    """(N,) share of ``light.ao_rays`` cosine-distributed rays about ``n`` that leave the
    vehicle within 0.5 units (a ray below the face's plane is mirrored above it); 1 with no
    rays."""
    k = int(light.ao_rays)
    N = start.shape[0]
    if k <= 0 or N == 0:
        return np.ones(N)
    u1 = rng.random((N, k))
    u2 = rng.random((N, k))
    rr, phi = np.sqrt(u1), 2.0 * np.pi * u2
    local = np.stack([rr * np.cos(phi), rr * np.sin(phi), np.sqrt(1.0 - u1)], axis=-1)
    a = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    t1 = np.cross(n, a)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    dirs = (local[..., :1] * t1[:, None] + local[..., 1:2] * t2[:, None]
            + local[..., 2:] * n[:, None]).reshape(-1, 3)
    fnk = np.repeat(fn, k, axis=0)
    below = (dirs * fnk).sum(axis=1, keepdims=True)
    dirs = np.where(below < 0, dirs - 2.0 * below * fnk, dirs)      # mirrored above the face
    o = np.repeat(start, k, axis=0)
    if tracer.opaque_faces.size == 0:
        return np.ones(N)
    res = tracer.opaque.run(np.ascontiguousarray(o, np.float32),
                            np.ascontiguousarray(dirs, np.float32),
                            dists=np.full(o.shape[0], 0.5, np.float32), query="OCCLUDED")
    free = (np.asarray(res) == -1).reshape(N, k)
    return free.mean(axis=1)


def _ground_shadow(tracer: _Tracer, mesh: Mesh, light: RefLight, o, d) -> np.ndarray:
    """(N,) factor on background rays: the sun's share of the ground's light removed where the
    ray meets the ground plane (y = the mesh's lowest point) within 1.5 units of the centre and
    the vehicle blocks the sun there; 1 elsewhere."""
    out = np.ones(d.shape[0])
    sun = np.asarray(light.sun_color, np.float64)
    ldir = _unit(light.sun_dir)
    if d.shape[0] == 0 or sun.max() <= 0 or ldir[1] <= 0:
        return out
    y0 = float(np.asarray(mesh.vertices)[:, 1].min())
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (y0 - o[1]) / d[:, 1]
    ok = np.isfinite(t) & (t > 0)
    g = o[None, :] + d * np.where(ok, t, 0.0)[:, None]
    ok &= np.hypot(g[:, 0], g[:, 2]) < 1.5
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return out
    shadow = tracer.blocked(g[idx] + np.array([0.0, _EPS, 0.0]), np.broadcast_to(ldir,
                                                                                 (idx.size, 3)))
    sky = _irradiance(light, np.array([[0.0, 1.0, 0.0]]))[0]
    share = float((sun * ldir[1]).mean() / ((sun * ldir[1]).mean() + sky.mean()))
    out[idx[shadow]] = 1.0 - 0.9 * share
    return out


def _unit(v) -> np.ndarray:
    a = np.asarray(v, np.float64)
    n = np.linalg.norm(a)
    return a / n if n > 0 else a


# ----------------------------------------------------------------------------- background

def _background(kind: str, rng, H: int, W: int, elevation: float, fov: float) -> np.ndarray:
    """(H, W, 3) linear image values of the background (see the module docstring)."""
    if kind == "plain":
        return np.broadcast_to(srgb8_to_linear(np.array([128, 128, 128])), (H, W, 3)).copy()
    import cv2

    img = _street(rng, H, W, elevation, fov) if rng.uniform() < 0.5 else _shapes(rng, H, W)
    # texture: a little per-pixel grain and a smooth illumination field
    grain = rng.normal(0.0, rng.uniform(2.0, 8.0), (H, W, 1))
    field = cv2.resize(rng.uniform(0.7, 1.3, (3, 4)).astype(np.float32), (W, H),
                       interpolation=cv2.INTER_CUBIC)[..., None]
    srgb = np.clip((img.astype(np.float64) + grain) * field, 0, 255)
    return srgb8_to_linear(srgb)


def _shapes(rng, H: int, W: int) -> np.ndarray:
    """Random filled rectangles, discs, lines and stripes over a gradient, uint8 sRGB."""
    import cv2

    c0, c1 = rng.integers(0, 256, 3), rng.integers(0, 256, 3)
    ang = rng.uniform(0, 2 * np.pi)
    yy, xx = np.mgrid[0:H, 0:W]
    t = (np.cos(ang) * xx / W + np.sin(ang) * yy / H + 1) / 2
    img = np.ascontiguousarray((c0 + (c1 - c0) * t[..., None]).astype(np.uint8))
    for _ in range(int(rng.integers(10, 25))):
        col = tuple(int(x) for x in rng.integers(0, 256, 3))
        p = (int(rng.integers(0, W)), int(rng.integers(0, H)))
        q = (int(rng.integers(0, W)), int(rng.integers(0, H)))
        shape = int(rng.integers(4))
        if shape == 0:
            cv2.rectangle(img, p, q, col, -1)
        elif shape == 1:
            cv2.circle(img, p, int(rng.integers(4, max(H // 3, 5))), col, -1)
        elif shape == 2:
            cv2.line(img, p, q, col, int(rng.integers(1, 6)))
        else:
            x0, x1 = sorted((p[0], q[0]))
            y0, y1 = sorted((p[1], q[1]))
            period = int(rng.integers(3, 20))
            sub = img[y0:y1 + 1, x0:x1 + 1]
            band = ((np.arange(sub.shape[1]) // period) % 2 == 0)
            sub[:, band] = col
    return img


def _street(rng, H: int, W: int, elevation: float, fov: float) -> np.ndarray:
    """A street: sky, facades with windows above the horizon, asphalt with lane markings."""
    import cv2

    f = 0.5 * min(H, W) / np.tan(np.radians(fov) / 2)
    horizon = int(H / 2 - f * np.tan(np.radians(elevation)) + rng.uniform(-0.1, 0.1) * H)
    img = np.empty((H, W, 3), np.uint8)
    sky0, sky1 = rng.integers(150, 256, 3), rng.integers(60, 200, 3)
    t = np.linspace(0, 1, H)[:, None, None]
    img[:] = (sky1 + (sky0 - sky1) * t).astype(np.uint8)
    x = int(rng.integers(-W // 4, 0))
    while x < W:
        w = int(rng.integers(max(W // 8, 2), max(W // 3, 3)))
        top = horizon - int(rng.integers(max(H // 8, 1), H // 2 + 2))
        col = tuple(int(c) for c in rng.integers(40, 230, 3))
        cv2.rectangle(img, (x, top), (x + w, horizon), col, -1)
        win = tuple(int(c) for c in rng.integers(0, 256, 3))
        ws, hs = int(rng.integers(6, 16)), int(rng.integers(8, 20))
        for yy in range(top + 4, horizon - hs, hs + 6):
            for xx in range(x + 4, x + w - ws, ws + 6):
                cv2.rectangle(img, (xx, yy), (xx + ws, yy + hs), win, -1)
        x += w + int(rng.integers(0, max(W // 10, 1)))
    g0 = min(max(horizon, 0), H)
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
                    p = (int(vx + (x1 - vx) * s), int(g0 + (H - g0) * s))
                    q = (int(vx + (x1 - vx) * (s + 0.05)), int(g0 + (H - g0) * (s + 0.05)))
                    cv2.line(img, p, q, colour, max(1, int(1 + 6 * s)))
    return img


def _jpeg(image: np.ndarray, quality: int) -> np.ndarray:
    """``image`` through Pillow's JPEG encoder and decoder (4:2:0, optimised tables off)."""
    buf = io.BytesIO()
    Image.fromarray(image, "RGB").save(buf, format="JPEG", quality=quality)
    buf.seek(0)
    with Image.open(buf) as im:
        return np.ascontiguousarray(np.asarray(im.convert("RGB"), np.uint8))
