"""Tool imagination (thesis Chapter 4) beside the thesis's Table 4.1, with physint's own commands.

    python benchmarks/toolsynth.py [--preset small] [--home DIR] [--workers 2] [--backend mujoco]
                                   [--set eval.max_steps=10000 ...]

Every step is a plain ``physint`` command run in its own process (printed as it starts, so any
figure can be re-made by hand); a step whose result is already under ``--home`` is not run
again, so an interrupted benchmark resumes where it stopped. Steps:

1. ``physint dataset toolsynth``: wall time (goal: <= 10 min on 2 AVX2 cores at the small preset)
   and the simulator's agreement with the geometric labels;
2. ``physint train toolsynth``: wall time of the three stages (goal: <= 45 min), classifier
   accuracy and reconstruction IoU;
3. ``physint eval toolsynth`` (with any ``--set``): wall time (goal: <= 10 min) and Table 4.1,
   task-driven / task-unaware imagination and the random walk per scenario type, with the no-op
   control beside them; the goal is task-driven > task-unaware > random walk on the total with
   gaps outside the 95 % intervals, and E (held out of training) above the random walk.

Set ``ATEN_CPU_CAPABILITY=avx2 ONEDNN_MAX_CPU_ISA=AVX2`` to hold torch to AVX2 on a newer CPU.
Results are read back from each run's ``metrics.json``; nothing here computes a metric itself.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from commands import Steps, benchmark_parser, machine, metrics, minutes, pct, report  # noqa: E402

# Table 4.1, success (%)
THESIS = {"task-driven": {"A": 96.4, "B": 78.8, "C": 76.4, "D": 81.2, "E": 86.4, "total": 83.8},
          "task-unaware": {"A": 55.6, "B": 42.0, "C": 56.8, "D": 75.2, "E": 88.4, "total": 63.6},
          "random walk": {"A": 3.6, "B": 5.6, "C": 23.6, "D": 2.4, "E": 13.6, "total": 9.8}}
GOALS = {"dataset_min": 10.0, "train_min": 45.0, "eval_min": 10.0}
ORDER = ("task-driven", "task-unaware", "random walk")


def rate(r: dict | None) -> str:
    return "-" if not r else f"{100 * r['rate']:.1f} ± {100 * r['ci95']:.1f} %"


def apart(a: dict, b: dict) -> bool:
    """Whether rate a lies above rate b with their 95 % intervals apart."""
    return a["rate"] - a["ci95"] > b["rate"] + b["ci95"]


def main(argv: list[str] | None = None) -> int:
    parser = benchmark_parser(__doc__, "toolsynth")
    parser.add_argument("--set", action="append", default=[], help="extra eval settings, e.g. eval.max_steps=10000")
    args = parser.parse_args(argv)
    home = Path(args.home)
    steps = Steps(home, args.preset, args.workers, args.backend)
    data = steps.dataset("dataset", home / "data", ["toolsynth", "--backend", args.backend])
    run = steps.train("train", home / "train", ["toolsynth", "--data", str(data)])
    extra = [a for s in args.set for a in ("--set", s)]
    tag = "-".join(s.replace("=", "") for s in args.set) or "default"
    ev = steps.verb(f"eval-{tag}", home / f"eval-{tag}", ["eval", "toolsynth", "--run", str(run), *extra])

    manifest = json.loads((data / "manifest.json").read_text())
    trained = metrics(run)
    stats = manifest.get("stats", {})
    rows = [("dataset wall time", "-", minutes(steps.times.get("dataset")), f"<= {GOALS['dataset_min']:.0f} min"),
            ("simulator agrees with the geometric labels", "-", pct(stats.get("sim_agreement")),
             f"of {stats.get('sim_checked', '-')} records"),
            ("training wall time (three stages)", "-", minutes(steps.times.get("train")),
             f"<= {GOALS['train_min']:.0f} min"),
            ("eval wall time", "-", minutes(steps.times.get(f"eval-{tag}")), f"<= {GOALS['eval_min']:.0f} min")]
    for title in ("task-driven", "task-unaware"):
        test = ev["test"][title]
        rows.append((f"{title}: classifier accuracy on the test split", "-", pct(test["accuracy"]), "chance 50 %"))
        rows.append((f"{title}: reconstruction IoU, other view / from above", "-",
                     f"{test['iou']:.3f} / {test['footprint_iou']:.3f}", "-"))
        rows.append((f"{title}: decoded tools keeping their label", "-", pct(test["reconstruction_keeps_label"]),
                     f"feasible ones {pct(test['reconstruction_keeps_feasible'])}"))
    imagination = ev["imagination"]
    for name, r in imagination.items():
        for letter in [*ev["types"], "total"]:
            thesis = THESIS.get(name, {}).get(letter)
            rows.append((f"Table 4.1 {name}, {letter}", "-" if thesis is None else f"{thesis:.1f} %",
                         rate(r["success"].get(letter)), "~0 % (control)" if name == "no-op" else "-"))
        rows.append((f"  {name}: reached p >= {ev['threshold']}, mean steps", "-",
                     f"{pct(r['reached_threshold'])}, " + ("-" if r["mean_steps"] is None else f"{r['mean_steps']:.0f}"), f"cap {ev['max_steps']}"))
        if "latent_moved" in r:
            rows.append((f"  {name}: distance moved in z_T / distance between two tools", "-",
                         f"{r['latent_moved']:.2f}", "-"))
    totals = {n: imagination[n]["success"]["total"] for n in ORDER if n in imagination}
    if len(totals) == len(ORDER):
        order = all(apart(totals[a], totals[b]) for a, b in zip(ORDER, ORDER[1:]))
        rows.append(("task-driven > task-unaware > random walk, intervals apart", "yes", "yes" if order else "no", "yes"))
    if "E" in ev["types"]:
        e = {n: imagination[n]["success"]["E"]["rate"] for n in ("task-driven", "random walk")}
        rows.append(("E (held out): task-driven above the random walk", "yes",
                     "yes" if e["task-driven"] > e["random walk"] else "no", "yes"))
    figures = {"machine": machine(), "dataset": stats, "train": trained, "eval": ev}
    report(f"toolsynth benchmark, preset {args.preset}, backend {args.backend}", rows, figures, steps, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
