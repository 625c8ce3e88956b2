"""The ``physint`` command line.

stdout carries results (one JSON object with ``--json``); stderr carries progress and logs.
Exit codes: 0 success, 1 runtime failure, 2 bad usage or bad input, 130 interrupted.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Annotated, Any, Optional

import typer

from . import __version__
from .errors import BadInput

app = typer.Typer(name="physint", no_args_is_help=True, add_completion=True, pretty_exceptions_enable=False,
                  help="Learning physical intuition for robotic manipulation: datasets, training, evaluation and "
                       "deployment of the thesis's methods on MuJoCo, PyBullet and robosuite.")

# the real stdout, kept for results; everything else written to fd 1 (simulator C code) goes to stderr
_RESULTS = sys.stdout


def _complete_methods(incomplete: str) -> list[str]:
    from .plugins import get_plugins

    return [m for m in get_plugins().registry.methods if m.startswith(incomplete)]


def _complete_backends(incomplete: str) -> list[str]:
    from .plugins import get_plugins

    return [b for b in get_plugins().registry.backends if b.startswith(incomplete)]


# -- options shared by every verb (spelled the same everywhere) -----------------------------------
Method = Annotated[str, typer.Argument(help="Method name (see `physint plugins`).", autocompletion=_complete_methods,
                                       show_default=False)]
BackendOpt = Annotated[Optional[str], typer.Option(
    "--backend", "-b", help="Simulator backend (default: the one the --run or --data was made on, else the method's first).",
    autocompletion=_complete_backends)]
SceneOpt = Annotated[Optional[str], typer.Option("--scene", help="Scene / scenario family (default: the method's first).")]
PresetOpt = Annotated[Optional[str], typer.Option("--preset", "-p", help="tiny (seconds), small (CPU default), paper (thesis, GPU).")]
ConfigOpt = Annotated[Optional[Path], typer.Option("--config", help="YAML file of config overrides.")]
SetOpt = Annotated[Optional[list[str]], typer.Option("--set", help="Override one config key: --set train.lr=1e-3 (repeatable).")]
SeedOpt = Annotated[int, typer.Option("--seed", help="Random seed: same seed and config, same data and episodes.")]
OutOpt = Annotated[Optional[Path], typer.Option("--out", "-o", help="Output directory (default: under $PHYSINT_HOME or ./physint_runs).")]
DataOpt = Annotated[Optional[Path], typer.Option("--data", help="Dataset directory (default: the cached dataset, generated once).")]
RunOpt = Annotated[Optional[Path], typer.Option("--run", help="Trained run directory (default: the latest run of the method).")]
WorkersOpt = Annotated[int, typer.Option("--workers", "-w", help="Local worker processes for generation/evaluation.")]
RayOpt = Annotated[Optional[str], typer.Option("--ray", help="Run work units on a Ray cluster: ADDRESS, 'auto', or 'local'.")]
DeviceOpt = Annotated[str, typer.Option("--device", help="auto, cpu or cuda.")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print exactly one JSON object on stdout.")]
ModelOpt = Annotated[Optional[str], typer.Option("--model", help="Model to train (see `physint plugins`).")]
TaskOpt = Annotated[Optional[str], typer.Option("--task", help="Deployment task of the method.")]
TargetOpt = Annotated[Optional[str], typer.Option("--target", help="Deployment target: an image file or a goal in words.")]
EpisodesOpt = Annotated[Optional[int], typer.Option("--episodes", help="Number of evaluation/deployment episodes.")]
HelpConfigOpt = Annotated[bool, typer.Option("--help-config", help="List the config keys, types and values for --preset, then exit.")]
QuietOpt = Annotated[bool, typer.Option("--quiet", "-q", help="No progress bars or logs on stderr.")]


def _version_callback(value: bool) -> None:
    if value:
        print(f"physint {__version__}", file=_RESULTS)
        raise typer.Exit()


@app.callback()
def _root(version: Annotated[bool, typer.Option("--version", callback=_version_callback, is_eager=True,
                                                help="Show the version and exit.")] = False) -> None:
    """physint: learning physical intuition for robotic manipulation."""


# -- output -------------------------------------------------------------------------------------

def emit(result: dict[str, Any], as_json: bool) -> None:
    """Print a verb's result: one JSON object, or a readable summary, on stdout."""
    if as_json:
        _RESULTS.write(json.dumps(result, default=str) + "\n")
        _RESULTS.flush()
        return
    from rich.console import Console
    from rich.pretty import Pretty

    console = Console(file=_RESULTS)
    console.print(Pretty(result, expand_all=False, max_length=20))


def _help_config(method_name: str, preset: str | None) -> None:
    from rich.console import Console
    from rich.table import Table

    from . import config as configs
    from .plugins import get_plugins

    method = get_plugins().method(method_name)
    preset = preset or "small"
    rows = configs.describe(method.config_class, method.presets, preset)
    table = Table(title=f"{method_name} config, preset {preset}")
    for col in ("key", "type", "value", "default", "help"):
        table.add_column(col)
    for r in rows:
        table.add_row(r["key"], r["type"], r["value"], r["default"], r["help"])
    Console(file=_RESULTS, width=160).print(table)


def _options(**kw: Any):
    from .workflow import Options

    kw["sets"] = kw.pop("sets", None) or []
    return Options(**kw)


# -- verbs ----------------------------------------------------------------------------------------

@app.command("dataset")
def dataset_cmd(method: Annotated[Optional[str], typer.Argument(help="Method name.", autocompletion=_complete_methods)] = None,
                backend: BackendOpt = None, scene: SceneOpt = None, preset: PresetOpt = None, config: ConfigOpt = None,
                sets: SetOpt = None, seed: SeedOpt = 0, out: OutOpt = None, workers: WorkersOpt = 1, ray: RayOpt = None,
                device: DeviceOpt = "auto", json_: JsonOpt = False, quiet: QuietOpt = False,
                verify: Annotated[Optional[Path], typer.Option("--verify", help="Check a dataset's shards and name the bad ones.")] = None,
                help_config: HelpConfigOpt = False) -> None:
    """Generate a sharded dataset (resumes if interrupted), or --verify one."""
    if verify is not None:
        from .datasets import verify as verify_dataset

        problems = verify_dataset(verify)
        emit({"verb": "verify", "path": str(verify), "ok": not problems, "problems": problems}, json_)
        if problems:
            for p in problems:
                print(f"bad shard: {p}", file=sys.stderr)
            raise typer.Exit(1)
        return
    if method is None:
        raise BadInput("missing METHOD (or --verify DIR); see `physint plugins` for the methods")
    if help_config:
        return _help_config(method, preset)
    from .workflow import run_dataset

    emit(run_dataset(_options(method=method, backend=backend, scene=scene, preset=preset, config=config, sets=sets, seed=seed,
                              out=out, workers=workers, ray=ray, device=device, quiet=quiet)), json_)


@app.command("train")
def train_cmd(method: Method, backend: BackendOpt = None, scene: SceneOpt = None, preset: PresetOpt = None,
              config: ConfigOpt = None, sets: SetOpt = None, seed: SeedOpt = 0, out: OutOpt = None, data: DataOpt = None,
              run: Annotated[Optional[Path], typer.Option("--run", help="With --resume: the run to continue (default: latest).")] = None,
              resume: Annotated[bool, typer.Option("--resume", help="Continue a run from its last checkpoint.")] = False,
              model: ModelOpt = None, workers: WorkersOpt = 1, ray: RayOpt = None, device: DeviceOpt = "auto",
              json_: JsonOpt = False, quiet: QuietOpt = False, help_config: HelpConfigOpt = False) -> None:
    """Train a model (generates and caches the dataset when --data is not given)."""
    if help_config:
        return _help_config(method, preset)
    from .workflow import run_train

    result = run_train(_options(method=method, backend=backend, scene=scene, preset=preset, config=config, sets=sets, seed=seed,
                                out=out, data=data, run=run, resume=resume, model=model, workers=workers, ray=ray,
                                device=device, quiet=quiet))
    if int(os.environ.get("RANK", "0")) == 0:
        emit(result, json_)


@app.command("eval")
def eval_cmd(method: Method, run: RunOpt = None, backend: BackendOpt = None, scene: SceneOpt = None, preset: PresetOpt = None,
             config: ConfigOpt = None, sets: SetOpt = None, seed: SeedOpt = 0, out: OutOpt = None, data: DataOpt = None,
             episodes: EpisodesOpt = None, workers: WorkersOpt = 1, ray: RayOpt = None, device: DeviceOpt = "auto",
             json_: JsonOpt = False, quiet: QuietOpt = False, help_config: HelpConfigOpt = False) -> None:
    """Evaluate a trained run (batch evaluation split into work units)."""
    if help_config:
        return _help_config(method, preset)
    from .workflow import run_eval

    emit(run_eval(_options(method=method, run=run, backend=backend, scene=scene, preset=preset, config=config, sets=sets,
                           seed=seed, out=out, data=data, episodes=episodes, workers=workers, ray=ray, device=device,
                           quiet=quiet)), json_)


@app.command("deploy")
def deploy_cmd(method: Method, run: RunOpt = None, task: TaskOpt = None, target: TargetOpt = None,
               backend: BackendOpt = None, scene: SceneOpt = None, preset: PresetOpt = None, config: ConfigOpt = None,
               sets: SetOpt = None, seed: SeedOpt = 0, out: OutOpt = None, episodes: EpisodesOpt = None,
               workers: WorkersOpt = 1, ray: RayOpt = None, device: DeviceOpt = "auto", json_: JsonOpt = False,
               quiet: QuietOpt = False, help_config: HelpConfigOpt = False) -> None:
    """Use a trained run for its downstream task; writes videos, plots and a rerun recording."""
    if help_config:
        return _help_config(method, preset)
    from .workflow import run_deploy

    emit(run_deploy(_options(method=method, run=run, task=task, target=target, backend=backend, scene=scene, preset=preset,
                             config=config, sets=sets, seed=seed, out=out, episodes=episodes, workers=workers, ray=ray,
                             device=device, quiet=quiet)), json_)


@app.command("pipeline")
def pipeline_cmd(method: Method, backend: BackendOpt = None, scene: SceneOpt = None, preset: PresetOpt = None,
                 config: ConfigOpt = None, sets: SetOpt = None, seed: SeedOpt = 0, out: OutOpt = None,
                 model: ModelOpt = None, workers: WorkersOpt = 1, ray: RayOpt = None, device: DeviceOpt = "auto",
                 json_: JsonOpt = False, quiet: QuietOpt = False) -> None:
    """Run dataset -> train -> eval -> deploy in one go."""
    from .workflow import run_pipeline

    result = run_pipeline(_options(method=method, backend=backend, scene=scene, preset=preset, config=config, sets=sets,
                                   seed=seed, out=out, model=model, workers=workers, ray=ray, device=device, quiet=quiet))
    if json_:
        emit(result, True)
    else:
        from rich.console import Console

        c = Console(file=_RESULTS)
        c.print(f"[bold]{method}[/bold] pipeline on {result['train']['backend']} finished in {result['seconds']:.1f} s")
        for verb in ("dataset", "train", "eval", "deploy"):
            r = result[verb]
            where = r.get("path") or r.get("run")
            c.print(f"  {verb:8s} {where}")
            if r.get("metrics"):
                c.print("           " + ", ".join(f"{k}={_fmt(v)}" for k, v in r["metrics"].items() if not isinstance(v, (dict, list))))
        c.print(f"Look at the results: physint view {result['deploy']['run']}  (or open its artifacts/ folder)")


def _fmt(v: Any) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


# -- listing ----------------------------------------------------------------------------------------

@app.command("plugins")
def plugins_cmd(json_: JsonOpt = False) -> None:
    """List installed plugins, their methods, scenes, models, metrics and backends, and broken plugins."""
    from .plugins import get_plugins

    p = get_plugins()
    methods = [{"name": m.name, "description": m.description, "chapter": m.chapter, "plugin": m.plugin,
                "backends": list(m.backends), "scenes": list(m.scenes), "presets": list(m.presets),
                "models": sorted(p.models_for(m.name)), "default_model": m.default_model,
                "metrics": sorted(n for (owner, n) in p.registry.metrics if owner == m.name)}
               for m in p.registry.methods.values()]
    result = {"plugins": [i.as_dict() for i in p.info.values()], "methods": methods,
              "broken": [{"name": b.name, "error": b.error} for b in p.broken], "conflicts": p.conflicts}
    if json_:
        return emit(result, True)
    from rich.console import Console
    from rich.table import Table

    c = Console(file=_RESULTS, width=160)
    t = Table(title="plugins")
    for col in ("plugin", "distribution", "version", "provides", "status"):
        t.add_column(col)
    for i in p.info.values():
        provides = "; ".join(f"{k}: {', '.join(v)}" for k, v in i.provides.items())
        t.add_row(i.name, i.distribution, i.version, provides, f"[red]broken: {i.error}[/red]" if i.error else "ok")
    c.print(t)
    t = Table(title="methods")
    for col in ("method", "chapter", "backends", "scenes", "models", "presets"):
        t.add_column(col)
    for m in methods:
        t.add_row(m["name"], m["chapter"], ", ".join(m["backends"]), ", ".join(m["scenes"]), ", ".join(m["models"]),
                  ", ".join(m["presets"]))
    c.print(t)
    for line in p.conflicts:
        c.print(f"[yellow]conflict:[/yellow] {line}")


@app.command("backends")
def backends_cmd(json_: JsonOpt = False,
                 probe: Annotated[bool, typer.Option("--probe/--no-probe", help="Render a test frame on each backend.")] = True) -> None:
    """List simulator backends: version, plugin, robot support, and whether each can render here."""
    from .plugins import get_plugins

    rows = []
    for b in get_plugins().registry.backends.values():
        status = b.probe() if (probe and b.probe) else {"can_render": None, "detail": "not probed"}
        rows.append({"name": b.name, "version": b.version(), "plugin": b.plugin, "robot": b.robot,
                     "description": b.description, **status})
    if json_:
        return emit({"backends": rows}, True)
    from rich.console import Console
    from rich.table import Table

    t = Table(title="backends")
    for col in ("backend", "version", "plugin", "robot", "can render", "detail"):
        t.add_column(col)
    for r in rows:
        t.add_row(r["name"], r["version"], r["plugin"], "yes" if r["robot"] else "no",
                  {True: "yes", False: "[red]no[/red]", None: "?"}[r["can_render"]], r["detail"])
    Console(file=_RESULTS, width=160).print(t)


@app.command("view")
def view_cmd(path: Annotated[Path, typer.Argument(help="A dataset, run directory or .rrd recording.")],
             save: Annotated[Optional[Path], typer.Option("--save", help="Write an .rrd file instead of opening the viewer.")] = None,
             limit: Annotated[int, typer.Option("--limit", help="Records per split to show for a dataset.")] = 32,
             json_: JsonOpt = False) -> None:
    """Show a dataset, run or recording in the rerun viewer (or save it as .rrd)."""
    from .view import view

    emit(view(path, save, limit), json_)


# -- entry point ------------------------------------------------------------------------------------

def _redirect_stray_stdout() -> None:
    """Keep stdout for results: point fd 1 at stderr so simulators' C-level prints can't pollute it."""
    global _RESULTS
    try:
        results_fd = os.dup(1)
        os.dup2(2, 1)
        _RESULTS = os.fdopen(results_fd, "w", buffering=1)
        sys.stdout = _RESULTS  # Python-level prints (plugin commands) still reach stdout
    except OSError:
        _RESULTS = sys.stdout


RESULT_VERBS = {"dataset", "train", "eval", "deploy", "pipeline", "plugins", "backends", "view"}
INTERRUPTED = "interrupted: finished work is saved; rerun the same command to resume"


def run(argv: list[str] | None = None) -> int:
    """Run the CLI and return its exit code (never raises, never prints a traceback)."""
    with _sigterm_as_ctrl_c():
        return _run(argv)


@contextlib.contextmanager
def _sigterm_as_ctrl_c():
    """SIGTERM (kill, a cluster's preemption, a job's time limit) stops a command as Ctrl-C does:
    finished work is saved and the same command resumes it."""
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler) if main_thread else None
    try:
        yield
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)


def _run(argv: list[str] | None) -> int:
    from .plugins import get_plugins

    try:
        get_plugins().register_commands(app)
    except Exception:  # plugin command registration problems are reported by `physint plugins`
        pass
    try:
        args = sys.argv[1:] if argv is None else argv
        verb = next((a for a in args if not a.startswith("-")), None)
        # the core's verbs print results only through emit(); stray prints from libraries go to stderr
        protect = verb in RESULT_VERBS and not _wants_help(args)
        guard = contextlib.redirect_stdout(sys.stderr) if protect else contextlib.nullcontext()
        with guard:
            rc = app(args=argv, standalone_mode=False, prog_name="physint")
        if rc == 130:  # typer turns Ctrl-C into exit code 130
            print(INTERRUPTED, file=sys.stderr)
        return rc if isinstance(rc, int) else 0
    except BadInput as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except (KeyboardInterrupt, typer.Abort):
        print(INTERRUPTED, file=sys.stderr)
        return 130
    except typer.Exit as exc:
        return exc.exit_code
    except Exception as exc:
        if hasattr(exc, "show") and hasattr(exc, "exit_code"):  # click usage errors (bad option, missing argument)
            exc.show(file=sys.stderr)
            return exc.exit_code
        if os.environ.get("PHYSINT_DEBUG"):
            raise
        print(f"error: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''} "
              "(set PHYSINT_DEBUG=1 for the traceback)", file=sys.stderr)
        return 1
    finally:
        _RESULTS.flush()


def _wants_help(args: list[str]) -> bool:
    return not args or any(a in ("--help", "--show-completion", "--install-completion") for a in args)


def main() -> None:
    if not _wants_help(sys.argv[1:]) and "_PHYSINT_COMPLETE" not in os.environ:
        _redirect_stray_stdout()
    sys.exit(run())


if __name__ == "__main__":  # pragma: no cover
    main()
