"""Stability (thesis Chapter 3, ShapeStacks) beside the thesis's numbers, with physint's own commands.

    python benchmarks/stability.py [--preset small] [--home DIR] [--workers 2] [--skip cubes,cross,deploy]

Every step is a plain ``physint`` command run in its own process (printed as it starts, so any
figure can be re-made by hand); a step whose result is already under ``--home`` is not run
again, so an interrupted benchmark resumes where it stopped. Steps:

1. ``physint dataset stability --scene ccs`` and ``--scene cubes``: wall time (goal: <= 10 min
   each on 2 cores for the small preset), simulator agreement, scenarios per CPU second.
2. ``physint train stability`` on each: wall time (goal: <= 30 min on 2 cores).
3. ``physint eval stability`` of each predictor on the all-shapes test split: Table 3.3's
   simulated row; the CCS predictor's occlusion study is Table 3.4.
4. cross-backend (not in the thesis): a PyBullet CCS dataset and predictor; the MuJoCo
   predictor tested on PyBullet renders and the PyBullet predictor on MuJoCo renders.
5. ``physint deploy stability --task stack`` with the CCS- and Cubes-trained predictors beside
   the random-placement baseline and the Lemma-1 oracle (Fig. 3.7); ``--task balance`` (Fig. 3.9);
   ``--task stackability`` (Figs. 3.5 and 3.6).

Wall times depend on the machine's load; the table says what machine it ran on. Results are
read back from each run's ``metrics.json``; nothing here computes a metric itself.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from commands import Steps, benchmark_parser, machine, minutes, pct, report  # noqa: E402

# thesis Table 3.3 (simulated row), Table 3.4 (first row) and the small-preset goals
THESIS = {
    "acc_ccs": 0.849, "acc_cubes": 0.777, "alexnet_ccs": 0.588, "alexnet_cubes": 0.605,
    "violation_area": 0.799, "violating_object": 0.389, "first_to_fall": 0.293,
}
GOALS = {"dataset_min": 10.0, "train_min": 30.0, "acc_ccs": 0.85, "violation_area": 0.799}


SHORT = {"cuboid largest face": "cuboid L", "cuboid middle face": "cuboid M", "cuboid smallest face": "cuboid S",
         "cube": "cube", "cylinder upright": "cyl. up", "cylinder lying": "cyl. lying", "sphere": "sphere"}


def class_order(means: dict[str, float]) -> str:
    """Stackability classes best first, with their mean scores."""
    return " > ".join(f"{SHORT.get(c, c)} {m:.2f}" for c, m in sorted(means.items(), key=lambda kv: -kv[1])) or "-"


class Bench(Steps):
    def dataset(self, scene: str, backend: str | None = None) -> Path:  # type: ignore[override]
        backend = backend or self.backend
        return super().dataset(f"dataset-{scene}-{backend}", self.home / f"data-{scene}-{backend}",
                               ["stability", "--scene", scene, "--backend", backend])

    def train(self, scene: str, data: Path, backend: str | None = None) -> Path:  # type: ignore[override]
        backend = backend or self.backend
        return super().train(f"train-{scene}-{backend}", self.home / f"train-{scene}-{backend}",
                             ["stability", "--data", str(data), "--backend", backend])

    def eval(self, name: str, run: Path, backend: str | None = None, *sets: str) -> dict:
        extra = [a for s in sets for a in ("--set", s)]
        return self.verb(f"eval-{name}", self.home / f"eval-{name}",
                         ["eval", "stability", "--run", str(run), "--backend", backend or self.backend,
                          "--workers", str(self.workers), *extra])

    def deploy(self, name: str, task: str, run: Path | None, agents: str, *extra: str) -> dict:
        source = ["--run", str(run)] if run is not None else []
        return self.verb(f"deploy-{name}", self.home / f"deploy-{name}",
                         ["deploy", "stability", "--task", task, *source, "--set", f"deploy.agents={agents}",
                          "--backend", self.backend, "--workers", str(self.workers), *extra])


def main(argv: list[str] | None = None) -> int:
    parser = benchmark_parser(__doc__, "stability")
    parser.add_argument("--cross-backend", default="pybullet", help="the other backend of step 4")
    parser.add_argument("--skip", default="", help="comma-separated steps to leave out: cubes, cross, deploy")
    args = parser.parse_args(argv)
    skip = {s.strip() for s in args.skip.split(",") if s.strip()}
    unknown = skip - {"cubes", "cross", "deploy"}
    if unknown:
        parser.error(f"--skip takes cubes, cross, deploy; got {', '.join(sorted(unknown))}")
    b = Bench(Path(args.home).resolve(), args.preset, args.workers, args.backend)
    rows: list[tuple[str, str, str, str]] = []  # (measure, thesis, physint, goal)
    figures: dict = {"preset": args.preset, "machine": machine()}

    # 1-3: CCS dataset, predictor, evaluation (Table 3.3, Table 3.4)
    ccs = b.dataset("ccs")
    manifest = json.loads((ccs / "manifest.json").read_text())
    t_ccs = b.times.get(f"dataset-ccs-{b.backend}")
    rows.append(("CCS dataset: wall time", "-", minutes(t_ccs), f"<= {GOALS['dataset_min']:.0f} min"))
    rows.append(("CCS dataset: simulator agreement", "not reported", pct(manifest["stats"]["agreement_rate"]), "-"))
    train_ccs = b.train("ccs", ccs)
    rows.append(("CCS predictor: training wall time", "-", minutes(b.times.get(f"train-ccs-{b.backend}")),
                 f"<= {GOALS['train_min']:.0f} min"))
    e_ccs = b.eval("ccs", train_ccs)
    figures["eval_ccs"] = e_ccs
    rows.append(("accuracy, trained on CCS, all-shapes test (Table 3.3)", pct(THESIS["acc_ccs"]), pct(e_ccs["accuracy"]),
                 f">= {pct(GOALS['acc_ccs'])}"))
    loc = e_ccs.get("localisation", {}).get("all", {})
    rows.append(("attention maxima in the violation area (Table 3.4)", pct(THESIS["violation_area"]),
                 pct(loc.get("violation_area")), f">= {pct(GOALS['violation_area'])}"))
    rows.append(("  ... on the violating object", pct(THESIS["violating_object"]), pct(loc.get("violating_object")), "-"))
    rows.append(("  ... on the first object to fall", pct(THESIS["first_to_fall"]), pct(loc.get("first_to_fall")), "-"))
    chance = e_ccs.get("localisation", {}).get("random_in_tower", {})
    rows.append(("  violation area by chance within the tower", "59.0 %", pct(chance.get("violation_area")), "-"))

    train_cubes = None
    if "cubes" not in skip:
        cubes = b.dataset("cubes")
        train_cubes = b.train("cubes", cubes)
        e_cubes = b.eval("cubes", train_cubes)
        figures["eval_cubes"] = e_cubes
        rows.append(("accuracy, trained on Cubes, all-shapes test (Table 3.3)", pct(THESIS["acc_cubes"]),
                     pct(e_cubes["accuracy"]), "-"))

    # 4: cross-backend generalisation (not in the thesis)
    if "cross" not in skip:
        other = args.cross_backend
        fwd = b.eval(f"ccs-on-{other}", train_ccs, None, f"eval.cross_backend={other}", "eval.occlusion_images=0")
        other_ccs = b.dataset("ccs", other)
        train_other = b.train("ccs", other_ccs, other)
        rev = b.eval(f"{other}-ccs-on-{b.backend}", train_other, other, f"eval.cross_backend={b.backend}",
                     "eval.occlusion_images=0")
        figures["cross"] = {"forward": fwd.get("cross_backend"), "reverse": rev.get("cross_backend")}
        rows.append((f"trained on {b.backend}, tested on {other} renders", "-",
                     pct((fwd.get("cross_backend") or {}).get(other, {}).get("accuracy")), f"same-backend {pct(fwd['accuracy'])}"))
        rows.append((f"trained on {other}, tested on {b.backend} renders", "-",
                     pct((rev.get("cross_backend") or {}).get(b.backend, {}).get("accuracy")), f"same-backend {pct(rev['accuracy'])}"))

    # 5: deployment (Figs. 3.5-3.9)
    if "deploy" not in skip:
        stack = b.deploy("stack-ccs", "stack", train_ccs, "predictor,oracle,random")
        figures["stack_ccs"] = stack
        for scenario, per in stack["scenarios"].items():
            rows.append((f"stacking {scenario}: mean height, CCS predictor (Fig. 3.7)", "figure only",
                         f"{per['predictor']['mean_height']:.2f}",
                         f"random {per['random']['mean_height']:.2f}, oracle {per['oracle']['mean_height']:.2f}"))
        if train_cubes is not None:
            stack_c = b.deploy("stack-cubes", "stack", train_cubes, "predictor")
            figures["stack_cubes"] = stack_c
            for scenario, per in stack_c["scenarios"].items():
                ccs_mean = stack["scenarios"][scenario]["predictor"]["mean_height"]
                rows.append((f"stacking {scenario}: mean height, Cubes predictor (Fig. 3.7)", "figure only",
                             f"{per['predictor']['mean_height']:.2f}", f"CCS predictor {ccs_mean:.2f}"))
        bal = b.deploy("balance-ccs", "balance", train_ccs, "predictor,oracle,random")
        figures["balance_ccs"] = bal
        for agent in ("predictor", "oracle", "random", "none"):
            if agent in bal["success_rate"]:
                rows.append((f"counterbalancing success, {agent} (Fig. 3.9)", "figure only (high)",
                             pct(bal["success_rate"][agent]), "-"))
        sa = b.deploy("stackability-ccs", "stackability", train_ccs, "predictor,oracle")
        figures["stackability_ccs"] = sa
        for agent in ("predictor", "oracle"):
            got = sa["agents"].get(agent, {})
            order = got.get("expected_order_holds")
            rows.append((f"stackability, {agent}: cuboid face > upright cyl. > lying cyl. > sphere (Fig. 3.6)",
                         "yes" if agent == "predictor" else "-", {True: "yes", False: "no", None: "-"}.get(order, str(order)),
                         class_order(got.get("class_means", {}))))
            corr = got.get("area_correlation", {})
            rows.append((f"  stackability vs projected area, {agent}: Pearson r per class (Fig. 3.6)", "grows with area",
                         ", ".join(f"{SHORT.get(c, c)} {r:+.2f}" for c, r in corr.items()) or "-", "-"))

    report(f"stability benchmark, preset {args.preset}, backend {args.backend}", rows, figures, b, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
