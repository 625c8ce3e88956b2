"""GEECO (thesis Chapter 6) beside the thesis's numbers, with physint's own commands.

    python benchmarks/geeco.py [--preset small] [--home DIR] [--workers 2] [--models geeco-f,geeco-d,geeco-r]
                               [--seeds 1] [--skip pickplace,goal1cube1,transfer,backgrounds,cross,commands,lambda0]

Every step is a plain ``physint`` command run in its own process (printed as it starts); a step
whose result is already under ``--home`` is not run again, so an interrupted benchmark resumes.
Steps, for each skill (push, pick-and-place) on GOAL2CUBE2:

1. ``physint dataset geeco --set data.skill=SKILL``: wall time (goal: both skills <= 15 min on
   2 cores at the small preset) and the expert's success rate;
2. ``physint train geeco --model M`` for GEECO-F, -D and -R: wall time (goal: <= 45 min each);
3. ``physint eval geeco``: REACH / PUSH, REACH / PICK / PLACE with 95 % CIs beside Table 6.4.1
   (lambda = 1) and the control rate (goal: >= 50 Hz on a CPU). With ``--seeds N`` each model is
   trained and evaluated with seeds 0..N-1 (``--seed``), and the models are ordered by their mean
   PUSH / PLACE (goal: GEECO-F and -D above GEECO-R); one seed's order is not evidence, since
   seeds of one model can differ by 20 points or more (docs/geeco.md). The later steps use seed 0;
4. (``goal1cube1``) GOAL1CUBE1, both skills, the unconditioned E2EVMC beside each GEECO model: Table 6.C.1;
5. (``transfer``) the pick-and-place controllers in FG:CLUTTER, BG:PRISMA, NUTONCONE and BALLINCUP:
   Table 6.4.2;
6. (``backgrounds``) pick-and-place controllers trained on demonstrations with random backgrounds
   (``--set data.backgrounds=mixed``; not in the thesis, which trained on the plain table only),
   evaluated on their own test split, on plain GOAL2CUBE2 (``--data`` the plain dataset) and in
   BG:PRISMA, beside the controllers trained on the plain table;
7. (``cross``) the pushing GEECO-F trained on this backend, evaluated on the others (not in the thesis);
8. (``lambda0``) Table 6.4.1's ablation without position supervision: each model and skill trained with
   lambda = 0 in Eq. 6.3 (``--set train.aux_weight=0``; pushing then commands from the network, as
   nothing learns positions), beside the thesis's lambda = 0 rows;
9. (``commands``) where the pushing GEECO-F's u_dEE comes from: the small preset's controller takes it
   from positions (``train.command=auto``, with DAgger rounds; not in the thesis), here also evaluated
   on the simulator's positions, beside a GEECO-F with the thesis's end-to-end command
   (``--set train.command=network``). A preset whose controller is end-to-end (paper) skips this.

``--skip push`` or ``--skip pickplace`` leaves that skill out of every step.

Results are read back from each run's ``metrics.json``; nothing here computes a metric itself.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from commands import Steps, benchmark_parser, machine, metrics, minutes, pct, report  # noqa: E402

# Table 6.4.1 (lambda = 1): (REACH, PUSH) and (REACH, PICK, PLACE) in %
THESIS = {
    ("push", "geeco-r"): (98.90, 79.80), ("push", "geeco-d"): (99.30, 86.60), ("push", "geeco-f"): (99.80, 89.30),
    ("pickplace", "geeco-r"): (84.90, 50.40, 33.70), ("pickplace", "geeco-d"): (96.20, 79.90, 61.40),
    ("pickplace", "geeco-f"): (94.80, 78.40, 46.30),
}
# Table 6.C.1, GOAL1CUBE1: (REACH, PUSH) and (REACH, PICK, PLACE) in %
GOAL1CUBE1 = {
    ("push", "e2evmc"): (95.20, 58.60), ("push", "geeco-r"): (98.80, 43.70), ("push", "geeco-d"): (99.50, 87.40),
    ("push", "geeco-f"): (99.20, 72.90),
    ("pickplace", "e2evmc"): (96.10, 72.00, 67.60), ("pickplace", "geeco-r"): (95.30, 73.00, 60.70),
    ("pickplace", "geeco-d"): (95.80, 77.40, 64.90), ("pickplace", "geeco-f"): (95.90, 83.30, 61.20),
}
# Table 6.4.1 without position supervision (lambda = 0)
THESIS_LAMBDA0 = {
    ("push", "geeco-r"): (98.70, 79.80), ("push", "geeco-d"): (98.70, 88.50), ("push", "geeco-f"): (98.00, 78.60),
    ("pickplace", "geeco-r"): (86.20, 58.90, 42.50), ("pickplace", "geeco-d"): (95.40, 65.80, 54.20),
    ("pickplace", "geeco-f"): (92.70, 71.00, 45.60),
}
# Table 6.4.2, pick-and-place: (REACH, PICK, PLACE) in %
TRANSFER = {
    ("clutter", "geeco-r"): (63.80, 29.40, 15.80), ("clutter", "geeco-d"): (77.00, 42.10, 20.70),
    ("clutter", "geeco-f"): (85.50, 62.60, 32.60), ("prisma", "geeco-r"): (0.50, 0.10, 0.00),
    ("prisma", "geeco-d"): (94.10, 66.00, 26.50), ("prisma", "geeco-f"): (93.40, 62.40, 19.30),
    ("nutoncone", "geeco-r"): (32.30, 6.90, 0.40), ("nutoncone", "geeco-d"): (66.60, 23.30, 3.30),
    ("nutoncone", "geeco-f"): (72.20, 26.90, 6.20), ("ballincup", "geeco-r"): (21.50, 3.90, 0.10),
    ("ballincup", "geeco-d"): (50.60, 9.70, 0.20), ("ballincup", "geeco-f"): (54.60, 16.30, 1.50),
}
LABELS = {"push": ("REACH", "PUSH"), "pickplace": ("REACH", "PICK", "PLACE")}
# the thesis's end-to-end command, beside the small preset's push controller commanded from positions
END_TO_END = ["--set", "train.command=network"]
STEPS = ("push", "pickplace", "goal1cube1", "transfer", "backgrounds", "cross", "lambda0", "commands")
# the models that see dynamic images, which the thesis finds above GEECO-R (Table 6.4.1)
ABOVE_R = ("geeco-f", "geeco-d")
GOALS = {"data_min": 15.0, "train_min": 45.0, "hz": 50.0,
         "push": {"REACH": 0.90, "PUSH": 0.50}, "pickplace": {"PICK": 0.40, "PLACE": 0.25}}


def rates_text(metrics: dict, labels: tuple[str, ...]) -> str:
    r = metrics["rates"]
    return " / ".join(f"{100 * r[k]['rate']:.1f} ± {100 * r[k]['ci95']:.1f}" for k in labels)


def thesis_text(values: tuple[float, ...] | None) -> str:
    return "-" if values is None else " / ".join(f"{v:.1f}" for v in values)


def order_row(skill: str, by_seed: dict[str, list[float]]) -> tuple[str, str, str, str]:
    """The models by their mean success over seeds, and whether GEECO-F and -D are above GEECO-R."""
    label = LABELS[skill][-1]
    means = {model: sum(v) / len(v) for model, v in by_seed.items()}
    ranked = sorted(means.items(), key=lambda kv: -kv[1])
    order = f"{ranked[0][0]} {100 * ranked[0][1]:.1f}" + "".join(
        f" {'>' if mean < ranked[i][1] else '='} {model} {100 * mean:.1f}" for i, (model, mean) in enumerate(ranked[1:]))
    seeds = min(len(v) for v in by_seed.values())
    thesis = " > ".join(f"{m} {THESIS[(skill, m)][-1]:.1f}" for m in sorted(means, key=lambda m: -THESIS[(skill, m)][-1]))
    above = [m for m in ABOVE_R if m in means]
    if "geeco-r" in means and above:
        holds = all(means[m] > means["geeco-r"] for m in above)
        goal = f"{', '.join(above)} above geeco-r: {'holds' if holds else 'does not hold'}"
    else:
        goal = "-"
    return (f"{skill}: models by mean {label} over {seeds} seed{'s' if seeds > 1 else ''}", thesis, order, goal)


def main(argv: list[str] | None = None) -> int:
    parser = benchmark_parser(__doc__, "geeco")
    parser.add_argument("--models", default="geeco-f,geeco-d,geeco-r")
    parser.add_argument("--seeds", type=int, default=1,
                        help="train and evaluate each GOAL2CUBE2 model with this many seeds (0..N-1)")
    parser.add_argument("--skip", default="", help=f"comma-separated steps to leave out: {', '.join(STEPS)}")
    args = parser.parse_args(argv)
    skip = {s.strip() for s in args.skip.split(",") if s.strip()}
    unknown = skip - set(STEPS)
    if unknown:
        parser.error(f"--skip takes {', '.join(STEPS)}; got {', '.join(sorted(unknown))}")
    models = [m.strip() for m in args.models.split(",") if m.strip()]
    if args.seeds < 1:
        parser.error(f"--seeds must be >= 1, got {args.seeds}")
    b = Steps(Path(args.home).resolve(), args.preset, args.workers, args.backend)
    rows: list[tuple[str, str, str, str]] = []
    figures: dict = {"preset": args.preset, "backend": args.backend,
                     "machine": machine()}
    w = ["--workers", str(args.workers)]

    def dataset(name: str, scene: str, skill: str, *extra: str) -> Path:
        return b.dataset(f"dataset-{name}", b.home / f"data-{name}",
                         ["geeco", "--scene", scene, "--backend", args.backend, "--set", f"data.skill={skill}", *extra])

    def train(name: str, data: Path, model: str, *extra: str, seed: int = 0) -> Path:
        key = f"train-{name}-{model}" + (f"-seed{seed}" if seed else "")  # seed 0 keeps the names of 1-seed homes
        return b.train(key, b.home / key, ["geeco", "--data", str(data), "--model", model, "--backend", args.backend,
                                           "--seed", str(seed), *extra])

    def evaluate(key: str, run: Path, *extra: str) -> dict:
        return b.verb(f"eval-{key}", b.home / f"eval-{key}", ["eval", "geeco", "--run", str(run), *w, *extra])

    def trained_row(name: str, data: Path, model: str, skill: str, label: str, table: str, thesis, *extra: str):
        """Train ``model`` on ``data`` (with ``extra`` options), evaluate it, and add its row with its training time."""
        m = evaluate(f"{name}-{model}", train(name, data, model, *extra))
        figures[f"{name}-{model}"] = m
        rows.append((f"{label} {' / '.join(LABELS[skill])} % ({table})", thesis_text(thesis),
                     rates_text(m, LABELS[skill]), f"training {minutes(b.times.get(f'train-{name}-{model}'))}"))

    data_seconds = 0.0
    trained: dict[tuple[str, str], Path] = {}
    for skill in ("push", "pickplace"):
        if skill in skip:
            continue
        data = dataset(skill, "goal2cube2", skill)
        stats = json.loads((data / "manifest.json").read_text())["stats"]
        seconds = b.times.get(f"dataset-{skill}")
        data_seconds += seconds or 0.0
        rows.append((f"{skill}: demonstrations ({stats['demos']}), wall time", "-", minutes(seconds), "-"))
        rows.append((f"{skill}: expert success rate", "-", pct(stats["expert_success_rate"]), "-"))
        by_seed: dict[str, list[float]] = {}
        for model in models:
            for seed in range(args.seeds):
                tag = f"{model}" + (f"-seed{seed}" if seed else "")
                run = train(skill, data, model, seed=seed)
                if seed == 0:
                    trained[(skill, model)] = run
                name = f"{model}, seed {seed}" if args.seeds > 1 else model
                rows.append((f"{skill}: {name} training wall time", "48 h (GPU)",
                             minutes(b.times.get(f"train-{skill}-{tag}")), f"<= {GOALS['train_min']:.0f} min"))
                m = evaluate(f"{skill}-{tag}", run)
                figures[f"{skill}-{tag}"] = m
                by_seed.setdefault(model, []).append(m["rates"][LABELS[skill][-1]]["rate"])
                goal = ", ".join(f"{k} >= {pct(v)}" for k, v in GOALS[skill].items())
                rows.append((f"{skill}: {name} {' / '.join(LABELS[skill])} % (Table 6.4.1)",
                             thesis_text(THESIS.get((skill, model))), rates_text(m, LABELS[skill]), goal))
                rows.append((f"{skill}: {name} control rate", "~20 Hz (GPU)", f"{m['control_hz']:.0f} Hz",
                             f">= {GOALS['hz']:.0f} Hz"))
        if args.seeds > 1 and len(by_seed) > 1 and all((skill, model) in THESIS for model in by_seed):
            rows.append(order_row(skill, by_seed))
    if data_seconds:
        rows.append(("demonstrations of both skills: wall time", "-", minutes(data_seconds),
                     f"<= {GOALS['data_min']:.0f} min"))

    if "goal1cube1" not in skip:
        for skill in ("push", "pickplace"):
            if skill in skip:
                continue
            data = dataset(f"goal1cube1-{skill}", "goal1cube1", skill)
            for model in dict.fromkeys(("e2evmc", *models)):  # E2EVMC first, once
                trained_row(f"goal1cube1-{skill}", data, model, skill, f"GOAL1CUBE1 {skill}: {model}", "Table 6.C.1",
                            GOAL1CUBE1.get((skill, model)))

    if "transfer" not in skip and "pickplace" not in skip:
        for scene in ("clutter", "prisma", "nutoncone", "ballincup"):
            for model in models:
                m = evaluate(f"{scene}-{model}", trained[("pickplace", model)], "--scene", scene)
                figures[f"{scene}-{model}"] = m
                rows.append((f"{scene}: {model} REACH / PICK / PLACE % (Table 6.4.2)",
                             thesis_text(TRANSFER.get((scene, model))), rates_text(m, LABELS["pickplace"]),
                             f"{m['no_target']} without a target"))

    if "backgrounds" not in skip and "pickplace" not in skip:
        plain = dataset("pickplace", "goal2cube2", "pickplace")
        mixed = dataset("pickplace-mixed", "goal2cube2", "pickplace", "--set", "data.backgrounds=mixed")
        for model in models:
            run = train("pickplace-mixed", mixed, model)
            # (where, its key, eval options, thesis figures, the same model trained on the plain table there)
            for where, on, extra, thesis, plain_key in (
                    ("random backgrounds", "random", (), None, None),
                    ("GOAL2CUBE2", "plain", ("--data", str(plain)), THESIS.get(("pickplace", model)),
                     f"pickplace-{model}"),
                    ("BG:PRISMA", "prisma", ("--scene", "prisma"), TRANSFER.get(("prisma", model)), f"prisma-{model}")):
                key = f"pickplace-mixed-{model}-on-{on}"
                m = evaluate(key, run, *extra)
                figures[key] = m
                trained_plain = figures.get(plain_key)
                rows.append((f"pickplace: {model} trained on random backgrounds, in {where}, REACH / PICK / PLACE %",
                             "not in the thesis" if thesis is None else thesis_text(thesis),
                             rates_text(m, LABELS["pickplace"]),
                             "-" if trained_plain is None
                             else f"trained on the plain table: {rates_text(trained_plain, LABELS['pickplace'])}"))

    if "cross" not in skip and "push" not in skip and "geeco-f" in models:
        for other in ("mujoco", "pybullet", "robosuite"):
            if other == args.backend:
                continue
            m = evaluate(f"push-geeco-f-on-{other}", trained[("push", "geeco-f")], "--backend", other)
            figures[f"push-geeco-f-on-{other}"] = m
            rows.append((f"push: geeco-f trained on {args.backend}, run on {other}", "not in the thesis",
                         rates_text(m, LABELS["push"]), f"{m['no_target']} without a target"))

    if "lambda0" not in skip:
        for skill in ("push", "pickplace"):
            if skill in skip:
                continue
            data = dataset(skill, "goal2cube2", skill)
            for model in models:
                trained_row(f"{skill}-lambda0", data, model, skill, f"{skill}: {model}, lambda = 0,", "Table 6.4.1",
                            THESIS_LAMBDA0.get((skill, model)), "--set", "train.aux_weight=0")

    push_f = trained.get(("push", "geeco-f"))
    if "commands" not in skip and push_f is not None and metrics(push_f).get("command") == "positions":
        m = evaluate("push-geeco-f-true-positions", push_f, "--set", "eval.positions=true")
        figures["push-geeco-f-true-positions"] = m
        rows.append(("push: geeco-f, its command head on the simulator's positions, REACH / PUSH %",
                     "not in the thesis", rates_text(m, LABELS["push"]), "the command head alone"))
        run = train("push-end-to-end", dataset("push", "goal2cube2", "push"), "geeco-f", *END_TO_END)
        rows.append(("push: geeco-f, u_dEE from the network (the thesis), training wall time", "48 h (GPU)",
                     minutes(b.times.get("train-push-end-to-end-geeco-f")), f"<= {GOALS['train_min']:.0f} min"))
        m = evaluate("push-end-to-end", run)
        figures["push-end-to-end"] = m
        rows.append(("push: geeco-f, u_dEE from the network (the thesis), REACH / PUSH %",
                     thesis_text(THESIS[("push", "geeco-f")]), rates_text(m, LABELS["push"]), "-"))

    report(f"geeco benchmark, preset {args.preset}, backend {args.backend}", rows, figures, b, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
