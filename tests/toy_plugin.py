"""A simulator-free method used to test the core: noisy samples of y = 2x + 1, with images."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np

from physint_cli import hookimpl
from physint_cli.config import field_
from physint_cli.errors import BadInput
from physint_cli.method import Context, Method, Unit, split_units
from physint_cli.registry import ModelInfo


@dataclass
class Data:
    train: int = field_(64, "training samples", ge=1)
    val: int = field_(16, "validation samples", ge=1)
    test: int = field_(16, "test samples", ge=1)
    per_shard: int = field_(16, "samples per shard", ge=1)
    image_size: int = field_(8, "image side")
    slow: float = field_(0.0, "seconds to sleep per shard (to test interruption)")
    die_on_shard: int = field_(-1, "a worker process dies on this train shard (to test crashes)")

    def validate(self) -> None:
        if self.per_shard > self.train:
            raise BadInput("data.per_shard must be at most data.train")


@dataclass
class Train:
    epochs: int = field_(20, "epochs", ge=1)
    lr: float = field_(0.05, "learning rate", gt=0, le=10)
    batch_size: int = field_(16, "batch size", ge=1)
    model: str = field_("linear", "linear or mlp")


@dataclass
class ToyConfig:
    data: Data = field_(Data())
    train: Train = field_(Train())


def linear(**_):
    import torch

    return torch.nn.Linear(1, 1)


def mlp(**_):
    import torch

    return torch.nn.Sequential(torch.nn.Linear(1, 8), torch.nn.Tanh(), torch.nn.Linear(8, 1))


MODELS = {"linear": linear, "mlp": mlp}


def eval_unit(ctx, unit):
    rng = np.random.default_rng(unit.seed)
    return {"pid": os.getpid(), "x": rng.uniform(-1, 1, unit.count).tolist()}


class Toy(Method):
    name = "toy"
    description = "y = 2x + 1"
    config_class = ToyConfig
    presets = {"tiny": {"data.train": 32}, "small": {}, "paper": {"data.train": 1000}}
    backends = ("mujoco", "pybullet")
    default_model = "linear"  # --scene choices: the scenes registered below

    def dataset_units(self, ctx: Context) -> list[Unit]:
        d = ctx.config.data
        return split_units({"train": d.train, "val": d.val, "test": d.test}, d.per_shard, ctx.seed)

    def generate(self, ctx, unit):
        time.sleep(ctx.config.data.slow)
        if unit.split == "train" and unit.index == ctx.config.data.die_on_shard:
            os._exit(1)  # a simulator segfault, an OOM kill
        rng = np.random.default_rng(unit.seed)
        x = rng.uniform(-1, 1, unit.count).astype(np.float32)
        y = (2 * x + 1 + rng.normal(0, 0.01, unit.count)).astype(np.float32)
        s = ctx.config.data.image_size
        img = rng.integers(0, 255, (unit.count, s, s, 3), dtype=np.uint8)
        return {"x": x, "y": y, "image": img}, {"samples": unit.count}

    def train(self, ctx):
        import torch

        from physint_cli.datasets import ShardedDataset
        from physint_cli.training import fit

        def tensors(r):
            return {"x": torch.tensor([float(r["x"])]), "y": torch.tensor([float(r["y"])])}

        tr = ShardedDataset(ctx.data, "train", ["x", "y"], transform=tensors, method="toy")
        va = ShardedDataset(ctx.data, "val", ["x", "y"], transform=tensors, method="toy")
        c = ctx.config.train
        name = ctx.model or c.model
        res = fit(MODELS[name](), tr, va, run=ctx.output(), epochs=c.epochs, batch_size=c.batch_size, lr=c.lr,
                  loss_fn=lambda m, b: torch.nn.functional.mse_loss(m(b["x"]), b["y"]),
                  metric_fn=lambda m, loader: float(sum(torch.nn.functional.mse_loss(m(b["x"]), b["y"], reduction="sum") for b in loader) / len(loader.dataset)),
                  seed=ctx.seed, resume=ctx.resume, log=ctx.log, meta={"model": name})
        return {"val_mse": res.best_metric, "epochs": res.epochs, "model": name}

    def evaluate(self, ctx):
        units = split_units({"eval": 8}, 2, ctx.seed)
        parts = ctx.map(eval_unit, units)
        return {"units": len(parts), "pids": sorted({p["pid"] for p in parts}), "n": sum(len(p["x"]) for p in parts)}

    def deploy(self, ctx):
        return {"target": ctx.target}


def read_split(root, split: str) -> tuple[np.ndarray, np.ndarray]:
    from physint_cli.datasets import ShardedDataset

    records = ShardedDataset(root, split, ["x", "y"], method="lsq")
    return (np.array([float(records[i]["x"]) for i in range(len(records))]),
            np.array([float(records[i]["y"]) for i in range(len(records))]))


class LeastSquares(Toy):
    """A method that trains without ``physint_cli.training.fit``: a closed-form least-squares line,
    saved with ``Run.save_trained`` and loaded by eval and deploy with ``Run.load_trained``. Its
    evaluation scores with a metric another plugin registered (``mse`` of method-independent
    metrics), found through the registry."""

    name = "lsq"
    description = "y = a x + b by least squares (no fit loop)"
    scenes = ("line",)  # registers no scene: its --scene choices are this tuple
    default_model = None

    def train(self, ctx):
        x, y = read_split(ctx.data, "train")
        a, b = np.polyfit(x, y, 1)  # the normal equations, in closed form
        if ctx.config.train.model == "forget":  # a broken method: returns without saving (test)
            return {"a": float(a)}
        ctx.output().save_trained(line=(float(a), float(b)), meta={"method": self.name, "model": "line"})
        return {"a": float(a), "b": float(b)}

    def evaluate(self, ctx):
        from physint_cli.plugins import get_plugins

        a, b = ctx.trained().load_trained()["line"]
        x, y = read_split(ctx.data, "test")
        mse = get_plugins().metric("mse").fn
        return {"test_mse": mse(a * x + b, y), "baseline_mse": mse(np.full_like(y, y.mean()), y)}

    def deploy(self, ctx):
        a, b = ctx.trained().load_trained()["line"]
        x = float(ctx.target or 0.0)
        return {"x": x, "y": a * x + b}


def mean_squared_error(pred, target) -> float:
    return float(np.mean((np.asarray(pred) - np.asarray(target)) ** 2))


@hookimpl
def register_methods(register):
    register(Toy())
    register(LeastSquares())


@hookimpl
def register_scenes(register):
    from physint_cli.registry import SceneInfo

    register(SceneInfo("line", method="toy", description="y = 2x + 1"))
    register(SceneInfo("curve", method="toy", description="the same line, by another name"))


@hookimpl
def register_metrics(register):
    from physint_cli.registry import MetricInfo

    register(MetricInfo("mse", fn=mean_squared_error, description="mean squared error (any method)"))


@hookimpl
def register_models(register):
    register(ModelInfo("linear", method="toy", build=linear))
    register(ModelInfo("mlp", method="toy", build=mlp))
