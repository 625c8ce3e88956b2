"""Peak memory of dataset generation and training, and of streaming a large dataset.

    python benchmarks/memory.py [--method freefall] [--preset small] [--stream-gb 2]

1. ``physint dataset METHOD --preset P`` and ``physint train METHOD --preset P``, each in its own
   process; peak resident memory (ru_maxrss) beside the 4 GiB limit of issue #2.
2. A synthetic dataset of 224x224 RGB images (``--stream-gb`` GiB on disk, incompressible noise)
   read through ShardedDataset + DataLoader, one full pass in random order: peak resident memory
   beside the dataset's size. Bounded memory means the peak does not grow with the dataset.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

LIMIT_GIB = 4.0


def peak_rss_of(cmd: list[str], env: dict[str, str]) -> tuple[float, float, int]:
    """Run ``cmd`` in a wrapper process; return (peak RSS in GiB, seconds, exit code) of the command."""
    wrapper = ("import resource, subprocess, sys, json, time; t = time.time(); "
               "rc = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL).returncode; "
               "print(json.dumps([resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, time.time() - t, rc]))")
    out = subprocess.run([sys.executable, "-c", wrapper, *cmd], capture_output=True, text=True, env=env)
    kib, seconds, rc = json.loads(out.stdout.strip().splitlines()[-1])
    return kib / 2**20, seconds, rc


def stream_benchmark(root: Path, gib: float) -> dict[str, float]:
    from torch.utils.data import DataLoader

    from physint_cli.datasets import ShardedDataset, finish_manifest, start_manifest, write_shard

    per_record = 224 * 224 * 3
    records = int(gib * 2**30 / per_record)
    per_shard = 256
    rng = np.random.default_rng(0)
    manifest = start_manifest(root, {"method": "memory-benchmark", "scene": "noise", "backend": "none",
                                     "preset": "none", "seed": 0, "config": {}})
    shards = []
    t0 = time.time()
    for index, start in enumerate(range(0, records, per_shard)):
        n = min(per_shard, records - start)
        images = rng.integers(0, 256, (n, 224, 224, 3), dtype=np.uint8)
        shards.append(write_shard(root, f"train-{index:05d}", "train", {"image": images, "label": np.zeros(n, np.int64)}))
    finish_manifest(root, manifest, shards, {}, time.time() - t0)
    disk = sum(s["bytes"] for s in shards) / 2**30
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    ds = ShardedDataset(root, "train")
    loader = DataLoader(ds, batch_size=32, shuffle=True, num_workers=0)
    t0 = time.time()
    seen = 0
    for batch in loader:
        seen += len(batch["label"])
    seconds = time.time() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    return {"records": seen, "disk_gib": disk, "peak_rss_gib": peak, "rss_before_gib": rss_before,
            "records_per_second": seen / seconds}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--method", default="freefall")
    parser.add_argument("--preset", default="small")
    parser.add_argument("--backend", default="mujoco")
    parser.add_argument("--stream-gb", type=float, default=2.0)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "PHYSINT_HOME": str(Path(tmp) / "home")}
        physint = [sys.executable, "-m", "physint_cli"]
        data = Path(tmp) / "data"
        common = [args.method, "--preset", args.preset, "--backend", args.backend, "--quiet"]
        for verb, extra in (("dataset", ["--out", str(data)]), ("train", ["--data", str(data)])):
            gib, seconds, rc = peak_rss_of([*physint, verb, *common, *extra], env)
            rows.append({"measure": f"{verb} {args.method} --preset {args.preset}", "peak_rss_gib": round(gib, 3),
                         "seconds": round(seconds, 1), "limit_gib": LIMIT_GIB, "met": rc == 0 and gib < LIMIT_GIB,
                         "exit_code": rc})
        stream = stream_benchmark(Path(tmp) / "stream", args.stream_gb)
        rows.append({"measure": f"stream {stream['disk_gib']:.2f} GiB of 224x224 images ({stream['records']} records)",
                     "peak_rss_gib": round(stream["peak_rss_gib"], 3), "seconds": None, "limit_gib": LIMIT_GIB,
                     "met": stream["peak_rss_gib"] < min(LIMIT_GIB, stream["disk_gib"]),
                     "records_per_second": round(stream["records_per_second"], 1)})
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; python {platform.python_version()}")
    print(f"{'measure':62s} {'peak RSS (GiB)':>15s} {'seconds':>8s} {'limit':>6s}  met")
    for r in rows:
        secs = f"{r['seconds']:.1f}" if r.get("seconds") is not None else "-"
        print(f"{r['measure']:62s} {r['peak_rss_gib']:15.3f} {secs:>8s} {r['limit_gib']:6.1f}  {'yes' if r['met'] else 'NO'}")
    if "records_per_second" in rows[-1]:
        print(f"streaming read: {rows[-1]['records_per_second']} records/s")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
