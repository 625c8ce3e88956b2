"""Generating the ShapeStacks dataset (thesis Section 3.3, Table 3.1).

Scenarios are planned up front (subsets and heights in Table 3.1's proportions, stable and
unstable balanced per height, unstable split between VCOM and VPSF), split ~70/15/15 and cut
into shards. Each scenario is labelled analytically by Lemma 1, simulated on the chosen backend,
and kept only if the simulation agrees with the label (footnote 2: the thesis discards the
others; the agreement rate goes into the manifest). Only the initial, static configuration is
rendered, from every camera, with a per-object segmentation map; the violating object, the
first object to fall, the tower base (object 0) and top (object n-1) are recorded with it, so
every semantic region of Table 3.4 can be derived from the map.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from physint_backends import SimulationError
from physint_cli.method import Context, Unit, unit_seed

from .scenes import SUBSETS, kinds_for, plan_scenarios, sample_scenario, simulate, to_scene

VIOLATION_CODE = {None: 0, "stable": 0, "VCOM": 1, "VPSF": 2}
SUBSET_CODE = {"cubes": 0, "ccs": 1}


def plan_units(ctx: Context) -> list[Unit]:
    """Shards of scenarios for the train / val / test splits (each split balanced on its own)."""
    d = ctx.config.data
    total = d.scenarios
    n_train = int(round(total * d.train_fraction))
    n_val = int(round(total * d.val_fraction))
    counts = {"train": n_train, "val": n_val, "test": max(0, total - n_train - n_val)}
    units = []
    for split, n in counts.items():
        plan = plan_scenarios(n, np.random.default_rng(unit_seed(ctx.seed, "plan", split)), ctx.scene)
        for index, start in enumerate(range(0, n, d.per_shard)):
            chunk = plan[start:start + d.per_shard]
            units.append(Unit(split, index, len(chunk) * d.cameras, unit_seed(ctx.seed, split, index),
                              {"plan": [(p.subset, p.height, p.kind, p.seed) for p in chunk]}))
    return units


def generate(ctx: Context, unit: Unit) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Simulate, filter and render one shard's scenarios; one record per camera image."""
    from .scenes import default_textures

    d = ctx.config.data
    textures = default_textures()[: d.textures]
    records: dict[str, list] = {k: [] for k in ("image", "segmentation", "label", "violation", "height", "subset",
                                                "camera", "scenario", "violating", "first_to_fall", "interface")}
    attempts = agreed = failures = 0
    kept = []
    for position, (subset, height, kind, seed) in enumerate(unit.params["plan"]):
        rng = np.random.default_rng(seed)
        for attempt in range(d.max_attempts):
            scenario = sample_scenario(int(rng.integers(2**31 - 1)), subset, height, kind)
            scene = to_scene(scenario, rng, cameras=d.cameras, resolution=d.resolution, textures=textures,
                             camera_jitter=d.camera_jitter, timestep=d.timestep)
            attempts += 1
            with ctx.make_sim(scene) as sim:
                # render the initial, static configuration first, then let physics decide
                frames = [sim.render(c.name, rgb=True, segmentation=True) for c in scene.cameras]
                try:  # the first fall decides both agreement and first_to_fall: stop there
                    outcome = simulate(sim, scenario, seconds=d.sim_seconds, stop_early=True)
                except SimulationError:  # the simulator failed on this sample: discard it like a disagreement
                    failures += 1
                    continue
            if outcome.stable == scenario.stable:  # keep only where simulation and Lemma 1 agree
                agreed += 1
                break
        else:
            continue  # no agreeing sample of this (subset, height, kind): the shard is one scenario short
        label = scenario.label
        first = outcome.first_to_fall if outcome.first_to_fall is not None else -1
        for camera, frame in enumerate(frames):
            records["image"].append(frame.rgb)
            records["segmentation"].append(frame.segmentation.astype(np.int8))
            records["label"].append(0 if scenario.stable else 1)  # y = 1 unstable (Eq. 3.2)
            records["violation"].append(VIOLATION_CODE[label.violation])
            records["height"].append(scenario.height)
            records["subset"].append(SUBSET_CODE[scenario.subset])
            records["camera"].append(camera)
            records["scenario"].append(unit.index * 10_000 + position)  # unique within its split
            records["violating"].append(-1 if label.violating_object is None else label.violating_object)
            records["first_to_fall"].append(first)
            records["interface"].append(-1 if label.interface is None else label.interface)
        kept.append(scenario.kind)
    r = d.resolution
    arrays = {
        "image": np.stack(records["image"]).astype(np.uint8) if records["image"] else np.zeros((0, r, r, 3), np.uint8),
        "segmentation": np.stack(records["segmentation"]) if records["segmentation"] else np.zeros((0, r, r), np.int8),
    }
    for k in ("label", "violation", "height", "subset", "camera", "scenario", "violating", "first_to_fall", "interface"):
        arrays[k] = np.asarray(records[k], dtype=np.int64)
    stats = {"scenarios": len(kept), "planned": len(unit.params["plan"]), "simulations": attempts,
             "agreed": agreed, "simulator_failures": failures, **{f"kept_{k}": kept.count(k) for k in ("stable", "VCOM", "VPSF")}}
    return arrays, stats


def summarize(stats: list[dict[str, Any]]) -> dict[str, Any]:
    total = {k: sum(s.get(k, 0) for s in stats) for k in ("scenarios", "planned", "simulations", "agreed", "simulator_failures",
                                                          "kept_stable", "kept_VCOM", "kept_VPSF")}
    seconds = sum(s.get("seconds", 0.0) for s in stats)
    return {**total,
            "agreement_rate": total["agreed"] / max(total["simulations"], 1),  # simulation vs Lemma 1
            "scenarios_per_cpu_second": total["scenarios"] / seconds if seconds else None,
            "subsets": list(SUBSETS), "kinds_by_subset": {s: list(kinds_for(s)) for s in ("cubes", "ccs")}}
