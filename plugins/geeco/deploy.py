"""Running a trained GEECO controller on a target image (thesis Section 6.3: "conditioned on a new task
with a single target image").

``--target`` is either an image file (the target image for the start state drawn from ``--seed``)
or a goal in words, "red cube onto green pad": then the expert renders the target image on this
backend first, as the demonstrations' last frames were made. Start states for deployment depend
on the seed only (they are laid out so that every task of the scene is doable), so a target image
written by one deployment (``target.png``) is the target of the same seed's start state again.

Written: ``target.png``, ``episode.mp4`` (camera view | target | dynamic image of the buffer |
dynamic image of the difference to the target; ``episode.gif`` where no H.264 encoder is at
hand), ``deploy.rrd`` (the same, plus commands and the predicted hand and object positions, for
``rerun``), and the outcome (REACH, PICK, PUSH/PLACE).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from physint_cli.errors import BadInput
from physint_cli.method import Context, unit_seed

from . import scenes as S
from .checkpoint import load_controller


def start_state(ctx: Context, skill: str, task: tuple[int, int]) -> S.Episode:
    """The seed's start state, laid out so that every task of the scene could be asked for."""
    tasks = S.tasks(ctx.scene)
    for attempt in range(200):
        rng = np.random.default_rng(unit_seed(ctx.seed, "deploy", ctx.scene, attempt))
        ep = S.sample_episode(ctx.scene, skill, tasks[0], rng)
        if all(_doable(ep, t) for t in tasks):
            ep.task = task
            if ctx.scene == "clutter":
                ep.clutter = S.sample_clutter(ep, np.random.default_rng(ep.seed))
            return ep
    raise RuntimeError(f"no start state of {ctx.scene} allows every task")


def _doable(ep: S.Episode, task: tuple[int, int]) -> bool:
    obj, tgt = S.OBJECTS[ep.scene][task[0]], S.TARGETS[ep.scene][task[1]]
    return bool(np.linalg.norm(ep.xy(obj) - ep.xy(tgt)) >= 0.16)


def read_target(path: Path, resolution: int) -> np.ndarray:
    from physint_cli.artifacts import read_rgb_image

    return read_rgb_image(path, resolution, "--target", "the controller sees")


def deploy(ctx: Context) -> dict[str, Any]:
    from physint_cli.artifacts import Recording, save_image, save_movie

    from .control import Policy, expert_target, run_episode
    from .dynamic import dynamic_image, to_rgb

    model, meta = load_controller(ctx.trained().path, ctx.device)
    skill, resolution = meta["skill"], model.image_size
    if ctx.episodes not in (None, 1):
        ctx.log("geeco deploy runs one episode toward one target (--seed picks the start state); "
                "--episodes counts the episodes of physint eval geeco")
    target_arg = ctx.target
    tasks = S.tasks(ctx.scene)
    image_file = target_arg is not None and Path(target_arg).suffix.lower() in (".png", ".jpg", ".jpeg", ".bmp")
    if image_file and not Path(target_arg).is_file():
        raise BadInput(f"--target {target_arg}: no such file")
    if target_arg is None or image_file:
        task = tasks[int(np.random.default_rng(ctx.seed).integers(len(tasks)))]
    else:
        try:
            task = S.parse_goal(target_arg, ctx.scene)
        except ValueError as exc:
            raise BadInput(str(exc)) from None
    ep = start_state(ctx, skill, task)
    run = ctx.output()
    sim = ctx.make_sim(S.build_scene(ep, resolution))
    try:
        if image_file:
            target = read_target(Path(target_arg), resolution)
            goal = f"the target image {target_arg}"
        else:
            target = expert_target(sim, ep, resolution, meta.get("horizon", 100))
            if target is None:
                raise BadInput(f"the expert could not do '{ep.goal_text()}' from this start state on {ctx.backend}; "
                               f"try another --seed")
            goal = ep.goal_text()
        save_image(run.artifact("target.png"), target)
        frames: list[np.ndarray] = []
        with Recording(run.artifact("deploy.rrd"), "physint geeco deploy") as rec:
            rec.image("target", target)

            def on_step(t: int, rgb: np.ndarray, action: np.ndarray, policy: Policy) -> None:
                import torch

                buffer = policy.last["frames"][0]
                motion = to_rgb(dynamic_image(buffer[None])[0])
                tgt = torch.as_tensor(target).float().div(255).movedim(-1, 0)
                diff = to_rgb(dynamic_image(torch.stack([buffer[-1], tgt])[None])[0])
                rec.time(step=t, seconds=t * sim.robot.control_dt)
                rec.image("camera", rgb)
                rec.image("dynamic/buffer", motion)
                rec.image("dynamic/to_target", diff)
                for i, name in enumerate(("dx", "dy", "dz", "gripper")):
                    rec.scalar(f"command/{name}", float(action[i]))
                rec.points("predicted/ee", policy.last["ee"][None], radii=0.01)
                rec.points("predicted/object", policy.last["obj"][None], radii=0.01)
                frames.append(np.concatenate([rgb, target, motion, diff], axis=1))

            outcome = run_episode(sim, ep, Policy(model, ctx.device), target if model.conditioned else None,
                                  ctx.config.deploy.steps, resolution, on_step=on_step)
        if ctx.config.deploy.video and frames:
            save_movie(run.artifact("episode"), frames)
    finally:
        sim.close()
    return {"goal": goal, "scene": ctx.scene, "backend": ctx.backend, "model": meta["model"], "skill": skill,
            "seed": ctx.seed, "task": ep.goal_text(), **outcome}
