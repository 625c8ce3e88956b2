"""RELATE's datasets, simulated (thesis Section 5.4, Appendix 5.C): ``--scene`` balls-in-bowl (sequences),
clevr-table and shapestacks (single images).

Every record is a clip of ``frames`` images (1 for the static scenes) of one scene from its one camera,
with the simulator's ground truth beside it, for evaluation only: each object's world position, pixel
position and pixel bounding box (``extent``: u_min, v_min, u_max, v_max of its projected outline) per frame, which of the ``max_objects`` slots are present, shape / colour / size
indices where the scene has them, and the bowl's (angle, a, b, depth). Record ``n`` of a split draws
everything from ``(unit seed, n)``; the number of objects of a static scene is uniform in
[``min_objects``, ``max_objects``]. Shapestacks has a third split, ``unstable`` (``data.unstable`` towers that
Lemma 1 calls unstable, VCOM): never trained on, it teaches and checks the evaluation's tower reader.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from physint_cli.errors import BadInput
from physint_cli.method import Context, Unit, split_units

from . import scenes as S

SEQUENCE_SCENES = ("balls-in-bowl",)


def slots(ctx: Context) -> int:
    """Object slots of a record: the balls, or the most objects of a static scene."""
    cfg = ctx.config.data
    return cfg.balls if ctx.scene == "balls-in-bowl" else cfg.max_objects


def frames_of(ctx: Context) -> int:
    return ctx.config.data.frames if ctx.scene in SEQUENCE_SCENES else 1


def plan_units(ctx: Context) -> list[Unit]:
    cfg = ctx.config.data
    if ctx.scene == "shapestacks" and cfg.min_objects < 2:
        raise BadInput("shapestacks towers have at least 2 blocks: set data.min_objects >= 2")
    counts = {"train": cfg.train, "test": cfg.test}
    if ctx.scene == "shapestacks" and cfg.unstable:
        counts["unstable"] = cfg.unstable
    return split_units(counts, cfg.per_shard, ctx.seed)


def draw_scene(ctx: Context, rng: np.random.Generator, split: str = "train"):
    """One scene of ``ctx.scene``, its ground truth, and the start velocities of its objects (or None)."""
    cfg = ctx.config.data
    if ctx.scene == "balls-in-bowl":
        bowl = S.sample_bowl(rng)
        starts, velocities = S.sample_balls(rng, bowl, cfg.balls, cfg.speed)
        scene, truth = S.balls_scene(bowl, starts, cfg.size)
        return scene, truth, velocities
    count = int(rng.integers(cfg.min_objects, cfg.max_objects + 1))
    if ctx.scene == "clevr-table":
        scene, truth = S.clevr_scene(rng, count, cfg.size)
        return scene, truth, None
    from physint_cli.plugins import get_plugins

    build = get_plugins().scene("stability", "ccs").build  # the stability plugin's towers, through the registry
    scene, truth = S.stack_scene(build, int(rng.integers(2 ** 31)), count, cfg.size, cfg.textures,
                                 kind="VCOM" if split == "unstable" else "stable")
    return scene, truth, None


def record(sim, scene, truth: S.Truth, velocities, frames: int, dt: float, k_max: int) -> dict[str, np.ndarray]:
    """Render ``frames`` frames ``dt`` apart (after giving the objects their start velocities) and
    read the ground truth at each."""
    camera = scene.cameras[0]
    if velocities is not None:
        for name, v in zip(truth.names, velocities):
            sim.set_velocity(name, v)
    images = np.zeros((frames, camera.height, camera.width, 3), np.uint8)
    world = np.zeros((frames, k_max, 3), np.float32)
    extent = np.full((frames, k_max, 4), -1.0, np.float32)
    bodies = [scene.body(name) for name in truth.names]
    for t in range(frames):
        if t:
            sim.advance(dt)
        images[t] = sim.render(camera.name).rgb
        for k, body in enumerate(bodies):
            pos, quat = sim.get_pose(body.name)
            world[t, k] = pos
            uv = camera.project(body.outline(pos, quat))
            extent[t, k] = (*uv.min(axis=0), *uv.max(axis=0))
    n = len(truth.names)
    pixels = np.full((frames, k_max, 2), -1.0, np.float32)
    pixels[:, :n] = camera.project(world[:, :n].reshape(-1, 3)).reshape(frames, n, 2)
    pad = lambda values, fill: np.array(list(values) + [fill] * (k_max - len(values)))  # noqa: E731
    return {"frames": images, "positions": world, "pixels": pixels, "extent": extent, "present": pad([1] * n, 0).astype(np.uint8),
            "shape": pad(truth.shapes or [0] * n, -1).astype(np.int8),
            "colour": pad(truth.colours or list(range(n)), -1).astype(np.int8),
            "size": pad(truth.sizes or [0.0] * n, 0.0).astype(np.float32),
            "bowl": np.asarray(truth.bowl or (0.0, 0.0, 0.0, 0.0), np.float32)}


def generate(ctx: Context, unit: Unit) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    cfg = ctx.config.data
    fields: dict[str, list] = {}
    stats: dict[str, Any] = {"records": 0, "frames": 0, "objects": 0, "left_bowl": 0}
    sim = None
    try:
        for k in range(unit.count):
            rng = np.random.default_rng([unit.seed, k])
            scene, truth, velocities = draw_scene(ctx, rng, unit.split)
            if sim is None:
                sim = ctx.make_sim(scene)
            else:
                sim.reset(scene)
            rec = record(sim, scene, truth, velocities, frames_of(ctx), cfg.frame_dt, slots(ctx))
            for key, value in rec.items():
                fields.setdefault(key, []).append(value)
            stats["records"] += 1
            stats["frames"] += len(rec["frames"])
            stats["objects"] += len(truth.names)
            if truth.bowl is not None:
                xy = rec["positions"][:, :len(truth.names), :2]
                stats["left_bowl"] += int(not S.inside_bowl(xy[..., 0], xy[..., 1], *truth.bowl[:3]).all())
    finally:
        if sim is not None:
            sim.close()
    return {k: np.stack(v) for k, v in fields.items()}, stats


def summarize(stats: list[dict[str, Any]]) -> dict[str, Any]:
    from physint_cli.datasets import add_up

    total = add_up(stats)
    total["objects_per_record"] = total.get("objects", 0) / max(total.get("records", 0), 1)
    return total


def load_split(root, split: str, fields=("frames", "positions", "pixels", "present")) -> dict[str, np.ndarray]:
    """A whole split in memory (small balls-in-bowl: 500 x 32 frames at 64 px, ~200 MB)."""
    from physint_cli.datasets import ShardedDataset

    return ShardedDataset(root, split, list(fields), method="relate", in_memory=True).arrays
