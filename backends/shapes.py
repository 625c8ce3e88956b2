"""Static furniture as spec bodies: bins, target pads and bowls, the same on every backend.

Each is one static :class:`~physint_backends.spec.Body` made of convex geoms, so every backend
builds it from the spec alone (a bowl is concave: it is a floor plus a ring of tilted slabs).
"""

from __future__ import annotations

import math

from .spec import Body, Geom, SpecError


def _quat_about(axis: str, angle: float) -> tuple[float, float, float, float]:
    c, s = math.cos(angle / 2), math.sin(angle / 2)
    return {"x": (c, s, 0.0, 0.0), "y": (c, 0.0, s, 0.0), "z": (c, 0.0, 0.0, s)}[axis]


def _quat_mul(a, b) -> tuple[float, float, float, float]:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return (w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2)


def pad(name: str, size=(0.1, 0.1), pos=(0.0, 0.0, 0.0), rgba=(0.2, 0.3, 0.9, 1.0), thickness: float = 0.002,
        texture=None, collide: bool = True) -> Body:
    """A flat target pad lying on the surface at ``pos`` (its top ``thickness`` above pos z);
    ``collide=False`` makes it a marking only (objects slide over it as over the surface)."""
    x, y, z = pos
    return Body(name, [Geom("box", (size[0], size[1], thickness), rgba=rgba, texture=texture)],
                pos=(x, y, z + thickness / 2), static=True, collide=collide)


def bin_(name: str, inner=(0.2, 0.15), height: float = 0.08, wall: float = 0.01, pos=(0.0, 0.0, 0.0),
         rgba=(0.55, 0.55, 0.6, 1.0)) -> Body:
    """An open box: a floor and four walls around an ``inner`` (x, y) space, standing at ``pos``."""
    ix, iy = inner
    if ix <= 0 or iy <= 0 or height <= 0 or wall <= 0:
        raise SpecError(f"bin {name!r}: inner size, height and wall must be positive")
    ox, oy = ix + 2 * wall, iy + 2 * wall
    geoms = [Geom("box", (ox, oy, wall), pos=(0, 0, wall / 2), rgba=rgba)]
    for sx in (-1, 1):
        geoms.append(Geom("box", (wall, oy, height), pos=(sx * (ix + wall) / 2, 0, height / 2), rgba=rgba))
    for sy in (-1, 1):
        geoms.append(Geom("box", (ix, wall, height), pos=(0, sy * (iy + wall) / 2, height / 2), rgba=rgba))
    return Body(name, geoms, pos=tuple(pos), static=True)


def bowl(name: str, radius: float = 0.1, height: float = 0.05, wall: float = 0.01, segments: int = 16,
         flare: float = 30.0, pos=(0.0, 0.0, 0.0), rgba=(0.85, 0.85, 0.8, 1.0)) -> Body:
    """A bowl: a round floor of ``radius`` and a ring of ``segments`` slabs leaning out by ``flare`` degrees."""
    if radius <= 0 or height <= 0 or wall <= 0:
        raise SpecError(f"bowl {name!r}: radius, height and wall must be positive")
    if not 6 <= segments <= 64:
        raise SpecError(f"bowl {name!r}: segments must be in [6, 64], got {segments}")
    tilt = math.radians(flare)
    geoms = [Geom("cylinder", (radius + wall, wall), pos=(0, 0, wall / 2), rgba=rgba)]
    slant = height / math.cos(tilt)  # length of a slab along its leaning axis
    width = 2 * (radius + height * math.tan(tilt)) * math.tan(math.pi / segments) + wall
    for k in range(segments):
        az = 2 * math.pi * k / segments
        r = radius + wall / 2 + (height / 2) * math.tan(tilt)  # radius of the slab's centre
        # lean the slab outwards (about the tangent), then turn it to face the bowl's axis
        quat = _quat_mul(_quat_about("z", az), _quat_about("y", tilt))
        geoms.append(Geom("box", (wall, width, slant), pos=(r * math.cos(az), r * math.sin(az), wall + height / 2),
                          quat=quat, rgba=rgba))
    return Body(name, geoms, pos=tuple(pos), static=True)


__all__ = ["pad", "bin_", "bowl"]
