"""Evaluating a trained RELATE model (thesis Section 5.4, Tables 5.4.1 and 5.A.1).

On ``eval.samples`` generated scenes, with Gamma and with Gamma bypassed (theta = theta_hat) on the same
model and the same latents:

* FD-truth: the Fréchet distance to the real test frames on the features of the in-project network
  that regresses the simulator's ground truth (``measure.TruthNet``; not FID, whose Inception weights
  cannot be downloaded here). The distance between the real training and test frames is its floor;
* physical plausibility (balls-in-bowl): the share of scenes with both balls seen, inside the bowl and
  not interpenetrating, read off the images (``measure.Detector``; its rate on real test frames too);
  (shapestacks) the share of towers whose blocks, as the tower reader reads them off the image, rest on
  each other and that Lemma 1 (the stability plugin's, through the registry) calls stable as seen
  (``measure.tower_plausibility``; the reader's rates on held-out real stable and unstable towers beside it);
* Table 5.A.1's toggle score: the median distance in pixels from the pixel that changes most when an
  object is left out to that object's pose (lower: each latent object is the thing drawn where it says).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from physint_cli.errors import BadInput
from physint_cli.method import Context

from . import measure
from .published import I3D, INCEPTION
from .checkpoint import dataset_header, image_grid, load_model, real_frames, to_uint8
from .dataset import load_split
from .model import present_mask

# Table 5.4.1: FID on BallsInBowl per ablation arm; Table 5.A.1: median toggle distance (BallsInBowl)
THESIS_FID = {"blockgan2d": 152.3, "no-residual": 133.9, "no-position": 154.8, "full": 81.9}
THESIS_TOGGLE = {"blockgan2d": 98.0, "full": 26.0}
FIELDS = ("frames", "pixels", "present", "bowl")
TRUTH_FRAMES = 8000  # training frames the ground-truth regressor learns from


def frame_truth(arrays: dict[str, np.ndarray], data_size: int, size: int, scene: str) -> np.ndarray:
    """Per frame the ground-truth targets of ``measure.truth_targets`` at the model's image size."""
    t = arrays["frames"].shape[1]
    pixels = arrays["pixels"].reshape(-1, *arrays["pixels"].shape[2:]) * size / data_size
    present = np.repeat(arrays["present"], t, axis=0)
    bowl = np.repeat(arrays["bowl"], t, axis=0) if scene == "balls-in-bowl" else None
    return measure.truth_targets(pixels, present, size, bowl)


TOWER_FIELDS = ("frames", "extent", "present")
READER_HELD_OUT = 0.2  # the share of the unstable towers kept to check the tower reader


def tower_check(ctx: Context, root: Path, size: int, data_size: int, train: dict, test: dict, train_frames: torch.Tensor,
                real_test: torch.Tensor, test_pick: torch.Tensor):
    """The tower reader (a TruthNet reading each block's box, trained once on the real training towers and 80 %
    of the unstable ones, kept beside the dataset) with Lemma 1 through the registry; the real rows: the
    held-out stable test towers and unstable towers as read, and the test towers' simulated boxes.
    Returns (read(images) -> tower_plausibility, real rows)."""
    from physint_cli.plugins import get_plugins

    lemma1 = get_plugins().metric("lemma1_side_view", "stability").fn  # Lemma 1 (Eq. 3.1), through the registry
    try:
        unstable = load_split(root, "unstable", TOWER_FIELDS)
    except BadInput:
        raise BadInput(f"{root} has no unstable towers to check the tower reader with: generate it again with "
                       "--set data.unstable=1000 (physint dataset relate --scene shapestacks)") from None
    cut = int(round(len(unstable["present"]) * (1 - READER_HELD_OUT)))
    boxes = lambda a: measure.box_targets(a["extent"][:, 0] * size / data_size, a["present"], size)  # noqa: E731
    unstable_frames = real_frames(unstable, size)
    keep = torch.randperm(len(train["present"]), generator=torch.Generator().manual_seed(4))[:TRUTH_FRAMES - cut]
    images = torch.cat([train_frames[keep], unstable_frames[:cut]])
    targets = np.concatenate([boxes(train)[keep.numpy()], boxes(unstable)[:cut]])
    path = root / "features" / f"towernet-{size}px-{ctx.config.eval.features_epochs}ep.pt"
    net = cached_truth_net(path, images, targets, ctx.config.eval.features_epochs, ctx.log, "real towers, stable and not")
    read = lambda x: measure.tower_plausibility(  # noqa: E731
        measure.tower_boxes(measure.embed(net, x, read_out=True), size), lemma1, size)
    rows = {"test towers, read": read(real_test[test_pick]),
            "unstable towers (held out), read": read(unstable_frames[cut:]),
            "test towers, simulated boxes": measure.tower_plausibility(
                measure.tower_boxes(boxes(test)[test_pick.numpy()], size), lemma1, size)}
    return read, rows


def truth_net(root: Path, frames: torch.Tensor, targets: np.ndarray, size: int, epochs: int, log) -> measure.TruthNet:
    """The dataset's ground-truth regressor at ``size`` px, trained once (seed 0) and kept beside the dataset
    (``features/truthnet-<size>px-<epochs>ep.pt``) so every arm is measured with the same features."""
    return cached_truth_net(root / "features" / f"truthnet-{size}px-{epochs}ep.pt", frames, targets, epochs, log)


def cached_truth_net(path: Path, images: torch.Tensor, targets: np.ndarray, epochs: int, log,
                     what: str = "real frames") -> measure.TruthNet:
    """A ground-truth regressor on uint8 images (N, C, s, s), loaded from ``path`` or trained (seed 0) and kept there."""
    if path.is_file():
        net = measure.TruthNet(images.shape[-1], targets.shape[1], channels=images.shape[1])
        try:
            net.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
            return net.eval()
        except (RuntimeError, OSError, EOFError, ValueError) as err:
            log(f"{path} is unreadable or of another network ({str(err).splitlines()[0][:80]}): training it again")
    pick = torch.randperm(len(images), generator=torch.Generator().manual_seed(0))[:TRUTH_FRAMES]
    log(f"training the ground-truth regressor on {len(pick)} {what} for {epochs} epochs (the distance's features)")
    net = measure.fit_truth_net(images[pick], targets[pick.numpy()], epochs)
    try:
        path.parent.mkdir(exist_ok=True)
        tmp = path.with_suffix(".tmp")
        torch.save(net.state_dict(), tmp)
        tmp.replace(path)
    except OSError:  # a read-only dataset: measured all the same, trained again next time
        pass
    return net


@torch.no_grad()
def generate(generator, latents: dict[str, torch.Tensor], use_relation: bool, batch: int = 250) -> torch.Tensor:
    out = []
    n = len(latents["z0"])
    for start in range(0, n, batch):
        part = {k: v[start:start + batch] for k, v in latents.items()}
        out.append(generator(part, use_relation=use_relation)[0])
    return torch.cat(out)


def truth_error(net: measure.TruthNet, frames: torch.Tensor, targets: np.ndarray) -> float:
    return float(np.sqrt(((measure.embed(net, frames, read_out=True) - targets) ** 2).mean()))


def table(results: dict[str, Any], arm: str, balls: bool) -> str:
    fid = lambda r: f"{r['fid']:.1f}" if "fid" in r else "-"  # noqa: E731
    lines = ["| generated with | FD-truth (ours) | FID (local Inception) | FID, thesis Table 5.4.1 | plausible % "
             "| toggle px (thesis at 128 px) |", "|---|---|---|---|---|---|"]
    for name, r in results["generated"].items():
        thesis = THESIS_FID.get(arm, "-") if balls and name == "Gamma" else "-"
        plaus = plausible_cell(r.get("plausibility") or r.get("towers"))
        toggle = f"{results['toggle_px']:.1f} ({THESIS_TOGGLE.get(arm, '-')})" if name == "Gamma" else "-"
        lines.append(f"| {name} ({arm}) | {r['fd_truth']:.2f} | {fid(r)} | {thesis} | {plaus} | {toggle} |")
    real = results["real"]
    plaus = plausible_cell(real.get("plausibility") or real.get("towers", {}).get("test towers, read"))
    lines.append(f"| real training frames (the floor) | {real['fd_truth']:.2f} | {fid(real)} | - | {plaus} | - |")
    if "towers" in real:
        lines.append("\nplausible towers (each block's box as the tower reader reads it, or as simulated): "
                     + "; ".join(f"{name} {100 * t['plausible']:.1f} % (rest {100 * t['resting']:.1f} %, Lemma 1 "
                                 f"{100 * t['stable']:.1f} %)" for name, t in towers_of(results)))
    if "decomposition" in results:
        d = results["decomposition"]
        lines.append(f"\nbackground alone shows no ball: {100 * d['background_without_balls']:.1f} %; one object alone shows "
                     f"one ball: {100 * d['one_object_one_ball']:.1f} %")
    return "\n".join(lines) + "\n\nFD-truth: Fréchet distance on the in-project ground-truth regressor's features (not FID)\n"


def plausible_cell(rates: dict | None) -> str:
    return f"{100 * rates['plausible']:.1f}" if rates else "-"


def towers_of(results: dict[str, Any]) -> list[tuple[str, dict]]:
    rows = [(name, r["towers"]) for name, r in results["generated"].items() if "towers" in r]
    return rows + [(f"real {name}", r) for name, r in results["real"]["towers"].items()]


# -- the video model (Section 5.4.3): FVD-truth beside the time-shuffled baseline ---------------------------------

THESIS_FVD = {"relate": 556, "time-shuffled training sequences": 920}  # BallsInBowl, Section 5.4.3


def clip_windows(sequences: torch.Tensor, frames: int) -> tuple[torch.Tensor, np.ndarray]:
    """Every window of ``frames`` consecutive frames of every sequence (N, F, 3, s, s): the clips (M, 3 frames,
    s, s) and their (sequence, start) pairs."""
    n, f = sequences.shape[:2]
    pairs = np.array([(i, t) for i in range(n) for t in range(f - frames + 1)])
    index = torch.from_numpy(pairs[:, 0, None] * f + pairs[:, 1, None] + np.arange(frames))
    return sequences.flatten(0, 1)[index].flatten(1, 2), pairs


def clip_truth(arrays: dict[str, np.ndarray], pairs: np.ndarray, frames: int, data_size: int) -> np.ndarray:
    """Per clip: every ball's position in every frame ([-1, 1]) and the bowl's (cos 2phi, sin 2phi, b/a)."""
    t = pairs[:, 1, None] + np.arange(frames)
    pixels = arrays["pixels"][pairs[:, 0, None], t] / data_size * 2 - 1  # (M, frames, K, 2)
    bowl = arrays["bowl"][pairs[:, 0]]
    shape = np.stack([np.cos(2 * bowl[:, 0]), np.sin(2 * bowl[:, 0]), bowl[:, 2] / bowl[:, 1]], axis=1)
    return np.concatenate([pixels.reshape(len(pairs), -1), shape], axis=1).astype(np.float32)


def ball_speed(clips: np.ndarray, detector: measure.Detector) -> float:
    """Mean distance (px) a detected ball moves between two frames of uint8 clips (N, T, H, W, 3)."""
    steps = []
    for clip in clips:
        centres = np.stack([detector(frame).balls for frame in clip])  # (T, K, 2), nan where unseen
        d = np.linalg.norm(np.diff(centres, axis=0), axis=-1)
        steps.append(d[~np.isnan(d)])
    steps = np.concatenate(steps)
    return float(steps.mean()) if len(steps) else float("nan")


@torch.no_grad()
def generate_clips(generator, latents: dict[str, torch.Tensor], frames: int, use_relation: bool,
                   batch: int = 50) -> torch.Tensor:
    out = []
    for start in range(0, len(latents["z0"]), batch):
        part = {k: v[start:start + batch] for k, v in latents.items()}
        out.append(generator(part, use_relation=use_relation, frames=frames)[0])
    return torch.cat(out)  # (N, frames, 3, H, W)


def evaluate_video(ctx: Context, model, meta: dict[str, Any], root: Path) -> dict[str, Any]:
    """FVD-truth (a Fréchet distance on the features of an in-project network that regresses the balls'
    trajectories and the bowl from whole clips; not FVD) of generated clips, of still clips (Gamma bypassed),
    of time-shuffled training clips (the thesis's baseline) and of real training clips (the floor), all
    against the real test clips; with per-frame plausibility and how far the balls move per frame."""
    import imageio.v3 as iio

    cfg, g, size = ctx.config.eval, model.generator, int(meta["size"])
    data_cfg = dataset_header(root)["config"]["data"]
    frames, data_size = cfg.frames, int(data_cfg["size"])
    if frames > int(data_cfg["frames"]):
        raise BadInput(f"eval.frames ({frames}) exceeds the dataset's {data_cfg['frames']} frames per sequence")
    train, test = load_split(root, "train", FIELDS), load_split(root, "test", FIELDS)
    train_seq = real_frames(train, size).reshape(*train["frames"].shape[:2], 3, size, size)
    test_seq = real_frames(test, size).reshape(*test["frames"].shape[:2], 3, size, size)
    train_clips, train_pairs = clip_windows(train_seq, frames)
    test_clips, test_pairs = clip_windows(test_seq, frames)
    as_seq = lambda x: x.reshape(len(x), frames, 3, size, size)  # noqa: E731
    i3d = I3D.open(cfg.i3d, as_seq(test_clips[:2])) if cfg.i3d else None
    path = root / "features" / f"videonet-{size}px-{frames}f-{cfg.features_epochs}ep.pt"
    targets = clip_truth(train, train_pairs, frames, data_size)
    net = cached_truth_net(path, train_clips, targets, cfg.features_epochs, ctx.log, "real clips")
    nets = {"fvd_truth": (lambda x: measure.embed(net, x), test_clips)}
    if i3d:
        nets["fvd"] = (lambda x: i3d.features(as_seq(x)), test_clips[:cfg.clips])
    distances = measure.Distances(nets)
    pick = torch.randperm(len(train_clips), generator=torch.Generator().manual_seed(2))[:cfg.clips]
    real = train_clips[pick]
    order = torch.argsort(torch.rand(len(real), frames, generator=torch.Generator().manual_seed(3)), dim=1)
    shuffled = real.reshape(len(real), frames, 3, size, size)[torch.arange(len(real))[:, None], order].flatten(1, 2)
    detector = measure.Detector(size, int(data_cfg["balls"]))
    as_clips = lambda x: to_uint8(x.reshape(-1, 3, size, size)).reshape(len(x), frames, size, size, 3)  # noqa: E731
    results: dict[str, Any] = {
        "real": {**distances(real),
                 "ball_speed_px": ball_speed(test_clips[:cfg.clips].unflatten(1, (frames, 3)).permute(0, 1, 3, 4, 2).numpy(),
                                             detector)},
        "time_shuffled": distances(shuffled)}
    gen = torch.Generator().manual_seed(ctx.seed)
    latents = g.sample(cfg.clips, bg_range=cfg.bg_range, generator=gen)
    results["generated"] = {}
    for name, use_relation in (("Gamma", True), ("Gamma bypassed (still)", False)):
        clips = generate_clips(g, latents, frames, use_relation)
        pics = as_clips(clips.flatten(1, 2))
        r = {**distances(clips.flatten(1, 2)),
             "plausibility": measure.plausibility(pics.reshape(-1, size, size, 3), detector),
             "ball_speed_px": ball_speed(pics, detector)}
        results["generated"][name] = r
        ctx.log(f"{name}: FVD-truth {r['fvd_truth']:.2f}, plausible frames {100 * r['plausibility']['plausible']:.1f} %, "
                f"balls move {r['ball_speed_px']:.2f} px per frame")
        if use_relation:
            iio.imwrite(ctx.output().artifact("clips.png"), image_grid(clips[:8, ::max(1, frames // 8)][:, :8].flatten(0, 1)))
    ctx.log(f"time-shuffled training clips: FVD-truth {results['time_shuffled']['fvd_truth']:.2f}; real training clips "
            f"(the floor): {results['real']['fvd_truth']:.2f}")
    results["decomposition"] = measure.decomposition(g, {k: v[:200] for k, v in latents.items()}, detector)
    fvd = lambda r: f"{r['fvd']:.1f}" if "fvd" in r else "-"  # noqa: E731
    lines = ["| clips | FVD-truth (ours) | FVD (local I3D) | FVD, thesis 5.4.3 | plausible frames % | ball speed px/frame |",
             "|---|---|---|---|---|---|"]
    for name, r in results["generated"].items():
        thesis = THESIS_FVD["relate"] if name == "Gamma" else "-"
        lines.append(f"| generated, {name} | {r['fvd_truth']:.2f} | {fvd(r)} | {thesis} | "
                     f"{100 * r['plausibility']['plausible']:.1f} | {r['ball_speed_px']:.2f} |")
    shuffled_r, real_r = results["time_shuffled"], results["real"]
    lines.append(f"| time-shuffled training clips | {shuffled_r['fvd_truth']:.2f} | {fvd(shuffled_r)} | "
                 f"{THESIS_FVD['time-shuffled training sequences']} | - | - |")
    lines.append(f"| real training clips (the floor) | {real_r['fvd_truth']:.2f} | {fvd(real_r)} | - | - | "
                 f"{real_r['ball_speed_px']:.2f} |")
    ctx.output().artifact("table_fvd.md").write_text(
        "\n".join(lines) + f"\n\n{frames}-frame clips at {size} px. FVD-truth: Fréchet distance on an in-project network "
        "regressing the simulator's trajectories from clips (not FVD)\n")
    return {"variant": "video", "arm": model.arm, "scene": meta["scene"], "clips": cfg.clips, "frames": frames,
            "size": size, **results, "thesis": {"fvd": THESIS_FVD}, "dataset": str(root)}


def evaluate(ctx: Context) -> dict[str, Any]:
    import imageio.v3 as iio

    cfg = ctx.config.eval
    model, meta = load_model(ctx.trained().path, "cpu")
    g = model.generator
    root = Path(ctx.data or meta["dataset"])
    data_scene = dataset_header(root)["scene"]
    if data_scene != meta["scene"]:
        raise BadInput(f"this model was trained on {meta['scene']} and {root} holds {data_scene}: pass --data with a "
                       f"{meta['scene']} dataset")
    if g.video:
        return evaluate_video(ctx, model, meta, root)
    scene, size = meta["scene"], int(meta["size"])
    balls, towers = scene == "balls-in-bowl", scene == "shapestacks"
    data_cfg = dataset_header(root)["config"]["data"]
    data_size = int(data_cfg["size"])
    fields = FIELDS + ("extent",) if towers else FIELDS
    train, test = load_split(root, "train", fields), load_split(root, "test", fields)
    train_frames, real_test = real_frames(train, size), real_frames(test, size)
    inception = INCEPTION.open(cfg.inception, real_test[:2]) if cfg.inception else None
    net = truth_net(root, train_frames, frame_truth(train, data_size, size, scene), size, cfg.features_epochs, ctx.log)
    pick = torch.randperm(len(real_test), generator=torch.Generator().manual_seed(1))[:cfg.samples]
    nets = {"fd_truth": (lambda x: measure.embed(net, x), real_test)}
    if inception:  # FID against the evaluated test frames, not all of them (the Inception is costly on a CPU)
        nets["fid"] = (inception.features, real_test[pick])
    distances = measure.Distances(nets)
    floor_pick = torch.randperm(len(train_frames), generator=torch.Generator().manual_seed(2))[:cfg.samples]
    real_train = train_frames[floor_pick]
    detector = measure.Detector(size, int(data_cfg["balls"])) if balls else None
    test_truth = frame_truth(test, data_size, size, scene)[pick.numpy()]
    results: dict[str, Any] = {"real": {**distances(real_train), "truth_rmse": truth_error(net, real_test[pick], test_truth)}}
    read_towers = None
    if detector:
        results["real"]["plausibility"] = measure.plausibility(real_test[pick].permute(0, 2, 3, 1).numpy(), detector)
    if towers:
        read_towers, results["real"]["towers"] = tower_check(ctx, root, size, data_size, train, test, train_frames,
                                                                real_test, pick)
    counts = meta.get("counts", [g.objects, g.objects])
    gen = torch.Generator().manual_seed(ctx.seed)
    present = present_mask(cfg.samples, counts[0], counts[1], g.objects, gen)
    latents = g.sample(cfg.samples, present=present, bg_range=cfg.bg_range, generator=gen)
    results["generated"] = {}
    for name, use_relation in (("Gamma", True), ("Gamma bypassed", False)):
        if not use_relation and g.relation is None:
            continue
        images = generate(g, latents, use_relation)
        r: dict[str, Any] = distances(images)
        if detector:
            r["plausibility"] = measure.plausibility(to_uint8(images), detector)
        if read_towers:
            r["towers"] = read_towers(images)
        results["generated"][name] = r
        grid = image_grid(images[:32])
        iio.imwrite(ctx.output().artifact(f"samples_{name.replace(' ', '_').lower()}.png"), grid)
        ctx.log(f"{name}: FD-truth {r['fd_truth']:.2f}" + (f", plausible {100 * r['plausibility']['plausible']:.1f} %"
                                                             if detector else "")
                + (f", plausible towers {100 * r['towers']['plausible']:.1f} %" if read_towers else ""))
    if detector:
        results["decomposition"] = measure.decomposition(g, {k: v[:200] for k, v in latents.items()}, detector)
    objects = cfg.toggle_objects or (g.objects if g.fixed_objects else 5)
    results["toggle_px"] = measure.toggle_distance(g, cfg.toggle_samples, objects, seed=ctx.seed)
    results["toggle_objects"] = objects
    out = ctx.output()
    out.artifact("table_5_4_1.md").write_text(table(results, model.arm, balls))
    return {"arm": model.arm, "scene": scene, "samples": cfg.samples, "size": size, **results,
            "thesis": {"fid": THESIS_FID, "toggle": THESIS_TOGGLE}, "dataset": str(root)}
