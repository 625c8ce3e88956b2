"""Recording GEECO's expert demonstrations (thesis Section 6.4, "Experimental setup and data collection").

Each demonstration starts from a random start state of the scene with a task balanced over the
split (record ``i`` of a split does task ``i mod n_tasks``), runs the scripted expert for
H = 100 steps at 25 Hz and keeps, per step t: the camera frame I_t, the 7 joint angles x_t, the
commanded displacement u_dEE and gripper command u_GRP, and the positions of the hand q_EE and
of the object to move q_OBJ. Only demonstrations that succeed (the object rests on its target)
with the hand parked before the end are kept: their last frame is the target image I_T. The
start state (layout, task, seed, and the seed of the background video with
``data.backgrounds=random`` or ``mixed``, else -1) is saved, so evaluation replays the test split's start states.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from physint_cli.errors import BadInput
from physint_cli.method import Context, Unit, split_units

from . import scenes as S
from .episode import Rollout, expert_drives, run
from .expert import on_target

SPLITS = {"train": 2, "val": 1, "test": 1}  # 2:1:1
SETTLE_STEPS = 4  # the hand must be parked this many steps before the demonstration ends


def split_counts(total: int) -> dict[str, int]:
    if total < 4:
        raise BadInput(f"data.demos must be >= 4 (one per split and more for training), got {total}")
    val = total // 4
    test = total // 4
    return {"train": total - val - test, "val": val, "test": test}


def check(ctx: Context) -> None:
    cfg = ctx.config.data
    if ctx.scene not in S.TRAIN_SCENES:
        raise BadInput(f"scene {ctx.scene!r} is for evaluation only; demonstrations are recorded in "
                       f"{', '.join(S.TRAIN_SCENES)}")
    # data.skill, resolution, action_noise, backgrounds and horizon: their ranges are the config's


def plan_units(ctx: Context) -> list[Unit]:
    check(ctx)
    return split_units(split_counts(ctx.config.data.demos), ctx.config.data.per_shard, ctx.seed)


def record(sim, ep: S.Episode, horizon: int, noise: float = 0.0, rng: np.random.Generator | None = None
           ) -> tuple[dict[str, np.ndarray], bool]:
    """Run the expert from ``ep``'s start state for ``horizon`` steps on a live simulation; with
    ``noise`` > 0 the executed displacements are perturbed (``Expert.perturb``), the recorded
    commands are the expert's own. The frames show ``ep``'s background video, if it has one."""
    rollout = Rollout(sim, ep, expert=True, record=horizon)
    run([rollout], horizon, expert_drives(noise, rng))
    done_at = rollout.done_at
    ok = on_target(ep, sim) and done_at is not None and done_at <= horizon - SETTLE_STEPS
    return rollout.arrays, ok


def demonstrations(ctx: Context, unit: Unit, sim=None):
    """Yield ``(episode, arrays, attempts)`` for each demonstration of ``unit`` (``sim`` is reused)."""
    cfg = ctx.config.data
    tasks = S.tasks(ctx.scene)
    own = sim is None
    try:
        for k in range(unit.count):
            index = unit.params["start"] + k
            task = tasks[index % len(tasks)]
            rng = np.random.default_rng([unit.seed, k])
            for attempt in range(1, cfg.max_attempts + 1):
                ep = S.sample_episode(ctx.scene, cfg.skill, task, rng)
                if random_background(cfg.backgrounds, index, len(tasks)):
                    ep.backdrop = int(rng.integers(2**31))
                scene = S.build_scene(ep, cfg.resolution)
                if sim is None:
                    sim = ctx.make_sim(scene)
                else:
                    sim.reset(scene)
                arrays, ok = record(sim, ep, cfg.horizon, cfg.action_noise, rng)
                if ok:
                    yield ep, arrays, attempt
                    break
            else:
                raise RuntimeError(f"the expert failed {cfg.max_attempts} start states in a row for task "
                                   f"{S.describe(S.OBJECTS[ctx.scene][task[0]])} -> "
                                   f"{S.describe(S.TARGETS[ctx.scene][task[1]])} on {ctx.backend}")
    finally:
        if own and sim is not None:
            sim.close()


def random_background(backgrounds: str, index: int, n_tasks: int) -> bool:
    """Whether demonstration ``index`` of a split gets a random background video: all of them with
    ``random``, none with ``plain``, half with ``mixed``: each task's demonstrations alternate
    between plain and random from one round of tasks to the next, and so do neighbouring tasks."""
    if backgrounds != "mixed":
        return backgrounds == "random"
    round_, task = divmod(index, n_tasks)
    return round_ % 2 != task % 2


def generate(ctx: Context, unit: Unit) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    fields: dict[str, list] = {}
    attempts = 0
    for ep, arrays, tries in demonstrations(ctx, unit):
        attempts += tries
        arrays = dict(arrays, layout=ep.layout.astype(np.float32), task=np.asarray(ep.task, np.int16),
                      seed=np.int64(ep.seed), backdrop=np.int64(ep.backdrop))
        for key, value in arrays.items():
            fields.setdefault(key, []).append(value)
    out = {k: np.stack(v) for k, v in fields.items()}
    return out, {"demos": unit.count, "attempts": attempts}


def summarize(stats: list[dict[str, Any]]) -> dict[str, Any]:
    demos = sum(s.get("demos", 0) for s in stats)
    attempts = sum(s.get("attempts", 0) for s in stats)
    seconds = sum(s.get("seconds", 0.0) for s in stats)
    return {"demos": demos, "attempts": attempts, "expert_success_rate": demos / max(attempts, 1),
            "cpu_seconds": seconds, "demos_per_cpu_second": demos / max(seconds, 1e-9)}
