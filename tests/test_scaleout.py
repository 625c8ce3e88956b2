"""Scale-out: work units on a local Ray cluster, training under torchrun with 2 CPU processes."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import TESTS, call, run_cli
from test_plugins import freefall_env  # noqa: F401  (fixture)

from physint_cli.datasets import ShardedDataset, verify


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def ray_cluster(tmp_path_factory):
    """A local Ray head node started by the test, whose workers can import the toy plugin."""
    ray_bin = shutil.which("ray", path=os.path.dirname(sys.executable)) or shutil.which("ray")
    if ray_bin is None:
        pytest.fail("Ray is not installed: pip install 'physint[ray]'")
    port = free_port()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]),
           "RAY_USAGE_STATS_ENABLED": "0"}
    temp = tmp_path_factory.mktemp("ray")
    subprocess.run([ray_bin, "start", "--head", f"--port={port}", "--num-cpus=2", "--include-dashboard=false",
                    "--disable-usage-stats", f"--temp-dir={temp}"], check=True, env=env, capture_output=True, timeout=180)
    yield f"127.0.0.1:{port}"
    import ray

    if ray.is_initialized():
        ray.shutdown()
    subprocess.run([ray_bin, "stop", "--force"], env=env, capture_output=True, timeout=120)


def test_dataset_and_eval_on_ray(toy_plugins, ray_cluster, tmp_path):
    code, out, err = call("dataset", "toy", "--preset", "tiny", "--out", str(tmp_path / "ray"), "--ray", ray_cluster, "--json")
    assert code == 0, err
    assert "ran 4 units on Ray" in err
    assert verify(tmp_path / "ray") == []
    assert call("dataset", "toy", "--preset", "tiny", "--out", str(tmp_path / "local"))[0] == 0
    for split in ("train", "val", "test"):  # same seed, same data, wherever it ran
        assert np.array_equal(ShardedDataset(tmp_path / "ray", split).column("y"),
                              ShardedDataset(tmp_path / "local", split).column("y"))
    assert call("train", "toy", "--data", str(tmp_path / "ray"), "--set", "train.epochs=1")[0] == 0
    code, out, err = call("eval", "toy", "--ray", ray_cluster, "--json")
    assert code == 0, err
    metrics = json.loads(out)["metrics"]
    assert metrics["units"] == 4 and os.getpid() not in metrics["pids"]


def test_bad_ray_address_is_bad_input(toy_plugins, tmp_path):
    code, _, err = call("dataset", "toy", "--preset", "tiny", "--out", str(tmp_path / "d"), "--ray", f"127.0.0.1:{free_port()}")
    assert code == 2 and "--ray" in err and "cannot connect" in err


def test_torchrun_trains_with_ddp_on_two_cpu_processes(freefall_env, tmp_path):  # noqa: F811
    env = {**freefall_env, "PHYSINT_HOME": str(tmp_path / "home")}
    data = tmp_path / "ds"
    result = run_cli("dataset", "freefall", "--preset", "tiny", "--out", str(data), env=env)
    assert result.returncode == 0, result.stderr
    run = tmp_path / "ddp"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", "--master_port", str(free_port()),
           "-m", "physint_cli", "train", "freefall", "--preset", "tiny", "--data", str(data), "--out", str(run),
           "--device", "cpu", "--json"]
    proc = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, **env}, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    assert len(lines) == 1  # only rank 0 reports
    result = json.loads(lines[0])
    info = json.loads((Path(run) / "run.json").read_text())
    assert info["world_size"] == 2 and info["status"] == "complete"
    curve = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert len(curve) == 40  # written once, by rank 0
    assert result["metrics"]["val_mae_s"] < 0.05  # a real fit of t(h): the mean baseline is ~0.1 s
