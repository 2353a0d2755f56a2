"""A vehicle's body as the cameras of the other vehicles see it: a central box, an arm to each rotor
and a disc per rotor, sized from the airframe's parameters, in the body (FLU) frame, segmentation class
``vehicle``.

Sizes: the arm length ``L`` is the distance of the first rotor's hub from the centre; the body box is
``0.6 L`` square and ``0.25 L`` tall, an arm is a ``0.1 L`` square bar from the centre to its hub, a
rotor disc has the set's ``rotor_radius`` (or ``0.45 L``) and sits ``0.06 L`` above its hub. The
collision sphere (``vehicle.collision_radius``) is what touches; the mesh is what is seen.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from droneulator.scenes.base import MeshPart, SemanticClass

#: the texture the vehicle meshes sample: two texels, the body's dark grey and the rotors' light grey
TEXTURE = "vehicle"
_BODY_UV, _ROTOR_UV = (0.25, 0.5), (0.75, 0.5)


def vehicle_texture() -> np.ndarray:
    """(2, 2, 4) RGBA: left column the body colour, right column the rotor discs'."""
    tex = np.empty((2, 2, 4), dtype=np.uint8)
    tex[:, 0] = (45, 45, 52, 255)
    tex[:, 1] = (205, 205, 210, 255)
    return tex


def _box(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Axis-aligned box: positions, normals, indices (flat shaded: 4 vertices per face)."""
    pos, nrm, idx = [], [], []
    for axis in range(3):
        for side in (0, 1):
            n = np.zeros(3)
            n[axis] = 1.0 if side else -1.0
            u, v = [a for a in range(3) if a != axis]
            quad = []
            for du, dv in ((0, 0), (1, 0), (1, 1), (0, 1)):
                p = np.array(lo, dtype=float)
                p[axis] = hi[axis] if side else lo[axis]
                p[u] = hi[u] if du else lo[u]
                p[v] = hi[v] if dv else lo[v]
                quad.append(p)
            base = len(pos)
            pos += quad
            nrm += [n] * 4
            tri = [(0, 1, 2), (0, 2, 3)]
            if np.dot(np.cross(quad[1] - quad[0], quad[2] - quad[0]), n) < 0:
                tri = [(0, 2, 1), (0, 3, 2)]
            idx += [(base + a, base + b, base + c) for a, b, c in tri]
    return np.array(pos), np.array(nrm), np.array(idx)


def _disc(centre: np.ndarray, radius: float, thickness: float, segments: int = 16) -> tuple[np.ndarray, ...]:
    """A flat cylinder about the body z axis: top and bottom faces and the rim."""
    pos, nrm, idx = [], [], []
    ang = 2 * math.pi * np.arange(segments) / segments
    ring = np.stack([np.cos(ang), np.sin(ang), np.zeros(segments)], axis=1)
    for z, sign in ((thickness / 2, 1.0), (-thickness / 2, -1.0)):
        base = len(pos)
        pos.append(centre + [0.0, 0.0, z])
        pos += list(centre + radius * ring + [0.0, 0.0, z])
        nrm += [np.array([0.0, 0.0, sign])] * (segments + 1)
        for k in range(segments):
            a, b = base + 1 + k, base + 1 + (k + 1) % segments
            idx.append((base, a, b) if sign > 0 else (base, b, a))
    base = len(pos)
    for k in range(segments):
        for z in (thickness / 2, -thickness / 2):
            pos.append(centre + radius * ring[k] + [0.0, 0.0, z])
            nrm.append(ring[k])
    for k in range(segments):
        a, b = base + 2 * k, base + 2 * ((k + 1) % segments)
        idx += [(a, a + 1, b + 1), (a, b + 1, b)]
    return np.array(pos), np.array(nrm), np.array(idx)


def vehicle_mesh(quad_params: dict[str, Any]) -> MeshPart:
    """The body of an airframe (module docstring), in its body frame (metres, FLU)."""
    hubs = np.array([quad_params["rotor_pos"][k] for k in quad_params["rotor_pos"]], dtype=float)
    arm = float(np.linalg.norm(hubs[0, :2]))
    rotor = float(quad_params.get("rotor_radius", 0.45 * arm))
    pieces: list[tuple[np.ndarray, np.ndarray, np.ndarray, tuple[float, float]]] = []
    half = np.array([0.3 * arm, 0.3 * arm, 0.125 * arm])
    pieces.append((*_box(-half, half), _BODY_UV))
    w = 0.05 * arm
    for hub in hubs:
        # the arm: a bar along the hub's direction, built along +x and turned
        length = float(np.linalg.norm(hub[:2]))
        p, n, i = _box(np.array([0.0, -w, -w]), np.array([length, w, w]))
        c, s = hub[0] / length, hub[1] / length
        Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        pieces.append((p @ Rz.T + [0.0, 0.0, hub[2]], n @ Rz.T, i, _BODY_UV))
        pieces.append((*_disc(hub + [0.0, 0.0, 0.06 * arm], rotor, 0.02 * arm), _ROTOR_UV))
    positions, normals, uvs, indices, start = [], [], [], [], 0
    for p, n, i, uv in pieces:
        positions.append(p)
        normals.append(n)
        uvs.append(np.tile(uv, (len(p), 1)))
        indices.append(i + start)
        start += len(p)
    pos = np.concatenate(positions).astype(np.float32)
    return MeshPart(
        name="vehicle",
        positions=pos,
        normals=np.concatenate(normals).astype(np.float32),
        uvs=np.concatenate(uvs).astype(np.float32),
        class_ids=np.full(len(pos), SemanticClass.VEHICLE, dtype=np.uint8),
        indices=np.concatenate(indices).astype(np.uint32),
        texture=TEXTURE,
    )
