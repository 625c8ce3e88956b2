"""A simulator-free method used to test the core: noisy samples of y = 2x + 1, with images."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np

from physint_cli import hookimpl
from physint_cli.config import field_
from physint_cli.method import Context, Method, Unit, split_units
from physint_cli.registry import ModelInfo


@dataclass
class Data:
    train: int = field_(64, "training samples")
    val: int = field_(16, "validation samples")
    test: int = field_(16, "test samples")
    per_shard: int = field_(16, "samples per shard")
    image_size: int = field_(8, "image side")
    slow: float = field_(0.0, "seconds to sleep per shard (to test interruption)")
    die_on_shard: int = field_(-1, "a worker process dies on this train shard (to test crashes)")


@dataclass
class Train:
    epochs: int = field_(20, "epochs")
    lr: float = field_(0.05, "learning rate")
    batch_size: int = field_(16, "batch size")
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
    scenes = ("line", "curve")
    default_model = "linear"

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
        from physint_cli.runs import Run
        from physint_cli.training import fit

        def tensors(r):
            return {"x": torch.tensor([float(r["x"])]), "y": torch.tensor([float(r["y"])])}

        tr = ShardedDataset(ctx.data, "train", ["x", "y"], transform=tensors, method="toy")
        va = ShardedDataset(ctx.data, "val", ["x", "y"], transform=tensors, method="toy")
        c = ctx.config.train
        name = ctx.options.get("model", c.model)
        res = fit(MODELS[name](), tr, va, run=Run(ctx.run), epochs=c.epochs, batch_size=c.batch_size, lr=c.lr,
                  loss_fn=lambda m, b: torch.nn.functional.mse_loss(m(b["x"]), b["y"]),
                  metric_fn=lambda m, loader: float(sum(torch.nn.functional.mse_loss(m(b["x"]), b["y"], reduction="sum") for b in loader) / len(loader.dataset)),
                  seed=ctx.seed, resume=bool(ctx.options.get("resume")), log=ctx.log, meta={"model": name})
        return {"val_mse": res.best_metric, "epochs": res.epochs, "model": name}

    def evaluate(self, ctx):
        units = split_units({"eval": 8}, 2, ctx.seed)
        parts = ctx.map(eval_unit, units)
        return {"units": len(parts), "pids": sorted({p["pid"] for p in parts}), "n": sum(len(p["x"]) for p in parts)}

    def deploy(self, ctx):
        return {"target": ctx.options.get("target")}


@hookimpl
def register_methods(register):
    register(Toy())


@hookimpl
def register_models(register):
    register(ModelInfo("linear", method="toy", build=linear))
    register(ModelInfo("mlp", method="toy", build=mlp))
