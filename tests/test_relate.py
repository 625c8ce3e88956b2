"""relate: the simulated scenes keep their physics, Gamma is a set function, the measurements read
real frames right, training resumes exactly, and the CLI runs dataset -> train -> eval -> deploy."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from conftest import call

from physint_cli.plugins import get_plugins
from physint_plugins.relate import measure
from physint_plugins.relate import scenes as S
from physint_plugins.relate.model import ABSENT, Dynamics, Generator, Relation, Stacking, translate


def make(scene, backend="mujoco"):
    return get_plugins().backend(backend).make(scene)


@pytest.mark.parametrize("backend", ["mujoco", "pybullet"])
def test_balls_roll_and_stay_in_their_bowl(backend):
    rng = np.random.default_rng(3)
    bowl = S.sample_bowl(rng)
    starts, velocities = S.sample_balls(rng, bowl, 2, speed=0.5)
    scene, truth = S.balls_scene(bowl, starts, 32)
    with make(scene, backend) as sim:
        for name, v in zip(truth.names, velocities):
            sim.set_velocity(name, v)
        path = []
        for _ in range(30):
            sim.advance(0.05)
            path.append([sim.get_pose(n)[0] for n in truth.names])
    path = np.array(path)
    assert S.inside_bowl(path[..., 0], path[..., 1], *bowl[:3]).all()
    surface = S.bowl_height(path[..., 0], path[..., 1], *bowl[:3], bowl[3])
    assert np.abs(path[..., 2] - surface - S.BALL_RADIUS).max() < 0.01  # on the surface, not through it
    assert np.linalg.norm(path[-1] - path[0], axis=-1).max() > 0.01  # they rolled
    gaps = np.linalg.norm(path[:, 0] - path[:, 1], axis=-1)
    assert gaps.min() > 2 * S.BALL_RADIUS - 0.004  # they collide rather than pass through each other


def test_clevr_objects_do_not_overlap_and_rest_where_placed():
    scene, truth = S.clevr_scene(np.random.default_rng(5), 5, 32)
    with make(scene) as sim:
        before = np.array([sim.get_pose(n)[0] for n in truth.names])
        sim.advance(0.5)
        after = np.array([sim.get_pose(n)[0] for n in truth.names])
    assert np.abs(after - before).max() < 0.003
    for i in range(5):
        for j in range(i + 1, 5):
            reach = [h * (math.sqrt(2) if S.CLEVR_SHAPES[s] == "cube" else 1) for h, s in
                     ((truth.sizes[i], truth.shapes[i]), (truth.sizes[j], truth.shapes[j]))]
            assert np.linalg.norm(before[i, :2] - before[j, :2]) >= sum(reach)


def test_shapestacks_come_through_the_registry_and_stand():
    build = get_plugins().scene("stability", "ccs").build
    scene, truth = S.stack_scene(build, seed=11, height=4, size=32, randomise=False)
    assert len(truth.names) == 4 and scene.cameras[0].name == "front"
    with make(scene) as sim:
        before = np.array([sim.get_pose(n)[0] for n in truth.names])
        sim.advance(1.0)
        after = np.array([sim.get_pose(n)[0] for n in truth.names])
    assert np.abs(after - before).max() < 0.01


def test_extent_boxes_bound_each_rendered_block_and_lemma1_reads_them():
    """The dataset's pixel boxes (projected outlines) hold each block's rendered pixels and no more than a pixel
    besides; Lemma 1 through the registry calls the real stable towers stable and a shifted top block not."""
    from physint_plugins.relate.dataset import record

    build = get_plugins().scene("stability", "ccs").build
    lemma1 = get_plugins().metric("lemma1_side_view", "stability").fn
    scene, truth = S.stack_scene(build, seed=5, height=3, size=64, randomise=False)
    with make(scene) as sim:
        rec = record(sim, scene, truth, None, 1, 0.05, 5)
        seg = sim.render("front", segmentation=True).segmentation
    boxes = measure.tower_boxes(measure.box_targets(rec["extent"][None, 0], rec["present"][None], 64), 64)[0]
    assert len(boxes) == 3
    index = [b.name for b in scene.bodies]
    for k, name in enumerate(truth.names):
        v, u = np.nonzero(seg == index.index(name))
        u0, v0, u1, v1 = boxes[k]  # every pixel of the block inside its box, which is at most 2 px wider
        assert len(u) and u0 - 1 <= u.min() and u.max() + 0.5 <= u1 + 1 and v0 - 1 <= v.min() and v.max() + 0.5 <= v1 + 1
        assert u1 - u0 <= u.max() + 1 - u.min() + 2
    tower = measure.tower_plausibility([boxes], lemma1, 64)
    assert tower["stable"] == 1.0 and tower["resting"] == 1.0
    shifted = boxes.copy()
    shifted[-1, [0, 2]] += (boxes[-2, 2] - boxes[-1, 0]) + 1  # the top block beyond the one below it
    floating = boxes.copy()
    floating[-1, [1, 3]] -= 10  # the top block 10 px above the one below
    towers = measure.tower_plausibility([shifted, floating], lemma1, 64)
    assert towers["stable"] == 0.5 and towers["resting"] == 0.5 and towers["plausible"] == 0.0


def test_gamma_is_order_invariant_and_ignores_absent_objects():
    torch.manual_seed(0)
    gamma = Relation(z_dim=4, z_bg=2)
    theta, z, z0 = torch.rand(3, 4, 2) * 2 - 1, torch.rand(3, 4, 4), torch.rand(3, 2)
    present = torch.ones(3, 4, dtype=torch.bool)
    out = gamma(theta, z, z0, present)
    perm = torch.tensor([2, 0, 3, 1])
    assert torch.allclose(gamma(theta[:, perm], z[:, perm], z0, present), out[:, perm], atol=1e-6)
    assert not torch.allclose(out, theta)  # it does correct the poses
    # an absent object sends no message and is parked off the canvas
    present[:, 3] = False
    masked = gamma(theta, z, z0, present)
    alone = gamma(theta[:, :3], z[:, :3], z0, present[:, :3])
    assert torch.allclose(masked[:, :3], alone, atol=1e-6) and (masked[:, 3] == ABSENT).all()


def test_dynamics_roll_poses_forward_from_interactions():
    torch.manual_seed(0)
    gamma = Dynamics(z_dim=3, z_bg=2, max_speed=0.1)
    theta, z, z0 = torch.rand(2, 3, 2) * 1.6 - 0.8, torch.rand(2, 3, 3), torch.rand(2, 2)
    present = torch.ones(2, 3, dtype=torch.bool)
    path = gamma(theta, z, z0, present, steps=6)
    assert path.shape == (2, 6, 3, 2)
    steps = (path[:, 1:] - path[:, :-1]).abs()
    assert (steps <= 0.1 + 1e-6).all() and (steps > 0).any()  # theta(t+1) = theta(t) + v(t+1), |v| bounded
    perm = torch.tensor([1, 2, 0])  # any order
    assert torch.allclose(gamma(theta[:, perm], z[:, perm], z0, present, 6), path[:, :, perm], atol=1e-6)
    # object 1's way depends on where object 2 is (h_k of Eq. 5.4); an absent object stays parked and sends nothing
    moved = theta.clone()
    moved[:, 2] += 0.3
    assert not torch.allclose(gamma(moved, z, z0, present, 6)[:, 1:, 1], path[:, 1:, 1])
    present[:, 2] = False
    parked = gamma(theta, z, z0, present, 6)
    assert (parked[:, :, 2] == ABSENT).all()
    assert torch.allclose(parked[:, :, :2], gamma(theta[:, :2], z[:, :2], z0, present[:, :2], 6), atol=1e-6)


def test_ordered_gamma_stacks_each_block_on_the_one_below():
    torch.manual_seed(0)
    gamma = Stacking(z_dim=4, z_bg=2)
    theta_hat, z, z0 = torch.rand(5, 6, 2) * 1.2 - 0.6, torch.rand(5, 6, 4), torch.rand(5, 2)
    present = torch.arange(6)[None] < torch.tensor([[1], [2], [4], [6], [3]])  # towers of 1 to 6 blocks
    theta = gamma(theta_hat, z, z0, present)
    assert (theta[:, 0] - theta_hat[:, 0]).abs().max() <= 0.5  # the base: theta_hat_1 + 0.5 f_0
    for tower, height in zip(theta, present.sum(1)):
        steps = tower[1:height] - tower[:height - 1]
        assert (steps[:, 1] <= -0.1).all() and (steps[:, 1] >= -0.4).all()  # above (y down), by 0.1-0.4
        assert (steps[:, 0].abs() <= 0.2).all() and (tower[height:] == ABSENT).all()
    # only the blocks below matter: the top block's latent does not move the others
    z2 = z.clone()
    z2[:, 5] = torch.rand(5, 4)
    assert torch.allclose(gamma(theta_hat, z2, z0, present), theta)


def test_translation_puts_a_window_at_its_pose():
    grid = 16
    window = torch.zeros(1, 1, grid, grid)
    window[0, 0, grid // 2 - 1:grid // 2 + 1, grid // 2 - 1:grid // 2 + 1] = 1.0
    for theta in ((0.5, -0.25), (-0.75, 0.5)):
        moved = translate(window, torch.tensor([theta]))[0, 0]
        v, u = np.unravel_index(moved.argmax().item(), moved.shape)
        centre = [(t + 1) / 2 * grid for t in theta]  # theta in [-1, 1], x right, y down
        assert abs(u + 0.5 - centre[0]) <= 1 and abs(v + 0.5 - centre[1]) <= 1
    # the scale-augmented model's H'_k (Section 5.A.2): twice the window covers about four times the area
    wide = translate(window, torch.tensor([[0.0, 0.0]]), torch.tensor([2.0]))[0, 0]
    assert wide.sum() / window.sum() == pytest.approx(4.0, rel=0.3) and wide[grid // 2, grid // 2] > 0.5


def test_scale_augmented_model_trains_and_varies_object_size(tiny_relate, tmp_path):
    out, _ = tiny_relate
    code, _, err = call("train", "relate", "--preset", "tiny", "--data", str(out / "dataset"), "--set", "train.scale=true",
                        "--out", str(tmp_path / "s"))
    assert code == 0, err
    from physint_plugins.relate.checkpoint import load_model

    model, meta = load_model(tmp_path / "s", "cpu")
    g = model.generator
    assert meta["kwargs"]["scale"] and g.scale is not None
    latents = g.sample(16, generator=torch.Generator().manual_seed(0))
    theta = g.still_poses(latents)
    sizes = 1 + g.scale(torch.cat([latents["z0"][:, None].expand(-1, g.objects, -1), theta, latents["z"]], dim=2))
    assert sizes.std() > 0  # each object gets its own H'_k


def test_toggle_distance_is_small_where_objects_are_drawn_at_their_pose():
    torch.manual_seed(0)
    g = Generator(size=32, grid=8, window=2, z_obj=4, z_bg=2, channels=8, objects=3, fixed_objects=False,
                  compose="max", relation=None)
    near = measure.toggle_distance(g, 20, 3)
    assert near < 32 / 4  # the renderer is local: leaving an object out changes the image round it


@pytest.mark.parametrize("balls", [2, 4])
def test_detector_reads_real_frames_and_catches_a_ball_outside_the_bowl(balls):
    rng = np.random.default_rng(8)
    bowl = S.sample_bowl(rng)
    starts, _ = S.sample_balls(rng, bowl, balls)
    scene, truth = S.balls_scene(bowl, starts, 64)
    camera = scene.cameras[0]
    detector = measure.Detector(64, balls)
    with make(scene) as sim:
        seen = detector(sim.render("top").rgb)
        assert seen.plausible
        truth_px = camera.project(np.array([sim.get_pose(n)[0] for n in truth.names]))
        assert np.abs(seen.balls - truth_px).max() < 1.0
        c, s = math.cos(bowl[0]), math.sin(bowl[0])
        out = 1.15 * bowl[1] * np.array([c, s])  # past the rim along the major axis
        sim.freeze(truth.names[0])
        sim.set_pose(truth.names[0], (out[0], out[1], S.BALL_RADIUS))
        assert not detector(sim.render("top").rgb).plausible


def test_frechet_distance_is_zero_for_one_set_and_grows_with_a_shift():
    x = np.random.default_rng(0).normal(size=(500, 8))
    assert abs(measure.frechet(x, x)) < 1e-6
    assert measure.frechet(x, x + 0.5) == pytest.approx(8 * 0.25, rel=0.05)


@pytest.fixture(scope="module")
def tiny_relate(tmp_path_factory):
    out = tmp_path_factory.mktemp("relate")
    code, stdout, err = call("pipeline", "relate", "--preset", "tiny", "--out", str(out), "--json")
    assert code == 0, err
    return out, json.loads(stdout)


def test_pipeline_generates_measures_and_deploys(tiny_relate):
    out, result = tiny_relate
    assert result["dataset"]["stats"]["left_bowl"] == 0
    ev = result["eval"]["metrics"]
    assert set(ev["generated"]) == {"Gamma", "Gamma bypassed"}
    assert ev["real"]["plausibility"]["plausible"] >= 0.9  # real test frames are plausible (balls 1.6 px wide at 16 px)
    for r in ev["generated"].values():
        assert r["fd_truth"] > ev["real"]["fd_truth"] >= 0
    assert (out / "dataset" / "features").is_dir()  # the regressor is kept beside the dataset
    assert set(ev["decomposition"]) == {"background_without_balls", "one_object_one_ball"}
    assert all(0 <= v <= 1 for v in ev["decomposition"].values())
    for name in ("samples.png", "components.png", "ood.png", "editing.png", "deploy.rrd"):
        assert (out / "deploy" / "artifacts" / name).stat().st_size > 0


class TinyInception(torch.nn.Module):
    """Stands in for NVlabs' TorchScript FID Inception: same call, two statistics per channel as features."""

    def forward(self, x: torch.Tensor, return_features: bool = True) -> torch.Tensor:
        x = x.float() / 255
        return torch.cat([x.mean((2, 3)), x.std((2, 3))], 1)


class TinyI3D(torch.nn.Module):
    """Stands in for StyleGAN-V's TorchScript I3D: same call; channel means and how much frames change."""

    def forward(self, x: torch.Tensor, rescale: bool = False, resize: bool = True,
                return_features: bool = True) -> torch.Tensor:
        change = (x[:, :, 1:] - x[:, :, :-1]).abs().mean((2, 3, 4), keepdim=False)
        return torch.cat([x.mean((2, 3, 4)), 10 * change], 1)


class NotAFeatureNet(torch.nn.Module):
    def forward(self, x: torch.Tensor, return_features: bool = True) -> torch.Tensor:
        return x.float()


def test_fid_from_a_local_inception_and_a_bad_weights_path_exits_2(tiny_relate, tmp_path):
    out, _ = tiny_relate
    good, wrong, junk = tmp_path / "inception.pt", tmp_path / "wrong.pt", tmp_path / "junk.pt"
    torch.jit.save(torch.jit.script(TinyInception()), str(good))
    torch.jit.save(torch.jit.script(NotAFeatureNet()), str(wrong))
    junk.write_bytes(b"not a network")
    code, stdout, err = call("eval", "relate", "--run", str(out / "train"), "--set", f"eval.inception={good}",
                             "--out", str(tmp_path / "e"), "--json")
    assert code == 0, err
    ev = json.loads(stdout)["metrics"]
    assert all(r["fid"] >= 0 for r in ev["generated"].values()) and ev["real"]["fid"] >= 0
    assert "FID (local Inception)" in (tmp_path / "e" / "artifacts" / "table_5_4_1.md").read_text()
    for path, words in ((tmp_path / "missing.pt", "no file at"), (junk, "not a TorchScript network"),
                        (wrong, "not one feature row")):
        code, _, err = call("eval", "relate", "--run", str(out / "train"), "--set", f"eval.inception={path}",
                            "--out", str(tmp_path / "bad"))
        assert code == 2 and words in err and "Traceback" not in err, err


def test_video_pipeline_trains_clips_measures_fvd_truth_and_deploys(tmp_path):
    out = tmp_path / "video"
    code, stdout, err = call("pipeline", "relate", "--preset", "tiny", "--set", "train.variant=video", "--out", str(out),
                             "--json")
    assert code == 0, err
    ev = json.loads(stdout)["eval"]["metrics"]
    assert ev["variant"] == "video" and set(ev["generated"]) == {"Gamma", "Gamma bypassed (still)"}
    assert ev["real"]["ball_speed_px"] > 0  # the real balls roll
    assert not ev["generated"]["Gamma bypassed (still)"]["ball_speed_px"] > 0  # still clips do not move (or show no ball)
    assert ev["time_shuffled"]["fvd_truth"] >= 0 and ev["real"]["fvd_truth"] >= 0
    for name in ("clips.mp4", "ood_clips.mp4", "samples.png", "deploy.rrd"):
        assert (out / "deploy" / "artifacts" / name).stat().st_size > 0
    # FVD on a local TorchScript I3D: shuffling the frames of real clips moves them away from the test clips
    torch.jit.save(torch.jit.script(TinyI3D()), str(tmp_path / "i3d.pt"))
    code, stdout, err = call("eval", "relate", "--run", str(out / "train"), "--set", f"eval.i3d={tmp_path / 'i3d.pt'}",
                             "--out", str(tmp_path / "fvd"), "--json")
    assert code == 0, err
    fvd = json.loads(stdout)["metrics"]
    assert fvd["time_shuffled"]["fvd"] > fvd["real"]["fvd"] >= 0 and fvd["generated"]["Gamma"]["fvd"] >= 0
    # clips come from sequences: a video model on still images, or without Gamma, exits 2
    code, _, err = call("train", "relate", "--preset", "tiny", "--data", str(out / "dataset"), "--set", "train.variant=video",
                        "--set", "train.arm=blockgan2d", "--out", str(tmp_path / "b"))
    assert code == 2 and "Gamma" in err
    code, _, err = call("train", "relate", "--preset", "tiny", "--data", str(out / "dataset"), "--set", "train.variant=video",
                        "--set", "train.clip=9", "--out", str(tmp_path / "c"))
    assert code == 2 and "train.clip" in err


def test_ordered_variant_trains_on_towers_only(tiny_relate, tmp_path):
    out, _ = tiny_relate
    code, _, err = call("train", "relate", "--preset", "tiny", "--data", str(out / "dataset"), "--set", "train.variant=ordered",
                        "--out", str(tmp_path / "o"))
    assert code == 2 and "shapestacks" in err  # balls in a bowl are no tower
    code, _, err = call("pipeline", "relate", "--preset", "tiny", "--scene", "shapestacks", "--set", "train.variant=ordered",
                        "--set", "data.train=4", "--set", "data.test=2", "--out", str(tmp_path / "stacks"))
    assert code == 0, err
    assert (tmp_path / "stacks" / "deploy" / "artifacts" / "ood.png").stat().st_size > 0
    towers = json.loads((tmp_path / "stacks" / "eval" / "metrics.json").read_text())
    towers = towers.get("metrics", towers)
    assert set(towers["real"]["towers"]) == {"test towers, read", "unstable towers (held out), read",
                                             "test towers, simulated boxes"}
    assert towers["real"]["towers"]["test towers, simulated boxes"]["stable"] == 1.0  # Lemma 1 on the simulator's boxes
    for name in ("Gamma", "Gamma bypassed"):
        assert 0.0 <= towers["generated"][name]["towers"]["plausible"] <= 1.0
    code, _, err = call("eval", "relate", "--run", str(out / "train"), "--data", str(tmp_path / "stacks" / "dataset"),
                        "--out", str(tmp_path / "e"))
    assert code == 2 and "trained on balls-in-bowl" in err  # a balls model is not measured on towers


def test_resume_refuses_another_model(tiny_relate, tmp_path):
    out, _ = tiny_relate
    common = ("--preset", "tiny", "--data", str(out / "dataset"), "--set", "train.checkpoint_every=5")
    code, _, err = call("train", "relate", *common, "--set", "train.iterations=5", "--out", str(tmp_path / "r"))
    assert code == 0, err
    code, _, err = call("train", "relate", *common, "--set", "train.iterations=10", "--set", "train.channels=12",
                        "--resume", "--run", str(tmp_path / "r"))
    assert code == 2 and "another model" in err and "Traceback" not in err


def test_training_resumes_where_it_stopped(tiny_relate, tmp_path):
    out, _ = tiny_relate
    data = str(out / "dataset")
    common = ("--preset", "tiny", "--data", data, "--set", "train.checkpoint_every=5")
    code, _, err = call("train", "relate", *common, "--set", "train.iterations=10", "--out", str(tmp_path / "straight"))
    assert code == 0, err
    code, _, err = call("train", "relate", *common, "--set", "train.iterations=5", "--out", str(tmp_path / "halves"))
    assert code == 0, err
    curves = tmp_path / "halves" / "metrics.jsonl"
    with open(curves, "a") as f:  # a point an interrupted run logged after its last checkpoint (update 5)
        f.write(json.dumps({"step": 7, "d_loss": 0.0}) + "\n")
    code, _, err = call("train", "relate", *common, "--set", "train.iterations=10", "--resume", "--run",
                        str(tmp_path / "halves"))
    assert code == 0, err
    assert [json.loads(line)["step"] for line in curves.read_text().splitlines()] == [5, 10]  # no point twice
    a = torch.load(tmp_path / "straight" / "checkpoints" / "best.pt", weights_only=False)["model"]
    b = torch.load(tmp_path / "halves" / "checkpoints" / "best.pt", weights_only=False)["model"]
    assert all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.parametrize("args, words", [
    (("dataset", "relate", "--preset", "tiny", "--scene", "shapestacks", "--set", "data.min_objects=1"), "at least 2"),
    (("dataset", "relate", "--preset", "tiny", "--set", "data.min_objects=4", "--set", "data.max_objects=3"), "must not exceed"),
    (("dataset", "relate", "--preset", "tiny", "--scene", "kitchen"), "kitchen"),
    (("train", "relate", "--preset", "tiny", "--set", "train.arm=gan"), "train.arm"),
])
def test_bad_input_is_one_line_and_exit_2(args, words, tmp_path):
    code, _, err = call(*args, "--out", str(tmp_path / "x"))
    assert code == 2 and words in err and "Traceback" not in err


def test_bad_run_or_task_is_one_line_and_exit_2(tiny_relate, tmp_path):
    out, _ = tiny_relate
    code, _, err = call("deploy", "relate", "--run", str(out / "train"), "--task", "dance", "--out", str(tmp_path / "d"))
    assert code == 2 and "sample or edit" in err
    code, _, err = call("train", "relate", "--preset", "tiny", "--data", str(out / "dataset"), "--set", "train.size=24",
                        "--out", str(tmp_path / "t"))
    assert code == 2 and "train.grid" in err
    code, _, err = call("train", "relate", "--preset", "tiny", "--data", str(out / "dataset"), "--set", "train.size=48",
                        "--set", "train.grid=6", "--out", str(tmp_path / "t2"))
    assert code == 2 and "4 times a power of 2" in err


@pytest.mark.parametrize("backend", ["pybullet", "robosuite"])
def test_dataset_on_the_other_backends(backend, tmp_path):
    from physint_plugins.relate.dataset import load_split

    code, stdout, err = call("dataset", "relate", "--preset", "tiny", "--backend", backend, "--set", "data.train=2",
                             "--set", "data.test=1", "--out", str(tmp_path / "d"), "--json")
    assert code == 0, err
    assert json.loads(stdout)["stats"]["left_bowl"] == 0
    arrays = load_split(tmp_path / "d", "train", ("frames", "pixels", "present"))
    assert arrays["frames"].shape == (2, 8, 32, 32, 3) and arrays["present"].all()
    inside = (arrays["pixels"] >= 0) & (arrays["pixels"] < 32)
    assert inside.all()  # the balls stay in the camera's view
    assert arrays["frames"].std() > 10  # something is drawn
