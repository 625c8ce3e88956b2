"""The geeco method through the CLI: demonstrations, training, closed-loop evaluation, deployment."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import call

from physint_cli.datasets import ShardedDataset
from physint_plugins.geeco import scenes as S
from physint_plugins.geeco.expert import SPEED


@pytest.fixture(scope="module")
def tiny_pipeline(tmp_path_factory):
    out = tmp_path_factory.mktemp("geeco") / "pipe"
    code, stdout, err = call("pipeline", "geeco", "--preset", "tiny", "--backend", "mujoco", "--out", str(out), "--json")
    assert code == 0, err
    return out, json.loads(stdout)


def test_demonstrations_are_balanced_successful_and_end_on_their_target_image(tiny_pipeline):
    out, result = tiny_pipeline
    stats = result["dataset"]["stats"]
    assert stats["demos"] == 16 and 0 < stats["expert_success_rate"] <= 1
    train = ShardedDataset(out / "dataset", "train")
    assert len(train) == 8 and len(ShardedDataset(out / "dataset", "test")) == 4  # 2:1:1
    tasks = [tuple(t) for t in train.column("task").tolist()]
    assert sorted(set(tasks)) == S.tasks("goal2cube2") and all(tasks.count(t) == 2 for t in set(tasks))
    for i in range(len(train)):
        r = train[i]
        assert r["rgb"].shape == (100, 32, 32, 3) and r["joints"].shape == (100, 7)
        assert np.abs(r["dee"]).max() <= SPEED + 1e-6 and set(np.unique(r["grip"])) <= {0, 1, 2}
        ep = S.Episode("goal2cube2", "push", r["layout"], tuple(int(v) for v in r["task"]))
        assert int(r["backdrop"]) == -1  # the thesis's plain background
        # the object moved from its start onto its target; the hand is parked at the end
        assert np.linalg.norm(r["obj"][0, :2] - ep.xy(ep.object)) < 1e-3
        assert np.all(np.abs(r["obj"][-1, :2] - ep.xy(ep.target)) <= S.PAD / 2)
        assert np.linalg.norm(r["ee"][-1] - np.asarray(S.REST_EE)) < 0.03
        assert np.abs(r["rgb"][-1].astype(int) - r["rgb"][-2].astype(int)).mean() < 2  # a still last frame


def test_pipeline_reports_thesis_metrics_and_leaves_things_to_look_at(tiny_pipeline):
    out, result = tiny_pipeline
    ev = result["eval"]["metrics"]
    assert ev["episodes"] == 2 and set(ev["rates"]) == {"REACH", "PUSH"}
    for rate in ev["rates"].values():
        assert 0 <= rate["rate"] <= 1 and rate["ci95"] >= 0
    assert ev["control_hz"] > 0 and ev["diverged"] == 0
    assert ev["object_to_target_m"]["start"] >= 0.16  # objects start at least 16 cm from their targets
    assert len((out / "eval" / "artifacts" / "episodes.jsonl").read_text().splitlines()) == 2
    de = result["deploy"]["metrics"]
    assert de["goal"] == de["task"] and de["steps"] == 40
    for name in ("target.png", "episode.mp4", "deploy.rrd"):
        assert (out / "deploy" / "artifacts" / name).stat().st_size > 0, name
    assert (out / "train" / "artifacts" / "training_curves.png").exists()


def test_a_goal_in_words_and_the_target_image_it_made_give_the_same_start(tiny_pipeline, tmp_path):
    out, _ = tiny_pipeline
    run = str(out / "train")
    code, stdout, err = call("deploy", "geeco", "--run", run, "--target", "red cube onto blue pad", "--seed", "3",
                             "--out", str(tmp_path / "a"), "--json")
    assert code == 0, err
    assert json.loads(stdout)["metrics"]["task"] == "red cube onto blue pad"
    image = tmp_path / "a" / "artifacts" / "target.png"
    code, stdout, err = call("deploy", "geeco", "--run", run, "--target", str(image), "--seed", "3",
                             "--episodes", "3", "--out", str(tmp_path / "b"), "--json")
    assert code == 0, err
    assert "geeco deploy runs one episode" in err  # --episodes is not silently dropped
    import imageio.v3 as iio

    assert np.array_equal(iio.imread(tmp_path / "b" / "artifacts" / "target.png"), iio.imread(image))


@pytest.mark.parametrize("args, message", [
    (["dataset", "geeco", "--scene", "clutter"], "for evaluation only"),
    (["dataset", "geeco", "--set", "data.skill=fly"], "data.skill: 'fly' is not one of push, pickplace"),
    (["dataset", "geeco", "--set", "data.demos=2"], "data.demos: must be >= 4, got 2"),
    (["dataset", "geeco", "--set", "data.action_noise=0.5"], "data.action_noise: must be in [0.0, 0.02], got 0.5"),
    (["dataset", "geeco", "--set", "data.backgrounds=video"], "data.backgrounds: 'video' is not one of plain, random, mixed"),
    (["train", "geeco", "--model", "geeco-x"], "geeco-x"),
])
def test_bad_input_exits_2_with_one_line(args, message):
    code, _, err = call(*args, "--preset", "tiny")
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err


def test_random_backgrounds_are_recorded_with_their_seeds_and_replayed_wherever_episodes_are_rebuilt(tmp_path):
    """data.backgrounds=random: each demonstration has its own background video, and training's
    episodes (validation, DAgger) and evaluation's test episodes rebuild it from the stored seed,
    so the frames a controller sees match its target image's background."""
    import physint_backends as pb
    from types import SimpleNamespace

    from physint_plugins.geeco.control import observe
    from physint_plugins.geeco.evaluate import episode_of, plan_episodes
    from physint_plugins.geeco.checkpoint import episodes_of
    from physint_plugins.geeco.train import load_split

    data = tmp_path / "random"
    code, _, err = call("dataset", "geeco", "--preset", "tiny", "--set", "data.demos=4", "--set",
                        "data.backgrounds=random", "--out", str(data))
    assert code == 0, err
    demos = load_split(data, "train")
    episodes = episodes_of(demos, "goal2cube2", "push")
    assert len({ep.backdrop for ep in episodes}) == len(episodes) and all(ep.backdrop >= 0 for ep in episodes)
    ctx = SimpleNamespace(scene="goal2cube2", data=data, backend="mujoco", seed=0)
    spec = plan_episodes(ctx, {"skill": "push", "scene": "goal2cube2", "backend": "mujoco"}, 1)[0]
    assert episode_of(spec, "goal2cube2", "push").backdrop == int(load_split(data, "test")["backdrop"][0]) >= 0
    ep = episodes[0]
    with pb.make("mujoco", S.build_scene(ep, 32)) as sim:
        replayed = observe(sim, 0, S.background_video(ep))
        plain = observe(sim, 0)
    assert (replayed == demos["rgb"][0, 0]).all()  # the first frame, background and all
    assert (replayed != plain).any(axis=-1).mean() > 0.03  # the background is not the plain one


@pytest.mark.parametrize("n_tasks", [1, 2, 4])
def test_mixed_backgrounds_give_half_of_each_tasks_demonstrations_a_random_one(n_tasks):
    from physint_plugins.geeco.dataset import random_background

    rounds = 6
    drawn = np.array([[random_background("mixed", r * n_tasks + t, n_tasks) for t in range(n_tasks)]
                      for r in range(rounds)])
    assert (drawn.sum(axis=0) == rounds // 2).all()  # every task: half random, half plain
    assert (drawn[1:] != drawn[:-1]).all()  # alternating from round to round
    if n_tasks > 1:
        assert (drawn.sum(axis=1) == n_tasks // 2).all()  # every round: half its tasks random
    assert not any(random_background("plain", i, n_tasks) for i in range(12))
    assert all(random_background("random", i, n_tasks) for i in range(12))


def test_bad_targets_exit_2(tiny_pipeline, tmp_path):
    out, _ = tiny_pipeline
    run = str(out / "train")
    not_image = tmp_path / "notes.png"
    not_image.write_text("not an image")
    big = tmp_path / "big.png"
    import imageio.v3 as iio

    iio.imwrite(big, np.zeros((64, 64, 3), np.uint8))
    for target, message in (("purple cube onto green pad", "objects: red cube, yellow cube"),
                            (str(not_image), "not an image"), (str(big), "sees 32x32 images, got 64x64"),
                            (str(tmp_path / "missing.png"), "no such file")):
        code, _, err = call("deploy", "geeco", "--run", run, "--target", target, "--out", str(tmp_path / "d"))
        assert code == 2 and message in err, (target, err)


def test_a_run_of_another_method_is_refused(tmp_path):
    code, _, err = call("train", "stability", "--preset", "tiny", "--scene", "cubes", "--out", str(tmp_path / "st"),
                        "--set", "train.epochs=1")
    assert code == 0, err
    code, _, err = call("eval", "geeco", "--run", str(tmp_path / "st"))
    assert code == 2 and "stability" in err


def test_a_diverging_controller_fails_its_episode_without_stopping_the_evaluation():
    from physint_plugins.geeco.control import run_episode

    import physint_backends as pb

    class Diverging:
        calls = 0

        def reset(self, target):
            pass

        def act(self, rgb, joints, hand=None, truth=None):
            self.calls += 1
            return np.array([0.01, 0.0, 0.0, 0.0]) if self.calls < 5 else np.array([np.nan, 0.0, 0.0, 0.0])

    ep = S.sample_episode("goal2cube2", "push", (0, 0), np.random.default_rng(0))
    with pb.make("mujoco", S.build_scene(ep, 32)) as sim:
        result = run_episode(sim, ep, Diverging(), None, steps=50, resolution=32)
        assert result["diverged"] and not result["success"] and result["steps"] == 5
        again = run_episode(sim, ep, Diverging(), None, steps=3, resolution=32)  # the next episode runs
        assert again["steps"] == 3 and not again["diverged"]


def test_episodes_side_by_side_end_as_each_alone_and_a_diverging_one_leaves_the_others_running():
    """``run_episodes`` steps episodes in lockstep (training's validation): each sees the same
    frames and ends as it would alone (lockstep and reused simulations change nothing but the
    network's batch), and one whose controller diverges stops there while the others go on."""
    import physint_backends as pb
    from physint_plugins.geeco.control import run_episode, run_episodes

    eps = [S.sample_episode("goal2cube2", "push", task, np.random.default_rng(i))
           for i, task in enumerate([(0, 0), (1, 1), (0, 1)])]
    sims = [pb.make("mujoco", S.build_scene(ep, 32)) for ep in eps]
    try:
        experts = [_ExpertWithDetour(sim, ep, detour=0) for sim, ep in zip(sims, eps)]
        alone = [run_episode(sim, ep, expert, None, 100, 32) for sim, ep, expert in zip(sims, eps, experts)]
        stand_ins = [_ExpertWithDetour(sim, ep, detour=0) for sim, ep in zip(sims, eps)]
        stand_ins[1].act = lambda *args: np.array([np.nan, 0.0, 0.0, 0.0]) if stand_ins[1].t > 9 else \
            _ExpertWithDetour.act(stand_ins[1], *args)
        together = run_episodes(sims, eps, stand_ins, [None] * 3, 100, 32)
    finally:
        for sim in sims:
            sim.close()
    assert all(r["success"] and r["reach"] for r in alone)
    for i in (0, 2):
        assert together[i]["success"] and together[i]["steps"] == 100
        assert together[i]["final_xy"] == alone[i]["final_xy"]
        assert stand_ins[i].frames == experts[i].frames and len(set(experts[i].frames)) > 10  # every pixel
    assert together[1]["diverged"] and together[1]["steps"] == 11 and not together[1]["success"]


def test_behaviour_cloning_on_demonstrations_beats_the_mean_command(tiny_pipeline):
    """Trained on the tiny demonstrations (Eq. 6.3), GEECO-D predicts the expert's commands on its
    training windows far better than always answering the average command."""
    from physint_cli.training import seed_everything
    from physint_plugins.geeco.model import Geeco, geeco_loss
    from physint_plugins.geeco.train import Chunks, load_split, to_float_frames

    out, _ = tiny_pipeline
    demos = load_split(out / "dataset", "train")
    chunks = Chunks(demos, 10)
    seed_everything(0)
    model = Geeco("geeco-d", image_size=32, width=0.25, norm=True)
    opt = torch.optim.Adam(model.parameters(), lr=2e-3)
    loader = torch.utils.data.DataLoader(chunks, batch_size=8, shuffle=True)
    for _ in range(60):  # 30 epochs left some seeds at 0.87 of the mean's error; 60 gave 0.26-0.37 over seeds 2-5
        for batch in loader:
            batch = to_float_frames(batch)
            loss, _ = geeco_loss(model(batch["frames"], batch["joints"], batch["target"]), batch)
            opt.zero_grad()
            loss.backward()
            opt.step()
    batch = to_float_frames(torch.utils.data.default_collate([chunks[i] for i in range(len(chunks))]))
    with torch.no_grad():
        pred = model(batch["frames"], batch["joints"], batch["target"])
    mse = float(((pred["dee"] - batch["dee"]) ** 2).mean())
    mean_mse = float(((batch["dee"] - batch["dee"].mean(dim=(0, 1))) ** 2).mean())
    grip_acc = float((pred["grip"].argmax(-1) == batch["grip"]).float().mean())
    majority = float(np.bincount(batch["grip"].flatten().numpy()).max() / batch["grip"].numel())
    assert mse < 0.8 * mean_mse, (mse, mean_mse)  # seen: 0.027-0.039 vs 0.105
    assert grip_acc > majority + 0.02, (grip_acc, majority)  # seen: 0.999 vs 0.960 (no-op most of the time)


def test_evaluation_gives_the_same_episodes_whatever_the_number_of_workers(tiny_pipeline, tmp_path):
    out, _ = tiny_pipeline
    code, _, err = call("eval", "geeco", "--run", str(out / "train"), "--workers", "2", "--out", str(tmp_path / "w2"))
    assert code == 0, err

    def episodes(run):
        rows = [json.loads(line) for line in (run / "artifacts" / "episodes.jsonl").read_text().splitlines()]
        return [{k: v for k, v in r.items() if k != "seconds"} for r in rows]

    assert episodes(tmp_path / "w2") == episodes(out / "eval")  # one worker ran the pipeline's evaluation


def test_episodes_evaluated_side_by_side_act_and_end_as_one_at_a_time(tiny_pipeline, tmp_path, monkeypatch):
    """eval.side_by_side steps a worker's episodes in lockstep: the same episodes with the same
    target images (stored, or made by the expert in a transfer scene) get the same actions and end
    where they end one at a time, up to a batch's float rounding."""
    from physint_plugins.geeco.control import ClosedLoop

    out, _ = tiny_pipeline
    run = str(out / "train")
    actions: dict[bytes, list] = {}  # each episode's actions, by its start state
    apply = ClosedLoop.apply

    def recording_apply(self, action):
        actions.setdefault(self.ep.layout.tobytes(), []).append(np.array(action))
        return apply(self, action)

    monkeypatch.setattr(ClosedLoop, "apply", recording_apply)

    def episodes(name, *args):
        actions.clear()
        code, stdout, err = call("eval", "geeco", "--run", run, "--set", "eval.per_unit=2", *args,
                                 "--out", str(tmp_path / name), "--json")
        assert code == 0, err
        rows = [json.loads(line) for line in (tmp_path / name / "artifacts" / "episodes.jsonl").read_text().splitlines()]
        return json.loads(stdout)["metrics"], rows, dict(actions)

    for scene in ("goal2cube2", "clutter"):
        m1, alone, acted_alone = episodes(f"{scene}1", "--scene", scene)
        m2, together, acted_together = episodes(f"{scene}2", "--scene", scene, "--set", "eval.side_by_side=2")
        assert (m1["side_by_side"], m2["side_by_side"]) == (1, 2) and m1["episodes"] >= 1
        assert [r["index"] for r in together] == [r["index"] for r in alone] == [0, 1]
        assert acted_alone.keys() == acted_together.keys() and len(acted_alone) == m1["episodes"]
        for layout, seq in acted_alone.items():
            # seen: 1e-9 apart (a batch's rounding); with the two targets swapped, 2e-5
            assert np.abs(np.array(seq) - np.array(acted_together[layout])).max() < 1e-6, scene
        for a, b in zip(alone, together):
            assert a.get("task") == b.get("task") and a.get("no_target") == b.get("no_target")
            if "final_xy" in a:
                assert np.allclose(a["final_xy"], b["final_xy"], atol=2e-3), (scene, a, b)
    code, _, err = call("eval", "geeco", "--run", run, "--set", "eval.side_by_side=3", "--set", "eval.per_unit=2",
                        "--out", str(tmp_path / "bad"))
    assert code == 2 and "eval.side_by_side must be in [1, eval.per_unit = 2], got 3" in err


def test_evaluation_on_another_backend_and_on_a_transfer_scene(tiny_pipeline, tmp_path):
    out, _ = tiny_pipeline
    run = str(out / "train")
    for args in (["--backend", "pybullet"], ["--scene", "prisma"], ["--scene", "clutter"]):
        code, stdout, err = call("eval", "geeco", "--run", run, *args, "--set", "eval.episodes=1", "--set",
                                 "eval.steps=10", "--out", str(tmp_path / "_".join(args).strip("-")), "--json")
        assert code == 0, (args, err)
        metrics = json.loads(stdout)["metrics"]
        # the target image comes from the expert on that backend / in that scene
        assert metrics["episodes"] + metrics["no_target"] == 1 and metrics["trained_on"]["backend"] == "mujoco"
    code, _, err = call("eval", "geeco", "--run", run, "--scene", "nutoncone", "--out", str(tmp_path / "nut"))
    assert code == 2 and "pick-and-place transfer task" in err
    # --episodes sets how many (the tiny preset's eval.episodes is 2)
    code, stdout, err = call("eval", "geeco", "--run", run, "--episodes", "1", "--set", "eval.steps=10", "--out",
                             str(tmp_path / "one"), "--json")
    assert code == 0 and json.loads(stdout)["metrics"]["episodes"] == 1, err
    import yaml

    assert yaml.safe_load((tmp_path / "one" / "config.yaml").read_text())["config"]["eval"]["episodes"] == 1
    code, _, err = call("eval", "geeco", "--run", run, "--episodes", "0", "--out", str(tmp_path / "none"))
    assert code == 2 and "--episodes" in err and "got 0" in err  # the core checks --episodes


def test_tiny_pipeline_on_robosuite(tmp_path):
    code, stdout, err = call("pipeline", "geeco", "--preset", "tiny", "--backend", "robosuite", "--out",
                             str(tmp_path / "rs"), "--json")
    assert code == 0, err
    result = json.loads(stdout)
    assert result["eval"]["metrics"]["backend"] == "robosuite" and result["deploy"]["metrics"]["steps"] == 40


def test_a_run_takes_the_scene_of_its_dataset(tiny_pipeline, tmp_path):
    out, _ = tiny_pipeline
    code, _, err = call("train", "geeco", "--preset", "tiny", "--data", str(out / "dataset"), "--scene", "goal1cube1",
                        "--out", str(tmp_path / "r"))
    assert code == 2 and "is of scene goal2cube2" in err


def test_bad_training_settings_exit_2(tiny_pipeline, tmp_path):
    out, _ = tiny_pipeline
    for setting, message in (("train.width=0", "train.width: must be > 0.0, got 0.0"),
                             ("train.chunk=0", "train.chunk: must be >= 1, got 0"),
                             ("train.chunk=101", "train.chunk must be in [1, 100]"),
                             ("train.epochs=0", "train.epochs: must be >= 1, got 0"),
                             ("train.min_side=0", "train.min_side: must be >= 1, got 0"),
                             ("train.stem_stride=3", "train.stem_stride: '3' is not one of 1, 2"),
                             ("train.dee_bins=1", "train.dee_bins: must be 0 (regression, the thesis) or >= 2, got 1"),
                             ("train.dee_modes=-2", "train.dee_modes: must be >= 0, got -2"),
                             ("train.readout=pool", "train.readout: 'pool' is not one of flatten, keypoints"),
                             ("train.command=plan", "train.command: 'plan' is not one of network, positions, auto"),
                             ("train.schedule=step", "train.schedule: 'step' is not one of cosine, constant"),
                             ("train.dagger_epochs=1", "train.dagger_epochs must lie in [2, train.epochs = 2]"),
                             ("train.dagger_epochs=two", "train.dagger_epochs must be comma-separated epoch numbers"),
                             ("train.dagger_beta=1", "train.dagger_beta: must be in [0.0, 1.0), got 1.0"),
                             ("train.command_epochs=-1", "train.command_epochs: must be >= 0, got -1")):
        code, _, err = call("train", "geeco", "--preset", "tiny", "--data", str(out / "dataset"), "--set", setting,
                            "--out", str(tmp_path / "r"))
        assert code == 2 and message in err, (setting, err)
    code, _, err = call("train", "geeco", "--preset", "tiny", "--data", str(out / "dataset"), "--set",
                        "train.dee_bins=5", "--set", "train.dee_modes=5", "--out", str(tmp_path / "r"))
    assert code == 2 and "set one of them" in err, err
    code, _, err = call("train", "geeco", "--preset", "tiny", "--data", str(out / "dataset"), "--set",
                        "train.command=positions", "--set", "train.dee_bins=5", "--out", str(tmp_path / "r"))
    assert code == 2 and "not with train.dee_bins" in err, err


class _ExpertWithDetour:
    """A stand-in controller: its own push expert's commands, except a 1 cm sideways detour per
    step for the first ``detour`` steps (its expert's plan follows the detour, as under noise)."""

    def __init__(self, sim, ep, detour: int):
        from physint_plugins.geeco.expert import Expert

        self.sim, self.expert, self.detour, self.t, self.commands = sim, Expert(ep), detour, 0, []
        self.frames: list[str] = []  # a digest of each frame it saw

    def reset(self, target):
        pass

    def act(self, rgb, joints, hand=None, truth=None):
        self.frames.append(hashlib.sha1(np.ascontiguousarray(rgb).tobytes()).hexdigest())
        action = self.expert.act(self.sim)
        self.commands.append(action.copy())
        if self.t < self.detour:
            action = self.expert.perturb(action, np.array([0.0, 0.01, 0.0]))
        self.t += 1
        return action


def test_dagger_labels_the_states_a_controller_reaches_with_the_experts_commands(tiny_pipeline):
    """Rolled out by a controller that strays, then behaves like the expert, the labelling expert
    knows where the hand was sent (``Expert.follow``): from the detour's end on its labels are the
    commands of an expert that drove itself, and the cube ends on its target."""
    import physint_backends as pb
    from physint_plugins.geeco.dagger import rollouts
    from physint_plugins.geeco.expert import on_target
    from physint_plugins.geeco.checkpoint import episodes_of

    out, _ = tiny_pipeline
    demos = ShardedDataset(out / "dataset", "train", method="geeco", in_memory=True).arrays
    ep = episodes_of(demos, "goal2cube2", "push")[0]
    with pb.make("mujoco", S.build_scene(ep, 32)) as sim:
        controller = _ExpertWithDetour(sim, ep, detour=8)
        (r,) = rollouts([sim], [ep], [controller], [demos["rgb"][0, -1]], 100)
        assert on_target(ep, sim)
    commands = np.array(controller.commands)
    assert np.allclose(r["dee"][8:], commands[8:, :3], atol=1e-9)
    assert not np.allclose(r["dee"][:8], commands[:8, :3] + [0, 0.01, 0])  # the detour is not what it labels
    assert (r["target"] == demos["rgb"][0, -1]).all() and r["rgb"].shape == (100, 32, 32, 3) and r["on_target"]
    # a controller that never moves, overruled by the expert at a step's chance of beta
    still = type("Still", (), {"reset": lambda self, target: None, "act": lambda self, rgb, joints, hand=None, truth=None: np.zeros(4)})()
    with pb.make("mujoco", S.build_scene(ep, 32)) as sim:
        assert not rollouts([sim], [ep], [still], [demos["rgb"][0, -1]], 100)[0]["on_target"]
        alone = rollouts([sim], [ep], [still], [demos["rgb"][0, -1]], 100, beta=0.95, rngs=[np.random.default_rng(0)])[0]
        assert alone["on_target"]
    # controllers that all diverge end their rollouts (None each), not the round
    nan = type("Nan", (), {"reset": lambda self, target: None, "act": lambda self, *a, **k: np.full(4, np.nan)})()
    with pb.make("mujoco", S.build_scene(ep, 32)) as a, pb.make("mujoco", S.build_scene(ep, 32)) as b:
        assert rollouts([a, b], [ep, ep], [nan, nan], [demos["rgb"][0, -1]] * 2, 5) == [None, None]
        # beside one that diverges, a rollout draws its own coins and ends as it does alone
        gone, kept = rollouts([a, b], [ep, ep], [nan, still], [demos["rgb"][0, -1]] * 2, 100, beta=0.95,
                              rngs=[np.random.default_rng(1), np.random.default_rng(0)])
        assert gone is None and all(np.array_equal(kept[k], alone[k]) for k in ("dee", "grip", "obj", "on_target"))


def test_dagger_rounds_join_the_training_data_and_are_reloaded_on_resume(tiny_pipeline, tmp_path):
    from physint_plugins.geeco.dagger import Aggregation
    from physint_plugins.geeco.checkpoint import load_controller
    from physint_plugins.geeco.train import Chunks, load_split

    out, _ = tiny_pipeline
    run = tmp_path / "dagger"
    code, stdout, err = call("train", "geeco", "--preset", "tiny", "--data", str(out / "dataset"), "--set",
                             "train.dagger_epochs=2", "--set", "train.dagger_episodes=3", "--out", str(run), "--json")
    assert code == 0, err
    (stats,) = json.loads(stdout)["metrics"]["dagger"]
    assert (stats["epoch"], stats["rollouts"], stats["train_demos"]) == (2, 3, 11) and 0 <= stats["on_target"] <= 1
    saved = np.load(run / "dagger" / "epoch-002.npz")
    assert saved["rgb"].shape == (3, 100, 32, 32, 3) and np.abs(saved["dee"]).max() <= SPEED + 1e-6
    # a training resumed after the round reloads it instead of rolling out again
    ctx = type("Ctx", (), {"seed": 0, "scene": "goal2cube2", "make_sim": None})()
    demos = load_split(out / "dataset", "train")
    chunks = Chunks(demos, 8)
    aggregation = Aggregation(ctx, run, chunks, demos, [2], 3, 100, log=lambda _: None)
    assert saved["on_target"].shape == (3,)
    aggregation(1, load_controller(run)[0])  # make_sim None: rolling out would fail
    assert chunks.demos == 11 and len(chunks) == 11 * 12
    assert (chunks[8 * 12]["target"].numpy() == saved["target"][0]).all()  # rollouts keep their own targets


def test_dagger_needs_the_push_expert():
    from physint_cli.errors import BadInput
    from physint_plugins.geeco.dagger import parse_epochs

    assert parse_epochs("8, 6,10", 12, "push") == [6, 8, 10] and parse_epochs("", 12, "pickplace") == []
    with pytest.raises(BadInput, match="pick-and-place expert is a plan"):
        parse_epochs("6", 12, "pickplace")


@pytest.mark.parametrize("setting", ["train.dee_bins=11", "train.dee_modes=6"])
def test_a_controller_with_classified_commands_trains_evaluates_and_keeps_its_head(tiny_pipeline, tmp_path, setting):
    from physint_plugins.geeco.control import DEE_SCALE
    from physint_plugins.geeco.model import command_modes
    from physint_plugins.geeco.checkpoint import load_controller
    from physint_plugins.geeco.train import load_split

    out, _ = tiny_pipeline
    run = tmp_path / "classified"
    code, _, err = call("train", "geeco", "--preset", "tiny", "--data", str(out / "dataset"),
                        "--set", setting, "--out", str(run))
    assert code == 0, err
    model, _ = load_controller(run)
    if setting == "train.dee_bins=11":
        assert model.dee_bins == 11 and model.heads["dee"].out_features == 33
    else:  # the centres are the training commands' k-means, saved with the weights
        assert model.dee_modes == 6 and model.heads["dee"].out_features == 24
        commands = load_split(out / "dataset", "train")["dee"] / DEE_SCALE
        assert np.allclose(model.dee_centres.numpy(), command_modes(commands, 6, seed=0), atol=1e-6)
    code, stdout, err = call("eval", "geeco", "--run", str(run), "--out", str(tmp_path / "eval"), "--json")
    assert code == 0, err
    assert json.loads(stdout)["metrics"]["episodes"] == 2
    # with bins or modes, train.command=auto gives the network's u_dEE: no command head to feed true positions
    code, _, err = call("eval", "geeco", "--run", str(run), "--set", "eval.positions=true", "--out",
                        str(tmp_path / "bad"))
    assert code == 2 and "not trained with train.command=positions" in err, err


def goal_demos(root, split):
    """A split of the tiny push demonstrations with each one's target position ``goal`` (x, y)."""
    from physint_plugins.geeco.train import add_goals, load_split

    return add_goals(load_split(root, split), "goal2cube2", "push")


def test_the_small_presets_push_controller_is_commanded_from_positions_and_trained_with_dagger(tiny_pipeline, tmp_path):
    """``train.command=auto`` and ``train.dagger_epochs=auto`` (the tiny and small presets): the
    pipeline's push controller takes u_dEE from positions and trains with a DAgger round before its
    last epoch; the rollouts carry their targets' positions, and the command head the controller
    keeps is the one its first stage chose (the network's training leaves it alone)."""
    from torch.nn import functional as F

    from physint_plugins.geeco.checkpoint import load_controller
    from physint_plugins.geeco.train import Chunks

    out, result = tiny_pipeline
    run, metrics = out / "train", result["train"]["metrics"]
    assert metrics["command"] == "positions" and metrics["dagger_epochs"] == [2] and len(metrics["dagger"]) == 1
    model, meta = load_controller(run)
    assert model.command == "positions" and meta["kwargs"]["command"] == "positions"
    assert model.heads["goal"].out_features == 2 and model.command_head[0].in_features == 4 * 6 + 2
    inputs, dee = Chunks(goal_demos(out / "dataset", "val"), 8).position_windows()
    with torch.no_grad():
        kept = float(F.mse_loss(model.command_from_positions(*inputs), dee))
    assert kept == pytest.approx(metrics["command_head"]["val_mse"], rel=1e-5)
    rollouts = np.load(run / "dagger" / "epoch-002.npz")
    demos = goal_demos(out / "dataset", "train")
    assert len(rollouts["goal"]) == 2  # the tiny preset's train.dagger_episodes
    for goal, start in zip(rollouts["goal"], rollouts["obj"][:, 0]):  # a rollout starts from a training start
        i = int(np.argmin(np.linalg.norm(demos["obj"][:, 0] - start, axis=1)))  # state: its goal is that one's
        assert np.allclose(goal, demos["goal"][i]) and np.allclose(start, demos["obj"][i, 0], atol=1e-3)
    # the command head with the simulator's positions instead of the network's estimates
    code, stdout, err = call("eval", "geeco", "--run", str(run), "--set", "eval.positions=true",
                             "--out", str(tmp_path / "eval-true"), "--json")
    assert code == 0, err
    assert json.loads(stdout)["metrics"]["positions"] == "true"
    code, _, err = call("eval", "geeco", "--run", str(run), "--set", "eval.positions=guessed", "--out",
                        str(tmp_path / "bad"))
    assert code == 2 and "eval.positions: 'guessed' is not one of seen, true" in err, err


@pytest.mark.parametrize("skill, command, epochs, rounds", [
    ("push", "positions", 12, [6, 8, 10]), ("push", "positions", 2, [2]), ("push", "positions", 1, []),
    ("push", "network", 12, []), ("pickplace", "network", 12, [])])
def test_automatic_dagger_rounds_are_for_positions_controllers_of_pushing(skill, command, epochs, rounds):
    from physint_plugins.geeco.dagger import parse_epochs
    from physint_plugins.geeco.train import resolve_command

    assert parse_epochs("auto", epochs, skill, command) == rounds
    assert resolve_command("auto", skill) == ("positions" if skill == "push" else "network")
    assert resolve_command(command, skill) == command
    assert resolve_command("auto", skill, aux_weight=0.0) == "network"  # lambda = 0: no positions learned


def test_a_positions_controller_without_position_supervision_is_refused(tiny_pipeline, tmp_path):
    out, _ = tiny_pipeline
    code, _, err = call("train", "geeco", "--preset", "tiny", "--data", str(out / "dataset"), "--set",
                        "train.command=positions", "--set", "train.aux_weight=0", "--out", str(tmp_path / "run"))
    assert code == 2 and "train.aux_weight=0 leaves unlearned" in err and len(err.strip().splitlines()) == 1, err


def test_the_paper_preset_keeps_the_thesiss_end_to_end_command():
    from physint_plugins.geeco.config import PRESETS

    assert PRESETS["paper"]["train.command"] == "network" and PRESETS["paper"]["train.dagger_epochs"] == ""


def test_the_command_head_learns_the_experts_commands_from_true_positions(tiny_pipeline):
    """Trained on the tiny demonstrations' positions alone (hand, cube over the buffer, pad), the
    command head of ``command="positions"`` answers the expert's commands on those windows far better
    than their mean does (8 demonstrations are too few to generalise from; docs/geeco.md has the
    held-out figures); then it is frozen for the network's training."""
    from torch.nn import functional as F

    from physint_cli.training import seed_everything
    from physint_plugins.geeco.model import Geeco
    from physint_plugins.geeco.train import Chunks, fit_command_head

    out, _ = tiny_pipeline
    demos = Chunks(goal_demos(out / "dataset", "train"), 8)
    seed_everything(0)  # the head's initial weights
    model = Geeco("e2evmc", image_size=32, width=0.25, command="positions")
    stats = fit_command_head(model, demos, demos, epochs=40, seed=0, log=lambda _: None, batch_size=64)
    inputs, dee = demos.position_windows()
    assert inputs[0].shape == (8 * 100, 4, 3) and inputs[2].shape == (8 * 100, 2) and dee.shape == (8 * 100, 3)
    with torch.no_grad():
        mse = float(F.mse_loss(model.command_from_positions(*inputs), dee))
    assert mse == pytest.approx(stats["val_mse"], rel=1e-5)
    assert mse < 0.5 * stats["val_mse_of_the_mean_command"], stats
    assert not any(p.requires_grad for p in model.command_head.parameters())
