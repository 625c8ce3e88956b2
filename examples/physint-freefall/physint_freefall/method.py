"""The freefall method: how long does a dropped object take to reach the ground?

Physics says t = sqrt(2h/g) for a drop from height h (the object's lowest point) with no air
drag. The method learns it from simulated drops instead:

* dataset: drop spheres and boxes of random size from random heights on the chosen backend and
  record the simulated time to ground (plus a snapshot of the first frame);
* train: fit an MLP from h to t;
* eval: simulate fresh drops in parallel work units and report the MAE of the MLP against the
  simulator and against sqrt(2h/g), beside a predict-the-mean baseline;
* deploy: predict a new drop (``--target HEIGHT``), simulate it, and write a GIF, a plot and a
  rerun recording of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from physint_cli.config import field_
from physint_cli.errors import BadInput
from physint_cli.method import Context, Method, Unit, split_units, unit_seed

G = 9.81
SHAPES = ("sphere", "box")


def analytic_time(height: np.ndarray | float, g: float = G) -> np.ndarray:
    """t = sqrt(2h/g): time for a body released at rest to fall a height h."""
    return np.sqrt(2.0 * np.asarray(height, dtype=float) / g)


def mean_absolute_error(pred: np.ndarray, target: np.ndarray) -> float:
    return float(np.mean(np.abs(np.asarray(pred) - np.asarray(target))))


# -- config -------------------------------------------------------------------------------------

@dataclass
class DataConfig:
    train: int = field_(256, "training drops", ge=1)
    val: int = field_(64, "validation drops", ge=1)
    test: int = field_(64, "test drops", ge=1)
    per_shard: int = field_(64, "drops per shard (work unit)", ge=1)
    min_height: float = field_(0.2, "lowest drop height (m)", gt=0)
    max_height: float = field_(2.0, "highest drop height (m)", gt=0)
    min_size: float = field_(0.01, "smallest object radius / half edge (m)", gt=0)
    max_size: float = field_(0.05, "largest object radius / half edge (m)", gt=0)
    timestep: float = field_(0.001, "physics step (s)", gt=0)
    image_size: int = field_(32, "side of the first-frame snapshot (px)", ge=8)

    def validate(self) -> None:  # rules between fields (the config layer calls this)
        if self.min_height >= self.max_height or self.min_size > self.max_size:
            raise BadInput("data.min_height must be below data.max_height, and data.min_size at most data.max_size")


@dataclass
class TrainConfig:
    model: str = field_("mlp", "model name (see `physint plugins`)")
    hidden: int = field_(32, "hidden units per layer", ge=1)
    layers: int = field_(2, "hidden layers", ge=1)
    epochs: int = field_(60, "passes over the training drops", ge=1)
    batch_size: int = field_(32, "drops per batch", ge=1)
    lr: float = field_(0.01, "Adam learning rate", gt=0)


@dataclass
class EvalConfig:
    drops: int = field_(64, "fresh drops simulated for evaluation", ge=1)
    per_unit: int = field_(16, "drops per evaluation work unit", ge=1)


@dataclass
class DeployConfig:
    height: float = field_(1.0, "drop height to predict when --target is not given (m)", gt=0)
    fps: float = field_(25.0, "frame rate of the drop video", gt=0)


@dataclass
class FreeFallConfig:
    data: DataConfig = field_(DataConfig(), "dataset generation")
    train: TrainConfig = field_(TrainConfig(), "training")
    eval: EvalConfig = field_(EvalConfig(), "evaluation")
    deploy: DeployConfig = field_(DeployConfig(), "deployment")


# -- simulation -----------------------------------------------------------------------------------

def drop_scene(shape: str, size: float, height: float, timestep: float, image_size: int, frame_top: float = 2.1):
    """A body whose lowest point is ``height`` above the ground, and a camera that frames 0..frame_top metres."""
    from physint_backends import Body, Camera, Scene

    z = height + size
    body = Body.sphere("object", size, pos=(0, 0, z), rgba=(0.9, 0.3, 0.2, 1)) if shape == "sphere" else \
        Body.box("object", (2 * size,) * 3, pos=(0, 0, z), rgba=(0.2, 0.4, 0.9, 1))
    middle = frame_top / 2
    camera = Camera("side", pos=(1.5 * frame_top, 0.0, middle), lookat=(0.0, 0.0, middle),
                    fovy=math.degrees(2 * math.atan(0.6 / 1.5)), width=image_size, height=image_size)
    return Scene(bodies=[body], cameras=[camera], timestep=timestep)


def sample_drop_scene(seed: int, image_size: int = 32):
    """One drop of the ``drop`` scene as a backend-neutral Scene (what ``SceneInfo.build`` gives)."""
    cfg = DataConfig(image_size=image_size)
    shape, size, height = sample_drops(1, seed, cfg)[0]
    return drop_scene(shape, size, height, cfg.timestep, image_size, frame_top=cfg.max_height + 2 * cfg.max_size)


def simulate_drop(ctx: Context, shape: str, size: float, height: float, frames: bool = False,
                  fps: float = 25.0) -> tuple[float, np.ndarray, list[np.ndarray]]:
    """Simulated time until the object touches the ground, its first frame, and (optionally) a video."""
    cfg = ctx.config.data
    if frames:  # a video frames this drop closely; dataset snapshots all frame the highest drop
        scene = drop_scene(shape, size, height, cfg.timestep, 160, frame_top=height + 4 * size)
    else:
        scene = drop_scene(shape, size, height, cfg.timestep, cfg.image_size, frame_top=cfg.max_height + 2 * cfg.max_size)
    video: list[np.ndarray] = []
    limit = 1.5 * math.sqrt(2 * cfg.max_height / G) + 0.5
    every = max(1, int(round(1.0 / (fps * cfg.timestep))))
    with ctx.make_sim(scene) as sim:
        first = sim.render("side").rgb
        steps, t_ground = 0, None
        while sim.time < limit:
            sim.step(1)
            steps += 1
            if frames and steps % every == 0:
                video.append(sim.render("side").rgb)
            if "ground" in sim.contacts("object"):
                t_ground = sim.time
                break
        if frames:  # a few frames after the impact
            for _ in range(int(0.3 * fps)):
                sim.advance(1.0 / fps)
                video.append(sim.render("side").rgb)
    if t_ground is None:
        raise RuntimeError(f"the object dropped from {height:.2f} m never reached the ground")
    return t_ground, first, video


def sample_drops(n: int, seed: int, cfg: DataConfig) -> list[tuple[str, float, float]]:
    rng = np.random.default_rng(seed)
    return [(SHAPES[rng.integers(len(SHAPES))], float(rng.uniform(cfg.min_size, cfg.max_size)),
             float(rng.uniform(cfg.min_height, cfg.max_height))) for _ in range(n)]


def _simulate_unit(ctx: Context, unit: Unit) -> dict[str, np.ndarray]:
    drops = sample_drops(unit.count, unit.seed, ctx.config.data)
    heights, sizes, shapes, times, images = [], [], [], [], []
    for shape, size, height in drops:
        t, first, _ = simulate_drop(ctx, shape, size, height)
        heights.append(height)
        sizes.append(size)
        shapes.append(SHAPES.index(shape))
        times.append(t)
        images.append(first)
    return {"height": np.asarray(heights, np.float32), "size": np.asarray(sizes, np.float32),
            "shape": np.asarray(shapes, np.int64), "time": np.asarray(times, np.float32),
            "analytic_time": analytic_time(heights).astype(np.float32), "image": np.stack(images).astype(np.uint8)}


def evaluate_unit(ctx: Context, unit: Unit) -> dict[str, list[float]]:
    """One batch of fresh evaluation drops (a work unit: runs in a worker process or on Ray)."""
    arrays = _simulate_unit(ctx, unit)
    return {"height": arrays["height"].tolist(), "time": arrays["time"].tolist()}


# -- the method -------------------------------------------------------------------------------------

class FreeFall(Method):
    name = "freefall"
    description = "learn the time a dropped object takes to hit the ground; compare with sqrt(2h/g)"
    chapter = "example plugin (not in the thesis)"
    config_class = FreeFallConfig
    presets = {
        "tiny": {"data.train": 48, "data.val": 16, "data.test": 16, "data.per_shard": 16, "data.image_size": 16,
                 "train.epochs": 40, "train.batch_size": 16, "eval.drops": 16, "eval.per_unit": 8},
        "small": {},
        "paper": {"data.train": 4000, "data.val": 500, "data.test": 500, "data.per_shard": 250,
                  "train.hidden": 64, "train.epochs": 200, "eval.drops": 1000, "eval.per_unit": 50},
    }
    backends = ("mujoco", "pybullet", "robosuite")  # --scene choices: the scenes __init__.py registers
    default_model = "mlp"

    # dataset ------------------------------------------------------------------------------------
    def dataset_units(self, ctx: Context) -> list[Unit]:
        d = ctx.config.data
        return split_units({"train": d.train, "val": d.val, "test": d.test}, d.per_shard, ctx.seed)

    def generate(self, ctx: Context, unit: Unit) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        arrays = _simulate_unit(ctx, unit)
        error = np.abs(arrays["time"] - arrays["analytic_time"])
        return arrays, {"drops": unit.count, "sum_abs_error_vs_analytic": float(error.sum())}

    def summarize_dataset(self, ctx: Context, stats: list[dict[str, Any]]) -> dict[str, Any]:
        drops = sum(s["drops"] for s in stats)
        return {"drops": drops, "sim_vs_analytic_mae_s": sum(s["sum_abs_error_vs_analytic"] for s in stats) / max(drops, 1),
                "generation_cpu_seconds": sum(s.get("seconds", 0.0) for s in stats)}

    # train --------------------------------------------------------------------------------------
    def _build(self, name: str, cfg: TrainConfig):
        from physint_cli.plugins import get_plugins

        return get_plugins().model(self.name, name).build(hidden=cfg.hidden, layers=cfg.layers)

    def train(self, ctx: Context) -> dict[str, Any]:
        import torch

        from physint_cli.artifacts import save_training_curves
        from physint_cli.datasets import ShardedDataset
        from physint_cli.training import fit

        cfg = ctx.config.train
        model_name = ctx.model or cfg.model
        model = self._build(model_name, cfg)
        fields = ["height", "time"]
        train_set = ShardedDataset(ctx.data, "train", fields, transform=_to_tensors, method=self.name)
        val_set = ShardedDataset(ctx.data, "val", fields, transform=_to_tensors, method=self.name)

        def loss_fn(net, batch):
            return torch.nn.functional.mse_loss(net(batch["height"]), batch["time"])

        def val_mae(net, loader):
            errors = [torch.abs(net(b["height"]) - b["time"]).sum() for b in loader]
            return float(torch.stack(errors).sum() / len(loader.dataset))

        result = fit(model, train_set, val_set, run=ctx.output(), epochs=cfg.epochs, batch_size=cfg.batch_size,
                     lr=cfg.lr, loss_fn=loss_fn, metric_fn=val_mae, device=ctx.device, seed=ctx.seed,
                     resume=ctx.resume, log=ctx.log, progress=not ctx.quiet,
                     meta={"method": self.name, "model": model_name,
                           "kwargs": {"hidden": cfg.hidden, "layers": cfg.layers}})
        save_training_curves(ctx.output().artifact("training_curve.png"), result.history,
                             loss="train MSE (s²)", metric="val MAE (s)")
        return {"model": model_name, "epochs": result.epochs, "val_mae_s": result.best_metric,
                "train_drops": len(train_set)}

    def _load(self, ctx: Context):
        from physint_cli.training import load_trained_model

        model, _meta = load_trained_model(ctx.trained().path, self.name, "freefall model")
        return model

    # eval ---------------------------------------------------------------------------------------
    def evaluate(self, ctx: Context) -> dict[str, Any]:
        import torch

        from physint_cli.artifacts import save_plot

        e = ctx.config.eval
        drops = int(ctx.episodes or e.drops)
        units = split_units({"eval": drops}, e.per_unit, unit_seed(ctx.seed, "eval"))
        parts = ctx.map(evaluate_unit, units, description="freefall eval drops")
        heights = np.concatenate([p["height"] for p in parts])
        sim_times = np.concatenate([p["time"] for p in parts])
        model = self._load(ctx)
        with torch.no_grad():
            pred = model(torch.as_tensor(heights, dtype=torch.float32)[:, None]).numpy()[:, 0]
        analytic = analytic_time(heights)
        mean_baseline = np.full_like(sim_times, sim_times.mean())  # the predict-the-mean baseline
        metrics = {
            "drops": int(len(heights)), "backend": ctx.backend,
            "mae_vs_sim_s": mean_absolute_error(pred, sim_times),
            "mae_vs_analytic_s": mean_absolute_error(pred, analytic),
            "baseline_mae_vs_sim_s": mean_absolute_error(mean_baseline, sim_times),
            "sim_vs_analytic_mae_s": mean_absolute_error(sim_times, analytic),
        }
        order = np.argsort(heights)

        def draw(ax):
            hs = np.linspace(heights.min(), heights.max(), 100)
            ax.plot(hs, analytic_time(hs), "k-", label="sqrt(2h/g)")
            ax.plot(heights, sim_times, "o", ms=3, label=f"simulated ({ctx.backend})")
            ax.plot(heights[order], pred[order], "r-", label="MLP")
            ax.set_xlabel("drop height h (m)")
            ax.set_ylabel("time to ground (s)")
            ax.legend()

        save_plot(ctx.output().artifact("predictions.png"), draw)
        return metrics

    # deploy -------------------------------------------------------------------------------------
    def deploy(self, ctx: Context) -> dict[str, Any]:
        import torch

        from physint_cli.artifacts import Recording, save_image, save_video

        target = ctx.target
        try:
            height = float(target) if target is not None else ctx.config.deploy.height
        except ValueError:
            raise BadInput(f"--target for freefall is a drop height in metres, got {target!r}") from None
        if not math.isfinite(height) or height <= 0:
            raise BadInput(f"--target must be a positive height in metres, got {target!r}")
        model = self._load(ctx)
        with torch.no_grad():
            predicted = float(model(torch.tensor([[height]], dtype=torch.float32))[0, 0])
        t_sim, first, video = simulate_drop(ctx, "sphere", 0.06, height, frames=True, fps=ctx.config.deploy.fps)
        run = ctx.output()
        save_image(run.artifact("first_frame.png"), first)
        save_video(run.artifact("drop.gif"), video, fps=ctx.config.deploy.fps)
        save_video(run.artifact("drop.mp4"), video, fps=ctx.config.deploy.fps)
        with Recording(run.artifact("drop.rrd"), "freefall") as rec:
            rec.text("prediction", f"predicted {predicted:.3f} s, simulated {t_sim:.3f} s, sqrt(2h/g) {analytic_time(height):.3f} s")
            for i, frame in enumerate(video):
                rec.time(step=i, seconds=i / ctx.config.deploy.fps)
                rec.image("camera/side", frame)
        in_range = ctx.config.data.min_height <= height <= ctx.config.data.max_height
        return {"height_m": height, "predicted_s": predicted, "simulated_s": t_sim,
                "analytic_s": float(analytic_time(height)), "abs_error_vs_sim_s": abs(predicted - t_sim),
                "within_training_range": in_range}


def _to_tensors(record: dict[str, np.ndarray]) -> dict[str, Any]:
    import torch

    return {k: torch.as_tensor(np.asarray(v, dtype=np.float32)).reshape(1) for k, v in record.items()}
