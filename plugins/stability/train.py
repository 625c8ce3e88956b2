"""Training the visual stability predictor (thesis Section 3.4.1).

Images of initial, static stacks with their 0/1 labels (1 = unstable) train a CNN with the
logistic loss of Eq. 3.2, with physically plausible augmentation (towers stay upright).
"""

from __future__ import annotations

import inspect
from typing import Any

import numpy as np

from physint_cli.errors import BadInput
from physint_cli.method import Context

FIELDS = ["image", "label"]


def build_model(name: str, input_size: int, width: int):
    """A registered stability model (``register_models``), given the input size (and width if it has one)."""
    from physint_cli.training import registered_model

    build = registered_model("stability", name).build
    kwargs: dict[str, Any] = {"in_size": input_size}
    if "width" in inspect.signature(build).parameters:
        kwargs["width"] = width
    try:
        return build(**kwargs), kwargs
    except ValueError as exc:  # e.g. an input size the architecture cannot take
        raise BadInput(f"model {name!r} cannot be built with train.input_size={input_size}: {exc}") from None


class ImageLabel:
    """ShardedDataset record -> {"image": ``transform(image)``, "label": float ()}; without a transform
    the image stays uint8 (H, W, 3), for a batched transform after collation."""

    def __init__(self, transform=None):
        self.transform = transform

    def __call__(self, record: dict[str, np.ndarray]) -> dict[str, Any]:
        import torch

        image = torch.from_numpy(np.ascontiguousarray(record["image"]))
        return {"image": self.transform(image) if self.transform is not None else image,
                "label": torch.tensor(float(record["label"]))}


class BatchAugment:
    """Collated batch {"image": uint8 (N, H, W, 3), ...} -> float (N, 3, S, S), augmented as one batch."""

    def __init__(self, transform):
        self.transform = transform

    def __call__(self, batch: dict[str, Any]) -> dict[str, Any]:
        return {**batch, "image": self.transform(batch["image"])}


def logits_of(model, images):
    out = model(images)
    return out.reshape(out.shape[0]).float()  # fp32 logits for the loss, also under bf16 autocast


def accuracy(model, loader) -> float:
    import torch

    correct, total = 0, 0
    with torch.no_grad():
        for batch in loader:
            pred = (logits_of(model, batch["image"]) > 0).float()  # logit > 0 <=> P(unstable) > 0.5
            correct += int((pred == batch["label"]).sum())
            total += len(pred)
    return correct / max(total, 1)


def train(ctx: Context) -> dict[str, Any]:
    import torch

    from physint_cli.datasets import ShardedDataset
    from physint_cli.artifacts import save_training_curves
    from physint_cli.training import fit

    from .augment import EvalTransform, TrainTransform
    from .model import adamw_cosine, logistic_loss, rmsprop_for

    cfg = ctx.config.train
    name = ctx.model or cfg.model
    model, kwargs = build_model(name, cfg.input_size, cfg.width)
    train_tf = TrainTransform(cfg.input_size) if cfg.augment else EvalTransform(cfg.input_size)
    # small preset: both splits (1.5 GB) are read once, not every epoch; paper preset: streamed
    train_set = ShardedDataset(ctx.data, "train", FIELDS, transform=ImageLabel(), method="stability", in_memory="auto")
    val_set = ShardedDataset(ctx.data, "val", FIELDS, transform=ImageLabel(EvalTransform(cfg.input_size)),
                             method="stability", in_memory="auto")
    labels = train_set.column("label")
    if len(labels) == 0 or labels.min() == labels.max():
        what = "no images" if len(labels) == 0 else ("no unstable images" if labels.max() == 0 else "no stable images")
        raise BadInput(f"dataset {ctx.data} has {what} in its train split; the predictor learns from stable and "
                       f"unstable stacks: make one with `physint dataset stability`")
    ctx.log(f"training {name} on {len(train_set)} images ({labels.mean():.0%} unstable), validating on {len(val_set)}")

    def loss_fn(net, batch):
        return logistic_loss(logits_of(net, batch["image"]), batch["label"])  # Eq. 3.2

    make_optimizer = None
    if cfg.optimizer == "rmsprop":  # the Inception-v4 paper's solver (thesis: "hyper-parameters as in [192]")
        def make_optimizer(net):
            return rmsprop_for(net, paper=True, lr=cfg.lr, weight_decay=cfg.weight_decay)
    elif cfg.optimizer == "adamw":  # the CPU default: AdamW, learning rate on a cosine over the epochs
        def make_optimizer(net):
            return adamw_cosine(net, lr=cfg.lr, weight_decay=cfg.weight_decay, epochs=cfg.epochs)
    result = fit(model, train_set, val_set, run=ctx.output(), epochs=cfg.epochs, batch_size=cfg.batch_size,
                 lr=cfg.lr, weight_decay=cfg.weight_decay, loss_fn=loss_fn, metric_fn=accuracy, device=ctx.device,
                 seed=ctx.seed, resume=ctx.resume, log=ctx.log, higher_is_better=True,
                 num_workers=cfg.num_workers, make_optimizer=make_optimizer, precision=cfg.precision,
                 channels_last=True, batch_transform=BatchAugment(train_tf),
                 progress=not ctx.quiet,
                 meta={"method": "stability", "model": name, "kwargs": kwargs, "scene": ctx.scene})
    save_training_curves(ctx.output().artifact("training_curves.png"), result.history,
                         loss="train logistic loss (Eq. 3.2)", metric="val accuracy", chance=0.5)
    return {"model": name, "epochs": result.epochs, "val_accuracy": result.best_metric,
            "train_images": len(train_set), "val_images": len(val_set), "scene": ctx.scene}


