"""Evaluating the stability predictor (thesis Sections 3.4.1 and 3.4.2).

1. Accuracy on the simulated test split featuring all shapes, overall and per subset, stack
   height and violation type: the "Simulated" row of Table 3.3.
2. Instability localisation by occlusion (Section 3.4.2, Table 3.4): a soft-edged Gaussian-
   blurred patch slides over each unstable test image; the drop in predicted instability maps
   where the network looks; its maximiser is checked against the segmentation map (violating
   object, first object to fall, violation area, tower base, tower top, background), beside
   random-chance rows computed from the same maps.
3. Cross-backend generalisation (not in the thesis): accuracy on another backend's renders.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from physint_cli.errors import BadInput
from physint_cli.method import Context

SUBSETS = ("cubes", "ccs")
VIOLATIONS = ("stable", "VCOM", "VPSF")
REGIONS = ("violating_object", "first_to_fall", "violation_area", "tower_base", "tower_top", "background")


# -- accuracy -----------------------------------------------------------------------------------

def predict(model, images: np.ndarray, input_size: int, batch_size: int = 128) -> np.ndarray:
    """P(unstable) for uint8 images (N, H, W, 3)."""
    import torch

    from .augment import EvalTransform

    tf = EvalTransform(input_size)
    out = []
    with torch.no_grad():
        for start in range(0, len(images), batch_size):
            x = tf(images[start:start + batch_size])
            out.append(torch.sigmoid(model(x).reshape(-1)).numpy())
    return np.concatenate(out) if out else np.zeros(0)


def test_split_scores(model, input_size: int, data, batch_size: int) -> dict[str, np.ndarray]:
    """Scores and annotations of every test image of a dataset, read shard by shard."""
    from physint_cli.datasets import ShardedDataset

    ds = ShardedDataset(data, "test", method="stability")
    columns = {k: [] for k in ("score", "label", "violation", "height", "subset")}
    for shard in ds.shard_arrays(["image", "label", "violation", "height", "subset"]):
        columns["score"].append(predict(model, shard["image"], input_size, batch_size))
        for k in ("label", "violation", "height", "subset"):
            columns[k].append(shard[k])
    ds.close()
    return {k: np.concatenate(v) for k, v in columns.items()}


def accuracy_table(s: dict[str, np.ndarray]) -> dict[str, Any]:
    correct = (s["score"] > 0.5) == (s["label"] == 1)

    def acc(mask) -> float | None:
        return float(correct[mask].mean()) if mask.any() else None

    return {
        "accuracy": float(correct.mean()), "images": int(len(correct)),
        "by_subset": {name: acc(s["subset"] == i) for i, name in enumerate(SUBSETS)},
        "by_height": {str(h): acc(s["height"] == h) for h in sorted(set(s["height"].tolist()))},
        "by_violation": {name: acc(s["violation"] == i) for i, name in enumerate(VIOLATIONS)},
        "unstable_fraction": float((s["label"] == 1).mean()),
    }


# -- occlusion study (Section 3.4.2) --------------------------------------------------------------

def gaussian_blur(images, sigma: float):
    """Separable Gaussian blur of float images (N, 3, H, W) with reflect padding."""
    import torch
    import torch.nn.functional as F

    radius = max(1, int(math.ceil(3 * sigma)))
    x = torch.arange(-radius, radius + 1, dtype=torch.float32)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = (k / k.sum()).to(images.dtype)
    c = images.shape[1]
    pad = min(radius, images.shape[-1] - 1, images.shape[-2] - 1)
    out = images
    for dim in (-1, -2):
        kernel = k.reshape(1, 1, 1, -1) if dim == -1 else k.reshape(1, 1, -1, 1)
        padding = (radius, radius, 0, 0) if dim == -1 else (0, 0, radius, radius)
        out = F.pad(out, padding, mode="replicate") if pad < radius else F.pad(out, padding, mode="reflect")
        out = F.conv2d(out, kernel.expand(c, 1, *kernel.shape[2:]), groups=c)
    return out


def soft_patch(size: int, centre: tuple[float, float], patch: float):
    """A mask that is 1 over a ``patch``-sized square at ``centre`` and fades out smoothly (no hard edge)."""
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    half, fade = patch / 2.0, max(patch / 3.0, 1.0)
    dx = np.clip(np.abs(xx - centre[0]) - half, 0, None)
    dy = np.clip(np.abs(yy - centre[1]) - half, 0, None)
    return np.exp(-0.5 * (dx ** 2 + dy ** 2) / fade ** 2)


def attention_map(model, image: np.ndarray, input_size: int, sigma: float, patch: float, stride: int):
    """Drop in P(unstable) when each patch is blurred, and the patch centres (x, y) in pixels."""
    import torch

    from .augment import EvalTransform

    size = image.shape[0]
    x = torch.as_tensor(image, dtype=torch.float32).permute(2, 0, 1)[None] / 255.0
    blurred = gaussian_blur(x, sigma)
    centres = [(cx + 0.5, cy + 0.5) for cy in range(stride // 2, size, stride) for cx in range(stride // 2, size, stride)]
    masks = torch.as_tensor(np.stack([soft_patch(size, c, patch) for c in centres]))[:, None]
    occluded = x * (1 - masks) + blurred * masks
    tf = EvalTransform(input_size)
    with torch.no_grad():
        base = torch.sigmoid(model(tf((x * 255).round().to(torch.uint8).permute(0, 2, 3, 1))).reshape(-1))[0]
        scores = []
        for start in range(0, len(occluded), 64):
            batch = (occluded[start:start + 64] * 255).round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1)
            scores.append(torch.sigmoid(model(tf(batch)).reshape(-1)))
    drop = (base - torch.cat(scores)).numpy()  # evidence for instability that the patch hid
    return drop, np.asarray(centres)


def regions(seg: np.ndarray, violating: int, first: int, height: int) -> dict[str, np.ndarray]:
    """Boolean masks of the semantic regions of Table 3.4 from a per-object segmentation map."""
    masks = {"violating_object": seg == violating, "first_to_fall": seg == first,
             "tower_base": seg == 0, "tower_top": seg == height - 1, "background": seg < 0}
    both = masks["violating_object"] | masks["first_to_fall"]
    area = np.zeros_like(both)
    if both.any():  # the smallest rectangle enclosing the violating object and the first to fall
        ys, xs = np.nonzero(both)
        area[ys.min():ys.max() + 1, xs.min():xs.max() + 1] = True
    masks["violation_area"] = area
    return masks


def tower_box(seg: np.ndarray) -> np.ndarray:
    box = np.zeros(seg.shape, dtype=bool)
    ys, xs = np.nonzero(seg >= 0)
    if len(ys):
        box[ys.min():ys.max() + 1, xs.min():xs.max() + 1] = True
    return box


def occlusion_unit(ctx: Context, unit) -> list[dict[str, Any]]:
    """The occlusion study on one batch of test images (a work unit: runs in a worker or on Ray)."""
    from physint_cli.datasets import ShardedDataset

    from .checkpoint import load_predictor

    e = ctx.config.eval
    model, input_size = load_predictor(ctx.source_run, "cpu")
    ds = ShardedDataset(unit.params["data"], "test", method="stability")
    out = []
    for index in unit.params["indices"]:
        rec = ds[index]
        size = rec["image"].shape[0]
        scale = size / 224.0  # the thesis's sigma 30 px, 14 px patches and stride 8 are at 224 px
        drop, centres = attention_map(model, rec["image"], input_size, e.occlusion_sigma * scale,
                                      max(2.0, e.occlusion_patch * scale), max(1, round(e.occlusion_stride * scale)))
        cx, cy = centres[int(np.argmax(drop))]
        px, py = min(int(cx), size - 1), min(int(cy), size - 1)
        masks = regions(rec["segmentation"], int(rec["violating"]), int(rec["first_to_fall"]), int(rec["height"]))
        box = tower_box(rec["segmentation"])
        out.append({"kind": VIOLATIONS[int(rec["violation"])],
                    "hit": {r: bool(masks[r][py, px]) for r in REGIONS},
                    "chance_image": {r: float(masks[r].mean()) for r in REGIONS},
                    "chance_tower": {r: float(masks[r][box].mean()) if box.any() else 0.0 for r in REGIONS},
                    "example": (rec["image"], drop, centres, (px, py)) if index == unit.params["indices"][0] else None})
    ds.close()
    return out


def occlusion_study(ctx: Context, data) -> dict[str, Any]:
    """Table 3.4 on ``eval.occlusion_images`` unstable test images (a seeded random sample)."""
    from physint_cli.datasets import ShardedDataset
    from physint_cli.method import Unit, unit_seed

    ds = ShardedDataset(data, "test", method="stability")
    unstable = np.flatnonzero(ds.column("label") == 1)
    ds.close()
    if ctx.config.eval.occlusion_images > 0 and len(unstable) == 0:
        raise BadInput(f"test split of {data} has no unstable images: the occlusion study (Table 3.4) needs some "
                       f"(or set eval.occlusion_images=0)")
    rng = np.random.default_rng(unit_seed(ctx.seed, "occlusion"))
    chosen = sorted(int(i) for i in rng.choice(unstable, size=min(ctx.config.eval.occlusion_images, len(unstable)),
                                                 replace=False)) if len(unstable) else []
    per_unit = 10
    units = [Unit("occlusion", k, len(chunk), 0, {"indices": chunk, "data": str(data)})
             for k, chunk in enumerate(chosen[i:i + per_unit] for i in range(0, len(chosen), per_unit))]
    images = [r for part in ctx.map(occlusion_unit, units, description="occlusion study") for r in part]

    def rate(values: list) -> float | None:
        return float(np.mean(values)) if values else None

    table: dict[str, Any] = {}
    for kind in ("all", "VCOM", "VPSF"):
        rows = [r for r in images if kind == "all" or r["kind"] == kind]
        table[kind] = {reg: rate([r["hit"][reg] for r in rows]) for reg in REGIONS}
    table["random_in_image"] = {reg: rate([r["chance_image"][reg] for r in images]) for reg in REGIONS}
    table["random_in_tower"] = {reg: rate([r["chance_tower"][reg] for r in images]) for reg in REGIONS}
    table["images"] = len(images)
    return {"table": table, "example": images[0]["example"] if images else None}


# -- the verb -------------------------------------------------------------------------------------

def evaluate(ctx: Context) -> dict[str, Any]:
    from physint_cli.plugins import get_plugins
    from physint_cli.runs import Run
    from physint_cli.workflow import ensure_dataset

    from .checkpoint import load_predictor

    method = get_plugins().method("stability")
    model, input_size = load_predictor(ctx.source_run, ctx.device)
    e = ctx.config.eval
    # the thesis tests on stacks of all shapes, whatever the predictor was trained on
    test_data = ctx.data if (ctx.scene == "all" and ctx.data) else \
        ensure_dataset(method, ctx.with_(scene="all"), None, splits=("test",))
    scores = test_split_scores(model, input_size, test_data, e.batch_size)
    metrics: dict[str, Any] = {"trained_on": _trained_scene(ctx), "backend": ctx.backend,
                               "test_data": str(test_data), **accuracy_table(scores)}
    run = Run(ctx.run)
    occlusion = occlusion_study(ctx, test_data)
    metrics["localisation"] = occlusion["table"]
    if e.cross_backend:
        other = ensure_dataset(method, ctx.with_(scene="all", backend=e.cross_backend), None, splits=("test",))
        metrics["cross_backend"] = {e.cross_backend: {"test_data": str(other),
                                                      **accuracy_table(test_split_scores(model, input_size, other, e.batch_size))}}
    _plots(run, metrics, occlusion["example"])
    _prediction_grid(run, model, input_size, test_data, ctx.seed)
    return metrics


def _prediction_grid(run, model, input_size: int, data, seed: int, n: int = 12) -> None:
    """``predictions.png``: ``n`` test images of the first shard (a seeded sample, stable and unstable
    alike) with the predicted P(unstable) and what the simulator did, green where the two agree."""
    from physint_cli.artifacts import save_plot
    from physint_cli.datasets import ShardedDataset

    ds = ShardedDataset(data, "test", method="stability")
    shard = next(iter(ds.shard_arrays(["image", "label"])), None)
    ds.close()
    if shard is None or len(shard["label"]) == 0:
        return
    chosen = np.random.default_rng(seed).permutation(len(shard["label"]))[:n]
    images, labels = shard["image"][chosen], shard["label"][chosen]
    scores = predict(model, images, input_size)
    cols = min(6, len(chosen))
    rows = -(-len(chosen) // cols)

    def draw(ax):
        ax.axis("off")
        fig = ax.figure
        for i, (image, label, p) in enumerate(zip(images, labels, scores)):
            sub = fig.add_subplot(rows, cols, i + 1)
            sub.imshow(image)
            sub.set_xticks([])
            sub.set_yticks([])
            colour = "tab:green" if (p > 0.5) == (label == 1) else "tab:red"
            for spine in sub.spines.values():
                spine.set_edgecolor(colour)
                spine.set_linewidth(3)
            sub.set_title(f"P(falls) {p:.2f}\n{'fell' if label == 1 else 'stood'}", fontsize=8, color=colour)

    save_plot(run.artifact("predictions.png"), draw, figsize=(1.8 * cols, 2.1 * rows))


def _trained_scene(ctx: Context) -> str:
    import json

    try:
        return json.loads((ctx.source_run / "run.json").read_text()).get("scene", "?")
    except (OSError, ValueError):
        return "?"


def _plots(run, metrics: dict[str, Any], example) -> None:
    from physint_cli.artifacts import save_image, save_plot

    def bars(ax):
        groups = [("all", metrics["accuracy"])] + [(k, v) for k, v in metrics["by_subset"].items() if v is not None] + \
                 [(f"h={k}", v) for k, v in metrics["by_height"].items() if v is not None] + \
                 [(k, v) for k, v in metrics["by_violation"].items() if v is not None]
        ax.bar(range(len(groups)), [v for _, v in groups])
        ax.set_xticks(range(len(groups)), [g for g, _ in groups], rotation=45, ha="right")
        ax.axhline(0.5, color="grey", ls=":", lw=1)
        ax.set_ylim(0, 1)
        ax.set_ylabel("accuracy")
        ax.set_title(f"stability predictor trained on {metrics['trained_on']}, tested on all shapes")

    save_plot(run.artifact("accuracy.png"), bars, figsize=(7, 4))
    if example is not None:
        image, drop, centres, (px, py) = example
        size = image.shape[0]
        heat = np.zeros((size, size), np.float32)
        stride = max(1, int(round(centres[1][0] - centres[0][0]))) if len(centres) > 1 else 1
        for (cx, cy), d in zip(centres, drop):
            heat[int(cy - stride / 2):int(cy + stride / 2) + 1, int(cx - stride / 2):int(cx + stride / 2) + 1] = d
        span = max(float(np.abs(heat).max()), 1e-6)
        rgb = np.zeros((size, size, 3), np.float32)
        rgb[..., 0] = np.clip(heat / span, 0, 1)  # red: occluding here lowers P(unstable)
        rgb[..., 2] = np.clip(-heat / span, 0, 1)
        overlay = (0.5 * image + 0.5 * 255 * rgb).astype(np.uint8)
        overlay[max(0, py - 1):py + 2, :, 1] = 255  # cross hair on the maximiser
        overlay[:, max(0, px - 1):px + 2, 1] = 255
        pair = np.concatenate([image, overlay], axis=1)
        zoom = max(1, 256 // size)  # small images are enlarged (nearest neighbour) to be seen
        save_image(run.artifact("occlusion_example.png"), pair.repeat(zoom, axis=0).repeat(zoom, axis=1))
