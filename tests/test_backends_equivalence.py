"""The same scene spec must behave the same on every backend (issue 3, 'Equivalence')."""

from __future__ import annotations

import math

import numpy as np
import pytest

import physint_backends as pb
from physint_backends import Body, Camera, Scene, SpecError

BACKENDS = ["mujoco", "pybullet", "robosuite"]
CUBE = 0.06  # edge of the stacked blocks, metres


def stack(offsets, shapes=None):
    """A single-stranded stack of cubes, each shifted in x by ``offsets[i]`` from the one below."""
    bodies, x = [], 0.0
    for i, dx in enumerate(offsets):
        x += dx
        bodies.append(Body.box(f"b{i}", (CUBE, CUBE, CUBE), pos=(x, 0.0, CUBE * (i + 0.5)), rgba=(0.8, 0.2 * i, 0.2, 1)))
    return bodies


def displacement(sim, name, start):
    pos, _ = sim.get_pose(name)
    return float(np.linalg.norm(pos - start))


@pytest.fixture(params=BACKENDS)
def backend(request):
    return request.param


def test_centred_stack_stands_for_two_seconds(backend):
    scene = Scene(bodies=stack([0.0, 0.0, 0.0]))
    with pb.make(backend, scene) as sim:
        start = {n: sim.get_pose(n)[0] for n in sim.body_names}
        sim.advance(2.0)
        assert sim.time == pytest.approx(2.0, abs=0.01)
        for name in sim.body_names:
            assert displacement(sim, name, start[name]) < 0.005, name


def test_stack_with_com_outside_support_falls(backend):
    # the top two blocks overhang by 0.7 and 0.7 of an edge: their COM lies outside block 0's top
    scene = Scene(bodies=stack([0.0, 0.7 * CUBE * 0.75, 0.7 * CUBE * 0.75]))
    with pb.make(backend, scene) as sim:
        top_start = sim.get_pose("b2")[0]
        sim.advance(2.0)
        assert sim.get_pose("b2")[0][2] < top_start[2] - CUBE / 2


@pytest.mark.parametrize("support", ["sphere", "lying_cylinder"])
def test_block_on_curved_surface_falls(backend, support):
    if support == "sphere":
        base = Body.sphere("base", 0.04, pos=(0, 0, 0.04))
        top_z = 0.08 + CUBE / 2
    else:
        base = Body.cylinder("base", 0.03, 0.12, pos=(0, 0, 0.03), quat=(math.cos(math.pi / 4), math.sin(math.pi / 4), 0, 0))
        top_z = 0.06 + CUBE / 2
    block = Body.box("block", (CUBE, CUBE, CUBE), pos=(0.004, 0.003, top_z))
    with pb.make(backend, Scene(bodies=[base, block])) as sim:
        sim.advance(2.0)
        assert sim.get_pose("block")[0][2] < top_z - CUBE / 3


def sphere_on_tilted_plank(hard_friction: bool, tilt_degrees: float = 0.05) -> Scene:
    """A 3 cm sphere resting on a fixed plank tilted by ``tilt_degrees`` about the y axis."""
    a = math.radians(tilt_degrees) / 2
    plank = Body.box("plank", (0.3, 0.1, 0.02), pos=(0, 0, 0.05), quat=(math.cos(a), 0.0, math.sin(a), 0.0), static=True)
    ball = Body.sphere("ball", 0.03, pos=(0, 0, 0.06 + 0.03 - 1e-4))
    return Scene(bodies=[plank, ball], hard_friction=hard_friction)


def test_hard_friction_keeps_a_sphere_on_a_slightly_tilted_plank(backend):
    # rolling friction (1e-4 m) holds a 3 cm sphere up to ~0.2 deg; soft contacts must not creep
    with pb.make(backend, sphere_on_tilted_plank(hard_friction=True)) as sim:
        sim.advance(0.1)
        start = sim.get_pose("ball")[0]
        sim.advance(2.0)
        assert displacement(sim, "ball", start) < 0.001


def test_without_hard_friction_mujoco_lets_the_sphere_creep():
    # the reason for Scene.hard_friction: MuJoCo's soft contacts alone let it roll ~1 cm in 2 s
    with pb.make("mujoco", sphere_on_tilted_plank(hard_friction=False)) as sim:
        sim.advance(0.1)
        start = sim.get_pose("ball")[0]
        sim.advance(2.0)
        assert displacement(sim, "ball", start) > 0.003


def test_dropped_sphere_time_to_ground(backend):
    h, r = 1.0, 0.02
    scene = Scene(bodies=[Body.sphere("ball", r, pos=(0, 0, h + r))], timestep=0.001)
    with pb.make(backend, scene) as sim:
        t_contact = None
        while sim.time < 1.0:
            sim.step(1)
            if sim.get_pose("ball")[0][2] <= r + 1e-3 or "ground" in sim.contacts("ball"):
                t_contact = sim.time
                break
        assert t_contact is not None
        assert t_contact == pytest.approx(math.sqrt(2 * h / 9.81), rel=0.02)


def test_segmentation_masks_agree_with_projection(backend):
    cam = Camera("front", pos=(0.7, 0.0, 0.35), lookat=(0.0, 0.0, 0.1), fovy=45, width=64, height=64)
    bodies = [Body.box("red", (0.08, 0.08, 0.08), pos=(0.0, -0.1, 0.04), rgba=(1, 0, 0, 1)),
              Body.sphere("blue", 0.04, pos=(0.0, 0.12, 0.04), rgba=(0, 0, 1, 1))]
    with pb.make(backend, Scene(bodies=bodies, cameras=[cam])) as sim:
        frame = sim.render("front", rgb=True, depth=True, segmentation=True)
    assert frame.rgb.shape == (64, 64, 3) and frame.rgb.dtype == np.uint8
    assert frame.depth.shape == (64, 64)
    seg = frame.segmentation
    for index, body in enumerate(bodies):
        mask = seg == index
        assert mask.sum() > 20, body.name
        v, u = np.nonzero(mask)
        expected = cam.project(np.asarray(body.pos))[0]
        assert abs(u.mean() - expected[0]) < 3 and abs(v.mean() - expected[1]) < 3, body.name
    # the depth of the red box's centre pixel is about its distance along the camera axis
    u, v = np.round(cam.project(np.asarray(bodies[0].pos))[0]).astype(int)
    axis = np.subtract(cam.lookat, cam.pos) / np.linalg.norm(np.subtract(cam.lookat, cam.pos))
    expected_depth = float(np.dot(np.subtract(bodies[0].pos, cam.pos), axis)) - 0.04
    assert frame.depth[v, u] == pytest.approx(expected_depth, abs=0.03)


def test_simulations_alive_side_by_side_each_render_their_own_scene(backend):
    """Several simulations in one process (a controller's episodes stepped side by side), rendered
    in turn as they move: every image shows its own simulation's scene."""
    cam = Camera("front", pos=(0.7, 0.0, 0.35), lookat=(0.0, 0.0, 0.1), fovy=45, width=48, height=48)

    def red_column(frame):  # where the red box is, across the image (pixels)
        red = (frame.rgb[..., 0] > 150) & (frame.rgb[..., 1] < 80) & (frame.rgb[..., 2] < 80)
        assert red.sum() > 10
        return np.nonzero(red)[1].mean()

    sims = [pb.make(backend, Scene(bodies=[Body.box("red", (0.08, 0.08, 0.08), pos=(0.0, y, 0.04), rgba=(1, 0, 0, 1))],
                                   cameras=[cam])) for y in (-0.15, 0.0, 0.15)]
    try:
        for step in range(3):
            for k, sim in enumerate(sims):
                sim.set_pose("red", (0.0, (k - 1) * 0.15 + 0.02 * step, 0.04))
                sim.step(1)
            columns = [red_column(sim.render("front")) for sim in sims]
            alone = [cam.project(np.asarray([0.0, (k - 1) * 0.15 + 0.02 * step, 0.04]))[0][0] for k in range(3)]
            assert np.allclose(columns, alone, atol=2.5), (step, columns, alone)
    finally:
        for sim in sims:
            sim.close()


def test_bad_input_leaves_state_unchanged(backend):
    scene = Scene(bodies=[Body.box("box", (0.1, 0.1, 0.1), pos=(0, 0, 0.05))], cameras=[Camera("cam")])
    with pb.make(backend, scene) as sim:
        before = sim.get_pose("box")
        with pytest.raises(SpecError, match="pos"):
            sim.set_pose("box", (0, float("nan"), 0))
        with pytest.raises(SpecError, match="no body named 'boks'"):
            sim.get_pose("boks")
        with pytest.raises(SpecError, match="no camera named"):
            sim.render("nope")
        after = sim.get_pose("box")
        assert np.allclose(before[0], after[0]) and np.allclose(before[1], after[1])


def test_freeze_holds_a_body_in_the_air(backend):
    scene = Scene(bodies=[Body.box("box", (0.05, 0.05, 0.05), pos=(0, 0, 0.5))])
    with pb.make(backend, scene) as sim:
        sim.freeze("box")
        sim.advance(0.5)
        assert sim.get_pose("box")[0][2] == pytest.approx(0.5, abs=1e-3)
        sim.unfreeze("box")
        sim.advance(0.5)
        assert sim.get_pose("box")[0][2] < 0.4


def test_set_pose_and_velocity_and_reset(backend):
    scene = Scene(bodies=[Body.sphere("ball", 0.03, pos=(0, 0, 0.03))])
    with pb.make(backend, scene) as sim:
        sim.set_pose("ball", (0.2, 0.1, 0.5))
        assert np.allclose(sim.get_pose("ball")[0], (0.2, 0.1, 0.5), atol=1e-6)
        sim.set_velocity("ball", (1.0, 0.0, 0.0))
        assert sim.get_velocity("ball")[0][0] == pytest.approx(1.0, abs=1e-6)
        sim.advance(0.1)
        assert sim.get_pose("ball")[0][0] > 0.25
        sim.reset()
        assert sim.time == 0.0
        assert np.allclose(sim.get_pose("ball")[0], (0, 0, 0.03), atol=1e-6)


# -- the Panda robot ------------------------------------------------------------------------

def robot_scene(with_cube=True):
    robot = pb.RobotSpec()
    table = robot.table_height
    bodies = [Body.box("cube", (0.04, 0.04, 0.04), pos=(0.0, 0.0, table + 0.02), mass=0.05, rgba=(1, 0, 0, 1))] if with_cube else []
    return Scene(bodies=bodies, robot=robot,
                 cameras=[Camera("front", pos=(0.9, 0.0, table + 0.5), lookat=(0.0, 0.0, table), width=64, height=64)])


def test_panda_moves_ten_centimetres_in_x(backend):
    with pb.make(backend, robot_scene(with_cube=False)) as sim:
        start = sim.robot.state()
        assert start.joints.shape == (7,) and start.ee_pos.shape == (3,)
        target = start.ee_pos + np.array([0.10, 0.0, 0.0])
        steps = int(1.0 * sim.robot.spec.control_hz)
        for _ in range(steps):
            delta = np.clip(target - sim.robot.state().ee_pos, -0.05, 0.05)
            state = sim.robot.act([*delta, 0])
        moved = state.ee_pos - start.ee_pos
        assert moved[0] == pytest.approx(0.10, abs=0.01)
        assert abs(moved[1]) < 0.01 and abs(moved[2]) < 0.01


def test_panda_grasps_and_lifts_a_cube(backend):
    with pb.make(backend, robot_scene()) as sim:
        table = sim.robot.spec.table_height
        cube = sim.get_pose("cube")[0]

        def go(target, gripper, steps):
            for _ in range(steps):
                delta = np.clip(np.asarray(target) - sim.robot.state().ee_pos, -0.05, 0.05)
                sim.robot.act([*delta, gripper])

        go(cube + [0, 0, 0.10], -1, 25)
        go(cube + [0, 0, 0.0], -1, 25)
        go(cube, 1, 15)
        assert sim.robot.touching("cube", "fingers")
        go(cube + [0, 0, 0.15], 0, 30)
        assert sim.get_pose("cube")[0][2] > table + 0.02 + 0.08
        assert sim.robot.state().gripper_opening < 0.05


def test_desired_goal_mode_follows_commanded_displacements(backend):
    """goal_mode="desired": the hand moves by the commanded displacements on every backend (within 10 %);
    "achieved" (the default) moves it by less: a proportional step towards hand + displacement."""
    moved = {}
    for mode in ("desired", "achieved"):
        with pb.make(backend, Scene(robot=pb.RobotSpec(goal_mode=mode))) as sim:
            start = sim.robot.state().ee_pos.copy()
            for _ in range(12):
                sim.robot.act([0.01, 0.0, -0.005, 0])
            for _ in range(6):
                state = sim.robot.act([0, 0, 0, 0])
            moved[mode] = state.ee_pos - start
    assert moved["desired"][0] == pytest.approx(0.12, rel=0.1) and moved["desired"][2] == pytest.approx(-0.06, rel=0.1)
    assert abs(moved["desired"][1]) < 0.005
    assert 0.0 < moved["achieved"][0] < 0.11
    with pytest.raises(SpecError, match="goal_mode 'velocity' is not known"):
        pb.RobotSpec(goal_mode="velocity")


@pytest.mark.parametrize("osc_backend", ["mujoco", "robosuite"])
def test_a_stiffer_operational_space_controller_follows_a_moving_goal_closer(osc_backend):
    """robot.osc_kp: at robosuite's default 150 the hand trails a goal moving 1.5 cm per step by
    about 3.6 steps; at 600 by under 2, and it still ends where it was sent."""
    lag, end = {}, {}
    for kp in (150.0, 600.0):
        with pb.make(osc_backend, Scene(robot=pb.RobotSpec(goal_mode="desired", osc_kp=kp))) as sim:
            start = sim.robot.state().ee_pos.copy()
            goal, gaps = start.copy(), []
            for _ in range(15):
                goal = goal + [0.012, 0.008, -0.004]
                gaps.append(np.linalg.norm(goal - sim.robot.act([0.012, 0.008, -0.004, 0]).ee_pos))
            for _ in range(10):
                state = sim.robot.act([0, 0, 0, 0])
            lag[kp], end[kp] = np.mean(gaps[8:]) / 0.0149, np.linalg.norm(goal - state.ee_pos)
    assert lag[150.0] > 3.0 and lag[600.0] < 2.0, lag
    assert max(end.values()) < 0.005, end
    with pytest.raises(SpecError, match="osc_kp must be a positive number"):
        pb.RobotSpec(osc_kp=0)


def test_bad_action_is_rejected_without_stepping(backend):
    with pb.make(backend, robot_scene(with_cube=False)) as sim:
        t = sim.time
        for bad in ([0, 0, 0], [0, 0, float("nan"), 0], [0, 0, 0, 0.5], "left"):
            with pytest.raises(SpecError, match="action"):
                sim.robot.act(bad)
        assert sim.time == t
        frame = sim.render("front", segmentation=True)
        assert (frame.segmentation == -2).sum() > 0  # the robot is visible and labelled -2


def test_background_and_table_look_the_same(backend):
    """Pixels showing nothing are the scene's background colour; the robot's table has its spec colour."""
    robot = pb.RobotSpec()
    cam = Camera("front", pos=(1.2, 0.0, robot.table_height + 0.3), lookat=(0.0, 0.0, robot.table_height + 0.3),
                 width=32, height=32)
    scene = Scene(robot=robot, cameras=[cam], background=(0.2, 0.4, 0.6))
    with pb.make(backend, scene) as sim:
        frame = sim.render("front", segmentation=True)
    sky = frame.rgb[0].astype(float)  # the top row looks above the horizon
    assert np.abs(sky - np.array([0.2, 0.4, 0.6]) * 255).max() < 8
    assert (frame.segmentation[-1] == -2).all()  # the bottom row shows the table: labelled robot


def test_six_block_stack_stands(backend):
    """Tall stacks are where solver settings show: six centred cubes must stand for 2 s."""
    scene = Scene(bodies=stack([0.0] * 6))
    with pb.make(backend, scene) as sim:
        sim.advance(2.0)
        top = sim.get_pose("b5")[0]
        assert abs(top[2] - CUBE * 5.5) < 0.005 and abs(top[0]) < 0.005


def test_ground_texture_tiles_at_the_same_scale(backend):
    """A checker texture repeated 20 times over a 4 m ground: squares of 0.1 m on every backend
    (PyBullet once drew them about 4x larger, so its renders looked unlike MuJoCo's)."""
    checker = np.zeros((64, 64, 3), np.uint8)
    checker[:32, :32] = checker[32:, 32:] = 255
    cam = Camera("top", pos=(0.1, 0.05, 1.0), lookat=(0.1, 0.05, 0.0), up=(0, 1, 0), fovy=60, width=128, height=128)
    scene = Scene(ground=pb.Ground(texture=pb.Texture(checker, repeat=(20.0, 20.0)), size=2.0), cameras=[cam])
    with pb.make(backend, scene) as sim:
        rgb = sim.render("top").rgb
    # the view is 2 tan(30 deg) = 1.15 m wide: 11.5 squares, so 11 or 12 black/white edges per row and column
    for line in (rgb[64, :, 0], rgb[:, 64, 0]):
        edges = int(np.abs(np.diff((line > 128).astype(int))).sum())
        assert 10 <= edges <= 13, edges


def test_a_cylinder_is_drawn_with_a_flat_cap_and_sharp_rims(backend):
    """Lit from straight above, an upright cylinder's cap is one flat colour seen from above, and
    a lying cylinder seen side-on is one colour along its axis. (PyBullet's own cylinder mesh
    shares normals between cap and side: the cap darkened towards its rim and a lying cylinder
    looked like a sphere, so predictors trained on one backend misread the other's cylinders.)"""
    light = pb.Light(pos=(0, 0, 3), lookat=(0, 0, 0), diffuse=(0.6, 0.6, 0.6), ambient=(0.3, 0.3, 0.3))
    lying = (math.cos(math.pi / 4), math.sin(math.pi / 4), 0, 0)  # axis along y
    bodies = [Body.cylinder("up", 0.05, 0.1, pos=(-0.2, 0, 0.05), rgba=(0.8, 0.2, 0.2, 1)),
              Body.cylinder("lying", 0.05, 0.2, pos=(0.2, 0, 0.05), quat=lying, rgba=(0.2, 0.8, 0.2, 1))]
    top = Camera("top", pos=(-0.2, 0, 1.0), lookat=(-0.2, 0, 0), up=(0, 1, 0), fovy=20, width=96, height=96)
    side = Camera("side", pos=(1.2, 0, 0.05), lookat=(0.2, 0, 0.05), up=(0, 0, 1), fovy=20, width=96, height=96)
    with pb.make(backend, Scene(bodies=bodies, lights=[light], cameras=[top, side])) as sim:
        cap = sim.render("top", segmentation=True)
        flank = sim.render("side", segmentation=True)
    up, lie = sim.body_names.index("up"), sim.body_names.index("lying")
    inner = np.zeros((96, 96), bool)
    inner[4:-4, 4:-4] = True  # away from the silhouette's anti-aliased edge
    pixels = cap.rgb[(cap.segmentation == up) & inner].astype(int)
    assert len(pixels) > 500 and np.ptp(pixels[:, 0]) <= 6, np.ptp(pixels[:, 0])
    rows = flank.rgb[..., 1].astype(int)
    mask = flank.segmentation == lie
    row = 40  # above the axis, facing the light
    cols = np.flatnonzero(mask[row])
    assert len(cols) > 20
    along = rows[row, cols[3:-3]]  # one height on the side, along the axis
    assert np.ptp(along) <= 6, np.ptp(along)
