"""Orientation cases and body variants: the 24 axis rotations, yaw and tilt poses, a trailer,
both ends alike, two vehicles side by side; the orientation truth they leave.
"""
from __future__ import annotations

import itertools
import math

import numpy as np

from .materials import make_material
from .shapes import Part, box, compact

MAX_TILT_DEG = 3.0


# --------------------------------------------------------------------------------------------
# orientation cases and body variants

def pose_rotation(pose: str, r: np.random.Generator) -> np.ndarray:
    """3x3 rotation of a pose case: 'axis' one of the 24 signed axis permutations with
    determinant +1 (uniformly), 'yaw' a uniform angle about +Y, 'tilt' a tilt of up to
    MAX_TILT_DEG about a random horizontal axis followed by a uniform yaw."""
    if pose == "axis":
        rots = axis_rotations()
        return rots[int(r.integers(len(rots)))]
    yaw = axis_angle(np.array([0.0, 1.0, 0.0]), r.uniform(0.0, 2 * math.pi))
    if pose == "yaw":
        return yaw
    phi = r.uniform(0.0, 2 * math.pi)
    tilt = axis_angle(np.array([math.cos(phi), 0.0, math.sin(phi)]),
                       math.radians(r.uniform(-MAX_TILT_DEG, MAX_TILT_DEG)))
    return yaw @ tilt


def axis_rotations() -> list[np.ndarray]:
    """The 24 rotations that permute the axes with signs (determinant +1), in a fixed order."""
    return [m for m in (np.eye(3)[list(p)] * np.array(sg)[:, None]
                        for p in itertools.permutations(range(3))
                        for sg in itertools.product((1.0, -1.0), repeat=3))
            if np.linalg.det(m) > 0]


def axis_angle(axis, angle: float) -> np.ndarray:
    """3x3 rotation by ``angle`` radians about ``axis`` (Rodrigues; ``axis`` need not be unit)."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def orientation_truth(bake: np.ndarray, pose: str | None, body: str | None) -> dict:
    """The car frame's up (+Y) and front (+X) as unit directions in the file frame."""
    up, front = bake[:3, 1], bake[:3, 0]
    return {"up": (up / np.linalg.norm(up)).tolist(),
            "front": (front / np.linalg.norm(front)).tolist(),
            "pose": pose or "as built", "body": body or "",
            "front_defined": body != "symmetric_ends"}


def body_variant(parts: list[Part], body: str, r: np.random.Generator) -> list[Part]:
    if body == "trailer":
        return parts + _trailer(parts, r)
    if body == "symmetric_ends":
        return _symmetric_ends(parts)
    gap = r.uniform(0.3, 1.0)                                  # two_vehicles
    allv = np.concatenate([q.vertices for q in parts])
    dz = float(np.ptp(allv[:, 2])) + gap
    return parts + [Part(f"{q.node}.2", q.part, q.material, q.vertices + [0.0, 0.0, dz],
                          q.faces) for q in parts]


def _trailer(parts: list[Part], r: np.random.Generator) -> list[Part]:
    """A box trailer on a drawbar behind the vehicle: as wide as the vehicle, 0.8-1.6 of
    its length, two axles at its back with the vehicle's rear wheels, red tail lamps."""
    allv = np.concatenate([q.vertices for q in parts])
    lo, hi = allv.min(axis=0), allv.max(axis=0)
    L, hw = hi[0] - lo[0], 0.5 * (hi[2] - lo[2]) * 0.95
    wheels = [q for q in parts if q.part in ("wheel", "rim") and q.node[-2:] in ("RL", "RR")]
    tyre = [q for q in wheels if q.part == "wheel"]
    R = 0.5 * float(np.ptp(tyre[0].vertices[:, 1])) if tyre else 0.4
    gap, Lt = r.uniform(1.0, 1.6), L * r.uniform(0.8, 1.6)
    x1 = lo[0] - gap
    x0 = x1 - Lt
    floor, top = 2.0 * R + 0.1, max(hi[1] * r.uniform(0.85, 1.1), 2.0 * R + 1.0)
    cell = 0.12
    out = [Part("trailer_box", "body", make_material("trailer_paint", "paint", (0.8, 0.8, 0.78)),
                 *box([x0, floor, -hw], [x1, top, hw], cell)),
           Part("trailer_drawbar", "other", make_material("trailer_drawbar", "plastic", (0, 0, 0)),
                 *box([x1, floor - 0.15, -0.06], [lo[0] + 0.05, floor - 0.03, 0.06], cell))]
    ax_back = x0 + 0.9 * R + 0.3
    for k, ax in enumerate((ax_back + 2.2 * R + 0.1, ax_back)):
        for q in wheels:
            cx = float(q.vertices[:, 0].mean())
            kind = "tyre" if q.part == "wheel" else "rim"
            nm = f"trailer_{kind}_{k + 1}{q.node[-1]}"
            out.append(Part(nm, q.part, make_material(nm, kind, (0, 0, 0)),
                             q.vertices + [ax - cx, 0.0, 0.0], q.faces.copy()))
    for side in (1.0, -1.0):
        nm = f"trailer_taillight_{'R' if side > 0 else 'L'}"
        z0, z1 = sorted((side * (hw - 0.35), side * (hw - 0.08)))
        out.append(Part(nm, "light", make_material(nm, "taillight", (0, 0, 0)),
                         *box([x0 - 0.04, floor + 0.1, z0], [x0 + 0.02, floor + 0.3, z1],
                               cell / 2)))
    return out


def _symmetric_ends(parts: list[Part]) -> list[Part]:
    """The front half of the vehicle and its mirror image across the middle of its length
    (faces whose centroid is in the front half, mirrored in x with their winding flipped):
    both ends alike, so nothing tells the front from the back."""
    allv = np.concatenate([q.vertices for q in parts])
    mid = 0.5 * (allv[:, 0].min() + allv[:, 0].max())
    out: list[Part] = []
    for q in parts:
        front = q.vertices[q.faces].mean(axis=1)[:, 0] >= mid
        if not front.any():
            continue
        v, f = compact(q.vertices, q.faces[front])
        out.append(Part(q.node, q.part, q.material, v, f))
        mv = v.copy()
        mv[:, 0] = 2.0 * mid - mv[:, 0]
        out.append(Part(f"{q.node}_2", q.part, q.material, mv, f[:, ::-1].copy()))
    return out


def symmetric_pairs(parts: list[Part]) -> list[tuple[str, str]]:
    """(left, right) material pairs of mirror-image nodes: node 'X_L' / 'X_FL' / 'X_L.003'
    pairs with the same name ending in R; kept when both materials are distinct and are used by
    that node only (merged materials drop out)."""
    users: dict[str, int] = {}
    for q in parts:
        users[q.material.name] = users.get(q.material.name, 0) + 1
    by_node = {q.node: q for q in parts}
    out = set()
    for q in parts:
        head, dot, tail = q.node.partition(".")
        if not head.endswith("L"):
            continue
        other = by_node.get(head[:-1] + "R" + dot + tail)
        if other is None:
            continue
        a, b = q.material.name, other.material.name
        if a != b and users[a] == 1 and users[b] == 1:
            out.add((a, b))
    return sorted(out)


def quat_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
