"""The stability method's config and its tiny / demo / small / paper presets (thesis Chapter 3).

``demo`` is `make demo`'s: 1,500 scenarios at 48 px and a 16-wide CNN, about five minutes end to end on
2 AVX2 cores. ``paper`` is the thesis's ShapeStacks: 20,000 scenarios split ~70/15/15, 16 cameras at 224x224,
25 background textures, 6 object colours, 5 lighting conditions (Table 3.1); Inception-v4 trained
from scratch with RMSProp for 80 epochs (Section 3.4.1); occlusion study on 1,500 images
(Section 3.4.2); stacking over 50 episodes per scenario (Section 3.5.2).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from physint_cli.config import field_
from physint_cli.errors import BadInput


@dataclass
class DataConfig:
    scenarios: int = field_(6000, "scenarios over all splits (thesis: 20,000)", ge=3)
    train_fraction: float = field_(0.70, "fraction of scenarios in the train split", gt=0.0, lt=1.0)
    val_fraction: float = field_(0.15, "fraction in the validation split (the rest is test)", ge=0.0, lt=1.0)
    per_shard: int = field_(50, "scenarios per shard (work unit)", ge=1)
    cameras: int = field_(6, "cameras orbiting each stack (thesis: 16)", ge=1)
    resolution: int = field_(128, "image side in pixels (thesis: 224)", ge=16)
    textures: int = field_(25, "background textures (thesis: 25)", ge=1)
    lights: int = field_(5, "lighting conditions (thesis: 5)", ge=1)
    camera_jitter: float = field_(0.02, "camera position noise (m)", ge=0.0)
    sim_seconds: float = field_(2.0, "simulated seconds to decide whether a stack stands", gt=0.0)
    timestep: float = field_(0.002, "physics step (s)", gt=0.0, le=0.01)
    max_attempts: int = field_(20, "samples per scenario before giving up on simulator agreement", ge=1)

    def validate(self) -> None:
        if self.train_fraction + self.val_fraction >= 1.0:
            raise BadInput(f"data.train_fraction + data.val_fraction must be < 1 (the rest is the test split), got "
                           f"{self.train_fraction} + {self.val_fraction}")


@dataclass
class TrainConfig:
    model: str = field_("cnn", "cnn (CPU default), alexnet or inception-v4 (paper)")
    epochs: int = field_(20, "passes over the training images (thesis: 80)", ge=1)
    batch_size: int = field_(64, "images per batch", ge=1)
    optimizer: Literal["adamw", "adam", "rmsprop"] = field_("adamw", "adamw (cosine learning-rate schedule), adam (constant), or rmsprop with the "
                                      "Inception-v4 paper's solver settings")
    lr: float = field_(2e-3, "peak learning rate (rmsprop: the paper's schedule starts at 0.045)", gt=0.0)
    weight_decay: float = field_(0.05, "weight decay (decoupled for adamw, L2 otherwise)", ge=0.0)
    augment: bool = field_(True, "colour jitter, aspect ratio, crops, mirror, small rotations")
    width: int = field_(20, "channels of the compact CNN's first layer (20 sizes the small preset for 2 AVX2 "
                                "cores; 32 was the earlier one, docs/stability.md)", ge=1)
    input_size: int = field_(128, "network input side in pixels (each model has its own least)", ge=1)
    num_workers: int = field_(0, "DataLoader worker processes", ge=0)
    precision: Literal["fp32", "bf16", "auto"] = field_("auto", "fp32, bf16, or auto: bf16 autocast where the hardware has native bf16 "
                                    "(CPUs with AMX or AVX512-BF16, recent GPUs)")


@dataclass
class EvalConfig:
    occlusion_images: int = field_(300, "unstable test images for the occlusion study (thesis: 1,500; 0: off)", ge=0)
    occlusion_sigma: float = field_(30.0, "Gaussian blur sigma at 224 px (scaled with the resolution)", gt=0.0)
    occlusion_patch: int = field_(14, "patch side at 224 px (scaled)", ge=1)
    occlusion_stride: int = field_(8, "patch stride at 224 px (scaled)", ge=1)
    cross_backend: str = field_("", "also test on this backend's renders of the same distribution ('' = off)")
    batch_size: int = field_(128, "images per evaluation batch", ge=1)


@dataclass
class DeployConfig:
    episodes: int = field_(50, "stacking / counterbalancing episodes per scenario (thesis: 50; --episodes N sets it)", ge=1)
    pool: int = field_(12, "objects in the stacking pool (thesis: 12)", ge=2)
    stackability_pool: int = field_(24, "objects whose stackability is scored, every class at varied sizes (Figs. "
                                        "3.5, 3.6); 12 left two or three bases per class", ge=2)
    anneal_steps: int = field_(30, "simulated-annealing steps per placement", ge=1)
    anneal_radius: float = field_(0.03, "placement search radius around the trunk (m)", gt=0.0)
    cameras: int = field_(6, "cameras watching the stack while stacking (thesis: 6)", ge=1)
    agents: str = field_("", "comma-separated agents of predictor, oracle, random ('' = predictor with --run, "
                             "oracle and random)")


@dataclass
class StabilityConfig:
    data: DataConfig = field_(DataConfig(), "dataset generation (Section 3.3)")
    train: TrainConfig = field_(TrainConfig(), "stability predictor (Section 3.4.1)")
    eval: EvalConfig = field_(EvalConfig(), "evaluation (Sections 3.4.1-3.4.2)")
    deploy: DeployConfig = field_(DeployConfig(), "stackability, stacking, counterbalancing (Section 3.5)")


PRESETS = {
    "tiny": {"data.scenarios": 48, "data.per_shard": 12, "data.cameras": 2, "data.resolution": 32,
             "data.textures": 4, "data.sim_seconds": 1.5, "train.epochs": 3, "train.batch_size": 16,
             "train.input_size": 32, "train.width": 8, "eval.occlusion_images": 4, "deploy.episodes": 1,
             "deploy.pool": 4, "deploy.stackability_pool": 4, "deploy.anneal_steps": 5},
    "demo": {"data.scenarios": 1500, "data.cameras": 6, "data.resolution": 48, "train.epochs": 12,
             "train.batch_size": 32, "train.input_size": 48, "train.width": 16, "eval.occlusion_images": 8,
             "deploy.stackability_pool": 8, "deploy.anneal_steps": 10},  # `make demo`: ~5 min on 2 AVX2 cores
    "small": {},
    "paper": {"data.scenarios": 20000, "data.per_shard": 50, "data.cameras": 16, "data.resolution": 224,
              "train.model": "inception-v4", "train.epochs": 80, "train.batch_size": 32,
              "train.optimizer": "rmsprop", "train.lr": 0.045, "train.weight_decay": 4e-5,
              "train.input_size": 224, "train.num_workers": 8, "eval.occlusion_images": 1500,
              "deploy.episodes": 50, "deploy.anneal_steps": 100},
}
