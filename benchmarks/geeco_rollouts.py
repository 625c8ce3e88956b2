"""Where a pushing controller leaves the demonstrations: its DAgger rollouts beside the expert's.

    python benchmarks/geeco_rollouts.py --data PUSH_DATASET --rounds RUN/dagger/epoch-004.npz [...]

A DAgger round (``physint train geeco --set train.dagger_epochs=...``) saves the states a
controller reached from training start states, each labelled with the push expert's command
there. This prints, for the training demonstrations and for each round:

* the hand's height over the episode and how soon the cube first moves;
* in states with the hand low (< 4 cm above the table) and near the cube (< 10 cm): how often
  the expert's command is to rise (dz > 2 cm a step: the hand is not where a push can go on)
  rather than to move the cube;
* where the hand is in those "rise" states, relative to the cube and the line from cube to target:
  along (+: past the cube's centre towards the target) and across it.

The figures are read from the saved episodes; nothing is simulated.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

LOW, NEAR, RISE = 0.04, 0.10, 0.02  # m: hand height above the table, hand-cube distance, dz of a "rise"


def targets_of(demos: dict[str, np.ndarray], start_obj: np.ndarray) -> np.ndarray:
    """The target centre (x, y) of each episode, found by its start state among the demonstrations."""
    from physint_plugins.geeco.checkpoint import episodes_of

    episodes = episodes_of(demos, "goal2cube2", "push")
    out = []
    for p in start_obj:
        i = int(np.argmin(np.linalg.norm(demos["obj"][:, 0, :2] - p[:2], axis=-1)))
        if np.linalg.norm(demos["obj"][i, 0, :2] - p[:2]) > 1e-4:
            raise SystemExit("a rollout's start state is not one of the dataset's training demonstrations")
        out.append(episodes[i].xy(episodes[i].target))
    return np.asarray(out)


def describe(name: str, ee: np.ndarray, obj: np.ndarray, dee: np.ndarray, target: np.ndarray, table_z: float) -> None:
    height = ee[..., 2] - table_z
    steps = [t for t in (0, 10, 15, 20, 30, 50, 80) if t < ee.shape[1]]
    print(f"{name} ({len(ee)} episodes)")
    print("  hand height (cm) at steps " + ", ".join(map(str, steps)) + ": "
          + ", ".join(f"{100 * np.median(height[:, t]):.1f}" for t in steps))
    moved = np.linalg.norm(obj[:, :, :2] - obj[:, :1, :2], axis=-1) > 0.005
    first = np.where(moved.any(1), moved.argmax(1), ee.shape[1])
    print(f"  first step the cube moved > 5 mm: median {np.median(first):.0f}")
    rel = ee[..., :2] - obj[..., :2]
    low_near = (height < LOW) & (np.linalg.norm(rel, axis=-1) < NEAR)
    rise = dee[..., 2] > RISE
    print(f"  hand low and near the cube in {low_near.mean():.0%} of the steps; there the expert says rise in "
          f"{rise[low_near].mean():.0%}")
    d = target[:, None] - obj[..., :2]
    d /= np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-9)
    along = (rel * d).sum(-1)
    across = np.abs(rel[..., 0] * d[..., 1] - rel[..., 1] * d[..., 0])
    m = low_near & rise
    if m.any():
        q = [25, 50, 75]
        print("  in those rise states, hand relative to the cube (cm), quartiles: along "
              + " / ".join(f"{v:+.1f}" for v in np.percentile(100 * along[m], q)) + ", across "
              + " / ".join(f"{v:.1f}" for v in np.percentile(100 * across[m], q)))
    final = np.linalg.norm(obj[:, -1, :2] - target, axis=-1)
    print(f"  cube to target at the end (cm): median {100 * np.median(final):.1f}")


def main(argv: list[str] | None = None) -> int:
    from physint_cli.datasets import ShardedDataset
    from physint_plugins.geeco.scenes import TABLE_Z

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="the push dataset the controller was trained on")
    parser.add_argument("--rounds", nargs="+", required=True, help="DAgger round files (RUN/dagger/epoch-NNN.npz)")
    args = parser.parse_args(argv)
    demos = ShardedDataset(args.data, "train", ["ee", "obj", "dee", "layout", "task", "seed"], method="geeco",
                           in_memory=True).arrays
    describe("training demonstrations", demos["ee"], demos["obj"], demos["dee"],
             targets_of(demos, demos["obj"][:, 0]), TABLE_Z)
    for path in args.rounds:
        with np.load(path) as r:
            describe(f"rollouts {Path(path).name}", r["ee"], r["obj"], r["dee"], targets_of(demos, r["obj"][:, 0]),
                     TABLE_Z)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
