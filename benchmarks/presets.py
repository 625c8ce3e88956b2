"""Wall time of each small preset's training, per epoch and projected to the whole training,
on the machine it runs on, beside the 45-minute goal (issue #36).

    python benchmarks/presets.py --method stability --data CCS_DATASET [--epochs-to-time 3]
    python benchmarks/presets.py --method geeco --data PUSH_DEMOS [--set train.width=0.5 ...]
    python benchmarks/presets.py --run RUN [--run RUN ...]     # runs trained before (or still training)

With ``--data`` it starts ``physint train METHOD --preset small`` (plus any ``--set``) in a fresh
run, lets it train ``--epochs-to-time`` epochs, stops it with Ctrl-C (``fit`` keeps what it did)
and projects the whole training from the epochs' wall times (the first epoch, which reads the
splits into memory, counted once; the later ones' mean for the rest). Epoch times include the
validation and, for GEECO, any DAgger round before the epoch, so a projection from the epochs
before the first round is a lower bound: give ``--run`` of a finished training for its measured
total. With ``--run`` it reads the runs' ``metrics.jsonl``.

Each run's CPU is printed with its vector extensions, as its run.json recorded them; set
``ATEN_CPU_CAPABILITY=avx2 ONEDNN_MAX_CPU_ISA=AVX2`` to hold torch and oneDNN to AVX2 on a newer
CPU (the run records that too), and ``--set train.precision=fp32`` for the fp32 figures of the
issue.
"""

from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from physint_cli.datasets import describe_machine, machine

GOAL_MINUTES = 45.0


def read_run(run: Path) -> dict:
    """Epoch wall times, the configured epochs and precision of a training run."""
    import yaml

    epochs = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines() if line.strip()] \
        if (run / "metrics.jsonl").is_file() else []
    saved = yaml.safe_load((run / "config.yaml").read_text()) if (run / "config.yaml").is_file() else {}
    train = saved.get("config", {}).get("train", {})
    info = json.loads((run / "run.json").read_text()) if (run / "run.json").is_file() else {}
    return {"run": str(run), "method": saved.get("method", "?"), "preset": saved.get("preset", "?"),
            "machine": describe_machine(info["machine"]) if "machine" in info else "not recorded",
            "seconds": [float(e["seconds"]) for e in epochs if "seconds" in e],
            "best": max((e["val_metric"] for e in epochs), default=None),
            "epochs": int(train.get("epochs", len(epochs))), "precision": train.get("precision", "?"),
            "width": train.get("width")}


def projected_minutes(seconds: list[float], epochs: int) -> float | None:
    """The whole training from the epochs timed: the first once, the later ones' mean for the rest."""
    if not seconds:
        return None
    if len(seconds) >= epochs:
        return sum(seconds[:epochs]) / 60
    later = seconds[1:] or seconds[:1]
    return (seconds[0] + sum(later) / len(later) * (epochs - 1)) / 60


def time_training(method: str, data: Path, sets: list[str], epochs_to_time: int, out: Path) -> Path:
    """Train ``epochs_to_time`` epochs of the small preset, then stop the training with Ctrl-C."""
    physint = Path(sys.executable).with_name("physint")
    cmd = [str(physint), "train", method, "--preset", "small", "--data", str(data), "--out", str(out), "--quiet"]
    for s in sets:
        cmd += ["--set", s]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    metrics = out / "metrics.jsonl"
    while proc.poll() is None:
        done = len(metrics.read_text().splitlines()) if metrics.is_file() else 0
        if done >= epochs_to_time:
            proc.send_signal(signal.SIGINT)
            break
        time.sleep(2)
    _, err = proc.communicate()
    if not metrics.is_file():
        sys.exit(f"training stopped before an epoch ended: {err.strip().splitlines()[-1:]}")
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--method", choices=["stability", "geeco", "freefall"])
    p.add_argument("--data", type=Path, help="the method's small-preset dataset")
    p.add_argument("--set", action="append", default=[], help="config override for the timed training")
    p.add_argument("--epochs-to-time", type=int, default=3)
    p.add_argument("--run", type=Path, action="append", default=[], help="a training run to report instead")
    p.add_argument("--out", type=Path, help="where the timed run goes (default: a temporary folder)")
    args = p.parse_args()
    runs = list(args.run)
    if args.data is not None:
        if args.method is None:
            p.error("--data needs --method")
        out = args.out or Path(tempfile.mkdtemp(prefix="physint-presets-")) / "run"
        runs.append(time_training(args.method, args.data, args.set, args.epochs_to_time, out))
    if not runs:
        p.error("give --method and --data to time a training, or --run RUN")
    print(f"this CPU: {describe_machine(machine())}; goal: each small preset's training within "
          f"{GOAL_MINUTES:.0f} min")
    print(f"{'method':10s} {'preset':7s} {'precision':9s} {'width':>5s} {'epochs':>10s} {'first s':>8s} {'later s':>8s} "
          f"{'total min':>10s} {'/ goal':>7s} {'best val':>8s}  run")
    for run in runs:
        r = read_run(Path(run))
        secs = r["seconds"]
        total = projected_minutes(secs, r["epochs"])
        later = sum(secs[1:]) / len(secs[1:]) if len(secs) > 1 else float("nan")
        timed = f"{len(secs)}/{r['epochs']}"
        kind = "measured" if len(secs) >= r["epochs"] else "projected"
        print(f"{r['method']:10s} {r['preset']:7s} {str(r['precision']):9s} {str(r['width']):>5s} {timed:>10s} "
              f"{secs[0] if secs else float('nan'):8.1f} {later:8.1f} "
              f"{total if total is not None else float('nan'):10.1f} "
              f"{(total or float('nan')) / GOAL_MINUTES:6.2f}x "
              f"{r['best'] if r['best'] is not None else float('nan'):8.4f}  {r['run']} ({kind})")
        print(f"{'':10s} trained on: {r['machine']}")


if __name__ == "__main__":
    main()
