"""Domain randomisation on backend-neutral specs: colours, textures, lights, cameras.

Everything here edits or creates spec objects, so the same randomisation (same seed, same
scene) gives the same world on every backend. Live changes go through
``Simulation.set_rgba`` and ``Simulation.set_camera``.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .spec import Camera, Light, Scene, SpecError, Texture

# the six object colours of ShapeStacks (red, green, blue, yellow, cyan, magenta)
PALETTE = ((0.85, 0.15, 0.15, 1.0), (0.15, 0.7, 0.2, 1.0), (0.15, 0.3, 0.85, 1.0),
           (0.9, 0.85, 0.15, 1.0), (0.15, 0.8, 0.85, 1.0), (0.8, 0.2, 0.8, 1.0))
TEXTURE_KINDS = ("checker", "stripes", "noise", "gradient", "dots", "marble")


def random_rgba(rng: np.random.Generator, palette=PALETTE) -> tuple[float, float, float, float]:
    """A colour from ``palette`` (or any colour with ``palette=None``)."""
    if palette is None:
        return (*rng.uniform(0.05, 0.95, 3).tolist(), 1.0)  # type: ignore[return-value]
    return tuple(palette[rng.integers(len(palette))])  # type: ignore[return-value]


def _two_colours(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    a = rng.uniform(0, 255, 3)
    b = np.clip(a + rng.choice([-1, 1], 3) * rng.uniform(60, 160, 3), 0, 255)
    return a, b


def procedural_texture(kind: str, rng: np.random.Generator, size: int = 64) -> Texture:
    """A seeded texture image: checker, stripes, noise, gradient, dots or marble."""
    if kind not in TEXTURE_KINDS:
        raise SpecError(f"texture kind {kind!r} is not known; allowed: {', '.join(TEXTURE_KINDS)}")
    a, b = _two_colours(rng)
    y, x = np.mgrid[0:size, 0:size] / size
    if kind == "checker":
        n = rng.integers(2, 9)
        w = ((np.floor(x * n) + np.floor(y * n)) % 2).astype(float)
    elif kind == "stripes":
        n, angle = rng.integers(3, 12), rng.uniform(0, math.pi)
        w = (np.sin(2 * math.pi * n * (x * math.cos(angle) + y * math.sin(angle))) > 0).astype(float)
    elif kind == "noise":
        coarse = rng.uniform(0, 1, (8, 8))
        w = np.kron(coarse, np.ones((size // 8 + 1, size // 8 + 1)))[:size, :size]
    elif kind == "gradient":
        angle = rng.uniform(0, 2 * math.pi)
        w = (x * math.cos(angle) + y * math.sin(angle))
        w = (w - w.min()) / max(np.ptp(w), 1e-9)
    elif kind == "dots":
        n = rng.integers(3, 8)
        w = ((((x * n) % 1 - 0.5) ** 2 + ((y * n) % 1 - 0.5) ** 2) < 0.08).astype(float)
    else:  # marble: a few octaves of smooth noise bent through a sine
        w = np.zeros_like(x)
        for octave in range(1, 4):
            fx, fy, phase = rng.uniform(1, 4) * octave, rng.uniform(1, 4) * octave, rng.uniform(0, 6.3)
            w += np.sin(2 * math.pi * (fx * x + fy * y) + phase) / octave
        w = 0.5 + 0.5 * np.sin(3 * w)
    img = a[None, None, :] * (1 - w[..., None]) + b[None, None, :] * w[..., None]
    return Texture(np.clip(img, 0, 255).astype(np.uint8), name=f"{kind}-{rng.integers(1 << 30)}")


def texture_bank(n: int, seed: int, size: int = 64) -> list[Texture]:
    """``n`` distinct textures, cycling through the kinds (ShapeStacks uses 25 backgrounds)."""
    rng = np.random.default_rng(seed)
    return [procedural_texture(TEXTURE_KINDS[i % len(TEXTURE_KINDS)], rng, size) for i in range(n)]


def random_lights(rng: np.random.Generator, n: int = 1, radius: float = 3.0, lookat=(0.0, 0.0, 0.0),
                  min_elevation: float = 30.0) -> list[Light]:
    """Lights on a hemisphere around ``lookat``, at random azimuth and elevation, of random strength."""
    lights = []
    for _ in range(n):
        az = rng.uniform(0, 2 * math.pi)
        el = math.radians(rng.uniform(min_elevation, 85.0))
        pos = np.asarray(lookat) + radius * np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
        strength = rng.uniform(0.5, 0.9)
        lights.append(Light(pos=tuple(pos), lookat=tuple(lookat), diffuse=(strength,) * 3,
                            ambient=(rng.uniform(0.2, 0.4),) * 3, directional=True))
    return lights


def jitter_camera(camera: Camera, rng: np.random.Generator, pos_sigma: float = 0.02, lookat_sigma: float = 0.01,
                  fovy_sigma: float = 1.0) -> Camera:
    """A copy of ``camera`` with Gaussian noise on its position, aim and field of view."""
    return dataclasses.replace(
        camera, pos=tuple(np.asarray(camera.pos) + rng.normal(0, pos_sigma, 3)),
        lookat=tuple(np.asarray(camera.lookat) + rng.normal(0, lookat_sigma, 3)),
        fovy=float(np.clip(camera.fovy + rng.normal(0, fovy_sigma), 5, 170)))


def orbit_cameras(n: int, radius: float, height: float, lookat=(0.0, 0.0, 0.0), fovy: float = 45.0,
                  width: int = 64, height_px: int | None = None, start: float = 0.0, prefix: str = "cam") -> list[Camera]:
    """``n`` cameras evenly spaced on a circle around ``lookat`` (e.g. 16 around a stack)."""
    cams = []
    for i in range(n):
        az = start + 2 * math.pi * i / n
        pos = (lookat[0] + radius * math.cos(az), lookat[1] + radius * math.sin(az), height)
        cams.append(Camera(f"{prefix}{i}", pos=pos, lookat=tuple(lookat), fovy=fovy, width=width,
                           height=height_px or width))
    return cams


def randomize_scene(scene: Scene, rng: np.random.Generator, colors: bool = True, ground_textures: list[Texture] | None = None,
                    lights: int | None = 1, camera_jitter: float = 0.0, palette=PALETTE) -> Scene:
    """A randomised copy of ``scene``: body colours, ground texture, lights and camera jitter."""
    bodies = []
    for body in scene.bodies:
        if colors and not body.static:
            rgba = random_rgba(rng, palette)
            body = dataclasses.replace(body, geoms=[dataclasses.replace(g, rgba=rgba) for g in body.geoms])
        bodies.append(body)
    ground = scene.ground
    if ground is not None and ground_textures:
        ground = dataclasses.replace(ground, texture=ground_textures[rng.integers(len(ground_textures))])
    cams = [jitter_camera(c, rng, camera_jitter, camera_jitter / 2, camera_jitter * 20) if camera_jitter > 0 else c
            for c in scene.cameras]
    new_lights = random_lights(rng, lights) if lights else scene.lights
    return dataclasses.replace(scene, bodies=bodies, ground=ground, cameras=cams, lights=new_lights)
