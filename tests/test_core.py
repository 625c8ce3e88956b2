"""The core: configs, datasets, runs, the CLI's verbs and its bad-input handling (no simulator)."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import h5py
import numpy as np
import pytest
from conftest import call

from physint_cli import config as configs
from physint_cli.datasets import ShardedDataset, verify
from physint_cli.errors import BadInput


def j(out: str) -> dict:
    lines = [line for line in out.splitlines() if line.strip()]
    assert len(lines) == 1, f"expected exactly one JSON line on stdout, got {out!r}"
    return json.loads(lines[0])


# -- configs --------------------------------------------------------------------------------------

def test_config_presets_files_and_sets(toy_plugins, tmp_path):
    from toy_plugin import Toy

    cfg = configs.resolve(Toy.config_class, Toy.presets, "tiny")
    assert cfg.data.train == 32 and cfg.train.lr == 0.05
    f = tmp_path / "c.yaml"
    f.write_text("train:\n  lr: 0.5\ndata:\n  val: 4\n")
    cfg = configs.resolve(Toy.config_class, Toy.presets, "paper", f, ["train.lr=1e-3", "data.test=7"])
    assert (cfg.data.train, cfg.data.val, cfg.data.test, cfg.train.lr) == (1000, 4, 7, 1e-3)
    # a trained run's saved config read for a downstream verb: its sections named there are skipped
    cfg = configs.resolve(Toy.config_class, Toy.presets, "tiny", f, [], skip_file_sections=("train",))
    assert (cfg.data.val, cfg.train.lr) == (4, 0.05)
    with pytest.raises(BadInput, match="unknown key 'train.learning_rate'.*valid keys: data.train"):
        configs.resolve(Toy.config_class, Toy.presets, "tiny", None, ["train.learning_rate=1"])
    with pytest.raises(BadInput, match="train.epochs: expected int, got 'many'"):
        configs.resolve(Toy.config_class, Toy.presets, "tiny", None, ["train.epochs=many"])
    with pytest.raises(BadInput, match="unknown preset 'huge'"):
        configs.resolve(Toy.config_class, Toy.presets, "huge")


def test_help_config_lists_keys_types_and_values(toy_plugins):
    code, out, _ = call("train", "toy", "--preset", "tiny", "--help-config")
    assert code == 0
    assert "data.train" in out and "int" in out and "32" in out and "training samples" in out


# -- datasets -------------------------------------------------------------------------------------

def test_dataset_generate_read_and_verify(toy_plugins, tmp_path):
    out = tmp_path / "ds"
    code, stdout, err = call("dataset", "toy", "--preset", "tiny", "--out", str(out), "--json")
    assert code == 0, err
    result = j(stdout)
    assert result["splits"] == {"train": 32, "val": 16, "test": 16}
    manifest = json.loads((out / "manifest.json").read_text())
    for key in ("method", "scene", "backend", "preset", "seed", "config", "schema", "splits", "versions", "created", "shards"):
        assert key in manifest, key
    assert manifest["status"] == "complete" and manifest["schema"]["image"] == {"dtype": "uint8", "shape": [8, 8, 3]}
    ds = ShardedDataset(out, "train")
    assert len(ds) == 32
    rec = ds[31]
    assert rec["image"].shape == (8, 8, 3) and rec["y"] == pytest.approx(2 * rec["x"] + 1, abs=0.1)
    with h5py.File(out / "shards" / "train-00000.h5") as f:  # images are chunked and compressed
        assert f["image"].compression == "gzip" and f["image"].chunks == (1, 8, 8, 3)
    assert verify(out) == []
    # read into memory once: the same records, in the same order, and no file left open
    mem = ShardedDataset(out, "train", ["image", "y"], in_memory="auto")
    assert mem.arrays is not None and mem.nbytes == 32 * (8 * 8 * 3 + mem.arrays["y"].itemsize) and not mem._files
    for i in (0, 17, 31, -1):
        assert np.array_equal(mem[i]["image"], ds[i]["image"]) and mem[i]["y"] == ds[i]["y"]
    assert np.array_equal(mem.column("y"), ds.column("y"))
    with pytest.raises(IndexError):
        mem[32]
    assert ShardedDataset(out, "train", in_memory=False).arrays is None
    with pytest.MonkeyPatch.context() as mp:  # a split larger than the limit is streamed
        mp.setattr("physint_cli.datasets.IN_MEMORY_LIMIT", mem.nbytes - 1)
        assert ShardedDataset(out, "train", ["image", "y"], in_memory="auto").arrays is None
    # same seed and config -> same data
    call("dataset", "toy", "--preset", "tiny", "--out", str(tmp_path / "ds2"))
    assert np.array_equal(ShardedDataset(tmp_path / "ds2", "test").column("x"), ShardedDataset(out, "test").column("x"))


def test_verify_names_corrupted_and_truncated_shards(toy_plugins, tmp_path):
    out = tmp_path / "ds"
    assert call("dataset", "toy", "--preset", "tiny", "--out", str(out))[0] == 0
    shard = out / "shards" / "train-00001.h5"
    data = bytearray(shard.read_bytes())
    data[len(data) // 2] ^= 0xFF
    shard.write_bytes(bytes(data))
    short = out / "shards" / "val-00000.h5"
    short.write_bytes(short.read_bytes()[:100])
    code, stdout, err = call("dataset", "--verify", str(out), "--json")
    assert code == 1
    problems = j(stdout)["problems"]
    assert any("train-00001.h5" in p and "checksum" in p for p in problems)
    assert any("val-00000.h5" in p and "truncated" in p for p in problems)
    assert len(problems) == 2


def test_interrupted_generation_resumes_without_redoing_shards(toy_plugins, tmp_path, monkeypatch):
    from toy_plugin import Toy

    out = tmp_path / "ds"
    calls = {"n": 0}
    original = Toy.generate

    def flaky(self, ctx, unit):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt  # Ctrl-C while the third shard is being made
        return original(self, ctx, unit)

    monkeypatch.setattr(Toy, "generate", flaky)
    code, _, err = call("dataset", "toy", "--preset", "tiny", "--out", str(out))
    assert code == 130 and "rerun the same command to resume" in err
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["status"] == "incomplete"
    done = sorted(p.name for p in (out / "shards").glob("*.h5"))
    assert done == ["train-00000.h5", "train-00001.h5"]
    assert not list((out / "shards").glob(".*tmp*"))  # nothing half-written left behind
    mtimes = {p: p.stat().st_mtime_ns for p in (out / "shards").glob("*.h5")}
    code, _, err = call("train", "toy", "--data", str(out))  # an incomplete dataset is refused
    assert code == 2 and "incomplete" in err
    monkeypatch.setattr(Toy, "generate", original)
    calls["n"] = 0
    code, _, err = call("dataset", "toy", "--preset", "tiny", "--out", str(out))
    assert code == 0, err
    assert "resuming: 2 of 4 shards already done" in err
    for p, t in mtimes.items():
        assert p.stat().st_mtime_ns == t  # finished shards were not redone
    assert verify(out) == []


def test_parallel_workers_give_the_same_dataset(toy_plugins, tmp_path):
    assert call("dataset", "toy", "--preset", "tiny", "--out", str(tmp_path / "a"))[0] == 0
    code, _, err = call("dataset", "toy", "--preset", "tiny", "--out", str(tmp_path / "b"), "--workers", "2")
    assert code == 0, err
    for split in ("train", "val", "test"):
        a, b = ShardedDataset(tmp_path / "a", split), ShardedDataset(tmp_path / "b", split)
        assert np.array_equal(a.column("y"), b.column("y"))


def test_machine_names_the_cpu_its_vector_extensions_and_any_isa_cap(monkeypatch):
    """The provenance each run and dataset records: an AVX2-only CPU reads as such, and a newer one
    held to AVX2 through torch's and oneDNN's variables says so."""
    from physint_cli.datasets import describe_machine, machine

    zen3 = "processor\t: 0\nmodel name\t: AMD EPYC 7B13\nflags\t\t: fpu sse2 avx avx2 fma\n\nprocessor\t: 1\n"
    monkeypatch.delenv("ATEN_CPU_CAPABILITY", raising=False)
    monkeypatch.delenv("ONEDNN_MAX_CPU_ISA", raising=False)
    m = machine(zen3)
    assert m["cpu"] == "AMD EPYC 7B13" and m["isa"] == ["AVX2"] and m["held_to"] == {}
    assert describe_machine(m).endswith("cores, AVX2")
    xeon = "model name\t: Intel Xeon\nflags\t\t: avx2 avx512f avx512_bf16 amx_tile\n"
    monkeypatch.setenv("ATEN_CPU_CAPABILITY", "avx2")
    m = machine(xeon)
    assert m["isa"] == ["AVX2", "AVX-512", "AVX512-BF16", "AMX"]
    assert m["held_to"] == {"ATEN_CPU_CAPABILITY": "avx2"}
    assert "(held to ATEN_CPU_CAPABILITY=avx2)" in describe_machine(m)
    assert machine("")["isa"] == [] and "no AVX2" in describe_machine(machine(""))


# -- train / eval / deploy -------------------------------------------------------------------------

def test_train_caches_dataset_resumes_and_evaluates(toy_plugins, physint_home):
    code, out, err = call("train", "toy", "--preset", "tiny", "--set", "train.epochs=3", "--json")
    assert code == 0, err
    first = j(out)
    run = Path(first["run"])
    for name in ("run.json", "config.yaml", "metrics.json", "metrics.jsonl", "checkpoints/last.pt", "checkpoints/best.pt"):
        assert (run / name).exists(), name
    info = json.loads((run / "run.json").read_text())
    for key in ("command", "versions", "machine", "seed", "git_commit", "data", "preset"):
        assert key in info
    assert info["machine"]["cores"] == os.cpu_count()
    assert len((run / "metrics.jsonl").read_text().splitlines()) == 3
    # the dataset was generated once, under the home, and is reused
    cached = list((physint_home / "datasets").iterdir())
    assert len(cached) == 1 and Path(first["data"]) == cached[0].resolve()
    code, out, err = call("train", "toy", "--preset", "tiny", "--set", "train.epochs=3", "--out", str(physint_home / "r2"))
    assert code == 0 and "generating" not in err
    # resume the first run to 60 epochs: continues at epoch 4
    code, out, err = call("train", "toy", "--resume", "--run", str(run), "--set", "train.epochs=60", "--json")
    assert code == 0, err
    assert "resumed from" in err and "at epoch 3" in err
    assert len((run / "metrics.jsonl").read_text().splitlines()) == 60
    assert j(out)["metrics"]["val_mse"] < 0.1  # learned y = 2x + 1 (predicting the mean scores ~1.3)
    code, out, err = call("eval", "toy", "--run", str(run), "--json")
    assert code == 0, err
    ev = j(out)
    assert ev["metrics"]["n"] == 8 and ev["source_run"] == str(run.resolve())
    code, out, err = call("deploy", "toy", "--target", "hello", "--json")  # latest run by default
    assert code == 0, err
    assert j(out)["metrics"]["target"] == "hello"


def test_a_run_started_with_model_resumes_with_that_model(toy_plugins, physint_home):
    """The run records the network --model chose (config.yaml's train.model, run.json's options);
    --resume rebuilds that one, and refuses another."""
    run = physint_home / "mlp"
    code, _, err = call("train", "toy", "--preset", "tiny", "--model", "mlp", "--set", "train.epochs=2",
                        "--out", str(run))
    assert code == 0, err
    assert "model: mlp" in (run / "config.yaml").read_text()
    code, out, err = call("train", "toy", "--resume", "--run", str(run), "--set", "train.epochs=3", "--json")
    assert code == 0, err
    assert "resumed from" in err and j(out)["metrics"]["model"] == "mlp"
    code, _, err = call("train", "toy", "--resume", "--run", str(run), "--model", "linear")
    assert code == 2 and "trains model 'mlp'; --model linear cannot continue it" in err


def test_eval_units_run_in_worker_processes(toy_plugins):
    assert call("train", "toy", "--preset", "tiny", "--set", "train.epochs=1")[0] == 0
    code, out, err = call("eval", "toy", "--workers", "2", "--json")
    assert code == 0, err
    pids = j(out)["metrics"]["pids"]
    assert os.getpid() not in pids and len(pids) >= 1


# -- bad input: one line, exit 2 -------------------------------------------------------------------

@pytest.mark.parametrize("args, message", [
    (["train", "tyo"], "unknown method 'tyo' (did you mean 'toy'?)"),
    (["train", "toy", "--backend", "mujocoo"], "unknown backend 'mujocoo' (did you mean 'mujoco'?)"),
    (["train", "toy", "--backend", "robosuite"], "does not support backend 'robosuite'; supported: mujoco, pybullet"),
    (["train", "toy", "--scene", "lien"], "unknown scene 'lien' (did you mean 'line'?)"),
    (["train", "toy", "--model", "linaer"], "(did you mean 'linear'?)"),
    (["train", "toy", "--set", "train.epoch=3"], "unknown key 'train.epoch' (did you mean 'train.epochs'?); valid keys:"),
    (["train", "toy", "--set", "train.lr=fast"], "train.lr: expected float, got 'fast'"),
    (["train", "toy", "--set", "nonsense"], "--set expects key=value"),
    (["train", "toy", "--preset", "huge"], "unknown preset 'huge'"),
    (["train", "toy", "--config", "/nonexistent.yaml"], "no such file"),
    (["train", "toy", "--data", "/nonexistent"], "no dataset at /nonexistent"),
    (["eval", "toy"], "no trained toy run"),
    (["eval", "toy", "--run", "/tmp"], "not a physint run directory"),
    (["dataset", "toy", "--workers", "0"], "--workers must be >= 1"),
    (["train", "toy", "--device", "tpu"], "--device 'tpu' is not valid"),
    (["dataset", "--verify", "/nonexistent"], "no dataset at /nonexistent"),
])
def test_bad_input_exits_2_with_one_line(toy_plugins, args, message):
    code, out, err = call(*args)
    assert code == 2, err
    assert message in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert out == ""


def test_dataset_of_another_method_and_run_without_checkpoint(toy_plugins, tmp_path):
    ds = tmp_path / "ds"
    assert call("dataset", "toy", "--preset", "tiny", "--out", str(ds))[0] == 0
    manifest = json.loads((ds / "manifest.json").read_text())
    manifest["method"] = "stability"
    (ds / "manifest.json").write_text(json.dumps(manifest))
    code, _, err = call("train", "toy", "--data", str(ds))
    assert code == 2 and "made for method 'stability', not 'toy'" in err
    (ds / "manifest.json").write_text("{not json")
    code, _, err = call("train", "toy", "--data", str(ds))
    assert code == 2 and "corrupted" in err
    run = tmp_path / "run"
    run.mkdir()
    (run / "run.json").write_text(json.dumps({"method": "toy"}))
    code, _, err = call("eval", "toy", "--run", str(run))
    assert code == 2 and "has no trained model" in err


def test_unwritable_out(toy_plugins, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")  # a file where a directory should go: unwritable for root too
    code, _, err = call("dataset", "toy", "--preset", "tiny", "--out", str(blocker / "ds"))
    assert code == 2 and "cannot write there" in err


def test_runtime_failure_exits_1_without_traceback(toy_plugins, monkeypatch, tmp_path):
    from toy_plugin import Toy

    def boom(self, ctx, unit):
        raise RuntimeError("simulator exploded")

    monkeypatch.setattr(Toy, "generate", boom)
    code, _, err = call("dataset", "toy", "--out", str(tmp_path / "ds"))
    assert code == 1 and "simulator exploded" in err and "Traceback" not in err


def test_ctrl_c_during_training_keeps_the_last_checkpoint_and_resumes(toy_plugins, monkeypatch, tmp_path):
    from physint_cli.runs import Run

    original = Run.log_metrics

    def interrupt_at_epoch_3(self, step, **metrics):
        if step == 3:
            raise KeyboardInterrupt
        return original(self, step, **metrics)

    monkeypatch.setattr(Run, "log_metrics", interrupt_at_epoch_3)
    out = tmp_path / "run"
    code, _, err = call("train", "toy", "--preset", "tiny", "--set", "train.epochs=5", "--out", str(out))
    assert code == 130 and "rerun the same command to resume" in err
    assert not (out / "metrics.json").exists()  # an interrupted run never reads as finished
    assert json.loads((out / "run.json").read_text())["status"] == "running"
    assert not list((out / "checkpoints").glob(".*tmp*"))
    monkeypatch.setattr(Run, "log_metrics", original)
    code, stdout, err = call("train", "toy", "--resume", "--run", str(out), "--json")
    assert code == 0, err
    assert "at epoch 2" in err and j(stdout)["metrics"]["epochs"] == 5
    assert [json.loads(line)["step"] for line in (out / "metrics.jsonl").read_text().splitlines()] == [1, 2, 3, 4, 5]


def _stop_in_epoch_2_and_resume(monkeypatch, tmp_path, stop, resumed_at: str) -> None:
    """Train the toy 3 epochs of 8 batches straight through, and again calling ``stop()`` in the
    fifth batch of epoch 2 (the interrupt must exit 130), resume that one: the log says where it
    resumed and it ends with the very weights and losses of the run that went straight through."""
    import torch

    from physint_cli import training

    args = ["train", "toy", "--preset", "tiny", "--set", "train.epochs=3", "--set", "train.batch_size=4"]  # 8 batches
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    code, _, err = call(*args, "--out", str(whole))
    assert code == 0, err
    original, batches = training.to_device, []

    def stop_in_the_fifth_batch_of_epoch_2(batch, *rest, **kw):
        batches.append(1)
        if len(batches) == 8 + 5:
            stop()
        return original(batch, *rest, **kw)

    monkeypatch.setattr(training, "to_device", stop_in_the_fifth_batch_of_epoch_2)
    code, _, err = call(*args, "--out", str(cut))
    assert code == 130 and "rerun the same command to resume" in err
    assert not list((cut / "checkpoints").glob(".*tmp*"))
    monkeypatch.setattr(training, "to_device", original)
    code, _, err = call("train", "toy", "--resume", "--run", str(cut), "--json")
    assert code == 0, err
    assert resumed_at in err
    ran, resumed = (torch.load(r / "checkpoints" / "last.pt", weights_only=False) for r in (whole, cut))
    assert all(torch.equal(ran["model"][k], resumed["model"][k]) for k in ran["model"])
    assert [h["train_loss"] for h in ran["history"]] == [h["train_loss"] for h in resumed["history"]]


@pytest.mark.parametrize("checkpoint_seconds", [0.0, 300.0])
def test_training_stopped_mid_epoch_resumes_at_its_batch_and_ends_as_if_never_stopped(toy_plugins, monkeypatch,
                                                                                      tmp_path, checkpoint_seconds):
    """An exception in a batch (Ctrl-C raised there): fit has saved the batches before it, both when
    it saves its place every CHECKPOINT_SECONDS (here after every batch) and when the last periodic
    save is long ago (the default 5 min: it saves as it stops)."""
    from physint_cli import training

    def ctrl_c():
        raise KeyboardInterrupt

    monkeypatch.setattr(training, "CHECKPOINT_SECONDS", checkpoint_seconds)
    _stop_in_epoch_2_and_resume(monkeypatch, tmp_path, ctrl_c, "at epoch 1, 4 batches into epoch 2")


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_during_an_optimiser_step_stops_training_after_it_and_loses_nothing(toy_plugins, monkeypatch,
                                                                                     tmp_path, signum):
    """Ctrl-C or a SIGTERM (kill, a cluster's preemption) arriving mid-step lets the step finish,
    saves it and exits 130; the resumed run ends as if never stopped."""
    # Python's Ctrl-C handler, as in a terminal (a shell starting pytest in the background ignores
    # SIGINT, and training leaves an ignored signal ignored)
    outer = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        handlers = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
        _stop_in_epoch_2_and_resume(monkeypatch, tmp_path, lambda: os.kill(os.getpid(), signum),
                                    "at epoch 1, 5 batches into epoch 2")
        assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == handlers  # put back
    finally:
        signal.signal(signal.SIGINT, outer)


def test_the_seed_sets_the_initial_weights(toy_plugins, tmp_path):
    """Trainings with one --seed start from the same weights, whatever ran before in the process;
    another seed starts elsewhere."""
    import torch

    def first_weights(seed: int, name: str):
        code, _, err = call("train", "toy", "--preset", "tiny", "--set", "train.epochs=1", "--seed", str(seed),
                            "--out", str(tmp_path / name))
        assert code == 0, err
        return torch.load(tmp_path / name / "checkpoints" / "last.pt", weights_only=False)["model"]["weight"]

    a, b, c = first_weights(0, "a"), first_weights(0, "b"), first_weights(1, "c")
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_a_dying_worker_is_a_clear_failure_and_finished_shards_are_kept(toy_plugins, tmp_path):
    out = tmp_path / "ds"
    code, _, err = call("dataset", "toy", "--preset", "tiny", "--out", str(out), "--workers", "2",
                        "--set", "data.die_on_shard=1", "--set", "data.slow=0.3")
    assert code == 1 and "a worker process died" in err and "rerun the same command to resume" in err
    assert "Traceback" not in err
    code, _, err = call("dataset", "toy", "--preset", "tiny", "--out", str(out), "--workers", "2", "--set", "data.slow=0.3")
    assert code == 2 and "already holds a different dataset" in err  # the config differs: not mixed in


def test_fit_in_bf16_channels_last_with_a_batch_transform_learns(tmp_path):
    """fit's mixed precision and batched transform: a tiny conv net still learns a separable task."""
    import torch

    from physint_cli.errors import BadInput
    from physint_cli.runs import Run
    from physint_cli.training import fit, resolve_precision

    g = torch.Generator().manual_seed(0)
    images = torch.rand(96, 3, 8, 8, generator=g)
    labels = (torch.arange(96) % 2).float()
    images[labels == 1, 0] += 0.5  # class 1: a redder image

    class Records(torch.utils.data.Dataset):
        def __len__(self):
            return len(labels)

        def __getitem__(self, i):
            return {"image": images[i], "label": labels[i]}

    seen = []

    def halve_contrast(batch):  # runs once per collated training batch
        seen.append(batch["image"].shape[0])
        return {**batch, "image": 0.5 + 0.5 * (batch["image"] - 0.5)}

    net = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 3), torch.nn.ReLU(), torch.nn.AdaptiveAvgPool2d(1),
                              torch.nn.Flatten(), torch.nn.Linear(4, 1))

    def loss_fn(model, batch):
        return torch.nn.functional.binary_cross_entropy_with_logits(model(batch["image"]).float().reshape(-1),
                                                                    batch["label"])

    def accuracy(model, loader):
        hits = [((model(b["image"]).float().reshape(-1) > 0).float() == b["label"]).float() for b in loader]
        return float(torch.cat(hits).mean())

    (tmp_path / "checkpoints").mkdir()
    result = fit(net, Records(), Records(), run=Run(tmp_path), epochs=25, batch_size=32, lr=0.05,
                 loss_fn=loss_fn, metric_fn=accuracy, precision="bf16", channels_last=True,
                 batch_transform=halve_contrast, higher_is_better=True, log=lambda _: None)
    assert result.best_metric >= 0.9
    assert seen[:3] == [32, 32, 32] and len(seen) == 25 * 3
    assert resolve_precision("fp32", "cpu") == "fp32" and resolve_precision("auto", "cpu") in ("fp32", "bf16")
    with pytest.raises(BadInput, match="fp32, bf16"):
        resolve_precision("fp8", "cpu")


def test_auto_precision_is_fp32_when_torch_is_held_to_avx2_even_on_a_cpu_with_native_bf16(monkeypatch):
    import torch

    from physint_cli.training import resolve_precision

    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: True, raising=False)
    monkeypatch.setattr(torch.backends.cpu, "get_cpu_capability", lambda: "AVX512")
    assert resolve_precision("auto", "cpu") == "bf16"
    monkeypatch.setattr(torch.backends.cpu, "get_cpu_capability", lambda: "AVX2")  # ATEN_CPU_CAPABILITY=avx2
    assert resolve_precision("auto", "cpu") == "fp32"


def test_each_epoch_reports_its_wall_time_and_the_time_left_and_auto_says_why_it_fell_back_to_fp32(
        tmp_path, monkeypatch):
    import torch

    from physint_cli.runs import Run
    from physint_cli.training import fit

    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: False, raising=False)
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: False, raising=False)
    xs = torch.randn(64, 2)
    records = [{"x": x, "y": x.sum(0, keepdim=True)} for x in xs]
    net = torch.nn.Linear(2, 1)
    lines: list[str] = []
    (tmp_path / "checkpoints").mkdir()
    result = fit(net, records, records, run=Run(tmp_path), epochs=3, batch_size=16, lr=0.05,
                 loss_fn=lambda m, b: torch.nn.functional.mse_loss(m(b["x"]), b["y"]),
                 metric_fn=lambda m, loader: 0.0, precision="auto", progress=True, log=lines.append)
    assert "in fp32 (auto: this CPU, or the vector capability torch is held to, has neither AMX nor AVX512-BF16" in lines[0]
    epochs = [line for line in lines if line.startswith("epoch ")]
    assert len(epochs) == 3 and all(" s" in line.rsplit("(", 1)[1] for line in epochs)
    assert "to go)" in epochs[0] and "to go" not in epochs[-1]  # nothing left after the last epoch
    assert all(point["seconds"] >= 0 for point in result.history)
    points = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [p["epoch"] for p in points] == [1, 2, 3] and all("seconds" in p for p in points)
    lines.clear()
    (tmp_path / "fp32" / "checkpoints").mkdir(parents=True)
    fit(torch.nn.Linear(2, 1), records, records, run=Run(tmp_path / "fp32"), epochs=1, batch_size=16, lr=0.05,
        loss_fn=lambda m, b: torch.nn.functional.mse_loss(m(b["x"]), b["y"]),
        metric_fn=lambda m, loader: 0.0, precision="fp32", log=lines.append)
    assert lines[0] == "training on cpu in fp32"  # asked for: nothing to explain


def test_a_run_trains_on_the_backend_its_dataset_was_made_on(toy_plugins, tmp_path):
    ds = tmp_path / "ds"
    assert call("dataset", "toy", "--preset", "tiny", "--backend", "pybullet", "--out", str(ds))[0] == 0
    code, out, err = call("train", "toy", "--preset", "tiny", "--data", str(ds), "--out", str(tmp_path / "r"), "--json")
    assert code == 0, err
    assert j(out)["backend"] == "pybullet"
    assert json.loads((tmp_path / "r" / "run.json").read_text())["backend"] == "pybullet"
    code, out, err = call("eval", "toy", "--run", str(tmp_path / "r"), "--json")  # evaluated where it was trained
    assert code == 0 and j(out)["backend"] == "pybullet", err
    code, _, err = call("train", "toy", "--preset", "tiny", "--data", str(ds), "--backend", "mujoco",
                        "--out", str(tmp_path / "r2"))
    assert code == 2 and "was made on pybullet" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "r2").exists()
