"""Benchmark steps that are plain ``physint`` commands: run once, timed, resumable.

Shared by the method benchmarks (``stability.py``, ``geeco.py``). Every step is printed as it
starts, so any figure can be re-made by hand; a step whose result is already under the
benchmark's home is not run again, so an interrupted benchmark resumes where it stopped.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def machine(device: str = "cpu", precision: str | None = None) -> str:
    """The machine a benchmark's wall times belong to: CPU, cores, vector capability, and the precision
    ``train.precision=auto`` trains in here (a 2-core CPU without native bf16 trains several times slower);
    ``precision`` names it instead for a method that always trains in one precision."""
    import torch

    from physint_cli.training import resolve_precision

    return (f"{platform.node()}: {cpu_model()}, {os.cpu_count()} CPUs ({torch.backends.cpu.get_cpu_capability()}), "
            f"training on {device} in {precision or resolve_precision('auto', device)}")


def physint() -> list[str]:
    exe = shutil.which("physint", path=str(Path(sys.executable).parent)) or shutil.which("physint")
    return [exe] if exe else [sys.executable, "-m", "physint_cli"]


class Steps:
    """Runs ``physint`` steps with ``PHYSINT_HOME`` set to ``home`` and keeps their wall times."""

    def __init__(self, home: Path, preset: str, workers: int, backend: str):
        self.home, self.preset, self.workers, self.backend = home, preset, workers, backend
        self.home.mkdir(parents=True, exist_ok=True)
        self.times_file = home / "benchmark_times.json"
        self.times = json.loads(self.times_file.read_text()) if self.times_file.exists() else {}

    def run(self, key: str, done: bool, args: list[str]) -> float | None:
        """Run ``physint ARGS`` unless ``done``; remember and return its wall time (s)."""
        if done:
            return self.times.get(key)
        exe = physint()
        cmd = exe + args + ["--preset", self.preset, "--quiet"]
        print("$ " + " ".join(["physint"] + cmd[len(exe):]), flush=True)
        env = dict(os.environ, PHYSINT_HOME=str(self.home))
        t0 = time.perf_counter()
        rc = subprocess.run(cmd, env=env, stdout=subprocess.DEVNULL).returncode
        seconds = time.perf_counter() - t0
        if rc != 0:
            raise SystemExit(f"benchmark step {key!r} failed (exit {rc}): {' '.join(cmd)}")
        self.times[key] = seconds
        self.times_file.write_text(json.dumps(self.times, indent=2))
        return seconds

    def finished_run(self, out: Path) -> bool:
        """Whether ``out`` holds a finished eval/deploy run; an interrupted one is removed (they restart)."""
        if (out / "metrics.json").exists():
            return True
        shutil.rmtree(out, ignore_errors=True)
        return False

    def dataset(self, key: str, out: Path, args: list[str]) -> Path:
        """A dataset step (an interrupted generation resumes its shards)."""
        self.run(key, complete(out), ["dataset", *args, "--workers", str(self.workers), "--out", str(out)])
        return out

    def train(self, key: str, out: Path, args: list[str]) -> Path:
        """A training step (an interrupted training goes on from its last checkpoint)."""
        resume = ["--resume", "--run", str(out)] if (out / "run.json").exists() else []
        self.run(key, (out / "metrics.json").exists(), ["train", *args, "--out", str(out), *resume])
        return out

    def verb(self, key: str, out: Path, args: list[str]) -> dict:
        """An eval or deploy step; returns its metrics."""
        self.run(key, self.finished_run(out), [*args, "--out", str(out)])
        return metrics(out)


def complete(dataset: Path) -> bool:
    m = dataset / "manifest.json"
    return m.exists() and json.loads(m.read_text()).get("status") == "complete"


def metrics(run: Path) -> dict:
    return json.loads((run / "metrics.json").read_text())


def pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.1f} %"


def minutes(s: float | None) -> str:
    return "-" if s is None else f"{s / 60:.1f} min"


def print_table(rows: list[tuple[str, ...]], header: tuple[str, ...] = ("measure", "thesis", "physint", "goal / reference")
                ) -> None:
    widths = [max(len(r[i]) for r in rows + [header]) for i in range(len(header))]
    print(" | ".join(h.ljust(w) for h, w in zip(header, widths)))
    print("-+-".join("-" * w for w in widths))
    for r in rows:
        print(" | ".join(c.ljust(w) for c, w in zip(r, widths)))


def report(title: str, rows: list[tuple[str, ...]], figures: dict, steps: Steps, json_path: str | None) -> None:
    """Print the table under its title (and the machine); with ``json_path``, write the figures too."""
    print(f"\n{title}, {figures['machine']}\n")
    print_table(rows)
    if json_path:
        Path(json_path).write_text(json.dumps({**figures, "rows": rows, "times_s": steps.times}, indent=2, default=str))


def benchmark_parser(doc: str, method: str) -> argparse.ArgumentParser:
    """The options every method benchmark takes: --preset, --home, --workers, --backend, --json."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="small")
    parser.add_argument("--home", default=f"physint_runs/benchmark-{method}", help="where runs and datasets go")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--backend", default="mujoco")
    parser.add_argument("--json", help="also write the measured figures to this file")
    return parser
