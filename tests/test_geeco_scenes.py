"""GEECO's environments, scripted expert and dynamic images (thesis Chapter 6)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import physint_backends as pb
from physint_plugins.geeco import scenes as S
from physint_plugins.geeco.dynamic import dynamic_image, rank_weights
from physint_plugins.geeco.expert import Expert, on_target

H = 100  # demonstration length (25 Hz, 4 s)


# -- dynamic images (Eqs. 6.1, 6.2) ---------------------------------------------------------------

def test_rank_weights_follow_eq_6_2():
    assert np.allclose(rank_weights(2), [-0.5, 0.5])  # rho(I_t, I_T) is half the difference image
    for h in (2, 4, 10):
        w = rank_weights(h)
        assert abs(w.sum()) < 1e-9  # a static sequence has no dynamics
        assert w[0] < 0 < w[-1]  # the oldest frame subtracts, the newest adds (not monotonic in between)
    # H = 4 by hand: alpha_t = 2(5 - t) - 5 (Harm_4 - Harm_{t-1})
    harm = [0, 1, 1.5, 11 / 6, 25 / 12]
    assert np.allclose(rank_weights(4), [2 * (5 - t) - 5 * (harm[4] - harm[t - 1]) for t in range(1, 5)])


def test_dynamic_image_shows_where_things_moved_from_and_to():
    frames = torch.zeros(1, 4, 3, 16, 16)
    for t in range(4):  # a white square moving right by 3 px per frame
        frames[0, t, :, 4:8, 2 + 3 * t:6 + 3 * t] = 1.0
    rho = dynamic_image(frames)[0]
    assert rho.shape == (3, 16, 16)
    assert rho[:, 6, 12].mean() > 0 > rho[:, 6, 2].mean()  # bright where it ends, dark where it started
    assert abs(float(rho.mean())) < 1e-5 and abs(float(rho.std()) - 1) < 1e-3  # normalised across channels
    static = dynamic_image(frames[:, :1].repeat(1, 4, 1, 1, 1))
    assert float(static.abs().max()) < 1e-5  # nothing moves: an empty dynamic image, not amplified noise


# -- scenes -----------------------------------------------------------------------------------------

@pytest.mark.parametrize("scene", S.SCENES)
def test_start_states_keep_things_apart_and_the_object_away_from_its_target(scene):
    rng = np.random.default_rng(1)
    skill = "pickplace" if scene in ("nutoncone", "ballincup") else "push"
    for k in range(10):
        task = S.tasks(scene)[k % len(S.tasks(scene))]
        ep = S.sample_episode(scene, skill, task, rng)
        xy = ep.layout[:, :2]
        gaps = [np.linalg.norm(xy[i] - xy[j]) for i in range(len(xy)) for j in range(i)]
        assert not gaps or min(gaps) > 0.09
        assert np.linalg.norm(ep.xy(ep.object) - ep.xy(ep.target)) >= 0.16
        assert (scene == "clutter") == (len(ep.clutter) == S.CLUTTER_OBJECTS)
    assert len(S.tasks("goal2cube2")) == 4 and len(S.tasks("goal1cube1")) == 1


def test_goals_in_words():
    assert S.parse_goal("red cube onto green pad", "goal2cube2") == (0, 1)
    assert S.parse_goal("Yellow cube on the blue pad", "goal2cube2") == (1, 0)
    assert S.parse_goal("ball into cup", "ballincup") == (0, 0)
    with pytest.raises(ValueError, match="objects: red cube, yellow cube"):
        S.parse_goal("purple cube onto green pad", "goal2cube2")
    with pytest.raises(ValueError, match="targets: blue pad"):
        S.parse_goal("red cube onto green pad", "goal1cube1")


@pytest.mark.parametrize("scene", S.SCENES)
def test_every_scene_builds_and_shows_its_objects(scene):
    skill = "pickplace" if scene in ("nutoncone", "ballincup") else "push"
    ep = S.sample_episode(scene, skill, (0, 0), np.random.default_rng(2))
    with pb.make("mujoco", S.build_scene(ep, 64)) as sim:
        sim.advance(0.3)
        frame = sim.render("front", segmentation=True)
        for name in S.items(scene):  # every object and target is in view
            assert (frame.segmentation == sim.body_names.index(name)).sum() > 0, name
            assert np.isfinite(sim.get_pose(name)[0]).all()
        assert (frame.segmentation == -1).sum() > 0  # background, which BG:PRISMA replaces
        video = S.replace_background(frame.rgb, frame.segmentation, step=3)
        changed = (video != frame.rgb).any(axis=-1)
        assert changed.any() and not changed[frame.segmentation != -1].any()


def test_random_background_videos_are_the_same_for_a_seed_differ_between_seeds_and_some_move():
    videos = [S.random_backdrop(seed) for seed in range(20)]
    first = [v(0, 32) for v in videos]
    assert all(f.shape == (32, 32, 3) and f.dtype == np.uint8 for f in first)
    assert (S.random_backdrop(7)(5, 32) == videos[7](5, 32)).all()  # a seed replays its video
    assert len({f.tobytes() for f in first}) == 20  # every seed its own
    moving = [not (v(0, 32) == v(10, 32)).all() for v in videos]
    assert any(moving) and not all(moving)  # some drift, some stand still
    ep = S.sample_episode("goal2cube2", "push", (0, 0), np.random.default_rng(0))
    assert S.background_video(ep) is None  # the thesis's plain background
    ep.backdrop = 7
    assert (S.background_video(ep)(3, 16) == videos[7](3, 16)).all()
    assert S.background_video(S.sample_episode("prisma", "push", (0, 0), np.random.default_rng(0))) is S.prisma_frame


def test_the_rainbow_video_has_colorsyss_colours_loops_and_drifts():
    import colorsys

    hues = np.random.default_rng(0).random(500)
    hues[:6] = [0.0, 1 / 6, 0.5, 4 / 6, 5 / 6, np.nextafter(1.0, 0.0)]  # sector edges
    expected = np.array([colorsys.hsv_to_rgb(h, 0.9, 0.95) for h in hues])
    assert (S.hsv_to_rgb(hues, 0.9, 0.95) == expected).all()  # the same floats, not merely close
    frame = S.prisma_frame(3, 32)
    assert frame.shape == (32, 32, 3) and frame.dtype == np.uint8 and len(np.unique(frame.reshape(-1, 3), axis=0)) > 20
    assert (S.prisma_frame(3 + S.PRISMA_PERIOD, 32) == frame).all() and not (S.prisma_frame(4, 32) == frame).all()

# -- the scripted expert ---------------------------------------------------------------------------

def run_expert(sim, ep: S.Episode) -> tuple[bool, bool]:
    sim.reset(S.build_scene(ep, 32))
    expert = Expert(ep)
    for _ in range(H):
        sim.robot.act(expert.act(sim))
    return on_target(ep, sim), expert.done


def test_expert_picks_and_places_each_goal2cube2_task_within_a_demonstration():
    rng = np.random.default_rng(3)
    episodes = [S.sample_episode("goal2cube2", "pickplace", task, rng) for task in S.tasks("goal2cube2")]
    with pb.make("mujoco", S.build_scene(episodes[0], 32)) as sim:
        results = [run_expert(sim, ep) for ep in episodes]
    assert sum(ok and done for ok, done in results) >= 3, results  # placed, and the hand parked by step 100


@pytest.mark.parametrize("backend", ["mujoco", "robosuite"])
def test_expert_threads_the_nut_over_the_cone_and_drops_the_ball_into_the_cup(backend):
    # the nut is held by one 12 mm wall: the fingers must close fully (slowly on robosuite) and the
    # inner finger must fit in the hole (it used to land on the far wall: 2 nuts of 12 threaded)
    rng = np.random.default_rng(6)
    episodes = [S.sample_episode(scene, "pickplace", (0, 0), rng) for scene in ("nutoncone", "ballincup") for _ in range(2)]
    with pb.make(backend, S.build_scene(episodes[0], 32)) as sim:
        results = [run_expert(sim, ep) for ep in episodes]
    assert all(ok and done for ok, done in results), results


def test_expert_pushes_each_goal2cube2_task_onto_its_pad_within_a_demonstration():
    rng = np.random.default_rng(5)
    episodes = [S.sample_episode("goal2cube2", "push", task, rng) for task in S.tasks("goal2cube2") * 2]
    with pb.make("mujoco", S.build_scene(episodes[0], 32)) as sim:
        results = [run_expert(sim, ep) for ep in episodes]
    assert sum(ok and done for ok, done in results) >= 6, results  # pushed onto the pad, hand parked by step 100


def test_demonstration_noise_moves_the_hand_not_the_recorded_command():
    from physint_plugins.geeco.expert import SETTLING

    ep = S.sample_episode("goal2cube2", "push", (0, 0), np.random.default_rng(2))
    expert = Expert(ep)
    with pb.make("mujoco", S.build_scene(ep, 32)) as sim:
        command = expert.act(sim)
        goal = expert.goal.copy()
        noise = np.array([0.004, -0.002, 0.001])
        executed = expert.perturb(command, noise)
        assert np.allclose(executed[:3], command[:3] + noise) and executed[3] == command[3]
        assert np.allclose(expert.goal, goal + noise)  # the plan goes on from where the hand was sent
        for phase in SETTLING:  # holding still or leaving: the hand and the target image stay clean
            expert.phase = phase
            assert np.array_equal(expert.perturb(command, noise), command)


def test_a_cube_left_beside_its_pad_is_not_on_target():
    ep = S.sample_episode("goal2cube2", "pickplace", (0, 1), np.random.default_rng(4))
    with pb.make("mujoco", S.build_scene(ep, 32)) as sim:
        sim.advance(0.2)
        assert not on_target(ep, sim)
        pad = ep.xy(ep.target)
        sim.set_pose(ep.object, (pad[0], pad[1], S.TABLE_Z + 0.02 + 0.025 + 0.002))
        sim.advance(0.5)
        assert on_target(ep, sim)
        sim.set_pose(ep.object, (pad[0] + 0.09, pad[1], S.TABLE_Z + 0.026))
        sim.advance(0.5)
        assert not on_target(ep, sim)


# -- the controllers (Section 6.3, Appendices 6.A-6.C) ---------------------------------------------

def test_encoders_halve_their_maps_as_table_6a1_unless_told_to_keep_a_spatial_map():
    from physint_plugins.geeco.model import Encoder

    def side(size, min_side, stem_stride=1):
        encoder = Encoder(0.25, image_size=size, min_side=min_side, stem_stride=stem_stride)
        return encoder(torch.rand(1, 3, size, size)).shape[-1]

    assert side(256, 1) == 2 and side(64, 1) == 1  # the thesis's strides: 2x2 at 256 px, 1x1 at 64 px
    assert side(64, 4) == 4 and side(32, 4) == 4 and side(256, 4) == 4  # train.min_side
    assert side(128, 4, 2) == 4 and side(16, 4, 2) == 4 and side(512, 1, 2) == 2  # train.stem_stride


@pytest.mark.parametrize("width", [0.25, 0.375, 0.5, 0.6, 1.0])
def test_group_normalisation_takes_any_encoder_width(width):
    """Each convolution's channels fall into up to 8 groups of at least 4 that divide them (0.375 gives
    18 channels in the second layer, which 4 groups do not divide), and the groups normalise."""
    from physint_plugins.geeco.model import Encoder

    encoder = Encoder(width, norm=True, image_size=32, min_side=4)
    for conv, norm in zip(encoder.convs, encoder.norms):
        channels = conv.out_channels
        assert channels % norm.num_groups == 0 and 1 <= norm.num_groups <= 8
        assert norm.num_groups == min(8, channels // 4) or channels % min(8, channels // 4)
    out = encoder(torch.rand(2, 3, 32, 32))
    assert out.shape[:2] == (2, encoder.convs[-1].out_channels) and torch.isfinite(out).all()


def test_a_strided_stem_gives_a_128_px_frame_the_maps_of_a_64_px_one():
    """train.stem_stride=2: the first convolution halves a 128 px frame, so every later layer
    works on maps of the sizes a 64 px frame gets with Table 6.A.1's strides (and costs as much)."""
    from physint_plugins.geeco.model import Encoder

    def maps(size, stem_stride):
        shapes, x = [], torch.rand(1, 3, size, size)
        encoder = Encoder(0.25, image_size=size, stem_stride=stem_stride)
        for conv in encoder.convs:
            x = conv(x)
            shapes.append(tuple(x.shape[1:]))
        return shapes

    assert maps(128, 2) == maps(64, 1)
    assert maps(128, 1)[0] == (8, 128, 128)  # Table 6.A.1: the first layer keeps the frame's size


def test_the_paper_preset_builds_table_6a1s_controller_at_256_px_and_learns_with_adam_at_1e_4():
    """The paper preset (the thesis's configuration, meant for a GPU) runs here too: its GEECO-F
    (full width, 256 px frames, Table 6.A.1's strides down to 2x2 maps, flattened into the LSTM)
    answers a batch, and Adam at 1e-4 lowers Eq. 6.3's loss on it."""
    from physint_cli import config as configs
    from physint_plugins.geeco.config import PRESETS, GeecoConfig
    from physint_plugins.geeco.model import ENCODER_FILTERS, feature_shape, geeco_loss
    from physint_plugins.geeco.train import build_model

    cfg = configs.resolve(GeecoConfig, PRESETS, "paper", None, [])
    t = cfg.train
    assert (cfg.data.resolution, t.width, t.readout, t.lr, t.batch_size) == (256, 1.0, "flatten", 1e-4, 32)
    assert feature_shape(256, t.width, t.min_side, t.stem_stride) == (ENCODER_FILTERS[-1], 2)
    torch.manual_seed(0)
    model, _ = build_model("geeco-f", cfg.data.resolution, t, t.command)
    g = torch.Generator().manual_seed(1)
    frames, target = torch.rand(2, 4, 3, 256, 256, generator=g), torch.rand(2, 3, 256, 256, generator=g)
    joints = torch.randn(2, 4, 7, generator=g)
    batch = {"dee": torch.randn(2, 1, 3, generator=g), "grip": torch.tensor([[0], [2]]),
             "ee": torch.randn(2, 1, 3, generator=g), "obj": torch.randn(2, 1, 3, generator=g)}
    optimizer = torch.optim.Adam(model.parameters(), lr=t.lr)
    losses = []
    for _ in range(4):
        out = model(frames, joints, target)
        assert out["dee"].shape == (2, 1, 3) and out["grip"].shape == (2, 1, 3)
        loss, _ = geeco_loss(out, batch, t.aux_weight)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    assert all(np.isfinite(losses)) and losses[-1] < losses[0], losses


@pytest.mark.parametrize("variant", ["geeco-f", "geeco-d", "geeco-r", "e2evmc"])
@pytest.mark.parametrize("min_side,stem_stride", [(1, 1), (4, 1), (1, 2)])
def test_a_chunk_answers_each_window_as_the_window_alone_would(variant, min_side, stem_stride):
    from physint_plugins.geeco.model import Geeco

    torch.manual_seed(0)
    model = Geeco(variant, image_size=32, width=0.25, min_side=min_side, stem_stride=stem_stride).eval()
    frames, joints, target = torch.rand(2, 7, 3, 32, 32), torch.randn(2, 7, 7), torch.rand(2, 3, 32, 32)
    with torch.no_grad():
        chunk = model(frames, joints, target)
        assert chunk["dee"].shape == (2, 4, 3) and chunk["grip"].shape == (2, 4, 3)
        for w in range(4):
            alone = model(frames[:, w:w + 4], joints[:, w:w + 4], target)
            for head in ("dee", "grip", "ee", "obj"):
                assert torch.allclose(chunk[head][:, w], alone[head][:, 0], atol=1e-5), (head, w)
    with pytest.raises(ValueError, match="at least 4 frames"):
        model(frames[:, :3], joints[:, :3], target)


def test_goal_conditioned_variants_read_the_task_from_the_target_image():
    """Same observations, two targets (a square on the left or the right): the conditioned
    controllers learn to move towards it (Eq. 6.3); the unconditioned E2EVMC cannot."""
    from physint_plugins.geeco.model import Geeco, geeco_loss

    def batch(n):
        side = torch.randint(0, 2, (n,))
        target = torch.zeros(n, 3, 32, 32)
        for i, s in enumerate(side):
            target[i, :, 12:20, (2 if s == 0 else 22):(10 if s == 0 else 30)] = 1.0
        frames = torch.zeros(n, 4, 3, 32, 32) + 0.3
        dee = torch.zeros(n, 1, 3)
        dee[:, 0, 1] = side.float() * 2 - 1  # +y towards a square on the right
        return frames, torch.zeros(n, 4, 7), target, {"dee": dee, "grip": side[:, None], "ee": torch.zeros(n, 1, 3),
                                                      "obj": torch.zeros(n, 1, 3)}

    errors = {}
    for variant in ("geeco-d", "e2evmc"):
        torch.manual_seed(0)
        model = Geeco(variant, image_size=32, width=0.25)
        opt = torch.optim.Adam(model.parameters(), lr=2e-3)
        for _ in range(150):
            frames, joints, target, truth = batch(16)
            loss, _ = geeco_loss(model(frames, joints, target), truth)
            opt.zero_grad()
            loss.backward()
            opt.step()
        frames, joints, target, truth = batch(64)
        with torch.no_grad():
            out = model(frames, joints, target)
        errors[variant] = float(((out["dee"] - truth["dee"]) ** 2).mean())
    # answering the mean (0) scores 1/3: only the y component (+-1) of the three is non-zero
    assert errors["geeco-d"] < 0.05 and errors["e2evmc"] > 0.25, errors


@pytest.mark.parametrize("variant,head", [("geeco-f", {}), ("geeco-d", {}), ("geeco-r", {}), ("e2evmc", {}),
                                          ("geeco-f", {"dee_bins": 21}), ("geeco-d", {"dee_bins": 21}),
                                          ("geeco-f", {"dee_modes": 8}), ("geeco-d", {"dee_modes": 8}),
                                          ("geeco-f", {"readout": "keypoints", "min_side": 4}),
                                          ("geeco-r", {"readout": "keypoints", "min_side": 4})])
def test_the_controller_step_by_step_answers_as_the_whole_window_would(variant, head):
    """Control keeps per-frame states for D, R and E2EVMC; its answers match the network on the
    padded window (the buffer starts as K copies of the first frame)."""
    from physint_plugins.geeco.control import DEE_SCALE, Policy
    from physint_plugins.geeco.model import Geeco

    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    model = Geeco(variant, image_size=32, width=0.25, **head)
    if model.dee_modes:
        model.set_modes(rng.uniform(-1, 1, (200, 3)))
    policy = Policy(model)
    target = rng.integers(0, 255, (32, 32, 3), dtype=np.uint8)
    policy.reset(target)
    frames = rng.integers(0, 255, (6, 32, 32, 3), dtype=np.uint8)
    joints = rng.normal(size=(6, 7)).astype(np.float32)
    padded = np.concatenate([frames[:1].repeat(3, 0), frames])
    padded_joints = np.concatenate([joints[:1].repeat(3, 0), joints])
    with torch.no_grad():
        whole = model(torch.from_numpy(padded).float().div(255).movedim(-1, -3)[None], torch.from_numpy(padded_joints)[None],
                      torch.from_numpy(target).float().div(255).movedim(-1, -3)[None])
    for t in range(6):
        action = policy.act(frames[t], joints[t])
        assert np.allclose(action[:3], whole["dee"][0, t].numpy() * DEE_SCALE, atol=1e-5)
        assert action[3] == (-1, 0, 1)[int(whole["grip"][0, t].argmax())]


@pytest.mark.parametrize("variant,head", [("geeco-f", {"norm": True}), ("geeco-d", {}), ("geeco-r", {}), ("e2evmc", {}),
                                          ("geeco-f", {"command": "positions"})])
def test_controllers_acting_together_answer_as_each_alone(variant, head):
    """Training's closed loops step episodes side by side, their frames through the network as one
    batch (``act_together``): each episode gets the action its policy would give on its own."""
    from physint_plugins.geeco.control import Policy, act_together
    from physint_plugins.geeco.model import Geeco

    torch.manual_seed(0)
    rng = np.random.default_rng(1)
    model = Geeco(variant, image_size=32, width=0.25, **head)
    with torch.no_grad():  # answers far apart for different frames (an untrained network's barely differ)
        for p in [*model.heads.parameters(), *getattr(model, "command_head", model.heads).parameters()]:
            p.normal_(0, 1)
    together, alone = [Policy(model) for _ in range(3)], [Policy(model) for _ in range(3)]
    for a, b in zip(together, alone):
        target = rng.integers(0, 255, (32, 32, 3), dtype=np.uint8)
        a.reset(target)
        b.reset(target)
    for t in range(6):
        if t == 3:  # one episode ends and the next begins while the others go on
            target = rng.integers(0, 255, (32, 32, 3), dtype=np.uint8)
            together[0].reset(target)
            alone[0].reset(target)
        observations = [(rng.integers(0, 255, (32, 32, 3), dtype=np.uint8), rng.normal(size=7).astype(np.float32),
                         rng.uniform(-0.2, 0.2, 3) + [0, 0, 0.9], None) for _ in range(3)]
        actions = act_together(together, observations)
        expected = [policy.act(*obs) for policy, obs in zip(alone, observations)]
        assert np.allclose(actions, expected, rtol=1e-4, atol=1e-5), t
        assert all(np.allclose(a.last["obj"], b.last["obj"], atol=1e-5) for a, b in zip(together, alone))
    assert len({tuple(np.round(a[:3], 4)) for a in actions}) == 3  # three episodes, three answers
    if model.conditioned:  # an episode without its target image is refused, whoever it acts with
        together[1].reset(None)
        with pytest.raises(ValueError, match="needs a target image"):
            act_together(together, observations)


@pytest.mark.parametrize("variant", ["geeco-f", "geeco-d", "geeco-r"])
def test_a_policy_reset_for_another_target_answers_as_a_new_one(variant):
    """A policy keeps what it knows of an episode's target image (GEECO-R its encoding) only for
    that episode: reset with another target, it answers as a new policy would."""
    from physint_plugins.geeco.control import Policy
    from physint_plugins.geeco.model import Geeco

    torch.manual_seed(0)
    rng = np.random.default_rng(2)
    model = Geeco(variant, image_size=32, width=0.25, norm=True)  # normalised: an untrained encoder's codes differ
    with torch.no_grad():  # answers far apart for different inputs (an untrained network's barely differ)
        for p in model.heads.parameters():
            p.normal_(0, 1)
    first, second = (rng.integers(0, 255, (32, 32, 3), dtype=np.uint8) for _ in range(2))
    frame, joints = rng.integers(0, 255, (32, 32, 3), dtype=np.uint8), rng.normal(size=7).astype(np.float32)
    reused, fresh = Policy(model), Policy(model)
    reused.reset(first)
    before = reused.act(frame, joints)
    reused.reset(second)
    fresh.reset(second)
    after = reused.act(frame, joints)
    assert np.allclose(after, fresh.act(frame, joints), atol=1e-6)
    assert not np.allclose(after[:3], before[:3], atol=1e-4)  # the target image matters to the answer


def test_a_positions_controller_commands_from_the_hand_it_feels_and_the_objects_it_sees():
    """With ``command="positions"`` the command is the command head's answer for the measured hand
    and the network's object estimates over the last K steps (padded with the first, as the frames
    are) and its estimate of the target: not the network's own u_dEE head."""
    from physint_plugins.geeco.control import DEE_SCALE, Policy, scale_positions
    from physint_plugins.geeco.model import Geeco

    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    model = Geeco("geeco-f", image_size=32, width=0.25, command="positions")
    policy = Policy(model)
    policy.reset(rng.integers(0, 255, (32, 32, 3), dtype=np.uint8))
    hands, objects, own = [], [], []
    for t in range(6):
        hand = rng.uniform(-0.2, 0.2, 3) + [0, 0, 0.9]
        action = policy.act(rng.integers(0, 255, (32, 32, 3), dtype=np.uint8), rng.normal(size=7).astype(np.float32),
                            hand)
        hands.append(scale_positions(hand))
        objects.append(scale_positions(policy.last["obj"]))
        padded = [np.array(([x[0]] * 3 + x)[-4:])[None] for x in (hands, objects)]
        with torch.no_grad():
            expected = model.command_from_positions(*map(torch.from_numpy, padded),
                                                    torch.from_numpy(policy.last["goal"][None] / 0.1).float())
        assert np.allclose(action[:3], expected[0].numpy() * DEE_SCALE, atol=1e-4)
        own.append(action[:3])
    assert len({tuple(np.round(a, 6)) for a in own}) == 6  # it moves with what it sees and feels
    # its network sees the frames only: its estimates cannot lean on where the joints put the hand
    frames, target = torch.rand(1, 5, 3, 32, 32), torch.rand(1, 3, 32, 32)
    with torch.no_grad():
        a, b = (model(frames, torch.randn(1, 5, 7), target) for _ in range(2))
    assert all(torch.equal(a[k], b[k]) for k in ("obj", "goal", "ee", "grip"))
    # eval.positions=true: the true object and target positions replace the network's estimates
    obj, goal = np.array([0.05, -0.1, 0.85]), np.array([-0.08, 0.12])
    action = policy.act(rng.integers(0, 255, (32, 32, 3), dtype=np.uint8), rng.normal(size=7).astype(np.float32),
                        hand, (obj, goal))
    padded = [np.array((x + [scale_positions(v)])[-4:])[None] for x, v in ((hands, hand), (objects, obj))]
    with torch.no_grad():
        expected = model.command_from_positions(*map(torch.from_numpy, padded), torch.from_numpy(goal[None] / 0.1).float())
    assert np.allclose(action[:3], expected[0].numpy() * DEE_SCALE, atol=1e-4)


def test_binned_commands_decode_their_two_hot_targets_and_pick_one_of_two_modes():
    from physint_plugins.geeco.model import decode_bins, two_hot

    values = torch.tensor([-1.0, -0.33, 0.0, 0.52, 0.97, 1.0])
    probs = two_hot(values, 21)
    assert torch.allclose(probs.sum(-1), torch.ones(6)) and int((probs > 0).sum(-1).max()) <= 2
    assert torch.allclose(decode_bins(torch.log(probs + 1e-9)), values, atol=1e-4)
    logits = torch.full((21,), -10.0)
    logits[5], logits[15] = 2.0, 2.1  # two commands, -0.5 and +0.5: the stronger one, not their mean
    assert abs(float(decode_bins(logits)) - 0.5) < 1e-3


def answer_after_training_on(commands: torch.Tensor, **head) -> torch.Tensor:
    """Train E2EVMC (loss Eq. 6.3) on one observation whose demonstrated u_dEE is drawn evenly
    from ``commands`` (n, 3); its answer (3,)."""
    from physint_plugins.geeco.model import Geeco, geeco_loss

    torch.manual_seed(0)
    generator = torch.Generator().manual_seed(1)
    model = Geeco("e2evmc", image_size=32, width=0.25, **head)
    if model.dee_modes:
        model.set_modes(commands)
    opt = torch.optim.Adam(model.parameters(), lr=2e-3)
    frames, joints = torch.full((64, 4, 3, 32, 32), 0.3), torch.zeros(64, 4, 7)
    for _ in range(100):
        dee = commands[torch.randint(0, len(commands), (64,), generator=generator)][:, None]
        batch = {"dee": dee, "grip": torch.zeros(64, 1, dtype=torch.long), "ee": torch.zeros(64, 1, 3),
                 "obj": torch.zeros(64, 1, 3)}
        loss, _ = geeco_loss(model(frames, joints), batch, centres=getattr(model, "dee_centres", None))
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        return model(frames[:1], joints[:1])["dee"][0, 0]


def test_where_the_demonstrations_disagree_binned_commands_follow_one_of_them_and_regression_stalls():
    """One observation, two demonstrated commands (+-1 on y, as pushing on or going round): the
    regressed command is their average, about 0; the binned one and the mode one are one of them."""
    two_ways = torch.tensor([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
    answers = {name: float(answer_after_training_on(two_ways, **head)[1])
               for name, head in (("regressed", {}), ("bins", {"dee_bins": 21}), ("modes", {"dee_modes": 4}))}
    # seen over 4 seeds: regressed |0.03-0.19|, binned 1.0
    assert abs(answers["regressed"]) < 0.4 and abs(answers["bins"]) > 0.8 and abs(answers["modes"]) > 0.8, answers


def test_where_the_demonstrations_go_three_ways_each_binned_axis_answers_zero_and_modes_pick_one_way():
    """Demonstrated commands +x, +y and +z, a third each: on every axis alone 0 is the most common
    value, so per-axis bins answer (0, 0, 0), a stall; classifying the whole command answers one of
    the three."""
    three_ways = torch.eye(3)
    binned = answer_after_training_on(three_ways, dee_bins=21)
    modes = answer_after_training_on(three_ways, dee_modes=3)
    assert float(binned.norm()) < 0.3, binned
    assert float((modes[None] - three_ways).norm(dim=1).min()) < 0.2, modes


def test_command_modes_are_kmeans_centres_of_the_commands():
    from physint_plugins.geeco.model import command_modes, nearest_mode

    rng = np.random.default_rng(0)
    corners = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, 0.5], [-0.5, 0.5, 0]])
    commands = corners[rng.integers(0, 4, 2000)] + rng.normal(0, 0.02, (2000, 3))
    centres = command_modes(commands, 4, seed=3)
    assert np.abs(np.sort(centres, axis=0) - np.sort(corners, axis=0)).max() < 0.02
    assert np.array_equal(centres, command_modes(commands, 4, seed=3))  # seeded
    few = command_modes(corners[:2], 5)  # fewer distinct commands than modes: each is a centre
    assert {tuple(c) for c in few} == {tuple(c) for c in corners[:2].astype(np.float32)}
    assert nearest_mode(torch.tensor([[0.9, 0.1, 0.0]]), torch.from_numpy(centres)).item() == \
        int(np.argmin(np.linalg.norm(centres - corners[0], axis=1)))


def test_spatial_softmax_reads_where_each_channel_peaks():
    from physint_plugins.geeco.model import spatial_softmax

    maps = torch.zeros(1, 2, 5, 9)
    maps[0, 0, 0, 8] = 50.0  # top right
    maps[0, 1, 2, 4] = 50.0  # centre
    points = spatial_softmax(maps, torch.tensor(1.0))
    assert torch.allclose(points, torch.tensor([[1.0, 0.0, -1.0, 0.0]]), atol=1e-4)  # (x of each channel, y of each)


def test_a_keypoint_readout_learns_where_a_square_is():
    """E2EVMC with keypoints, trained on the q_OBJ head of Eq. 6.3 alone, places a square it has not
    seen in that position at well under the error of answering the mean position."""
    from physint_plugins.geeco.model import Geeco, geeco_loss

    def batch(n, generator):
        corner = torch.randint(0, 28, (n, 2), generator=generator)
        frames = torch.zeros(n, 4, 3, 32, 32)
        for i, (r, c) in enumerate(corner.tolist()):
            frames[i, :, :, r:r + 4, c:c + 4] = 1.0
        obj = torch.zeros(n, 1, 3)
        obj[:, 0, :2] = (corner.float() + 2) / 16 - 1  # the square's centre, in [-1, 1]
        return frames, {"dee": torch.zeros(n, 1, 3), "grip": torch.ones(n, 1, dtype=torch.long),
                        "ee": torch.zeros(n, 1, 3), "obj": obj}

    torch.manual_seed(0)
    generator = torch.Generator().manual_seed(0)
    model = Geeco("e2evmc", image_size=32, width=0.25, norm=True, min_side=8, readout="keypoints")
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    joints = torch.zeros(32, 4, 7)
    for _ in range(150):
        frames, b = batch(32, generator)
        loss, _ = geeco_loss(model(frames, joints), b)
        opt.zero_grad()
        loss.backward()
        opt.step()
    frames, b = batch(256, torch.Generator().manual_seed(99))
    with torch.no_grad():
        error = (model(frames, torch.zeros(256, 4, 7))["obj"] - b["obj"])[..., :2].norm(dim=-1).mean()
    chance = (b["obj"][..., :2] - b["obj"][..., :2].mean(0)).norm(dim=-1).mean()
    assert error < 0.5 * chance, (float(error), float(chance))
