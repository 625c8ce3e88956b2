"""The stability method through the CLI: dataset, train, eval, deploy with the tiny preset."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import call

from physint_cli.datasets import ShardedDataset


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("stability") / "ds"
    code, stdout, err = call("dataset", "stability", "--preset", "tiny", "--scene", "all", "--out", str(out), "--json")
    assert code == 0, err
    return out, json.loads(stdout)


def test_dataset_is_balanced_labelled_and_agrees_with_simulation(tiny_dataset):
    out, result = tiny_dataset
    stats = result["stats"]
    assert stats["scenarios"] == 48 and stats["agreement_rate"] >= 0.9
    assert stats["kept_stable"] + stats["kept_VCOM"] + stats["kept_VPSF"] == 48
    assert abs(stats["kept_stable"] - 24) <= 2  # equal stable and unstable (per height, Table 3.1)
    assert stats["scenarios_per_cpu_second"] > 0
    ds = ShardedDataset(out, "train")
    labels, violations = ds.column("label"), ds.column("violation")
    assert set(labels.tolist()) == {0, 1}
    assert ((violations > 0) == (labels == 1)).all()  # unstable <=> a VCOM (1) or VPSF (2) violation
    for i in range(0, len(ds), 7):
        r = ds[i]
        seg, h = r["segmentation"], int(r["height"])
        assert r["image"].shape == (32, 32, 3) and seg.shape == (32, 32)
        assert set(np.unique(seg).tolist()) <= set(range(-1, h))  # background or one of the h objects
        if r["label"] == 1:
            assert 0 <= r["violating"] < h and 0 <= r["first_to_fall"] < h
        else:
            assert r["violating"] == -1 and r["first_to_fall"] == -1


def test_train_eval_deploy_tiny(tiny_dataset, tmp_path):
    out, _ = tiny_dataset
    code, stdout, err = call("train", "stability", "--preset", "tiny", "--scene", "all", "--data", str(out),
                             "--out", str(tmp_path / "run"), "--json")
    assert code == 0, err
    code, stdout, err = call("eval", "stability", "--run", str(tmp_path / "run"), "--set", "eval.cross_backend=pybullet",
                             "--json")
    assert code == 0, err
    metrics = json.loads(stdout)["metrics"]
    assert metrics["cross_backend"]["pybullet"]["images"] > 0  # trained on MuJoCo renders, tested on PyBullet's
    # only the test split of PyBullet's all-shapes dataset was made, the very shards the whole one holds
    other = json.loads((Path(metrics["cross_backend"]["pybullet"]["test_data"]) / "manifest.json").read_text())
    assert set(other["splits"]) == {"test"} and other["only_splits"] == ["test"]
    whole = json.loads((out / "manifest.json").read_text())
    assert [s["file"] for s in other["shards"]] == [s["file"] for s in whole["shards"] if s["split"] == "test"]
    assert metrics["images"] > 0 and 0 <= metrics["accuracy"] <= 1
    assert set(metrics["by_violation"]) == {"stable", "VCOM", "VPSF"}
    table = metrics["localisation"]
    chance = table["random_in_image"]
    assert chance["background"] > chance["violating_object"] > 0  # the tower is a small part of the image
    assert chance["violation_area"] >= chance["violating_object"]
    assert table["images"] == 4
    run = Path(json.loads(stdout)["run"])
    assert (run / "artifacts" / "accuracy.png").exists() and (run / "artifacts" / "occlusion_example.png").exists()
    assert (run / "artifacts" / "predictions.png").exists()  # P(falls) on rendered test towers
    code, stdout, err = call("deploy", "stability", "--run", str(tmp_path / "run"), "--task", "balance", "--json")
    assert code == 0, err
    deployed = json.loads(stdout)
    assert (Path(deployed["run"]) / "artifacts" / "balance_success.png").exists()
    code, stdout, err = call("deploy", "stability", "--run", str(tmp_path / "run"), "--task", "juggle")
    assert code == 2 and "stackability" in err
    code, stdout, err = call("train", "stability", "--preset", "tiny", "--data", str(out), "--model", "nope")
    assert code == 2 and "unknown model" in err
    code, _, err = call("deploy", "stability", "--run", str(tmp_path / "run"), "--task", "stack", "--set", "deploy.pool=0")
    assert code == 2 and "deploy.pool" in err  # an empty object pool
    code, _, err = call("deploy", "stability", "--run", str(tmp_path / "run"), "--task", "stackability", "--set",
                        "deploy.stackability_pool=1")
    assert code == 2 and "deploy.stackability_pool" in err
    code, _, err = call("deploy", "stability", "--run", str(tmp_path / "run"), "--set", "deploy.agents=oracle,robot")
    assert code == 2 and "robot" in err and "predictor" in err


def _stable_only_dataset(root: Path) -> Path:
    """A stability-shaped dataset whose train split holds stable stacks only."""
    from physint_cli.datasets import finish_manifest, start_manifest, write_shard

    manifest = start_manifest(root, {"method": "stability", "scene": "ccs", "backend": "mujoco", "preset": "tiny",
                                     "seed": 0, "config": {}})
    rng = np.random.default_rng(0)
    shards = [write_shard(root, f"{split}-00000", split, {"image": rng.integers(0, 256, (6, 32, 32, 3), dtype=np.uint8),
                                                          "label": np.zeros(6, np.int64)})
              for split in ("train", "val", "test")]
    finish_manifest(root, manifest, shards, {}, 0.0)
    return root


def test_bad_input_exits_2_with_one_clear_line(tiny_dataset, tmp_path):
    out, _ = tiny_dataset
    stable_only = _stable_only_dataset(tmp_path / "stable-only")
    code, _, err = call("train", "stability", "--preset", "tiny", "--data", str(stable_only))
    assert code == 2 and "no unstable images" in err and "Traceback" not in err
    code, _, err = call("train", "stability", "--preset", "tiny", "--data", str(out), "--set", "train.input_size=8")
    assert code == 2 and "cannot be built with train.input_size=8" in err and "16x16" in err
    code, _, err = call("train", "stability", "--preset", "tiny", "--data", str(out), "--model", "alexnet")
    assert code == 2 and "alexnet" in err and "63x63" in err  # tiny images are 32 px
    code, _, err = call("train", "freefall", "--preset", "tiny", "--data", str(out))
    assert code == 2 and "made for method 'stability'" in err


def test_tiny_pipeline_on_robosuite(tmp_path, monkeypatch):
    """``physint pipeline stability --preset tiny``: dataset, train, eval and deploy, on robosuite's simulator."""
    monkeypatch.setenv("PHYSINT_HOME", str(tmp_path))
    code, stdout, err = call("pipeline", "stability", "--preset", "tiny", "--backend", "robosuite", "--json")
    assert code == 0, err
    result = json.loads(stdout)
    text = json.dumps(result)
    assert '"backend": "robosuite"' in text
    assert "agreement_rate" in text and "accuracy" in text and "violation_area" in text


def test_oracle_and_random_deploy_without_a_trained_run():
    """The Lemma-1 oracle and random placement need no predictor: deploy runs with no train run anywhere,
    and asking for the predictor then says to pass --run."""
    code, stdout, err = call("deploy", "stability", "--preset", "tiny", "--task", "balance", "--set",
                             "deploy.agents=oracle,random", "--json")
    assert code == 0, err
    deployed = json.loads(stdout)
    assert deployed["source_run"] is None
    assert set(deployed["metrics"]["success_rate"]) >= {"oracle", "random"}
    assert "predictor" not in deployed["metrics"]["success_rate"]
    code, _, err = call("deploy", "stability", "--preset", "tiny", "--task", "balance", "--set", "deploy.agents=predictor")
    assert code == 2 and "--run" in err and "Traceback" not in err
    code, _, err = call("eval", "stability", "--preset", "tiny")
    assert code == 2 and "no trained stability run" in err


def test_the_paper_preset_trains_inception_v4_with_rmsprop_at_224_px_and_evaluates(tmp_path):
    """The thesis's configuration (Inception-v4, 224 px, RMSProp) end to end at toy scale on a CPU:
    the GPU preset is the same code, so a broken key or shape shows here, not on a lent GPU."""
    import torch

    toy = ["--preset", "paper", "--set", "data.scenarios=24", "--set", "data.per_shard=24", "--set", "data.cameras=1"]
    code, _, err = call("dataset", "stability", *toy, "--out", str(tmp_path / "ds"))
    assert code == 0, err
    code, stdout, err = call("train", "stability", "--preset", "paper", "--data", str(tmp_path / "ds"),
                             "--set", "train.epochs=1", "--set", "train.num_workers=0", "--set", "train.batch_size=4",
                             "--out", str(tmp_path / "run"), "--json")
    assert code == 0, err
    assert json.loads(stdout)["metrics"]["model"] == "inception-v4"
    state = torch.load(tmp_path / "run" / "checkpoints" / "best.pt", weights_only=False)
    assert state["meta"]["model"] == "inception-v4"
    assert "square_avg" in next(iter(state["optimizer"]["state"].values()))  # RMSProp's running average
    assert ShardedDataset(tmp_path / "ds", "train")[0]["image"].shape == (224, 224, 3)
    code, stdout, err = call("eval", "stability", "--run", str(tmp_path / "run"), *toy,
                             "--set", "eval.occlusion_images=0", "--json")  # occlusion: 3 min an image on a CPU
    assert code == 0, err
    metrics = json.loads(stdout)["metrics"]
    assert metrics["images"] > 0 and 0 <= metrics["accuracy"] <= 1
