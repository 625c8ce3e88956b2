"""The stability plugin's mechanics (thesis Section 3.3.2, Lemma 1 / Eq. 3.1) and ShapeStacks scenario
generation (Section 3.3.1, Table 3.1): analytic labels, and that the simulators agree with them."""

from __future__ import annotations

import json
import math
from collections import Counter

import numpy as np
import pytest

import physint_backends as pb
from physint_backends.randomize import PALETTE
from physint_cli.errors import BadInput
from physint_plugins.stability import physics, scenes
from physint_plugins.stability.physics import StackObject, analyse

CUBE = 0.06


def cube(x=0.0, y=0.0, edge=CUBE, yaw=0.0):
    return StackObject("box", (edge, edge, edge), "z", x=x, y=y, yaw=yaw)


def area(poly):
    return physics.polygon_area(poly)


def rotate(q, v):
    return scenes._rotate(np.asarray(q), np.asarray(v, dtype=float))


# -- convex polygons ----------------------------------------------------------------------------

def test_clip_polygon_known_squares():
    a = physics.rectangle((0, 0), (2, 2))  # [-1, 1]^2
    b = physics.rectangle((1, 1), (2, 2))  # [0, 2]^2
    inter = physics.clip_polygon(a, b)
    assert area(inter) == pytest.approx(1.0)
    assert sorted(map(tuple, np.round(inter, 9).tolist())) == [(0, 0), (0, 1), (1, 0), (1, 1)]
    # disjoint squares: empty; a square inside another: itself
    assert len(physics.clip_polygon(a, physics.rectangle((5, 0), (2, 2)))) == 0
    small = physics.rectangle((0.2, -0.1), (0.5, 0.5), yaw=0.3)
    assert area(physics.clip_polygon(small, a)) == pytest.approx(area(small))
    assert area(physics.clip_polygon(a, small)) == pytest.approx(area(small))
    # a square and the same square turned by 45 degrees: a regular octagon
    octagon = physics.clip_polygon(a, physics.rectangle((0, 0), (2, 2), yaw=math.pi / 4))
    assert len(octagon) == 8
    assert area(octagon) == pytest.approx(8 * (math.sqrt(2) - 1))
    assert area(octagon) > 0  # counter-clockwise


def test_clip_segment_and_signed_distance():
    a = physics.rectangle((0, 0), (2, 2))
    seg = physics.clip_segment(np.array([[-3.0, 0.5], [3.0, 0.5]]), a)
    assert np.allclose(seg, [[-1, 0.5], [1, 0.5]])
    assert len(physics.clip_segment(np.array([[-3.0, 2.0], [3.0, 2.0]]), a)) == 0
    assert physics.signed_distance((0, 0), a) == pytest.approx(1.0)
    assert physics.signed_distance((0.5, 0.2), a) == pytest.approx(0.5)
    assert physics.signed_distance((2, 0), a) == pytest.approx(-1.0)
    assert physics.signed_distance((2, 2), a) == pytest.approx(-math.sqrt(2))
    # curved contacts have no inside: a point or a segment
    assert physics.signed_distance((0, 0), np.array([[0.0, 0.0]])) == 0.0
    assert physics.signed_distance((0, 1), np.array([[-1.0, 0.0], [1.0, 0.0]])) == pytest.approx(-1.0)
    assert physics.signed_distance((0, 0), np.zeros((0, 2))) == -math.inf


def test_inradius():
    assert physics.inradius(physics.rectangle((0.3, 0.1), (0.1, 0.04), yaw=0.7)) == pytest.approx(0.02)
    assert physics.inradius(physics.disc((0, 0), 0.03)) == pytest.approx(0.03 * math.cos(math.pi / 32), rel=1e-3)
    square = physics.rectangle((0, 0), (2, 2))
    octagon = physics.clip_polygon(square, physics.rectangle((0, 0), (2, 2), yaw=math.pi / 4))
    assert physics.inradius(octagon) == pytest.approx(1.0, rel=0.01)
    lens = physics.clip_polygon(physics.disc((0, 0), 1.0), physics.disc((1.0, 0), 1.0))  # width 1, height sqrt(3)
    assert physics.inradius(lens) == pytest.approx(0.5, rel=0.01)


# -- objects ------------------------------------------------------------------------------------

@pytest.mark.parametrize("orientation, up, extents", [("z", 2, (0.02, 0.04)), ("x", 0, (0.08, 0.04)),
                                                       ("y", 1, (0.02, 0.08))])
def test_box_orientations(orientation, up, extents):
    size = (0.02, 0.04, 0.08)
    box = StackObject("box", size, orientation, yaw=0.0)
    assert box.height == pytest.approx(size[up])
    assert box.extents == pytest.approx(extents)
    # the quaternion turns the box's own `up` axis to world z, and its world bounding box matches
    axis = np.eye(3)[up]
    assert abs(rotate(box.quat, axis)[2]) == pytest.approx(1.0)
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * np.array(size) / 2
    world = np.stack([rotate(box.quat, c) for c in corners])
    assert np.ptp(world, axis=0) == pytest.approx([*extents, size[up]])


def test_cylinder_and_sphere_geometry():
    lying = StackObject("cylinder", (0.03, 0.1), "lying", x=0.1, yaw=math.pi / 2)
    assert lying.height == pytest.approx(0.06) and lying.curved_top and lying.top_face() is None
    assert np.allclose(rotate(lying.quat, (0, 0, 1)), (0, 1, 0), atol=1e-9)  # axis along the yaw direction
    assert np.allclose(lying.footprint(), [[0.1, -0.05], [0.1, 0.05]])  # a line contact
    upright = StackObject("cylinder", (0.03, 0.1), "upright")
    assert upright.height == pytest.approx(0.1) and not upright.curved_top and len(upright.top_face()) == 32
    ball = StackObject("sphere", (0.02,))
    assert ball.height == pytest.approx(0.04) and ball.footprint().shape == (1, 2)
    assert ball.mass == pytest.approx(1000 * 4 / 3 * math.pi * 0.02 ** 3)
    with pytest.raises(ValueError, match="orientation"):
        StackObject("cylinder", (0.03, 0.1), "sideways")
    stacked = physics.stack_up([cube(), upright, ball])
    assert [o.z for o in stacked] == pytest.approx([0.03, 0.11, 0.18])


# -- Lemma 1 on hand-made stacks --------------------------------------------------------------

def test_centred_stack_is_stable():
    label = analyse([cube(), cube(), cube()])
    assert label.stable and label.violation is None and label.interface is None and label.violating_object is None
    assert label.margins == pytest.approx([CUBE / 2] * 3)
    assert label.relative_margins == pytest.approx([1.0] * 3)


def test_top_com_out_is_vcom_at_the_right_interface():
    label = analyse([cube(), cube(), cube(x=0.04)])  # the top cube's centre 1 cm past the edge below
    assert not label.stable and label.violation == "VCOM"
    assert label.interface == 2 and label.violating_object == 1
    assert label.violations == [(2, "VCOM")]
    assert label.margins[2] == pytest.approx(-0.01)
    assert label.margins[:2] == pytest.approx([0.03 - 0.04 / 3, 0.03 - 0.02])


def test_sub_stack_com_decides_not_the_single_block():
    # each block rests on the one below, but the two upper ones together overhang the base
    label = analyse([cube(), cube(x=0.025), cube(x=0.05)])
    assert label.violations == [(1, "VCOM")] and label.violating_object == 0
    assert label.interfaces[1].com[0] == pytest.approx(0.0375)
    assert label.interfaces[2].status == "ok"


def test_block_on_sphere_is_vpsf():
    ball = StackObject("sphere", (0.03,))
    label = analyse([ball, cube(x=0.002)])
    assert not label.stable and label.violation == "VPSF"
    assert label.interface == 1 and label.violating_object == 0  # the curved support
    assert label.violations == [(1, "VPSF")]  # the sphere's own point contact is part of the same violation
    assert label.interfaces[0].status == "carried"
    assert label.margins[1] == -math.inf
    # perfectly centred: still a VPSF (it depends on the shapes, not on the positions)
    assert analyse([ball, cube()]).violation == "VPSF"


def test_block_on_lying_cylinder_is_vpsf():
    log = StackObject("cylinder", (0.03, 0.12), "lying", yaw=0.4)
    label = analyse([cube(), log, cube()])
    assert label.violations == [(2, "VPSF")] and label.violating_object == 1
    assert label.interfaces[1].status == "carried"


def test_sphere_on_top_is_stable_unless_off_the_face():
    ball = StackObject("sphere", (0.025,), x=0.01)
    label = analyse([cube(), ball])
    assert label.stable and label.margins[1] == pytest.approx(0.02)
    off = analyse([cube(), StackObject("sphere", (0.025,), x=0.035)])
    assert off.violations == [(1, "VCOM")] and off.violating_object == 0


def counterbalanced_stack():
    """Block 1 alone would tip off block 0 (its centre 1 cm past the edge); the heavier block 2,
    set back on its other side, holds it (thesis Fig. 3.2 B)."""
    return [cube(), cube(x=0.04), cube(x=0.015, edge=CUBE * 2 ** (1 / 3))]


def test_counterbalanced_stack_is_stable():
    label = analyse(counterbalanced_stack())
    assert label.stable
    one = label.interfaces[1]
    assert one.own_margin < 0 < one.margin and one.counterbalanced
    assert one.com[0] == pytest.approx((0.04 + 2 * 0.015) / 3)
    # without the counterweight it is a VCOM at the same interface
    assert analyse(counterbalanced_stack()[:2]).violations == [(1, "VCOM")]


@pytest.mark.parametrize("backend", ["mujoco", "pybullet"])
def test_simulator_agrees_with_hand_made_stacks(backend):
    for objects, stable, first in [(counterbalanced_stack(), True, None), (counterbalanced_stack()[:2], False, 1),
                                   ([cube(), cube(), cube(x=0.04)], False, 2)]:
        objects = physics.stack_up(objects)
        scenario = scenes.Scenario("cubes", "stable", objects, analyse(objects), 0)
        with pb.make(backend, scenes.to_scene(scenario, np.random.default_rng(0), cameras=0)) as sim:
            out = scenes.simulate(sim, scenario, 2.0)
        assert out.stable == stable == scenario.label.stable
        assert out.first_to_fall == first
        if stable:
            assert out.max_displacement < 0.005
        else:
            assert out.max_displacement > 0.02 and 0 < out.fall_time < 1.0


def test_stopping_at_the_first_fall_decides_the_same_outcome():
    """The dataset stops each simulation at the first fall: stability and first_to_fall stay those of the full run."""
    for objects in (counterbalanced_stack(), counterbalanced_stack()[:2], [cube(), cube(), cube(x=0.04)]):
        objects = physics.stack_up(objects)
        scenario = scenes.Scenario("cubes", "stable", objects, analyse(objects), 0)
        outcomes = []
        for early in (False, True):
            with pb.make("mujoco", scenes.to_scene(scenario, np.random.default_rng(0), cameras=0)) as sim:
                outcome = scenes.simulate(sim, scenario, 2.0, stop_early=early)
                outcomes.append((outcome, sim.time))
        (full, t_full), (early, t_early) = outcomes
        assert (early.stable, early.first_to_fall, early.fall_time) == (full.stable, full.first_to_fall, full.fall_time)
        assert t_early == pytest.approx(t_full) if full.stable else t_early < 0.5 * t_full


# -- scenario generation ------------------------------------------------------------------------

def check_scenario(sc: scenes.Scenario, kind: str, height: int):
    label, objs = sc.label, sc.objects
    assert sc.height == height and sc.kind == kind
    assert label.stable == (kind == "stable")
    assert label.violation == (None if kind == "stable" else kind)
    assert len(label.violations) == (0 if kind == "stable" else 1)
    assert scenes._max_load_ratio(objs) <= scenes.MAX_LOAD_RATIO
    others = [i for i in range(height) if i != label.interface]
    for i in others:
        f = label.interfaces[i]
        assert f.margin >= scenes.STABLE_MARGIN_ABS and f.relative_margin >= scenes.STABLE_MARGIN, (i, f)
    if kind == "VCOM":
        f = label.interfaces[label.interface]
        assert f.relative_margin <= -scenes.VCOM_MARGIN and f.margin <= -scenes.VCOM_MARGIN_ABS
        assert label.violating_object == label.interface - 1
    if kind == "VPSF":
        assert objs[label.violating_object].curved_top
    # spheres and lying cylinders: only on top, or as the curved support of the VPSF
    for i, o in enumerate(objs):
        if o.curved_top:
            assert i == height - 1 or (kind == "VPSF" and i == label.violating_object), (i, o)
    if sc.subset == "cubes":
        assert all(o.shape == "box" and len(set(o.size)) == 1 for o in objs)
    # the objects rest on each other, heights from the bottom up
    assert objs[0].z == pytest.approx(objs[0].height / 2)
    for lower, upper in zip(objs, objs[1:]):
        assert upper.z - upper.height / 2 == pytest.approx(lower.z + lower.height / 2)


@pytest.mark.parametrize("subset, kind", [("ccs", "stable"), ("ccs", "VCOM"), ("ccs", "VPSF"),
                                          ("cubes", "stable"), ("cubes", "VCOM")])
def test_sample_scenario_has_exactly_the_requested_label(subset, kind):
    rng = np.random.default_rng(7)
    for height in scenes.HEIGHTS:
        for _ in range(4):
            sc = scenes.sample_scenario(rng, subset, height, kind)
            assert sc.subset == subset
            check_scenario(sc, kind, height)
    # the seed rebuilds the scenario exactly, and so does its dict
    again = scenes.sample_scenario(sc.seed, subset, height, kind)
    assert [(o.shape, o.size, o.orientation, o.x, o.y, o.yaw) for o in again.objects] == \
           [(o.shape, o.size, o.orientation, o.x, o.y, o.yaw) for o in sc.objects]
    back = scenes.Scenario.from_dict(json.loads(json.dumps(sc.to_dict())))
    assert back.objects == sc.objects and back.label.violations == sc.label.violations


def test_scenarios_are_diverse():
    rng = np.random.default_rng(3)
    stable = [scenes.sample_scenario(rng, "ccs", h, "stable") for h in (3, 4, 5) for _ in range(20)]
    assert sum(any(f.counterbalanced for f in s.label.interfaces) for s in stable) >= 3  # Fig. 3.2 B
    shapes = Counter(o.shape for s in stable for o in s.objects)
    assert shapes["box"] > 0 and shapes["cylinder"] > 0
    offsets = [np.linalg.norm(u.xy - lo.xy) for s in stable for lo, u in zip(s.objects, s.objects[1:])]
    assert max(offsets) > 0.02 and min(offsets) < 0.005
    vpsf = [scenes.sample_scenario(rng, "ccs", 4, "VPSF") for _ in range(20)]
    assert {s.label.interface for s in vpsf} == {1, 2, 3}
    assert {s.objects[s.label.violating_object].shape for s in vpsf} == {"sphere", "cylinder"}
    vcom = [scenes.sample_scenario(rng, "cubes", 4, "VCOM") for _ in range(20)]
    assert {s.label.interface for s in vcom} == {1, 2, 3}


def test_cubes_cannot_violate_the_planar_surface_criterion():
    assert scenes.kinds_for("cubes") == ("stable", "VCOM")
    with pytest.raises(BadInput, match="cannot have a VPSF"):
        scenes.sample_scenario(0, "cubes", 3, "VPSF")
    assert scenes.sample_scenario(0, "all", 3, "VPSF").subset == "ccs"
    with pytest.raises(BadInput, match="subset"):
        scenes.sample_scenario(0, "pyramids", 3, "stable")
    with pytest.raises(BadInput, match="height"):
        scenes.sample_scenario(0, "ccs", 7, "stable")


def test_balanced_kinds_and_plan():
    rng = np.random.default_rng(0)
    kinds = Counter(scenes.balanced_kinds(100, rng, "ccs"))
    assert kinds == {"stable": 50, "VCOM": 25, "VPSF": 25}
    assert Counter(scenes.balanced_kinds(40, rng, "cubes")) == {"stable": 20, "VCOM": 20}
    odd = Counter(scenes.balanced_kinds(7, rng, "ccs"))
    assert sum(odd.values()) == 7 and abs(odd["stable"] - (7 - odd["stable"])) == 1
    assert abs(odd["VCOM"] - odd["VPSF"]) <= 1

    plan = scenes.plan_scenarios(2000, np.random.default_rng(1), "all")
    assert len(plan) == 2000 and len({p.seed for p in plan}) == 2000
    by_subset = Counter(p.subset for p in plan)
    assert by_subset["ccs"] / 2000 == pytest.approx(9124 / (9124 + 10310), abs=0.002)
    for subset in ("ccs", "cubes"):
        heights = Counter(p.height for p in plan if p.subset == subset)
        weights = np.array(scenes.HEIGHT_WEIGHTS[subset], dtype=float)
        expected = by_subset[subset] * weights / weights.sum()
        assert [heights[h] for h in scenes.HEIGHTS] == pytest.approx(expected, abs=1)
        for h in scenes.HEIGHTS:
            kinds = Counter(p.kind for p in plan if p.subset == subset and p.height == h)
            unstable = kinds["VCOM"] + kinds["VPSF"]
            assert abs(kinds["stable"] - unstable) <= 1
            if subset == "cubes":
                assert kinds["VPSF"] == 0
            else:
                assert abs(kinds["VCOM"] - kinds["VPSF"]) <= 1
    assert plan == scenes.plan_scenarios(2000, np.random.default_rng(1), "all")
    drawn = Counter(scenes.sample_height(rng, "ccs") for _ in range(3000))
    assert drawn[3] > drawn[2] > drawn[5] > drawn[6]  # most CCS towers are 3 high (Table 3.1)


# -- scenes ---------------------------------------------------------------------------------------

def test_to_scene_bodies_cameras_lights_textures():
    sc = scenes.sample_scenario(11, "ccs", 6, "stable")
    textures = scenes.default_textures()
    assert len(textures) == scenes.N_TEXTURES == 25 and len(scenes.lighting_conditions()) == 5
    scene = scenes.to_scene(sc, np.random.default_rng(0))
    assert [b.name for b in scene.bodies] == [f"obj{i}" for i in range(6)]
    for body, obj in zip(scene.bodies, sc.objects):
        assert body.pos == pytest.approx((obj.x, obj.y, obj.z)) and body.quat == pytest.approx(obj.quat)
        assert body.total_mass == pytest.approx(obj.mass)
        assert body.geoms[0].shape == obj.shape and body.geoms[0].size == pytest.approx(obj.size)
        assert body.geoms[0].rgba in PALETTE
    assert all(a.geoms[0].rgba != b.geoms[0].rgba for a, b in zip(scene.bodies, scene.bodies[1:]))
    assert len(scene.cameras) == 16 and {(c.width, c.height) for c in scene.cameras} == {(224, 224)}
    assert scene.lights in scenes.lighting_conditions()
    assert scene.ground.texture.image is not None
    assert any(np.array_equal(scene.ground.texture.image, t.image) for t in textures)
    # the same rng gives the same scene
    again = scenes.to_scene(sc, np.random.default_rng(0))
    assert [c.pos for c in again.cameras] == [c.pos for c in scene.cameras]


@pytest.mark.parametrize("height", [2, 6])
def test_cameras_see_the_whole_tower(height):
    sc = scenes.sample_scenario(5, "cubes", height, "stable")
    scene = scenes.to_scene(sc, randomise=False, resolution=224)
    unit = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) / 2
    corners = [o.com + rotate(o.quat, c * np.array(o.size)) for o in sc.objects for c in unit]
    for cam in scene.cameras:
        uv = cam.project(np.array(corners))
        assert uv.min() >= 0 and uv.max() <= 224, cam.name
    # randomised rings still look at the tower
    for seed in range(5):
        for cam in scenes.to_scene(sc, np.random.default_rng(seed)).cameras:
            u, v = cam.project(np.array([[sc.objects[0].x, sc.objects[0].y, sum(o.height for o in sc.objects) / 2]]))[0]
            assert 30 < u < 194 and 30 < v < 194


def test_rendered_segmentation_shows_every_object():
    sc = scenes.sample_scenario(2, "ccs", 4, "VPSF")
    scene = scenes.to_scene(sc, np.random.default_rng(0), cameras=2, resolution=64)
    with pb.make("mujoco", scene) as sim:
        frame = sim.render("cam0", segmentation=True)
    assert frame.rgb.shape == (64, 64, 3)
    assert set(range(4)) <= set(np.unique(frame.segmentation).tolist())


# -- the simulators agree with Lemma 1 -----------------------------------------------------------

AGREEMENT_SEED = 2024
N_PER_KIND = 20  # ccs: 20 stable, 20 VCOM, 20 VPSF; cubes: 10 stable, 10 VCOM


@pytest.fixture(scope="module")
def sampled():
    rng = np.random.default_rng(AGREEMENT_SEED)
    out = []
    for subset, kinds, n in (("ccs", scenes.KINDS, N_PER_KIND), ("cubes", ("stable", "VCOM"), N_PER_KIND // 2)):
        for kind in kinds:
            for j in range(n):
                out.append(scenes.sample_scenario(rng, subset, scenes.HEIGHTS[j % 5], kind))
    return out


@pytest.mark.parametrize("backend", ["mujoco", "pybullet"])
def test_simulator_agrees_with_lemma_1(backend, sampled):
    agree, first_ok = {}, {}
    for sc in sampled:
        key = (sc.subset, sc.kind)
        with pb.make(backend, scenes.to_scene(sc, np.random.default_rng(sc.seed), cameras=0)) as sim:
            out = scenes.simulate(sim, sc, 2.0, stop_early=not sc.label.stable)
        agree.setdefault(key, []).append(out.stable == sc.label.stable)
        if not sc.label.stable and not out.stable:  # what falls first is the object that rests badly, or above it
            first_ok.setdefault(key, []).append(out.first_to_fall >= sc.label.interface - (sc.kind == "VPSF"))
    rates = {f"{s}/{k}": round(float(np.mean(v)), 3) for (s, k), v in agree.items()}
    print(f"\n{backend} agreement with Lemma 1:", rates)
    for key, v in agree.items():
        assert np.mean(v) >= 0.9, (backend, key, rates)
    for key, v in first_ok.items():
        assert np.mean(v) >= 0.9, (backend, key)


def test_lemma1_side_view_is_lemma1_on_the_tower_as_seen():
    """Blocks as (centre, width, height): the load's centre of mass must lie over the contact below."""
    from physint_plugins.stability.physics import lemma1_side_view

    assert lemma1_side_view([(0, 10, 5), (4, 10, 5)])["stable"]
    assert not lemma1_side_view([(0, 10, 5), (6, 10, 5)])["stable"]  # the top's centre beyond the edge below
    label = lemma1_side_view([(0, 10, 5), (4, 10, 5), (8, 10, 5)])  # each on its support, the load of two not
    assert not label["stable"] and label["interface"] == 1 and label["violation"] == "VCOM"
    # the block overhangs on its own (centre 3 beyond the edge 2 below), a heavier one on top holds it
    assert not lemma1_side_view([(0, 4, 4), (3, 4, 2)])["stable"]
    assert lemma1_side_view([(0, 4, 4), (3, 4, 2), (1.2, 3, 6)])["stable"]
