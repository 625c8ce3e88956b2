"""RELATE (thesis Chapter 5) beside the thesis's Tables 5.4.1 and 5.A.1, with physint's own commands.

    python benchmarks/relate.py [--preset small] [--home DIR] [--workers 2] [--backend mujoco]
                                [--arms full,no-position,blockgan2d,no-residual] [--seeds 0]

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
    figures = {"machine": machine(precision="fp32"), "dataset": manifest.get("stats", {}), "eval": results}
    report(f"relate benchmark, preset {args.preset}, backend {args.backend}", rows, figures, steps, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
