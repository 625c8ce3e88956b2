"""RELATE (thesis Chapter 5) beside the thesis's Tables 5.4.1 and 5.A.1, with physint's own commands.

    python benchmarks/relate.py [--preset small] [--home DIR] [--workers 2] [--backend mujoco]
                                [--arms full,no-position,blockgan2d,no-residual] [--seeds 0]
                                [--ordered-seeds 0,1]

Every step is a plain ``physint`` command run in its own process (printed as it starts, so any
figure can be re-made by hand); a step whose result is already under ``--home`` is not run
again, so an interrupted benchmark resumes where it stopped. Steps:

1. ``physint dataset relate`` (balls-in-bowl): wall time (goal: <= 10 min on 2 AVX2 cores at the small preset);
2. ``physint train relate --set train.arm=ARM --seed S`` per arm and seed: wall time (goal: <= 45 min per arm);
3. ``physint eval relate`` per run: FD-truth (the Fréchet distance on the in-project ground-truth
   regressor's features; not FID: the thesis's FID column is beside it for the order of the arms, not
   the values), the share of physically plausible scenes with Gamma and with Gamma bypassed, and the
   toggle score. The goal: full RELATE below BlockGAN2D and the no-position arm on FD-truth and on the
   toggle score by more than the spread over seeds, and Gamma raising the plausibility rate.

With ``--ordered-seeds``, the same for the ordered variant on ShapeStacks towers (Table 5.4.2): a shapestacks
dataset of 5,000 / 500 stable towers and 1,000 unstable ones (``home/shapestacks``), one ``train.variant=ordered``
training per seed, and per run FD-truth and the share of plausible towers (blocks resting on each other, Lemma 1
as seen) with Gamma and bypassed, beside the tower reader's rates on held-out real stable and unstable towers.

Set ``ATEN_CPU_CAPABILITY=avx2 ONEDNN_MAX_CPU_ISA=AVX2`` to hold torch to AVX2 on a newer CPU.
Results are read back from each run's ``metrics.json``; nothing here computes a metric itself.
"""

from __future__ import annotations

import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from commands import Steps, benchmark_parser, machine, minutes, pct, report  # noqa: E402

THESIS_FID = {"blockgan2d": 152.3, "no-residual": 133.9, "no-position": 154.8, "full": 81.9}  # Table 5.4.1
THESIS_TOGGLE = {"blockgan2d": 98.0, "full": 26.0}  # Table 5.A.1, BallsInBowl
GOALS = {"dataset_min": 10.0, "train_min": 45.0}


def spread(values: list[float]) -> str:
    if len(values) < 2:
        return f"{values[0]:.2f}" if values else "-"
    return f"{statistics.mean(values):.2f} ± {statistics.stdev(values):.2f} (n={len(values)})"


def main(argv: list[str] | None = None) -> int:
    parser = benchmark_parser(__doc__, "relate")
    parser.add_argument("--arms", default="full,no-position,blockgan2d,no-residual", help="ablation arms to train")
    parser.add_argument("--seeds", default="0", help="comma-separated training seeds per arm")
    parser.add_argument("--ordered-seeds", default="", help="comma-separated seeds of the ordered variant on shapestacks")
    args = parser.parse_args(argv)
    home = Path(args.home)
    steps = Steps(home, args.preset, args.workers, args.backend)
    data = steps.dataset("dataset", home / "data", ["relate", "--backend", args.backend])
    manifest = json.loads((data / "manifest.json").read_text())
    rows = [("dataset wall time", "-", minutes(steps.times.get("dataset")), f"<= {GOALS['dataset_min']:.0f} min")]
    results: dict[str, list[dict]] = {}
    for arm in args.arms.split(","):
        for seed in args.seeds.split(","):
            run = steps.train(f"train-{arm}-{seed}", home / f"train-{arm}-{seed}",
                              ["relate", "--data", str(data), "--seed", seed, "--set", f"train.arm={arm}"])
            ev = steps.verb(f"eval-{arm}-{seed}", home / f"eval-{arm}-{seed}", ["eval", "relate", "--run", str(run),
                                                                                "--seed", seed])
            results.setdefault(arm, []).append(ev)
            rows.append((f"training wall time, {arm}, seed {seed}", "-", minutes(steps.times.get(f"train-{arm}-{seed}")),
                         f"<= {GOALS['train_min']:.0f} min"))
    real = next(iter(results.values()))[0]["real"] if results else None
    if real:
        rows.append(("FD-truth, real training vs test frames (the floor)", "-", f"{real['fd_truth']:.2f}", "-"))
        if "plausibility" in real:
            rows.append(("plausible real test frames (the detector's check)", "-", pct(real["plausibility"]["plausible"]), "100 %"))
    for arm, evs in results.items():
        fd = [e["generated"]["Gamma"]["fd_truth"] for e in evs]
        rows.append((f"Table 5.4.1 {arm}: FD-truth (thesis: FID)", f"{THESIS_FID.get(arm, '-')}", spread(fd), "lower"))
        rows.append((f"Table 5.A.1 {arm}: toggle distance px", f"{THESIS_TOGGLE.get(arm, '-')} (at 128 px)",
                     spread([e["toggle_px"] for e in evs]), "lower"))
        for name in ("Gamma", "Gamma bypassed"):
            rates = [e["generated"][name]["plausibility"]["plausible"] for e in evs
                     if name in e["generated"] and "plausibility" in e["generated"][name]]
            if rates:
                rows.append((f"  {arm}: plausible scenes, {name}", "-", spread([100 * r for r in rates]) + " %", "-"))
    towers = ordered(steps, home, args, rows) if args.ordered_seeds else []
    figures = {"machine": machine(precision="fp32"), "dataset": manifest.get("stats", {}), "eval": results,
               "ordered": towers}
    report(f"relate benchmark, preset {args.preset}, backend {args.backend}", rows, figures, steps, args.json)
    return 0


def ordered(steps: Steps, home: Path, args, rows: list) -> list[dict]:
    """The ordered variant on ShapeStacks (Table 5.4.2): its steps, and its rows added to ``rows``."""
    data = steps.dataset("dataset-shapestacks", home / "shapestacks" / "data",
                         ["relate", "--backend", args.backend, "--scene", "shapestacks", "--set", "data.train=5000",
                          "--set", "data.test=500", "--set", "data.unstable=1000"])
    rows.append(("shapestacks dataset wall time", "-", minutes(steps.times.get("dataset-shapestacks")),
                 f"<= {GOALS['dataset_min']:.0f} min"))
    evs = []
    for seed in args.ordered_seeds.split(","):
        run = steps.train(f"train-ordered-{seed}", home / "shapestacks" / f"train-ordered-{seed}",
                          ["relate", "--data", str(data), "--seed", seed, "--set", "train.variant=ordered"])
        evs.append(steps.verb(f"eval-ordered-{seed}", home / "shapestacks" / f"eval-ordered-{seed}",
                              ["eval", "relate", "--run", str(run), "--seed", seed]))
        rows.append((f"training wall time, ordered, seed {seed}", "-", minutes(steps.times.get(f"train-ordered-{seed}")),
                     f"<= {GOALS['train_min']:.0f} min"))
    for name in ("Gamma", "Gamma bypassed"):
        rows.append((f"Table 5.4.2 ordered, {name}: FD-truth (thesis: FID)", "95.8" if name == "Gamma" else "-",
                     spread([e["generated"][name]["fd_truth"] for e in evs]), "lower"))
        rows.append((f"  ordered, {name}: plausible towers", "-",
                     spread([100 * e["generated"][name]["towers"]["plausible"] for e in evs]) + " %", "-"))
    for name in evs[0]["real"]["towers"]:
        rows.append((f"  tower reader: real {name} called plausible", "-",
                     spread([100 * e["real"]["towers"][name]["plausible"] for e in evs]) + " %", "-"))
    return evs


if __name__ == "__main__":
    sys.exit(main())
