"""Orientation stage: the rotation from a mesh's file frame to the canonical vehicle frame.

``orient_mesh(mesh, mode)`` returns the mesh in the canonical vehicle frame (+Y up, the
vehicle's front toward +X, its right side toward +Z; see docs/CONVENTIONS.md) with the
:class:`~ucad_cl.artifacts.Orientation` record in ``mesh.orientation`` and the rotation folded
into ``mesh.file_to_norm``. ``mode`` is ``"auto"`` (estimate it), ``"file"`` (trust the file:
+Y up, no rotation, the frame ingest always used) or an ``(up, front)`` pair of signed file axes
such as ``("+Z", "-Y")`` (a curated library's convention). ``estimate_orientation(mesh)`` is the
estimator alone.

How ``auto`` decides (every step works on pose-invariant statistics, so a re-posed file gives
the same decisions; ties go to fixed rules written next to the code):

1. **Samples.** 4,096 area-weighted surface points with their face normals and 4,096 faces
   drawn by count (finely tessellated parts such as tyres get many), from a fixed random
   stream. A ground sheet, cloth or display base under the vehicle (one thin material broader
   than the rest, all of the rest on one side) is left out and says which way is up. Several
   vehicles apart in one file (separate clusters of surface): only the largest one's
   samples are kept, so the file is oriented by that vehicle (and flagged).
2. **Mirror plane** (the width axis). Candidate normals (the principal axes, the file axes and
   in-between directions; not the length axis of an elongated body) are ranked by how many
   reflected samples land on the surface; the best are refined by a point-to-plane
   symmetric ICP (converges from ~10 degrees off to ~0.05 degree). Left and right of a vehicle
   mirror each other; front and back, top and bottom do not.
3. **Side view.** In the mirror plane, the length axis is the long side of the side view's
   smallest bounding rectangle (a vehicle stands on its wheels or sills).
4. **Wheels.** A Hough vote with normals for circles in the side view, checked to be whole,
   round tyres on both sides of the mirror plane, low on the body, two or more on one line
   standing on the ground (``find_wheels``). They give the ground line (up is levelled on the
   tyres' contacts, so a tilted car comes out level) and the axle pattern.
5. **Up** (which side is the ground): cues each scoring in [-1, 1], weighted (UP_WEIGHTS) and
   summed: wheels, ground sheet, glazing high, the side view's long flat edge low, lamps low,
   names (roof, floor, underbody...), wheel names low, the roof narrower than the body.
6. **Front** (which end is the nose): names of materials and nodes (front/rear, head/tail,
   FL/RR..., in several languages), lamp colours (red at the rear; white, yellow or amber at
   the front), the windscreen (more glazing across the length at the front of the glazed
   region), glazing only near one end (a cab), side mirrors (spikes of the width in the front
   half), an axle pattern (a lone steering axle at the front, tandem axles at the rear),
   the roof profile (the nose lower than the tail), the cabin's place (the roof's middle
   behind the middle of the length: it decides low-poly cars whose lamps share the body
   colour, without glazing or names) and an open load bed at the rear (a pickup's, whose
   cab is ahead of the middle); weights FRONT_WEIGHTS (docs/ORIENTATION.md).
7. **Snap.** Up within SNAP_DEG of a signed file axis (SNAP_DEG_COARSE when no wheels level
   it; SNAP_DEG_ALIGNED when no wheels level it but the mirror plane is a file plane, within
   SNAP_DEG: the file is then axis-aligned, and a wedge-shaped body without found wheels, whose
   side view's smallest rectangle tilts with the wedge, must not pitch it: a low-poly DeLorean
   came out 13.5 degrees nose-down) is snapped to it, then front within SNAP_DEG; an
   axis-aligned file, the common case,
   gets an exact signed permutation, applied by indexing, so a re-posed file gives
   bit-identical canonical vertices.
8. **Flags.** ``multiple_vehicles`` (vehicles side by side: nothing crosses the mirror plane;
   apart: separate clusters of surface; on top of each other: node groups that each look like
   a whole vehicle), ``no_wheels``, ``asymmetric`` (a poor mirror plane), ``ground_plane``,
   ``up_ambiguous`` / ``front_ambiguous`` (confidence under UNCERTAIN_BELOW).

**Cascade** (coarse to fine). The steps above run first on a small budget (``FAST``: 1,024
area and 4,096 face samples, fewer mirror candidates refined, 6 Hough radii); that cheap pass
is kept when it is clearly decided: no flag raised, symmetry at least FAST_ACCEPT_SYMMETRY and
both confidences at least FAST_ACCEPT_UP / FAST_ACCEPT_FRONT (margins chosen on tuning data:
generator seeds 800000-800499 and the real models; none of the cheap pass's kept decisions
differed from the full estimate there; with the cabin cue, one low-poly tuning vehicle of 140
differs: the cheap pass finds its wheels and is right, the full estimate does not and is
flagged, see docs/ORIENTATION.md). It gives up as soon as it cannot be kept (the
commonest reason, no wheels found on the small budget, comes before the costly cues), and
the full estimate (``FULL``: the budgets above) decides. Both passes draw their samples
from the same content-independent stream, so the path taken and the result are the same for
a file and any re-posing of it.

Confidences are in [0, 1]: ``1 - exp(-|score| / scale)`` of the summed cue scores, so one
strong cue or several weak agreeing ones give a confident answer, and cues that cancel give
a low one. ``Orientation.uncertain`` is ``min(up, front) < UNCERTAIN_BELOW``. The cues and
their weights were designed on the generator and on the 20 real models of ``../shared``
(``bench/orient.py`` says which figures are held out); none of those models is special-cased.

Layout (a package by cue family): this file holds the public functions, the canonical
placement and the cascade (``_estimate``, ``_estimate_pass``: the steps above in order);
``geometry`` the budgets, samples and the side view (``Context``) every cue reads; ``mirror``
step 2; ``wheels`` step 4; ``up`` and ``front`` the cues of steps 5 and 6 (and the ground
sheet); ``names`` the name, lamp-colour and glass cues they share; ``vehicles`` several
vehicles in one file. Submodules import only ``geometry``, ``names`` and ``wheels``, never
this file.

Canonical placement (after the rotation): x and y centred on the bounding box, so the ground
contact (the lowest point: the tyres' contact for a wheeled vehicle) is at y = -height / 2;
z centred on the mirror plane when the model is mirror-symmetric (``symmetry`` >= 0.5) and
the plane is 0.2 % to 2 % of the diagonal off the box centre, on the box otherwise (for a
symmetric model they coincide); scale: the bounding-box diagonal is 1.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import replace
from pathlib import Path
from typing import Sequence

import numpy as np

from ..artifacts import Mesh, Orientation
from .front import front_cue_scores
from .geometry import FAST, FULL, Budget, Context, Geometry, cross3, face_geometry, surface_samples
from .mirror import mirror_plane
from .names import Names, NameTable
from .up import ground_sheet, up_cue_scores
from .vehicles import largest_vehicle, overlapping_vehicles, several_vehicles
from .wheels import find_wheels

AXES: dict[str, np.ndarray] = {f"{s}{a}": (1.0 if s == "+" else -1.0) * np.eye(3)[i]
                               for i, a in enumerate("XYZ") for s in "+-"}
SNAP_DEG = 1.5                  # snap front, and up levelled on wheels, within this angle
SNAP_DEG_COARSE = 6.0           # snap up within this angle when no wheels level it
SNAP_DEG_ALIGNED = 25.0         # ... and within this one when the mirror plane is a file plane
UNCERTAIN_BELOW = Orientation.UNCERTAIN_BELOW   # confidence under which it is flagged
UP_SCALE = 0.8                  # confidence = 1 - exp(-|summed score| / scale)
FRONT_SCALE = 0.8
MIRROR_CENTRE_MAX = 0.02        # z-centre on the mirror plane when it is off the box centre
MIRROR_MIN_SHIFT = 0.002        # by more than this and at most that (bbox-diagonal units)
#: the cheap pass is kept when it raises no flag and both confidences reach these
#: (chosen on tuning data only: generator seeds 800000-800499 and the real models)
FAST_ACCEPT_UP = 0.8
FAST_ACCEPT_FRONT = 0.8
FAST_ACCEPT_SYMMETRY = 0.5
FLAGS = ("multiple_vehicles", "no_wheels", "front_ambiguous", "up_ambiguous", "asymmetric",
         "ground_plane")

#: weight of each cue in the summed score (see the module docstring and ``bench/orient.py``)
UP_WEIGHTS: dict[str, float] = {"wheels": 3.0, "ground_plane": 3.0, "glass_high": 1.5,
                                "hull_base": 1.0, "lamps_low": 0.5, "names_up": 1.5,
                                "wheel_names_low": 1.0, "roof_narrow": 0.5}
FRONT_WEIGHTS: dict[str, float] = {"names": 3.0, "lamp_colours": 2.0, "windscreen": 1.5,
                                   "cab_glass": 1.5, "mirrors": 1.0, "axles": 1.5,
                                   "profile": 0.5, "cabin": 1.0, "bed": 1.0}


def orient_mesh(mesh: Mesh, mode: str | tuple[str, str] = "auto", *,
                disabled: Sequence[str] = ()) -> Mesh:
    """``mesh`` moved into the canonical vehicle frame, with ``mesh.orientation`` recorded.

    mode: ``"auto"``, ``"file"`` or ``(up, front)`` signed file axes (see :func:`parse_mode`).
    disabled: cue names left out of the estimate (ablation; see UP_WEIGHTS, FRONT_WEIGHTS).
    The input mesh is not modified. ``file_to_norm`` of the result maps the file frame to the
    new canonical frame (the rotation is part of it).
    """
    mode = parse_mode(mode)
    if mode == "auto":
        orientation, plane = _estimate(mesh, disabled)
        return _apply(mesh, orientation, plane)
    if mode == "file":
        return _apply(mesh, Orientation(rotation=np.eye(3), source="file"))
    up, front = mode
    return _apply(mesh, Orientation(rotation=rotation_from_axes(up, front), up_confidence=1.0,
                                    front_confidence=1.0, source="override"))


def estimate_orientation(mesh: Mesh, *, disabled: Sequence[str] = (),
                         cascade: bool = True) -> Orientation:
    """The :class:`Orientation` ``orient_mesh(mesh, "auto")`` would apply (rotation only).
    ``cascade=False``: the full estimate alone, without trying the cheap pass first (the
    reference the cascade is checked against; slower)."""
    return _estimate(mesh, disabled, cascade)[0]


def takes_fast_path(mesh: Mesh, *, disabled: Sequence[str] = ()) -> bool:
    """True when the cascade's cheap pass decides ``mesh`` (the full estimate is not run)."""
    return _estimate_pass(mesh, disabled, FAST, face_geometry(mesh), Names(mesh),
                          give_up=True) is not None


def in_frame(mesh: Mesh, file_to_norm: np.ndarray) -> Mesh:
    """``mesh`` moved into the frame ``file_to_norm`` maps its file to (e.g. the frame a
    catalogue stored, whose cameras are in it); its orientation record becomes None."""
    T = np.asarray(file_to_norm, np.float64) @ np.linalg.inv(np.asarray(mesh.file_to_norm))
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"{mesh.path}: file_to_norm must be a finite 4 x 4 matrix")
    v = np.asarray(mesh.vertices, np.float64) @ T[:3, :3].T + T[:3, 3]
    return replace(mesh, vertices=v, file_to_norm=np.asarray(file_to_norm, np.float64),
                   orientation=None)


def parse_mode(mode) -> str | tuple[str, str]:
    """``"auto"`` | ``"file"`` | ``"UP,FRONT"`` (e.g. ``"+Z,-Y"``) | ``(up, front)`` -> the
    normalised mode; ValueError naming the problem otherwise. Axes: ``+X -X +Y -Y +Z -Z``
    (a missing sign means +); up and front must be perpendicular."""
    if isinstance(mode, str):
        text = mode.strip()
        if text.lower() in ("auto", "file"):
            return text.lower()
        parts = [p.strip() for p in text.split(",")]
        if len(parts) != 2:
            raise ValueError(f"orientation {mode!r}: expected 'auto', 'file' or 'UP,FRONT' "
                             f"with signed axes such as '+Z,-Y'")
        mode = tuple(parts)
    try:
        up, front = (_axis_name(a) for a in mode)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"orientation {mode!r}: {exc}") from None
    if up[1] == front[1]:
        raise ValueError(f"orientation {mode!r}: up and front must be different axes")
    return up, front


def rotation_from_axes(up: str, front: str) -> np.ndarray:
    """3x3 rotation (file -> canonical) that sends file axis ``up`` to +Y and ``front`` to +X."""
    u, f = AXES[_axis_name(up)], AXES[_axis_name(front)]
    if abs(float(u @ f)) > 0.5:
        raise ValueError(f"up {up} and front {front} must be perpendicular")
    return np.stack([f, u, np.cross(f, u)]) + 0.0


class OrientationOverrides:
    """Per-mesh orientations of a curated library: ``{key: (up, front)}``, key = a file's
    sha256 (as ``Mesh.sha256``) or its path (absolute, or relative to the overrides file).

    ``read(path)`` takes JSON (``{"KEY": "+Z,-Y"}`` or ``{"KEY": {"up": "+Z", "front":
    "-Y"}}``, also ``"auto"`` / ``"file"``) or text lines ``KEY UP FRONT`` / ``KEY UP,FRONT``
    (``#`` starts a comment). ValueError names the file, the line and the problem."""

    def __init__(self, entries: dict | None = None):
        self.entries: dict[str, str | tuple[str, str]] = {}
        for key, mode in (entries or {}).items():
            self.entries[str(key)] = parse_mode(mode)

    @classmethod
    def read(cls, path: str | os.PathLike) -> "OrientationOverrides":
        p = Path(path)
        try:
            text = p.read_text(encoding="utf-8-sig")    # an editor's BOM dropped
        except (OSError, UnicodeDecodeError) as exc:
            raise ValueError(f"{p}: cannot read orientation overrides: {exc}") from None
        raw: dict = {}
        if p.suffix.lower() == ".json":
            try:
                data = json.loads(text)
            except json.JSONDecodeError as exc:
                raise ValueError(f"{p}: invalid JSON: {exc}") from None
            if not isinstance(data, dict):
                raise ValueError(f"{p}: expected a JSON object {{path or sha256: 'UP,FRONT'}}")
            for key, val in data.items():
                raw[key] = (val.get("up"), val.get("front")) if isinstance(val, dict) else val
        else:
            for n, line in enumerate(text.splitlines(), 1):
                words = line.split("#", 1)[0].replace(",", " ").split()
                if not words:
                    continue
                if len(words) not in (2, 3):
                    raise ValueError(f"{p}:{n}: expected 'KEY UP FRONT' (e.g. 'car.obj +Z -Y'), "
                                     f"got {line.strip()!r}")
                raw[words[0]] = words[1] if len(words) == 2 else (words[1], words[2])
        out = cls()
        for key, val in raw.items():
            try:
                mode = parse_mode(val)
            except ValueError as exc:
                raise ValueError(f"{p}: entry {key!r}: {exc}") from None
            if not _is_sha256(key):
                kp = Path(key)
                key = str((kp if kp.is_absolute() else p.parent / kp).resolve())
            out.entries[key] = mode
        return out

    def mode_for(self, path: str | os.PathLike, sha256: str, default):
        """The override for this file (its sha256 first, then its resolved path), or
        ``default``."""
        if not self.entries:
            return default
        if sha256 in self.entries:
            return self.entries[sha256]
        return self.entries.get(str(Path(path).resolve()), default)

    def as_items(self) -> tuple[tuple[str, str], ...]:
        """Sorted ``(key, "UP,FRONT" | "auto" | "file")`` pairs (what a build hashes)."""
        return tuple(sorted((k, v if isinstance(v, str) else ",".join(v))
                            for k, v in self.entries.items()))


def _is_sha256(text: str) -> bool:
    return len(text) == 64 and all(c in "0123456789abcdef" for c in text)


def axis_label(v: np.ndarray) -> str:
    """'+X', '-Z', ... for the signed file axis nearest to the unit vector ``v``."""
    k = int(np.argmax(np.abs(v)))
    return ("+" if v[k] >= 0 else "-") + "XYZ"[k]


# ----------------------------------------------------------------------------- placement

def _axis_name(a) -> str:
    s = str(a).strip().upper()
    if len(s) == 1:
        s = "+" + s
    if s not in AXES:
        raise ValueError(f"{a!r} is not a signed axis (one of {', '.join(AXES)})")
    return s


def _apply(mesh: Mesh, orientation: Orientation, plane=None) -> Mesh:
    """Rotate, centre and scale (see the module docstring); fold it into file_to_norm.
    ``plane``: the mirror plane (normal, offset, a point on it) in the mesh's frame."""
    R = np.asarray(orientation.rotation, np.float64)
    v = _rotate(np.asarray(mesh.vertices, np.float64), R)
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre = (lo + hi) / 2.0
    diag = _diag(lo, hi)
    if not math.isfinite(diag) or diag <= 0.0:
        raise ValueError(f"{mesh.path}: mesh has zero extent")
    mirror_z = centre[2]
    if plane is not None:
        mirror_z = float(R[2] @ plane[2])
        shift = abs(mirror_z - centre[2])
        if (orientation.symmetry >= 0.5
                and MIRROR_MIN_SHIFT * diag < shift <= MIRROR_CENTRE_MAX * diag):
            # on a grid of 2^-20 diagonals, so a re-posed file gives the same bits
            grid = diag * 2.0 ** -20
            centre = np.array([centre[0], centre[1], round(mirror_z / grid) * grid])
    step = np.eye(4)
    step[:3, :3] = R / diag
    step[:3, 3] = -centre / diag
    orientation = replace(orientation, mirror_z=round(float((mirror_z - centre[2]) / diag), 6))
    return replace(mesh, vertices=(v - centre) / diag,
                   file_to_norm=step @ np.asarray(mesh.file_to_norm, np.float64),
                   orientation=orientation)


def _diag(lo: np.ndarray, hi: np.ndarray) -> float:
    """Bounding-box diagonal summed in a fixed order (sorted squares), so a permuted or
    mirrored box gives the same bits."""
    return float(np.sqrt(np.sort((hi - lo) ** 2).sum()))


def _rotate(v: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``v @ R.T``; an exact signed permutation is applied by indexing (bit-exact)."""
    if np.all(np.isin(R, (-1.0, 0.0, 1.0))) and np.all(np.abs(R).sum(axis=1) == 1.0):
        cols = np.argmax(np.abs(R), axis=1)
        out = v[:, cols]
        neg = R[np.arange(3), cols] < 0
        out[:, neg] = -out[:, neg]
        return out
    return v @ R.T


# ----------------------------------------------------------------------------- estimate

def _estimate(mesh: Mesh, disabled: Sequence[str] = (),
              cascade: bool = True) -> tuple[Orientation, tuple | None]:
    """(orientation, mirror plane (normal, offset, a point on it) or None), by a cascade:
    a cheap pass (budget FAST) is kept when it is clearly decided; otherwise the full
    estimate (budget FULL) decides. The cheap pass gives up as soon as it cannot be kept."""
    geometry, names = face_geometry(mesh), Names(mesh)       # shared by both passes
    fast = (_estimate_pass(mesh, disabled, FAST, geometry, names, give_up=True) if cascade
            else None)
    if fast is not None:
        return fast
    return _estimate_pass(mesh, disabled, FULL, geometry, names)


def _clearly_decided(o: Orientation) -> bool:
    """A cheap pass is kept when it raises no flag, its mirror plane is good (symmetry at
    least FAST_ACCEPT_SYMMETRY) and both confidences reach FAST_ACCEPT_UP / _FRONT."""
    return (not o.flags and o.symmetry >= FAST_ACCEPT_SYMMETRY
            and o.up_confidence >= FAST_ACCEPT_UP and o.front_confidence >= FAST_ACCEPT_FRONT)


def _estimate_pass(mesh: Mesh, disabled: Sequence[str], budget: Budget,
                   geometry: Geometry, mesh_names: Names,
                   give_up: bool = False) -> tuple[Orientation, tuple | None] | None:
    """One pass of the estimate with the given budget (see ``_estimate``). ``give_up``:
    None as soon as the result cannot be clearly decided (``_clearly_decided``): a flag
    is raised or a confidence or the symmetry falls under its margin; the steps are ordered
    so that the likeliest reasons (no wheels) come before the costly cues."""
    S = surface_samples(mesh, budget.samples, geometry=geometry, n_faces=budget.face_samples)
    p = S.points
    if not np.isfinite(p).all() or np.ptp(p, axis=0).max() <= 0.0:
        return None if give_up else (Orientation(rotation=np.eye(3), source="auto",
                                                 flags=("up_ambiguous", "front_ambiguous")),
                                     None)
    flags: list[str] = []
    base = ground_sheet(mesh, S, budget, geometry)
    if base is not None and give_up:
        return None
    if base is not None:
        S, base_up = base
        p = S.points
        flags.append("ground_plane")
    mu = p.mean(axis=0)
    evals, evecs = np.linalg.eigh(np.cov((p - mu).T))
    one = largest_vehicle(S, evecs[:, -1])
    if one is not None and give_up:
        return None
    if one is not None:                                    # vehicles apart: orient by one
        S = one
        p = S.points
        flags.append("multiple_vehicles")
        mu = p.mean(axis=0)
        evals, evecs = np.linalg.eigh(np.cov((p - mu).T))
    pca = evecs[:, ::-1]                                   # columns: major -> minor
    w, wd, sym = mirror_plane(p, S.normals, mu, pca, evals[::-1], budget)
    if sym < 0.35:
        flags.append("asymmetric")
    if give_up and sym < FAST_ACCEPT_SYMMETRY:
        return None
    ctx = Context(mesh, S, w, wd)
    wheels = find_wheels(ctx, budget)
    if wheels is None and give_up:
        return None
    if wheels is not None:
        ctx.set_length_axis(wheels.ground_dir)
    else:
        flags.append("no_wheels")
        ctx.level_from_hull()
    names = NameTable(mesh_names, S)
    up_cues = up_cue_scores(ctx, wheels, names)
    if base is not None:
        up_cues["ground_plane"] = float(np.clip(3.0 * (base_up @ ctx.b), -1, 1))
    up_cues = {k: v for k, v in up_cues.items() if k not in disabled}
    up_score = sum(UP_WEIGHTS[k] * v for k, v in up_cues.items())
    up_sign = 1.0 if up_score >= 0 else -1.0               # tie: +b (a fixed rule)
    up_conf = 1.0 - math.exp(-abs(up_score) / UP_SCALE)
    if give_up and round(up_conf, 4) < FAST_ACCEPT_UP:
        return None
    ctx.flip_up(up_sign < 0)
    snap_up = SNAP_DEG
    if wheels is not None:
        ctx.set_length_axis(wheels.settle(ctx))            # level on the tyres' contacts
    else:
        snap_up = SNAP_DEG_ALIGNED if _on_file_axis(ctx.w) else SNAP_DEG_COARSE
    front_cues = {k: v for k, v in front_cue_scores(ctx, wheels, names).items()
                  if k not in disabled}
    front_score = sum(FRONT_WEIGHTS[k] * v for k, v in front_cues.items())
    front_sign = 1.0 if front_score >= 0 else -1.0         # tie: +a (a fixed rule)
    front_conf = 1.0 - math.exp(-abs(front_score) / FRONT_SCALE)
    if give_up and round(front_conf, 4) < FAST_ACCEPT_FRONT:
        return None
    if up_conf < UNCERTAIN_BELOW:
        flags.append("up_ambiguous")
    if front_conf < UNCERTAIN_BELOW:
        flags.append("front_ambiguous")
    if "multiple_vehicles" not in flags and (several_vehicles(ctx)
                                             or overlapping_vehicles(ctx, names)):
        flags.append("multiple_vehicles")
    R = _snap(ctx.b, front_sign * ctx.a, snap_up)
    cues = {f"up.{k}": round(float(up_sign * v), 4) for k, v in up_cues.items()}
    cues.update({f"front.{k}": round(float(front_sign * v), 4) for k, v in front_cues.items()})
    o = Orientation(rotation=R, up_confidence=round(up_conf, 4),
                    front_confidence=round(front_conf, 4), source="auto", cues=cues,
                    flags=tuple(f for f in FLAGS if f in flags), symmetry=round(sym, 4))
    if give_up and not _clearly_decided(o):
        return None
    return o, (ctx.w, ctx.wd, mu - (mu @ ctx.w - ctx.wd) * ctx.w)


def _on_file_axis(n: np.ndarray) -> bool:
    """True when the unit vector ``n`` is within SNAP_DEG of a signed file axis."""
    return float(np.abs(n).max()) >= math.cos(math.radians(SNAP_DEG))


def _snap(up: np.ndarray, front: np.ndarray, snap_up_deg: float) -> np.ndarray:
    """Rotation rows (front, up, right = front x up). Up is snapped to a signed file axis
    within ``snap_up_deg``, then front (made perpendicular to up) within SNAP_DEG."""
    up = up / np.linalg.norm(up)
    k = int(np.argmax(np.abs(up)))
    up_axis = abs(up[k]) >= math.cos(math.radians(snap_up_deg))
    if up_axis:
        up = np.sign(up[k]) * np.eye(3)[k]
    front = front - (front @ up) * up
    front /= np.linalg.norm(front)
    j = int(np.argmax(np.abs(front)))
    if up_axis and j != k and abs(front[j]) >= math.cos(math.radians(SNAP_DEG)):
        R = np.stack([np.sign(front[j]) * np.eye(3)[j], up])
        return np.vstack([R, cross3(R[0], R[1])]) + 0.0  # exact signed permutation, no -0
    right = cross3(front, up)
    return np.stack([front, up, right / np.linalg.norm(right)]) + 0.0
