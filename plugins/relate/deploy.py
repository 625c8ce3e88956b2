"""Using a trained RELATE model: sampling, out-of-distribution scenes and editing (thesis Section 5.4, Figs. 5.4.1-5.4.5).

``physint deploy relate [--task sample|edit]`` writes into the run's artifacts:

``sample`` (the default) writes all of them, ``edit`` only the editing grid, the movie and the recording.

* ``samples.png``: ``deploy.samples`` scenes, each with Gamma (top) and with Gamma bypassed (below);
* ``components.png``: per scene the background alone, then each object alone with the background;
* ``ood.png``: scenes with more objects than trained (``deploy.objects``; default two more);
* ``editing.png``: rows of one scene edited: the background swapped, one object's appearance changed,
  one object moved (``deploy.move``, 'K:DX,DY');
* ``move.mp4`` (or .gif): the moved object sliding along its way, frame by frame;
* video models: ``clips.mp4`` (four generated clips of ``deploy.frames`` frames side by side) and
  ``ood_clips.mp4`` (clips with more balls than trained);
* ``deploy.rrd``: the same images, for ``rerun``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from physint_cli.errors import BadInput
from physint_cli.method import Context

from .checkpoint import image_grid, load_model, to_uint8

TASKS = ("sample", "edit")


def parse_move(text: str, objects: int) -> tuple[int, tuple[float, float]]:
    """'K:DX,DY' -> (K, (DX, DY)); anything else exits 2."""
    try:
        k, rest = text.split(":")
        dx, dy = (float(v) for v in rest.split(","))
        k = int(k)
    except ValueError:
        raise BadInput(f"deploy.move must be 'K:DX,DY' (object K moved by DX, DY in image units), got {text!r}") from None
    if not 0 <= k < objects:
        raise BadInput(f"deploy.move: object {k} does not exist; the scene has objects 0..{objects - 1}")
    return k, (dx, dy)


def rows(*batches: torch.Tensor) -> np.ndarray:
    """Image batches as grid rows, one batch per row."""
    columns = max(len(b) for b in batches)
    return np.concatenate([image_grid(b, columns=columns) for b in batches], axis=0)


@torch.no_grad()
def deploy(ctx: Context) -> dict[str, Any]:
    from physint_cli.artifacts import Recording, save_image, save_movie

    task = ctx.task or "sample"
    if task not in TASKS:
        raise BadInput(f"relate deploys --task {' or '.join(TASKS)}, got {task!r}")
    cfg = ctx.config.deploy
    model, meta = load_model(ctx.trained().path, "cpu")
    g = model.generator
    objects = g.objects
    move = parse_move(cfg.move or "0:0.5,0", objects)
    out = ctx.output()
    gen = torch.Generator().manual_seed(ctx.seed)
    n = cfg.samples
    latents = g.sample(n, generator=gen)
    theta = g.still_poses(latents)  # the video model's first frame
    with_gamma, _ = g(latents, theta=theta)
    without, _ = g(latents, theta=g.still_poses(latents, use_relation=False))
    images: dict[str, np.ndarray] = {}
    shown = min(n, 8)
    extra = cfg.objects or objects + 2
    if task == "sample":
        images["samples"] = rows(with_gamma, without)
        # each latent drawn alone with the background (Fig. 5.4.1)
        part = {key: v[:shown] for key, v in latents.items()}
        none = torch.zeros(shown, objects, dtype=torch.bool)
        alone = [g(part, keep=none, theta=theta[:shown])[0]]
        for j in range(objects):
            keep = none.clone()
            keep[:, j] = True
            alone.append(g(part, keep=keep, theta=theta[:shown])[0])
        images["components"] = rows(*alone)
        # more objects than trained (out of distribution)
        more = g.sample(shown, objects=extra, generator=gen)
        images["ood"] = rows(g(more, theta=g.still_poses(more))[0])
    # editing one scene (Fig. 5.4.4): background swapped, object k's appearance changed, object k moved
    k, (dx, dy) = move
    base = {key: v[:1].repeat(shown, *[1] * (v.dim() - 1)) for key, v in latents.items()}
    swapped = dict(base, z0=g.sample(shown, generator=gen)["z0"])
    restyled = dict(base, z=base["z"].clone())
    restyled["z"][:, k] = g.sample(shown, generator=gen)["z"][:, 0]
    base_theta = theta[:1].repeat(shown, 1, 1)
    steps = torch.linspace(0, 1, shown)
    moved_theta = base_theta.clone()
    moved_theta[:, k] += steps[:, None] * torch.tensor([dx, dy])
    edits = [g(swapped, theta=base_theta)[0], g(restyled, theta=base_theta)[0], g(base, theta=moved_theta)[0]]
    images["editing"] = rows(*edits)
    for name, picture in images.items():
        save_image(out.artifact(f"{name}.png"), picture)
    frames_theta = base_theta[:1].repeat(24, 1, 1)
    frames_theta[:, k] += torch.linspace(0, 1, 24)[:, None] * torch.tensor([dx, dy])
    clip = g({key: v[:1].repeat(24, *[1] * (v.dim() - 1)) for key, v in latents.items()}, theta=frames_theta)[0]
    frames = [np.kron(f, np.ones((4, 4, 1), np.uint8)) for f in to_uint8(clip)]  # 4x larger
    movie = save_movie(out.artifact("move"), frames, fps=12)
    videos = []
    if g.video and task == "sample":  # generated clips (Fig. 5.4.6), side by side, and OOD clips with more balls
        for name, part in (("clips", {key: v[:4] for key, v in latents.items()}),
                           ("ood_clips", g.sample(4, objects=extra, generator=gen))):
            pics = to_uint8(g(part, frames=cfg.frames)[0].flatten(0, 1))
            clips = pics.reshape(len(part["z0"]), cfg.frames, *pics.shape[1:])
            video = [np.kron(np.concatenate(list(clips[:, t]), axis=1), np.ones((4, 4, 1), np.uint8))
                     for t in range(cfg.frames)]
            videos.append((name, video))
            save_movie(out.artifact(name), video, fps=12)
    with Recording(out.artifact("deploy.rrd"), "physint relate deploy") as rec:
        for name, picture in images.items():
            rec.image(name, picture)
        for t, f in enumerate(frames):
            rec.time(step=t)
            rec.image("move", f)
        for name, video in videos:
            for t, f in enumerate(video):
                rec.time(step=t)
                rec.image(name, f)
    ctx.log(f"wrote {', '.join([*images, *(name for name, _ in videos)])} and {movie.name}: object {k} moved by "
            f"({dx}, {dy})")
    return {"task": task, "arm": model.arm, "scene": meta["scene"], "samples": n, "objects": objects,
            "ood_objects": extra, "moved": {"object": k, "by": [dx, dy]}, "movie": movie.name}
