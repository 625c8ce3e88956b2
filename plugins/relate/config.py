"""The relate config and its tiny / small / paper presets (thesis Chapter 5, Tables 5.D.1, 5.A.3).

``paper`` is the thesis's setup for BallsInBowl: 2,500 training and 500 test sequences, 128 px, K = 2
objects, N_f = 1 and N_b = 3 latent dimensions, object windows H' = 8, sum composition, Adam at 1e-3 with
betas (0.5, 0.999), one discriminator step per generator step, 60 epochs of 10,000 iterations at batch
64. ``small`` is sized for two CPU cores in fp32 (docs/relate.md has its figures).

Deviations from the thesis (docs/relate.md says why):

* the scenes are simulated here (MuJoCo, PyBullet or robosuite) rather than taken from the published
  datasets, so every image comes with its simulator ground truth, which the evaluation uses and the
  models never see;
* ``small`` renders 32 px images (``data.size``; 128 in the thesis) from 8x8 feature maps with
  narrower networks (``train.width``);
* the bowl is built from convex slabs (24 sectors by 8 rings), the simulators collide convex meshes only;
* the evaluation's distance is FD-truth, the Fréchet distance on the features of an in-project network
  trained to regress the simulator's ground truth, not FID: Inception's weights cannot be downloaded here;
* images are in [-1, 1] for the data as for the generator's tanh (the released code scales the data
  to [-0.5, 0.5]); a pose is the object's centre (the released code draws an object at -theta);
* Gamma's correction is scaled by 0.5 (theta = theta_hat + 0.5 zeta), the released code's factor;
* ``small`` computes the background's map on a 2x2 grid, upsampled to the 8x8 one: with the thesis's
  full-resolution background the small model draws the balls into the background (docs/relate.md);
* ``small`` gives the balls windows of a quarter of the grid (2 of 8 cells; the thesis's 8 of 16 would
  be four times a ball's width at 32 px);
* the video model's velocities are bounded by ``train.max_speed`` per frame (the released code: 1, an
  image's half-width), and it trains on a random window of a rollout ``train.clip`` + 4 frames long
  (the released code: 20).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from physint_cli.config import field_
from physint_cli.errors import BadInput

VARIANTS = ("static", "ordered", "video")
ARMS = ("full", "no-residual", "no-position", "blockgan2d")


@dataclass
class DataConfig:
    train: int = field_(500, "training sequences (balls-in-bowl) or images (clevr-table, shapestacks) "
                             "(thesis BallsInBowl: 2,500)", ge=1)
    test: int = field_(100, "test sequences or images (thesis BallsInBowl: 500)", ge=1)
    size: int = field_(64, "image side in pixels; training may read them smaller (train.size)", ge=16, le=512)
    frames: int = field_(32, "frames per balls-in-bowl sequence (FVD uses 30)", ge=2)
    frame_dt: float = field_(0.05, "seconds between two frames of a sequence", gt=0.0)
    balls: int = field_(2, "balls in the bowl (thesis: 2, fixed colours)", ge=1, le=4)
    speed: float = field_(0.8, "largest start speed of a ball along each axis (m/s)", gt=0.0)
    min_objects: int = field_(2, "fewest objects of a clevr-table scene or blocks of a tower", ge=1)
    max_objects: int = field_(5, "most objects of a clevr-table scene or blocks of a tower", ge=1, le=10)
    unstable: int = field_(1000, "shapestacks: towers Lemma 1 calls unstable (VCOM), a split of their own never trained "
                                 "on, which teaches and checks the evaluation's tower reader", ge=0)
    textures: bool = field_(False, "shapestacks: the stability plugin's random textures and colours")
    per_shard: int = field_(50, "sequences or images per shard (work unit)", ge=1)

    def validate(self) -> None:
        if self.min_objects > self.max_objects:
            raise BadInput(f"data.min_objects ({self.min_objects}) must not exceed data.max_objects ({self.max_objects})")


@dataclass
class TrainConfig:
    variant: Literal["static", "ordered", "video"] = field_(
        "static", "static: a scene from independent latents through Gamma (Eqs. 5.1, 5.2); ordered: towers, each "
                  "block placed on the one below (Eq. 5.3; shapestacks); video: clips, Gamma rolling the poses "
                  "forward from velocities and pairwise interactions (Eq. 5.4; balls-in-bowl)")
    clip: int = field_(8, "video: frames per training clip, generated and real (thesis BallsInBowl: 15)", ge=2)
    scale: bool = field_(False, "the scale-augmented model (Section 5.A.2, 'Ours + scale'): each object's window "
                                "size H'_k = H' (1 + sc(z_0, theta_k, z_k))")
    max_speed: float = field_(0.25, "video: the fastest an object may move per frame, in image units (-1..1 across)",
                              gt=0.0, le=1.0)
    arm: Literal["full", "no-residual", "no-position", "blockgan2d"] = field_(
        "full", "the ablation arm of Table 5.4.1: full RELATE, Gamma without the residual, without the position "
                "loss, or BlockGAN2D (no Gamma, no position loss)")
    size: int = field_(32, "image side the model generates (the dataset's frames are resized to it; thesis: 128)", ge=16)
    grid: int = field_(8, "side of the feature grid the objects are placed on (thesis: 16 at 128 px)", ge=4)
    window: float = field_(0.0, "object window H' as a share of the grid (0: the thesis's, 8 of 16 for balls-in-bowl, "
                                "4 of 16 for the others; small: a quarter, the balls being small at 32 px)", ge=0.0, le=1.0)
    pose_scale: float = field_(1.0, "the independent poses theta_hat are drawn from the thesis's range (Table 5.D.1: "
                                    "[-0.8, 0.8]^2 balls-in-bowl, [-0.6, 0.6]^2 otherwise) times this", gt=0.0, le=1.0)
    background_grid: int = field_(0, "side of the background's own feature map, upsampled bilinearly to the grid "
                                     "(0: the grid's, as the thesis; smaller keeps the background from drawing the "
                                     "objects itself)", ge=0)
    z_obj: int = field_(0, "object appearance latent N_f (0: the thesis's, 1 for balls-in-bowl, 64 otherwise)", ge=0)
    z_bg: int = field_(0, "background latent N_b (0: the thesis's, 3 for balls-in-bowl, 12 for shapestacks, 1 "
                          "otherwise)", ge=0)
    channels: int = field_(64, "generator feature channels (thesis: 256; objects twice as many)", ge=4)
    d_channels: int = field_(32, "discriminator's first layer channels, doubling per layer (thesis: 64)", ge=4)
    iterations: int = field_(8000, "generator updates (thesis BallsInBowl: 60 epochs of 10,000)", ge=1)
    batch_size: int = field_(32, "images per batch (the released code: 64)", ge=2)
    lr: float = field_(1e-3, "Adam learning rate of G and D (Table 5.D.1: 1e-3 balls-in-bowl and shapestacks, 1e-4 "
                             "clevr)", gt=0.0)
    beta1: float = field_(-1.0, "Adam beta1 (-1: the thesis's, 0.5 for balls-in-bowl, 0 otherwise)", ge=-1.0, lt=1.0)
    g_steps: int = field_(1, "generator steps M per discriminator step (Table 5.D.1: 1 balls-in-bowl, 2 otherwise)", ge=1)
    position_weight: float = field_(1.0, "weight of the position loss ||theta_k - P(G(z_0, z_k, theta_k))||^2", ge=0.0)
    checkpoint_every: int = field_(250, "generator updates between checkpoints (--resume continues from the last)", ge=1)
    samples_every: int = field_(1000, "generator updates between sample grids in the run's artifacts", ge=1)


@dataclass
class EvalConfig:
    samples: int = field_(1000, "generated images the distances and rates are measured on (thesis FID: 10,000)", ge=2)
    features_epochs: int = field_(8, "epochs of the in-project feature network that regresses the ground truth", ge=1)
    inception: str = field_("", "path of a local TorchScript FID Inception (NVlabs' inception-2015-12-05.pt) for FID "
                                "beside FD-truth; empty: no FID (nothing is downloaded)")
    i3d: str = field_("", "video: path of a local TorchScript Kinetics I3D (i3d_torchscript.pt, StyleGAN-V's FVD) for FVD "
                          "beside FVD-truth; empty: no FVD")
    bg_range: float = field_(0.5, "background latents are drawn from U[-r, r] at test time (the thesis's 0.5)", gt=0.0,
                             le=1.0)
    clips: int = field_(500, "video: generated clips FVD-truth is measured on (thesis FVD: 500)", ge=2)
    frames: int = field_(30, "video: frames per evaluated clip, generated and real (thesis FVD: 30)", ge=2)
    toggle_samples: int = field_(200, "scenes of the toggle disentanglement score (Table 5.A.1)", ge=1)
    toggle_objects: int = field_(0, "objects per toggle scene (0: the thesis's 5, or the model's own count where "
                                    "objects have fixed identities)", ge=0)


@dataclass
class DeployConfig:
    samples: int = field_(16, "scenes in the sample grid", ge=1)
    objects: int = field_(0, "objects per generated scene (0: as trained); more than trained is out of distribution", ge=0)
    frames: int = field_(30, "video: frames per generated clip", ge=2)
    move: str = field_("", "--task edit: which object to move and by how much, 'K:DX,DY' in image units ([-1, 1] "
                           "across), e.g. '0:0.3,0'")


@dataclass
class RelateConfig:
    data: DataConfig = field_(DataConfig(), "the simulated scenes (Section 5.4)")
    train: TrainConfig = field_(TrainConfig(), "the generator, Gamma and the discriminator (Section 5.3, App. 5.D)")
    eval: EvalConfig = field_(EvalConfig(), "distances, physical plausibility and the toggle score (5.4, 5.A)")
    deploy: DeployConfig = field_(DeployConfig(), "sampling and editing scenes")


PRESETS = {
    "tiny": {"data.train": 8, "data.test": 4, "data.unstable": 8, "data.size": 32, "data.frames": 8, "data.per_shard": 4,
             "train.size": 16, "train.grid": 4, "train.channels": 8, "train.d_channels": 8, "train.iterations": 30,
             "train.batch_size": 8, "train.clip": 4, "train.checkpoint_every": 10, "train.samples_every": 15, "eval.samples": 32,
             "eval.features_epochs": 2, "eval.clips": 8, "eval.frames": 6, "eval.toggle_samples": 8, "deploy.samples": 4},
    "small": {"train.window": 0.25, "train.background_grid": 2},
    "paper": {"data.train": 2500, "data.test": 500, "data.size": 128, "data.per_shard": 100, "train.size": 128,
              "train.grid": 16, "train.channels": 256, "train.d_channels": 64, "train.iterations": 600000,
              "train.batch_size": 64, "eval.samples": 10000, "eval.features_epochs": 20, "eval.toggle_samples": 1000},
}
