"""The toolsynth config and its tiny / small / paper presets (thesis Chapter 4, Appendices 4.A, 4.B).

``paper`` is the thesis's setup: 16,000 training and 2,500 validation tasks at 128 px with 12
tool views, balanced 50/50 per scenario type (Table 4.A.1: A-D in training, A-E in validation);
Adam at 1e-4, batch 16 (Appendix 4.B); imagination with step 0.01 for at most 10,000 steps or
until p(success) >= 0.997 (Section 4.4.3), on 250 infeasible instances per type. ``small`` is sized
for two CPU cores in fp32 (docs/toolsynth.md has its figures).

Deviations from the thesis (docs/toolsynth.md says why):

* a third split, ``test`` (A-E, as large as the validation split), holds the instances imagination
  is measured on, so that the checkpoint chosen on the validation split never sees them;
* Eq. 4.5 adds the gradient of L_task to z_T, which ascends the loss; imagination descends it
  (towards p(success) = 1), as the text around the equation describes;
* imagination steps with Adam at learning rate eta by default (``eval.optimizer``): the thesis says
  only "via backpropagation using a learning rate of 0.01"; ``sgd`` is Eq. 4.5 to the letter;
* the reconstruction loss is the silhouette IoU in the other view (L_s) plus mu times the
  Laplacian and flatten losses of Kato et al. / S. Liu et al. (L_g), with a soft rasteriser
  written in torch (SoftRas is not installable here);
* a pose that keeps less than 2 mm from an obstacle counts as touching it (``feasibility.CLEARANCE``);
* the ring's cameras look down from 55 degrees (``data.elevation``; the thesis does not say): from
  30 degrees a 2 cm handle is one pixel wide at 64 px;
* the decoder's vertices may cross the template's centre (``train.deform=free``; SoftRas keeps each
  in its octant round a centroid, which leaves hooks a second leg, ``model.MeshDecoder``);
* imagination and the random walk stay inside the box round the training records' tool latents
  (``eval.latent_box``, on): outside it the decoder draws tools unlike any record (one giant hook
  for every task, once hard examples have taught the classifier to refuse sticks through walls);
* a 64-dimensional z_T (``train.z_tool``; ``paper``: 512), and ``train.latent=layer`` standardises
  it over its coordinates (``paper``: SoftRas's linear layer), so that L_task cannot inflate its scale;
* ``train.hard_examples`` (off in ``paper``) adds imagined tools labelled by the geometric check to
  the classifier's batches in stages 2 and 3 (``hard.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from physint_cli.config import field_
from physint_cli.errors import BadInput

from .tasks import parse_types


@dataclass
class DataConfig:
    train: int = field_(4000, "training tasks, balanced over data.train_types and feasible / infeasible "
                              "(thesis: 16,000)", ge=2)
    val: int = field_(500, "validation tasks over data.eval_types (thesis: 2,500)", ge=2)
    test: int = field_(2500, "test tasks over data.eval_types, the instances imagination is measured on (not "
                             "in the thesis, which measured on its validation split): 250 infeasible per type", ge=2)
    train_types: str = field_("ABCD", "scenario types in training (Table 4.A.1: E is held out)")
    eval_types: str = field_("ABCDE", "scenario types in the validation and test splits")
    task_size: int = field_(64, "task image side in pixels (thesis: 128)", ge=32)
    tool_size: int = field_(64, "tool view side in pixels (thesis: 128)", ge=32)
    views: int = field_(12, "cameras on the ring round each tool; a record keeps two of them (thesis: 12)", ge=2)
    elevation: float = field_(55.0, "degrees above the horizontal of the ring's cameras (not in the thesis); the "
                                    "higher, the more of a tool's width its silhouettes show", ge=5.0, le=85.0)
    per_shard: int = field_(100, "tasks per shard (work unit)", ge=1)
    sim_check: float = field_(0.05, "share of records whose label the simulator confirms by contacts (the "
                                    "agreement rate goes to the manifest)", ge=0.0, le=1.0)
    max_attempts: int = field_(50, "tasks tried per record before giving up on finding a tool with its label; "
                                   "each task tries 100 tools", ge=1)

    def validate(self) -> None:
        parse_types(self.train_types, "data.train_types")
        parse_types(self.eval_types, "data.eval_types")


@dataclass
class TrainConfig:
    recon_epochs: int = field_(12, "stage 1: epochs of 3D reconstruction alone (Section 4.4.1)", ge=1)
    joint_epochs: int = field_(12, "stage 2: epochs of reconstruction and task prediction together; the "
                                   "task-unaware model trains its task encoder and classifier as long", ge=1)
    batch_size: int = field_(32, "records per batch (thesis: 16)", ge=1)
    lr: float = field_(3e-4, "Adam learning rate of stage 1, reconstruction (thesis: 1e-4)", gt=0.0)
    joint_lr: float = field_(1e-4, "Adam learning rate of stage 2 (task-driven) and of the task-unaware "
                                   "classifier (thesis: 1e-4)", gt=0.0)
    width: float = field_(0.5, "tool encoder filter multiplier (1.0: SoftRas's 64-128-256)", gt=0.0)
    task_width: float = field_(0.5, "task encoder filter multiplier (1.0: Appendix 4.B's 16-32-64-64-128)", gt=0.0)
    z_tool: int = field_(64, "size of the tool latent z_T (thesis, SoftRas: 512)", ge=2)
    z_task: int = field_(256, "size of the task latent z_G", ge=2)
    subdivisions: int = field_(2, "icosphere subdivisions of the template mesh (2: 162 vertices, 320 faces; "
                                  "SoftRas: 642 vertices)", ge=1, le=4)
    deform: Literal["octant", "free"] = field_("free", "how the decoder moves template vertices: octant "
                                                         "(SoftRas: each stays in its octant round a centroid) "
                                                         "or free (any coordinate may cross the centre)")
    norm: Literal["batch", "group", "none"] = field_("batch", "normalisation after each tool-encoder convolution "
                                                              "(SoftRas: batch)")
    latent: Literal["linear", "layer"] = field_("layer", "the tool encoder's last layer: linear (SoftRas's) or "
                                                          "layer (z_T standardised over its coordinates, a fixed "
                                                          "scale that L_task cannot inflate)")
    sigma: float = field_(0.1, "softness of the silhouette rasteriser's edges (pixels squared; SoftRas: 0.1 "
                               "at 64 px). Softer edges bleed over thin handles, and the decoder learns to "
                               "shrink its tools to make up for it", gt=0.0)
    laplacian: float = field_(5e-3, "weight of the Laplacian loss in mu * L_g (Eq. 4.2)", ge=0.0)
    flatten: float = field_(5e-4, "weight of the flatten loss in mu * L_g (Eq. 4.2)", ge=0.0)
    latent_noise: float = field_(0.0, "Gaussian noise added to z_T before the classifier in stages 2 and 3, in "
                                      "units of the batch's per-coordinate spread (0: none, as the thesis)", ge=0.0)
    hard_examples: int = field_(8, "infeasible records per batch of stages 2 and 3 that imagination starts from, "
                                   "the latents where it stops labelled by the geometric check for the "
                                   "classifier (0: none, as the thesis; hard.py)", ge=0)
    hard_steps: int = field_(100, "step cap of the imagination that makes hard examples", ge=1)
    task_weight: float = field_(1.0, "weight of L_task in stage 2 (Eq. 4.4: 1)", ge=0.0)
    precision: Literal["fp32", "bf16", "auto"] = field_("fp32", "fp32, bf16, or auto (bf16 where the hardware has "
                                                                "it natively)")


@dataclass
class EvalConfig:
    types: str = field_("ABCDE", "scenario types to imagine tools for")
    instances: int = field_(250, "infeasible test instances per type, each warm-starting every imagination "
                                 "process (thesis: 250)", ge=1)
    step: float = field_(0.01, "imagination learning rate eta (Eq. 4.5) and the random walk's step", gt=0.0)
    optimizer: Literal["adam", "sgd"] = field_("adam", "how imagination steps on the gradient: adam (each coordinate "
                                                       "moves about eta, as the random walk's) or sgd (Eq. 4.5: "
                                                       "eta times the gradient)")
    max_steps: int = field_(2000, "step cap S (thesis: 10,000)", ge=1)
    threshold: float = field_(0.997, "stop once p(success) reaches gamma", gt=0.0, lt=1.0)
    latent_box: bool = field_(True, "keep imagination and the random walk inside the box of the training "
                                     "records' tool latents (per coordinate their least and greatest value; not "
                                     "in the thesis): beyond it the decoder extrapolates")
    sim_check: bool = field_(True, "also place each imagined tool in the simulator and check it by contacts")

    def validate(self) -> None:
        parse_types(self.types, "eval.types")


@dataclass
class DeployConfig:
    type: str = field_("D", "scenario type of the generated task (with no --target image)")
    tool: str = field_("", "a start tool as a mesh file (.obj, .stl, .ply; metres, lying flat) instead of a "
                           "generated tool that cannot reach")
    every: int = field_(0, "draw the tool in the optimisation strip every k steps (0: eight frames)", ge=0)
    video: bool = field_(True, "write a video of the imagination and of the robot's tool reaching the target")

    def validate(self) -> None:
        if len(parse_types(self.type, "deploy.type")) != 1:
            raise BadInput(f"deploy.type is one scenario type, got {self.type!r}")


@dataclass
class ToolsynthConfig:
    data: DataConfig = field_(DataConfig(), "reaching tasks and tools (Appendix 4.A)")
    train: TrainConfig = field_(TrainConfig(), "the tool and task encoders, mesh decoder and classifier (4.3, 4.B)")
    eval: EvalConfig = field_(EvalConfig(), "tool imagination against its baselines (Section 4.4.3, Table 4.1)")
    deploy: DeployConfig = field_(DeployConfig(), "imagining a tool for one task")


PRESETS = {
    "tiny": {"data.train": 64, "data.val": 20, "data.test": 40, "data.task_size": 32, "data.tool_size": 32,
             "data.views": 4, "data.per_shard": 32, "data.sim_check": 0.2, "train.recon_epochs": 2,
             "train.joint_epochs": 2, "train.joint_lr": 3e-4, "train.batch_size": 8, "train.width": 0.25, "train.task_width": 0.25,
             "train.z_tool": 64, "train.z_task": 32, "train.subdivisions": 1, "train.hard_examples": 0, "eval.instances": 4,
             "eval.max_steps": 100},
    "small": {},
    "paper": {"data.train": 16000, "data.val": 2500, "data.test": 2500, "data.task_size": 128,
              "data.tool_size": 128, "data.per_shard": 250, "data.sim_check": 0.02, "train.batch_size": 16,
              "train.lr": 1e-4, "train.z_tool": 512, "train.latent": "linear", "train.hard_examples": 0,
              "train.width": 1.0, "train.task_width": 1.0, "train.subdivisions": 3,
              "train.recon_epochs": 40, "train.joint_epochs": 40, "eval.instances": 250, "eval.max_steps": 10000},
}
