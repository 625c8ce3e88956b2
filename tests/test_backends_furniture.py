"""Static furniture (bins, pads, bowls) and camera poses behave the same on every backend."""

from __future__ import annotations

import math

import numpy as np
import pytest

import physint_backends as pb
from physint_backends import Body, Camera, Scene
from physint_backends.shapes import bin_, bowl, pad

BACKENDS = ["mujoco", "pybullet", "robosuite"]


@pytest.mark.parametrize("backend", BACKENDS)
def test_ball_rolling_in_a_bowl_stays_inside(backend):
    ball = Body.sphere("ball", 0.02, pos=(0.05, 0.0, 0.08), mass=0.05)
    scene = Scene(bodies=[bowl("bowl", radius=0.1, height=0.05), ball])
    with pb.make(backend, scene) as sim:
        sim.set_velocity("ball", (0.0, 0.4, 0.0))
        radii = []
        for _ in range(20):
            sim.advance(0.1)
            pos = sim.get_pose("ball")[0]
            radii.append(math.hypot(pos[0], pos[1]))
        assert max(radii) < 0.13 and pos[2] < 0.06  # rolled around inside, never escaped
        assert "bowl" in sim.contacts("ball")


@pytest.mark.parametrize("backend", BACKENDS)
def test_cube_dropped_into_a_bin_stays_in_it_and_a_pad_is_touched(backend):
    cube = Body.box("cube", (0.04, 0.04, 0.04), pos=(0.05, 0.02, 0.2), quat=(0.92, 0.2, 0.3, 0.1))
    on_pad = Body.box("block", (0.04, 0.04, 0.04), pos=(0.5, 0.0, 0.022))
    scene = Scene(bodies=[bin_("bin", inner=(0.2, 0.15), height=0.08), cube,
                          pad("pad", size=(0.1, 0.1), pos=(0.5, 0.0, 0.0)), on_pad])
    with pb.make(backend, scene) as sim:
        sim.advance(1.5)
        x, y, z = sim.get_pose("cube")[0]
        assert abs(x) < 0.1 and abs(y) < 0.075 and z < 0.05
        assert "bin" in sim.contacts("cube")
        assert sim.in_contact("block", "pad") and sim.get_pose("pad")[0][2] == pytest.approx(0.001)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_pad_that_does_not_collide_is_drawn_and_slid_over(backend):
    marking = pad("mark", size=(0.1, 0.1), pos=(0.15, 0.0, 0.0), thickness=0.003, collide=False)
    cube = Body.box("cube", (0.04, 0.04, 0.04), pos=(0.06, 0.0, 0.02), friction=0.3)
    scene = Scene(bodies=[marking, cube], cameras=[Camera("top", pos=(0.15, 0.0, 0.6), lookat=(0.15, 0.0, 0.0),
                                                          up=(1, 0, 0), width=32, height=32)])
    with pb.make(backend, scene) as sim:
        sim.advance(0.1)
        sim.set_velocity("cube", (1.2, 0.0, 0.0))
        sim.advance(0.6)
        x, _, z = sim.get_pose("cube")[0]
        assert x > 0.11 and z == pytest.approx(0.02, abs=0.003)  # slid onto the marking, not stopped at its edge
        assert sim.contacts("mark") == [] and "mark" not in sim.contacts("cube")
        seg = sim.render("top", segmentation=True).segmentation
        assert (seg == 0).sum() > 0  # the marking is drawn
    with pytest.raises(pb.SpecError, match="does not collide must be static"):
        Body.box("ghost", (0.1, 0.1, 0.1), collide=False)


def test_camera_from_pose_matches_lookat():
    ref = Camera("a", pos=(1.0, 0.0, 0.5), lookat=(0.0, 0.0, 0.5))
    rot = ref.rotation()
    # quaternion of that rotation matrix
    w = math.sqrt(1 + np.trace(rot)) / 2
    quat = (w, (rot[2, 1] - rot[1, 2]) / (4 * w), (rot[0, 2] - rot[2, 0]) / (4 * w), (rot[1, 0] - rot[0, 1]) / (4 * w))
    cam = Camera.from_pose("b", (1.0, 0.0, 0.5), quat)
    assert np.allclose(cam.rotation(), rot, atol=1e-9)
    points = np.array([[0.0, 0.1, 0.6], [0.2, -0.1, 0.4]])
    assert np.allclose(cam.project(points), ref.project(points))
