"""Run directories and the physint home.

Every train, eval and deploy writes a run directory::

    run.json          method, verb, backend, scene, preset, seed, command line, versions,
                      machine (CPU, cores, vector extensions, ISA caps), git commit, dataset,
                      source run, times, status
    config.yaml       the resolved config
    checkpoints/      best.pt: the trained model that eval and deploy load (Run.save_trained /
                      Run.load_trained; training.fit writes it at every better epoch), and
                      last.pt: fit's resume state (model, optimizer, epoch/batch, RNG states)
    metrics.json      final metrics (written once, at the end)
    metrics.jsonl     curves: one JSON object per logged step
    artifacts/        PNG plots, MP4/GIF videos, rerun .rrd recordings

The physint home is ``$PHYSINT_HOME`` or ``./physint_runs``; it holds ``datasets/`` (cached
datasets) and ``runs/<method>/``.
"""

from __future__ import annotations

import json
import os
import secrets
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from .datasets import atomic_write_bytes, atomic_write_json, check_writable, machine, versions
from .errors import BadInput

CHECKPOINTS = "checkpoints"
ARTIFACTS = "artifacts"
TRAINED = "best"  # checkpoints/best.pt: what a trained run hands to eval and deploy


def home() -> Path:
    return Path(os.environ.get("PHYSINT_HOME", "physint_runs")).expanduser()


def git_commit() -> str | None:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5,
                             cwd=Path(__file__).resolve().parent)
        return out.stdout.strip() or None if out.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        return None


@dataclass
class Run:
    path: Path

    # -- creation -----------------------------------------------------------------------------
    @classmethod
    def create(cls, verb: str, ctx: Any, config: dict[str, Any], out: Path | None = None, extra: dict | None = None) -> Run:
        if out is None:
            stamp = time.strftime("%Y%m%d-%H%M%S")
            out = home() / "runs" / ctx.method / f"{stamp}-{verb}-{ctx.backend}-{secrets.token_hex(2)}"
        path = Path(out)
        if (path / "run.json").exists() and verb != "train":
            raise BadInput(f"--out {path} already holds a run; choose a new directory")
        check_writable(path)
        run = cls(path)
        (path / CHECKPOINTS).mkdir(exist_ok=True)
        (path / ARTIFACTS).mkdir(exist_ok=True)
        info = {
            "method": ctx.method, "verb": verb, "backend": ctx.backend, "scene": ctx.scene, "preset": ctx.preset,
            "seed": ctx.seed, "device": ctx.device, "command": sys.argv, "cwd": os.getcwd(),
            "versions": versions("mujoco", "pybullet", "robosuite"), "machine": machine(), "git_commit": git_commit(),
            "data": str(ctx.data) if ctx.data else None,
            "source_run": str(ctx.source_run) if ctx.source_run else None,
            "options": ctx.verb_options(), "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "status": "running",
            **(extra or {}),
        }
        atomic_write_json(path / "run.json", info)
        atomic_write_bytes(path / "config.yaml", yaml.safe_dump({"method": ctx.method, "preset": ctx.preset,
                                                                  "config": config}, sort_keys=False).encode())
        return run

    # -- contents -----------------------------------------------------------------------------
    @property
    def info(self) -> dict[str, Any]:
        return json.loads((self.path / "run.json").read_text())

    def update_info(self, **changes: Any) -> None:
        atomic_write_json(self.path / "run.json", {**self.info, **changes})

    def checkpoint(self, name: str = "last") -> Path:
        return self.path / CHECKPOINTS / f"{name}.pt"

    # -- the trained artefact: the contract between train and eval / deploy ----------------------
    def save_trained(self, **state: Any) -> Path:
        """Save what eval and deploy load, atomically, as ``checkpoints/best.pt`` (a ``torch.save``
        of ``state``). For a registered network: ``model=state_dict(), meta={"method": ...,
        "model": registered name, "kwargs": its constructor arguments}``, which
        :func:`physint_cli.training.load_trained_model` rebuilds. ``training.fit`` calls this for
        every better epoch; a method that trains without ``fit`` calls it itself."""
        from .checkpoints import save_checkpoint

        path = self.checkpoint(TRAINED)
        path.parent.mkdir(exist_ok=True)
        save_checkpoint(path, **state)
        return path

    @property
    def trained_file(self) -> Path | None:
        """The saved trained artefact (``best.pt``; ``last.pt`` of a training stopped before any
        epoch ended better), or None if this run has none yet."""
        for name in (TRAINED, "last"):
            if self.checkpoint(name).is_file():
                return self.checkpoint(name)
        return None

    def load_trained(self, device: str = "cpu") -> dict[str, Any]:
        """The state :meth:`save_trained` saved; BadInput if the run has none or it cannot be read."""
        from .checkpoints import load_checkpoint

        path = self.trained_file
        if path is None:
            raise BadInput(f"--run {self.path} has no trained model (checkpoints/{TRAINED}.pt); train it first "
                           f"with `physint train {self.info.get('method', 'METHOD')}` (or --resume)")
        return load_checkpoint(path, device)

    def artifact(self, name: str) -> Path:
        """Where artifact ``name`` goes (its folder made, also in a run resumed from a copy)."""
        path = self.path / ARTIFACTS / name
        path.parent.mkdir(parents=True, exist_ok=True)
        return path

    def log_metrics(self, step: int, **metrics: Any) -> None:
        """Append one point of the training/evaluation curves to metrics.jsonl."""
        with open(self.path / "metrics.jsonl", "a") as f:
            f.write(json.dumps({"step": step, "time": round(time.time(), 3), **metrics}, default=float) + "\n")

    def rewind_metrics(self, step: int) -> None:
        """Drop the curve points after ``step``: a run resumed from its checkpoint at ``step`` logs those again."""
        curves = self.path / "metrics.jsonl"
        if not curves.is_file():
            return
        kept = [line for line in curves.read_text().splitlines() if line.strip() and json.loads(line)["step"] <= step]
        atomic_write_bytes(curves, "".join(line + "\n" for line in kept).encode())

    def finish(self, metrics: dict[str, Any]) -> None:
        atomic_write_json(self.path / "metrics.json", metrics)
        self.update_info(status="complete", finished=time.strftime("%Y-%m-%dT%H:%M:%S%z"))

    def artifacts(self) -> list[str]:
        return sorted(str(p.relative_to(self.path)) for p in (self.path / ARTIFACTS).rglob("*") if p.is_file())


def open_run(path: Path | str, method: str | None = None, need_checkpoint: bool = True) -> Run:
    """A trained run to evaluate or deploy, or BadInput saying what is wrong."""
    p = Path(path)
    if not (p / "run.json").is_file():
        raise BadInput(f"--run {p}: not a physint run directory (no run.json)")
    run = Run(p)
    info = run.info
    if method and info.get("method") != method:
        raise BadInput(f"--run {p} is a run of method {info.get('method')!r}, not {method!r}")
    if need_checkpoint and run.trained_file is None:
        raise BadInput(f"--run {p} has no trained model (checkpoints/{TRAINED}.pt); train it first with "
                       f"`physint train {info.get('method')}` (or --resume)")
    return run


def latest_run(method: str, verb: str = "train", need_checkpoint: bool = True) -> Run:
    root = home() / "runs" / method
    candidates = sorted(root.glob(f"*-{verb}-*"), reverse=True) if root.is_dir() else []
    for path in candidates:
        run = Run(path)
        if (path / "run.json").is_file() and (not need_checkpoint or run.trained_file is not None):
            return run
    raise BadInput(f"no trained {method} run under {root}; train one with `physint train {method}` or pass --run DIR")
