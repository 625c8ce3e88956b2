"""Imagining a tool for one task (thesis Section 4.4.3, Fig. 4.4-4.5) and using it in the simulator.

The task is a generated one of type ``deploy.type`` (seeded by --seed) or, with ``--target``, a
task image file of the dataset's task size, read back into a target and obstacles
(``scenes.task_from_image``). The start is a stick or hook that cannot reach (the geometric
check), or the mesh file ``deploy.tool``, rendered in the first ring view as the dataset renders tools. The task-driven model
descends Eq. 4.5 from it; what is left in the run:

* ``task.png``, ``strip.png`` (the tool every k steps over the task, with p(success) and the
  check's verdict), ``imagination.mp4`` (every step kept);
* ``imagined.obj`` and ``imagined.stl``: the decoded mesh (metres, the tool's frame);
* ``reach.mp4`` and ``reach.png``: the imagined tool, as convex parts in the simulator, pushed from
  behind the red line onto the target along the check's pose (kinematically, contacts reported);
* ``deploy.rrd``: the task, the frames and p(success) per step, for ``rerun``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from physint_cli.errors import BadInput
from physint_cli.method import Context, unit_seed

from . import feasibility
from . import scenes as S
from .checkpoint import load_models, training_box
from .imagine import footprints, imagine
from .model import task_input, tool_input
from .tasks import EXTENT, LINE_Y, Task, parse_types, sample_task
from .tools import export_mesh, footprint_parts, sample_tool

FRAME_SIZE = 256  # px of the pictures (the model sees the dataset's task size)
APPROACH = 0.15  # m the tool travels onto the target in reach.mp4


def posed(shape, verdict: feasibility.Verdict, task: Task, offset: float = 0.0):
    """The outline at the check's pose (a feasible verdict) or, otherwise, upright with its top
    interior point on the target; ``offset`` m back along the tool's axis."""
    from shapely import affinity

    if verdict.feasible:
        point, angle = verdict.point, verdict.angle
    else:
        pts = feasibility.interior_points(shape)
        point, angle = pts[np.argmax(pts[:, 1])], 0.0
    moved = affinity.rotate(affinity.translate(shape, -point[0], -point[1]), angle, origin=(0, 0), use_radians=True)
    back = np.array([np.sin(angle), -np.cos(angle)]) * offset  # the tool's axis, towards the grip
    return affinity.translate(moved, task.target[0] + back[0], task.target[1] + back[1]), point, angle


def frame(task_image: np.ndarray, shape, verdict, task: Task, title: str) -> np.ndarray:
    """The task image with the tool's outline drawn at its pose, as an RGB array."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(3, 3.2), dpi=80)
    ax.imshow(task_image, extent=(-EXTENT, EXTENT, -EXTENT, EXTENT))
    if shape is not None:
        outline, _, _ = posed(shape, verdict, task)
        x, y = outline.exterior.xy
        ax.fill(x, y, color="orange" if verdict.feasible else "grey", alpha=0.7, lw=1.5,
                ec="darkorange" if verdict.feasible else "black")
    ax.set_xlim(-EXTENT, EXTENT)
    ax.set_ylim(-EXTENT, EXTENT)
    ax.set_title(title, fontsize=9)
    ax.axis("off")
    fig.canvas.draw()
    image = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return image


def start_task(ctx: Context, task_size: int) -> tuple[Task, np.ndarray | None]:
    """The task to imagine for: from --target's image, or generated (its image is rendered later)."""
    if ctx.target:
        from physint_cli.artifacts import read_rgb_image

        image = read_rgb_image(Path(ctx.target), task_size, "--target", "this model sees task images of")
        try:
            return S.task_from_image(image), image
        except ValueError as exc:
            raise BadInput(f"--target {ctx.target}: {exc}; a task image shows a green target (see task.png of "
                           f"a deployment)") from None
    (kind,) = parse_types(ctx.config.deploy.type, "deploy.type")
    return sample_task(kind, np.random.default_rng(unit_seed(ctx.seed, "deploy-task"))), None


def start_tool(path: str, task: Task, rng: np.random.Generator, tries: int = 2000) -> tuple[str, list]:
    """The start tool's description and convex parts: the mesh file ``path`` (its outline seen from
    above), or a generated stick or hook that cannot reach ``task``'s target."""
    if path:
        import trimesh

        try:
            mesh = trimesh.load(path, force="mesh")
            closed = bool(mesh.is_watertight and mesh.is_winding_consistent)
            shape = feasibility.mesh_footprint(mesh.vertices, mesh.faces, closed=closed)
        except Exception as exc:  # trimesh raises many kinds for a file that is not a mesh
            raise BadInput(f"deploy.tool {path}: not a mesh trimesh can read ({type(exc).__name__})") from None
        if shape is None:
            raise BadInput(f"deploy.tool {path}: the mesh has no area seen from above (metres, lying flat in x-y)")
        centre = np.array(shape.centroid.coords[0])
        from shapely import affinity

        return f"the mesh {Path(path).name}", footprint_parts(affinity.translate(shape, *(-centre)))
    for _ in range(tries):
        tool = sample_tool(rng)
        if not feasibility.check(tool.footprint(), task).feasible:
            return tool.describe(), tool.convex_parts()
    raise BadInput("every tool drawn reaches this task's target already: nothing to imagine")


def reach_frames(ctx: Context, task: Task, shape, verdict, steps: int = 30) -> tuple[list[np.ndarray], list[str]]:
    """The imagined tool slid onto the target along its pose, rendered from above; the contacts at
    the final pose."""
    from physint_backends.spec import Scene

    outline, point, angle = posed(shape, verdict, task)
    bodies = S.task_bodies(task) + [S.tool_body(footprint_parts(shape), (0.95, 0.55, 0.1, 1.0), pos=(0, 0, 1),
                                                static=False)]
    sim = ctx.make_sim(Scene(bodies=bodies, cameras=[S.task_camera(FRAME_SIZE)], ground=None, gravity=(0, 0, 0),
                             background=S.BACKGROUND))
    frames = []
    try:
        for k in range(steps + 1):
            back = APPROACH * (1 - k / steps)
            target = (task.target[0] + np.sin(angle) * back, task.target[1] - np.cos(angle) * back)
            pos, quat = feasibility.pose(point, angle, target, 0.012)
            sim.set_pose("tool", pos, quat)
            frames.append(sim.render("task").rgb)
        touching = sorted(sim.contacts("tool"))
    finally:
        sim.close()
    return frames, touching


def deploy(ctx: Context) -> dict[str, Any]:
    from physint_cli.artifacts import Recording, save_image, save_movie

    cfg, ecfg = ctx.config.deploy, ctx.config.eval
    driven, _, meta = load_models(ctx.trained().path, ctx.device)
    task_size, tool_size = driven.kwargs["task_size"], driven.kwargs["image_size"]
    views = int(meta["views"])
    task, given_image = start_task(ctx, task_size)
    rng = np.random.default_rng(unit_seed(ctx.seed, "deploy-tool"))
    described, parts = start_tool(cfg.tool, task, rng)
    rgba = (*rng.uniform(0.15, 0.85, 3), 1.0)
    scene = S.record_scene(task, parts, rgba, task_size, views, tool_size, float(meta.get("elevation", S.ELEVATION)))
    sim = ctx.make_sim(scene)
    try:
        record = S.render_record(sim, [0, views // 2], tool_index=len(scene.bodies) - 1)
        big = S.record_scene(task, parts, rgba, FRAME_SIZE, 1, 32)
        sim.reset(big)
        picture = sim.render("task").rgb
    finally:
        sim.close()
    task_image = given_image if given_image is not None else record["task"]
    with torch.no_grad():
        z_task = driven.encode_task(task_input(task_image[None]))
        z0 = driven.encode_tool(tool_input(record["tool_rgb"][:1], record["tool_sil"][:1]))
    keep = cfg.every or max(1, ecfg.max_steps // 64)
    run = imagine(driven, z_task, z0, "descent", ecfg.step, ecfg.max_steps, ecfg.threshold, seed=ctx.seed,
                  keep_every=keep, optimizer=ecfg.optimizer,
                  box=training_box(meta, "driven", driven) if ecfg.latent_box else None)
    zs = torch.cat([z for _, z, _ in run.trace])
    shapes = footprints(driven, zs)
    verdicts = [feasibility.check(s, task) for s in shapes]
    p = [float(pk[0]) for _, _, pk in run.trace]
    frames = [frame(picture, s, v, task, f"step {k}: p = {pk:.3f} {'reaches' if v.feasible else 'does not reach'}")
              for (k, _, _), s, v, pk in zip(run.trace, shapes, verdicts, p)]
    out = ctx.output()
    save_image(out.artifact("task.png"), task_image)
    picks = np.unique(np.linspace(0, len(frames) - 1, min(8, len(frames))).round().astype(int)) if not cfg.every \
        else np.arange(len(frames))
    save_image(out.artifact("strip.png"), np.concatenate([frames[i] for i in picks], axis=1))
    with torch.no_grad():
        vertices = driven.decode(run.z)[0].numpy()
    import trimesh

    mesh = trimesh.Trimesh(vertices, driven.faces.numpy(), process=False)
    for suffix in (".obj", ".stl"):
        export_mesh(mesh, out.artifact(f"imagined{suffix}"))
    final_shape, final = shapes[-1], verdicts[-1]
    result: dict[str, Any] = {"task": {"type": task.type, "target": list(task.target), "obstacles": len(task.obstacles),
                                       "from_image": given_image is not None},
                              "start_tool": described, "p_start": float(run.p_start[0]),
                              "p_end": float(run.p_end[0]), "steps": int(run.steps[0]),
                              "reached_threshold": bool(run.reached[0]), "feasible": bool(final.feasible),
                              "start_feasible": bool(verdicts[0].feasible)}
    if final_shape is not None:
        reach, touching = reach_frames(ctx, task, final_shape, final)
        save_image(out.artifact("reach.png"), reach[-1])
        hits = [t for t in touching if t.startswith("obstacle")]
        result["sim_obstacle_contacts"] = hits  # at the final pose, in the simulator
        result["crosses_line"] = bool(posed(final_shape, final, task)[0].bounds[1] < LINE_Y)
        if cfg.video:
            save_movie(out.artifact("reach"), reach, fps=15)
    if cfg.video:
        save_movie(out.artifact("imagination"), frames, fps=8)
    with Recording(out.artifact("deploy.rrd"), "physint toolsynth deploy") as rec:
        rec.image("task", task_image)
        for (k, _, _), f, pk in zip(run.trace, frames, p):
            rec.time(step=k)
            rec.image("imagination", f)
            rec.scalar("p_success", pk)
    ctx.log(f"imagined from {described}: p(success) {result['p_start']:.3f} -> {result['p_end']:.3f} in "
            f"{result['steps']} steps; the decoded tool {'reaches' if final.feasible else 'does not reach'} the target")
    return result
