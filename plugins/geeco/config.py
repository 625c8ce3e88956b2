"""GEECO's config and its tiny / small / paper presets (thesis Chapter 6, Appendix 6.A).

``paper`` is the thesis's setup: 4,000 demonstrations per skill at 256x256, split 2:1:1; batch
32 windows, Adam at 1e-4 for ~300k gradient steps (40 epochs of the 2,000 training
demonstrations' 100 windows each: 250k steps); 1,000 test episodes of 200 steps. ``small`` is
sized for a 2-core CPU (64x64 frames, encoders at 3/8 width, 10 epochs, windows batched in chunks
that share their frames) and reads the encoders' 8x8 maps as keypoints; its push controller takes u_dEE
from positions and trains with DAgger rounds (``train.command=auto``, ``train.dagger_epochs=auto``;
none of these is in the thesis, docs/geeco.md says why): on GOAL2CUBE2 the positions controller
pushed 77.5 % where the thesis's end-to-end command (``--set train.command=network``) pushed 14.5 %
at this scale (both at the earlier width 0.5 and 12 epochs).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from physint_cli.config import field_
from physint_cli.errors import BadInput


def dagger_rounds(text: str, epochs: int) -> list[int] | None:
    """``train.dagger_epochs`` ("5,7,9") as sorted epoch numbers in [2, ``epochs``] (None for
    ``auto``, which the dataset's skill and the resolved ``train.command`` decide: ``dagger.parse_epochs``);
    anything else exits 2."""
    if str(text).strip() == "auto":
        return None
    try:
        rounds = sorted({int(v) for v in str(text).split(",") if v.strip()})
    except ValueError:
        raise BadInput(f"train.dagger_epochs must be comma-separated epoch numbers or auto, got {text!r}") from None
    if rounds and not all(2 <= e <= epochs for e in rounds):
        raise BadInput(f"train.dagger_epochs must lie in [2, train.epochs = {epochs}] (the controller trains on "
                       f"the demonstrations first), got {text!r}")
    return rounds


@dataclass
class DataConfig:
    skill: Literal["push", "pickplace"] = field_("push", "push or pickplace")
    demos: int = field_(800, "expert demonstrations over all splits, 2:1:1 train/val/test (thesis: 4,000; at "
                             "least one per split and more for training)", ge=4)
    resolution: int = field_(64, "camera image side in pixels (thesis: 256)", ge=16)
    horizon: int = field_(100, "steps per demonstration, H (25 Hz: 4 s; the expert needs ~60)", ge=60)
    per_shard: int = field_(20, "demonstrations per shard (work unit)", ge=1)
    max_attempts: int = field_(30, "start states tried per demonstration before giving up", ge=1)
    action_noise: float = field_(0.003, "std (m) of noise added to the executed hand displacements, not to the "
                                        "recorded commands (DART; the thesis: 0)", ge=0.0, le=0.02)
    backgrounds: Literal["plain", "random", "mixed"] = field_(
        "plain", "plain (the thesis), random or mixed: with random each demonstration's background (what is not "
                 "table, robot or object) becomes a random colour field or bands, still or drifting, so the controller "
                 "learns to ignore it (domain randomisation, not in the thesis; against BG:PRISMA); mixed: half of "
                 "each task's demonstrations random, half plain")


@dataclass
class TrainConfig:
    model: str = field_("geeco-f", "geeco-f, geeco-d, geeco-r or e2evmc")
    epochs: int = field_(10, "passes over the training windows", ge=1)
    batch_size: int = field_(16, "chunks per batch", ge=1)
    chunk: int = field_(8, "consecutive windows per chunk (they share frames: each is encoded once; at most the "
                           "dataset's horizon)", ge=1)
    lr: float = field_(5e-4, "Adam learning rate (thesis: 1e-4)", gt=0.0)
    schedule: Literal["cosine", "constant"] = field_("cosine", "learning rate over the epochs: cosine (one warm-up "
                                                               "epoch, then a half cosine to 0) or constant (the thesis)")
    aux_weight: float = field_(1.0, "lambda of Eq. 6.3: weight of the auxiliary position losses (thesis: 0 or 1)",
                               ge=0.0)
    width: float = field_(0.375, "encoder filter multiplier (1.0: Table 6.A.1; 0.375 sizes the small preset for "
                                        "2 AVX2 cores, 0.25 for a slower CPU: docs/geeco.md)",
                               gt=0.0)
    norm: bool = field_(True, "group normalisation after each convolution (not in Table 6.A.1; the plain "
                              "encoders learned the commands slower, see docs/geeco.md)")
    min_side: int = field_(8, "the encoders stop halving their maps at this side (1: Table 6.A.1's strides, whose "
                              "2x2 maps at 256 px become 1x1 at 64 px; the keypoint readout takes positions on an 8x8 "
                              "map)", ge=1)
    stem_stride: Literal[1, 2] = field_(1, "stride of the encoders' first convolution (1: Table 6.A.1; 2 halves the "
                                           "frame there, so 128 px frames cost about what 64 px frames do)")
    dee_bins: int = field_(0, "0: regress u_dEE with MSE (the thesis); N >= 2: classify each axis over N bins across "
                              "the expert's largest step (cross-entropy), so states with two demonstrated commands get "
                              "one of them, not their average", ge=0)
    dee_modes: int = field_(0, "0: off; K >= 2: classify the whole u_dEE over K k-means centres of the demonstrated "
                               "commands, each with a regressed offset (not with dee_bins)", ge=0)
    readout: Literal["flatten", "keypoints"] = field_(
        "keypoints", "how the encoders' maps reach the LSTM: flatten (Table 6.A.1) or keypoints (a spatial softmax "
                     "per channel: its expected image position; pick-and-place PLACE 84.5 % against 22.5 % "
                     "flattened, docs/geeco.md)")
    command: Literal["network", "positions", "auto"] = field_(
        "auto", "where u_dEE comes from: network (its u_dEE head, the thesis), positions (an MLP over the hand's "
                "measured position and the network's estimates of the object's and the target's over the buffer, "
                "learned from the demonstrations' true ones; not in the thesis) or auto (positions for pushing, "
                "network for pick-and-place)")
    command_epochs: int = field_(30, "train.command=positions: epochs over the demonstrations' windows in which the "
                                     "command head learns alone from true positions, before the network trains with it "
                                     "fixed (0: it learns with the network, one loss)", ge=0)
    val_episodes: int = field_(12, "closed-loop validation episodes after each epoch picking the best checkpoint "
                                    "(0: validation loss instead)", ge=0)
    dagger_epochs: str = field_("auto", "comma-separated epochs before which the controller drives the robot from "
                                        "training start states and the push expert labels what it sees (DAgger, not "
                                        "in the thesis); '' = off; auto: for a positions controller of pushing, "
                                        "before the epochs at 1/2, 2/3 and 5/6 of the training (5, 7, 9 of 10), "
                                        "else off")
    dagger_episodes: int = field_(100, "rollouts per DAgger round", ge=1)
    dagger_beta: float = field_(0.0, "probability that a rollout step executes the expert's command instead of "
                                     "the controller's (beta of DAgger)", ge=0.0, lt=1.0)
    precision: Literal["fp32", "bf16", "auto"] = field_("auto", "fp32, bf16, or auto (bf16 where the hardware has "
                                                                "it natively)")

    def validate(self) -> None:
        """The rules between this section's fields; those that need the dataset (``chunk`` against its
        horizon, DAgger against its skill) are checked by ``train.train``."""
        for key, off in (("dee_bins", "regression, the thesis"), ("dee_modes", "off")):
            if getattr(self, key) == 1:
                raise BadInput(f"train.{key}: must be 0 ({off}) or >= 2, got 1")
        if self.dee_bins and self.dee_modes:
            raise BadInput("train.dee_bins and train.dee_modes are two ways to read u_dEE: set one of them")
        if self.command == "positions" and self.aux_weight == 0:
            raise BadInput("train.command=positions commands from the network's position estimates, which "
                           "train.aux_weight=0 leaves unlearned (lambda of Eq. 6.3): use train.command=network or "
                           "auto")
        if self.command == "positions" and (self.dee_bins or self.dee_modes):
            raise BadInput("train.command=positions regresses u_dEE from positions: not with train.dee_bins or "
                           "train.dee_modes")
        dagger_rounds(self.dagger_epochs, self.epochs)


@dataclass
class EvalConfig:
    episodes: int = field_(200, "test episodes (thesis: 1,000; --episodes N sets it)", ge=1)
    steps: int = field_(200, "control steps per episode (thesis: 200, 8 s)", ge=1)
    per_unit: int = field_(10, "episodes per work unit", ge=1)
    positions: Literal["seen", "true"] = field_(
        "seen", "for train.command=positions controllers: seen (the network's estimates of the object's and the "
                "target's positions) or true (the simulator's: what the command head does with perfect perception)")
    side_by_side: int = field_(1, "episodes a worker steps in lockstep, their frames through the network as one "
                                  "batch (at most eval.per_unit): 1.5x faster on 2 CPU cores, but a batch's float "
                                  "rounding, amplified over the closed loop, changes single episodes' outcomes "
                                  "(docs/geeco.md); control_hz is then the steps per second of them all, not one "
                                  "controller's rate (1: one at a time, the control rate; the reported figures)",
                                 ge=1)

    def validate(self) -> None:
        if self.side_by_side > self.per_unit:
            raise BadInput(f"eval.side_by_side must be in [1, eval.per_unit = {self.per_unit}], "
                           f"got {self.side_by_side}")


@dataclass
class DeployConfig:
    steps: int = field_(200, "control steps", ge=1)
    video: bool = field_(True, "write an MP4 of the camera view beside the target and the dynamic images")


@dataclass
class GeecoConfig:
    data: DataConfig = field_(DataConfig(), "expert demonstrations (Section 6.4)")
    train: TrainConfig = field_(TrainConfig(), "the controller (Section 6.3, Appendix 6.A)")
    eval: EvalConfig = field_(EvalConfig(), "closed-loop evaluation (Section 6.4)")
    deploy: DeployConfig = field_(DeployConfig(), "running a controller on a target image")


PRESETS = {
    "tiny": {"data.demos": 16, "data.resolution": 32, "data.per_shard": 8, "train.epochs": 2, "train.batch_size": 4,
             "train.width": 0.25, "train.val_episodes": 1, "train.command_epochs": 2, "train.dagger_episodes": 2,
             "eval.episodes": 2, "eval.steps": 60, "eval.per_unit": 1, "deploy.steps": 40},
    "small": {},
    "paper": {"data.demos": 4000, "data.resolution": 256, "data.per_shard": 25, "data.action_noise": 0.0,
              "train.epochs": 40, "train.batch_size": 32, "train.chunk": 1, "train.lr": 1e-4,
              "train.schedule": "constant", "train.width": 1.0, "train.norm": False,
              "train.readout": "flatten", "train.min_side": 1, "train.command": "network", "train.dagger_epochs": "",
              "train.val_episodes": 50, "eval.episodes": 1000},
}
