"""Domain randomisation helpers take effect on every backend; spec validation names the field."""

from __future__ import annotations

import numpy as np
import pytest

import physint_backends as pb
from physint_backends import Body, Camera, Ground, Scene, SpecError
from physint_backends.randomize import TEXTURE_KINDS, orbit_cameras, procedural_texture, randomize_scene, texture_bank

BACKENDS = ["mujoco", "pybullet", "robosuite"]


def base_scene():
    cam = Camera("top", pos=(0.0, -0.6, 0.6), lookat=(0, 0, 0.0), width=48, height=48)
    return Scene(bodies=[Body.box("box", (0.1, 0.1, 0.1), pos=(0, 0, 0.05), rgba=(0.5, 0.5, 0.5, 1))], cameras=[cam])


@pytest.mark.parametrize("backend", BACKENDS)
def test_ground_texture_and_colours_change_the_image(backend):
    plain = base_scene()
    textured = randomize_scene(plain, np.random.default_rng(3), ground_textures=texture_bank(4, seed=1), lights=None)
    with pb.make(backend, plain) as sim:
        a = sim.render("top", segmentation=True)
        sim.set_rgba("box", (1, 0, 0, 1))
        red = sim.render("top").rgb
    with pb.make(backend, textured) as sim:
        b = sim.render("top").rgb
    ground = a.segmentation == -1
    assert np.abs(a.rgb[ground].astype(int) - b[ground].astype(int)).mean() > 5  # the floor changed
    box = a.segmentation == 0
    assert red[box][:, 0].mean() > red[box][:, 1].mean() + 40  # the box turned red


def test_textures_are_seeded_and_distinct():
    bank = texture_bank(25, seed=0)
    again = texture_bank(25, seed=0)
    assert all(np.array_equal(x.image, y.image) for x, y in zip(bank, again))
    assert len({x.image.tobytes() for x in bank}) == 25
    with pytest.raises(SpecError, match="allowed: checker"):
        procedural_texture("plaid", np.random.default_rng(0))
    assert set(TEXTURE_KINDS) >= {"checker", "noise"}


def test_orbit_cameras_look_at_the_centre():
    cams = orbit_cameras(16, radius=1.0, height=0.5, lookat=(0, 0, 0.2))
    assert len(cams) == 16 and len({c.name for c in cams}) == 16
    for c in cams:
        u, v = c.project(np.array([0.0, 0.0, 0.2]))[0]
        assert abs(u - 32) < 1e-6 and abs(v - 32) < 1e-6


@pytest.mark.parametrize("make, message", [
    (lambda: Body("b", []), "needs at least one geom"),
    (lambda: Body.box("b", (0.1, -0.1, 0.1)), "box size must be a positive number"),
    (lambda: Body.box("b", (0.1, 0.1)), "box size must have 3 value"),
    (lambda: Body.sphere("b", 0.1, mass=0), "mass must be a positive number"),
    (lambda: Body.sphere("b", 0.1, pos=(0, float("inf"), 0)), "pos must be finite"),
    (lambda: pb.Geom("cone", (1,)), "allowed: box, cylinder, sphere, mesh"),
    (lambda: Camera("c", fovy=200), "fovy must be in (0, 180)"),
    (lambda: Camera("c", width=0), "width must be an integer"),
    (lambda: Scene(bodies=[Body.sphere("a", 0.1), Body.sphere("a", 0.1)]), "repeated: a"),
    (lambda: Ground(rgba=(2, 0, 0)), "components in [0, 1]"),
    (lambda: pb.RobotSpec(name="ur5"), "allowed: panda"),
])
def test_bad_specs_name_the_field(make, message):
    with pytest.raises(SpecError) as err:
        make()
    assert message in str(err.value)
