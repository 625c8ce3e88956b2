"""toolsynth through the CLI: dataset -> train (three stages) -> imagination against its
baselines -> deployment, on two backends, and the bad input a user meets."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from conftest import call

from physint_plugins.toolsynth import scenes as S
from physint_plugins.toolsynth.checkpoint import load_models
from physint_plugins.toolsynth.imagine import imagine
from physint_plugins.toolsynth.tasks import sample_task


@pytest.fixture(scope="module", params=["mujoco", "pybullet"])
def tiny_pipeline(request, tmp_path_factory):
    out = tmp_path_factory.mktemp("toolsynth") / request.param
    code, stdout, err = call("pipeline", "toolsynth", "--preset", "tiny", "--backend", request.param,
                             "--out", str(out), "--json")
    assert code == 0, err
    return out, json.loads(stdout)


def test_pipeline_trains_three_stages_and_reports_table_4_1(tiny_pipeline):
    out, result = tiny_pipeline
    tr = result["train"]["metrics"]
    assert tr["epochs"] == {"recon": 2, "task-driven": 2, "task-unaware": 2} and tr["train_types"] == "ABCD"
    for stage in ("1-reconstruction", "2-task-driven", "3-task-unaware"):
        assert (out / "train" / "stages" / stage / "checkpoints" / "best.pt").is_file()
    driven, _, meta = load_models(out / "train")
    for which in ("driven", "unaware"):  # the box imagination stays in (eval.latent_box)
        low, high = (np.array(b) for b in meta["latent_box"][which])
        assert low.shape == high.shape == (driven.kwargs["z_tool"],) and (low < high).all()
    ev = result["eval"]["metrics"]
    assert ev["latent_box"] is True
    assert set(ev["imagination"]) == {"task-driven", "task-unaware", "random walk", "no-op"}
    for name, r in ev["imagination"].items():
        assert set(r["success"]) == {"A", "B", "C", "D", "E", "total"} and r["success"]["total"]["n"] == 20
        assert 0 <= r["success"]["total"]["rate"] <= 1 and r["success"]["total"]["ci95"] >= 0
    for title in ("task-driven", "task-unaware"):
        test = ev["test"][title]
        assert 0 <= test["accuracy"] <= 1 and 0 <= test["iou"] <= 1 and 0 <= test["footprint_iou"] <= 1
        assert 0 <= test["reconstruction_keeps_label"] <= 1 and set(test["reconstruction_keeps_label_per_type"]) <= set("ABCDE")
    noop = ev["imagination"]["no-op"]
    assert noop["p_end"] == pytest.approx(noop["p_start"])  # the control does not move
    assert ev["imagination"]["task-driven"]["p_end"] > ev["imagination"]["random walk"]["p_end"]
    table = (out / "eval" / "artifacts" / "table_4_1.md").read_text()
    assert "(83.8)" in table and "no-op" in table
    de = result["deploy"]["metrics"]
    assert de["task"]["type"] == "D" and not de["start_feasible"] and de["p_end"] >= de["p_start"]
    for name in ("task.png", "strip.png", "imagination.mp4", "imagined.obj", "imagined.stl", "deploy.rrd"):
        assert (out / "deploy" / "artifacts" / name).stat().st_size > 0, name


def test_descent_raises_p_success_where_the_random_walk_does_not(tiny_pipeline):
    out, _ = tiny_pipeline
    driven, _, _ = load_models(out / "train")
    torch.manual_seed(0)
    z_task, z0 = torch.randn(16, driven.kwargs["z_task"]), torch.randn(16, driven.kwargs["z_tool"])
    walk = imagine(driven, z_task, z0, "random", step=0.05, max_steps=200, threshold=0.999)
    for optimizer in ("adam", "sgd"):
        descent = imagine(driven, z_task, z0, "descent", step=0.05, max_steps=200, threshold=0.999,
                          optimizer=optimizer)
        assert (descent.p_end >= descent.p_start - 1e-6).all() and descent.p_end.mean() > walk.p_end.mean()
        assert (descent.steps <= 200).all() and ((descent.p_end >= 0.999) == descent.reached).all()


def test_task_image_reads_back_into_its_task():
    from physint_backends.spec import Scene
    from physint_cli.plugins import get_plugins

    task = sample_task("E", np.random.default_rng(3))
    sim = get_plugins().backend("mujoco").make(Scene(bodies=S.task_bodies(task), cameras=[S.task_camera(128)],
                                                     ground=None, background=S.BACKGROUND))
    try:
        image = sim.render("task").rgb
    finally:
        sim.close()
    back = S.task_from_image(image)
    pixel = 2 * 0.3 / 128
    assert np.allclose(back.target, task.target, atol=1.5 * pixel) and len(back.obstacles) == len(task.obstacles)
    for got, want in zip(sorted(back.obstacles), sorted(task.obstacles)):
        assert np.allclose(got, want, atol=2.5 * pixel)


def test_bad_input_exits_2_with_one_line(tiny_pipeline, tmp_path):
    out, _ = tiny_pipeline
    not_image = tmp_path / "task.png"
    not_image.write_text("not an image")
    from PIL import Image

    wrong_size = tmp_path / "big.png"
    Image.fromarray(np.zeros((40, 40, 3), np.uint8)).save(wrong_size)
    blank = tmp_path / "blank.png"
    Image.fromarray(np.full((32, 32, 3), 255, np.uint8)).save(blank)
    cases = [(("deploy", "toolsynth", "--run", str(out / "train"), "--target", str(not_image)), "not an image"),
             (("deploy", "toolsynth", "--run", str(out / "train"), "--target", str(wrong_size)), "32x32"),
             (("deploy", "toolsynth", "--run", str(out / "train"), "--target", str(blank)), "no green target"),
             (("deploy", "toolsynth", "--run", str(out / "train"), "--set", f"deploy.tool={not_image}"), "not a mesh"),
             (("eval", "toolsynth", "--run", str(out / "train"), "--set", "eval.types=AZ"), "unknown scenario type Z"),
             (("train", "toolsynth", "--data", str(out / "train")), "no dataset")]
    for args, words in cases:
        code, _, err = call(*args, "--out", str(tmp_path / f"run{len(words)}"))
        assert code == 2 and words in err and len(err.strip().splitlines()) == 1, (args, err)


def test_deploy_imagines_from_a_tool_mesh_file_and_writes_its_mesh(tiny_pipeline, tmp_path):
    import trimesh

    from physint_plugins.toolsynth.tools import Tool, export_mesh

    out, _ = tiny_pipeline
    path = export_mesh(Tool("stick", 0.12, 0.03).mesh(), tmp_path / "short.stl")
    code, stdout, err = call("deploy", "toolsynth", "--run", str(out / "train"), "--set", f"deploy.tool={path}",
                             "--set", "deploy.video=false", "--out", str(tmp_path / "dep"), "--json")
    assert code == 0, err
    result = json.loads(stdout)["metrics"]
    assert result["start_tool"] == "the mesh short.stl" and not result["start_feasible"]
    mesh = trimesh.load(tmp_path / "dep" / "artifacts" / "imagined.obj", force="mesh")
    assert len(mesh.faces) == 80 and np.abs(mesh.vertices).max() <= 0.3 + 1e-6  # tiny: 1 subdivision
