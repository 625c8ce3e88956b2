"""What float rounding does to a GEECO controller's closed-loop episodes.

    python benchmarks/geeco_rounding.py --run RUN [--episodes 200] [--side-by-side 10]
                                        [--shadow-episodes 50] [--out DIR]

``eval.side_by_side`` sends several episodes' frames through the network as one batch, whose
float sums are ordered otherwise than a batch of one's. Two measurements:

1. *shadow*: an evaluation side by side in which, beside every batched step, each episode's
   controller also acts alone on the same frames (a second policy of the same model, with its own
   buffer, at batch size one): the largest difference between the two actions, by step of the
   episode. Small at every step means a batch is exact up to rounding, and any larger difference
   between whole episodes is the closed loop's (frames that differ because earlier actions did).
2. *outcomes*: the test episodes evaluated one at a time (the reported figures), side by side, and
   one at a time with the network on two torch threads instead of one (another order of float
   sums, no batch); for each pair, the episodes that succeeded under only one of the two and the
   exact McNemar test on them.

Prints both tables; each evaluation's run is kept under ``--out`` (default: a temporary folder).
Nothing here is a product path (docs/geeco.md, "Known deviations": eval.side_by_side).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
import time
from pathlib import Path
from unittest.mock import patch

import numpy as np
from scipy.stats import binomtest

import physint_cli.cli as cli
import physint_cli.training as training
import physint_plugins.geeco.control as control
from physint_cli.cli import run as physint

STEP_RANGES = ((0, 1), (1, 10), (10, 50), (50, 100), (100, 200))


def evaluate(run: str, out: Path, *args: str) -> dict[int, dict]:
    """``physint eval geeco --run RUN ARGS``, in this process: its episodes by index."""
    out.mkdir(parents=True, exist_ok=True)
    with patch.object(cli, "_RESULTS", io.StringIO()):  # its printed result: the run's files are read below
        code = physint(["eval", "geeco", "--run", run, "--out", str(out), "--quiet", "--json", *args])
    if code != 0:
        sys.exit(f"physint eval geeco {' '.join(args)} failed ({code})")
    rows = [json.loads(line) for line in (out / "artifacts" / "episodes.jsonl").read_text().splitlines()]
    return {r["index"]: r for r in rows if "success" in r}


def shadow(run: str, out: Path, episodes: int, side_by_side: int) -> list[tuple[int, float]]:
    """(step of the episode, max |batched action - the same policy's action alone|) for every batched action."""
    batched = control.act_together
    shadows: dict[int, tuple[control.Policy, list[int]]] = {}
    diffs: list[tuple[int, float]] = []

    def checked(policies, observations):
        if len(policies) < 2 or not all(isinstance(p, control.Policy) for p in policies):
            return batched(policies, observations)
        for p in policies:
            if not p.buffer:  # an episode's first step: a fresh shadow with the same target
                alone = control.Policy(p.model, p.device)
                alone.target = p.target
                shadows[id(p)] = (alone, [0])
        actions = batched(policies, observations)
        for p, obs, action in zip(policies, observations, actions, strict=True):
            alone, step = shadows[id(p)]
            diffs.append((step[0], float(np.nanmax(np.abs(np.asarray(action) - batched([alone], [obs])[0])))))
            step[0] += 1
        return actions

    with patch.object(control, "act_together", checked):
        evaluate(run, out, "--workers", "1", "--set", f"eval.side_by_side={side_by_side}",
                 "--episodes", str(episodes))
    return diffs


def two_threads():
    """The network on two torch threads where evaluation asks for one."""
    one_thread = training.torch_threads
    return patch.object(training, "torch_threads", lambda n: one_thread(2))


def mcnemar(b: int, c: int) -> float:
    """Exact two-sided McNemar p for b and c discordant pairs (a binomial test of b in b + c at 1/2)."""
    return 1.0 if b + c == 0 else binomtest(b, b + c, 0.5).pvalue


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", required=True, help="a trained geeco run")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--side-by-side", type=int, default=10)
    parser.add_argument("--shadow-episodes", type=int, default=50)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="geeco_rounding_"))

    diffs = np.array(shadow(args.run, out / "shadow", args.shadow_episodes, args.side_by_side))
    print(f"\nshadow: {len(diffs)} batched actions ({args.side_by_side} side by side) against the same "
          "controller alone on the same frames")
    print("| steps | max difference | median |\n|---|---|---|")
    for lo, hi in STEP_RANGES:
        sel = diffs[(diffs[:, 0] >= lo) & (diffs[:, 0] < hi), 1] if len(diffs) else []
        if len(sel):
            print(f"| {lo}-{hi - 1} | {sel.max():.1e} | {np.median(sel):.1e} |")

    common = ["--episodes", str(args.episodes)]
    runs: dict[str, tuple[dict[int, dict], float]] = {}
    for name, extra, context in (
            ("one at a time, 1 thread", ["--workers", "2"], contextlib.nullcontext()),
            (f"{args.side_by_side} side by side, 1 thread",
             ["--workers", "2", "--set", f"eval.side_by_side={args.side_by_side}"], contextlib.nullcontext()),
            ("one at a time, 2 threads", ["--workers", "1"], two_threads())):
        t0 = time.perf_counter()
        with context:
            episodes = evaluate(args.run, out / name.replace(" ", "_").replace(",", ""), *common, *extra)
        runs[name] = (episodes, time.perf_counter() - t0)

    first = next(iter(runs))
    print(f"\noutcomes of {args.episodes} test episodes (runs under {out})")
    print("| evaluation | seconds | REACH | success | only the first / only the second, against "
          f"'{first}' | exact McNemar p |\n|---|---|---|---|---|---|")
    base = runs[first][0]
    for name, (episodes, seconds) in runs.items():
        reach = sum(bool(r["reach"]) for r in episodes.values())
        success = sum(bool(r["success"]) for r in episodes.values())
        row = f"| {name} | {seconds:.0f} | {reach} | {success} |"
        if name == first:
            print(row + " | |")
            continue
        shared = sorted(set(base) & set(episodes))
        only_base = sum(bool(base[i]["success"]) and not episodes[i]["success"] for i in shared)
        only_this = sum(bool(episodes[i]["success"]) and not base[i]["success"] for i in shared)
        print(f"{row} {only_base} / {only_this} | {mcnemar(only_base, only_this):.3f} |")


if __name__ == "__main__":
    main()
