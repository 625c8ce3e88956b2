"""The four verbs as functions: dataset, train, eval, deploy (the CLI is a thin layer on top).

Each takes the shared options, builds a :class:`~physint_cli.method.Context`, runs the
method's verb and returns one JSON-serialisable result (paths, metrics, timings).
"""

from __future__ import annotations

import contextlib
import functools
import os
import shutil
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from . import config as configs
from .datasets import (check_writable, finish_manifest, machine, read_manifest, shard_done, start_manifest, versions,
                       write_shard)
from .errors import BadInput, RunFailure, unknown
from .method import Context, Unit
from .plugins import get_plugins
from .runs import Run, home, latest_run, open_run
from .training import resolve_device, seed_everything

# config sections named after the verbs that use a trained run: taken from the preset and --set,
# never from the run's saved config
DOWNSTREAM_SECTIONS = ("eval", "deploy")


@dataclass
class Options:
    """The options every verb shares, as given on the command line."""

    method: str
    backend: str | None = None
    scene: str | None = None
    preset: str | None = None
    config: Path | None = None
    sets: list[str] = field(default_factory=list)
    seed: int = 0
    out: Path | None = None
    data: Path | None = None
    run: Path | None = None
    workers: int = 1
    ray: str | None = None
    device: str = "auto"
    resume: bool = False
    model: str | None = None
    task: str | None = None
    target: str | None = None
    episodes: int | None = None
    quiet: bool = False


def make_context(opts: Options, base: dict[str, Any] | None = None) -> tuple[Any, Context]:
    """Resolve the method, backend, scene, config and device; ``base`` is a trained run's info."""
    plugins = get_plugins()
    method = plugins.method(opts.method)
    base = base or {}
    backend = opts.backend or base.get("backend") or method.backends[0]
    if backend not in plugins.registry.backends:
        raise unknown("backend", backend, plugins.registry.backends)
    method.check_backend(backend)
    scene = opts.scene or base.get("scene") or method.scenes[0]
    method.check_scene(scene)
    preset = opts.preset or base.get("preset") or "small"
    config_file, skip = opts.config, ()
    if config_file is None and base.get("_config_file"):
        config_file = base["_config_file"]
        # a trained run fixes its data and model; how it is evaluated and deployed comes from the
        # preset and --set, so a run trained before a preset changed is evaluated the current way
        skip = DOWNSTREAM_SECTIONS if base.get("_downstream") else ()
    cfg = configs.resolve(method.config_class, method.presets, preset, config_file, opts.sets, skip)
    if opts.workers < 1:
        raise BadInput(f"--workers must be >= 1, got {opts.workers}")
    if opts.model:
        models = plugins.models_for(method.name)
        if opts.model not in models:
            raise unknown(f"model for method {method.name!r}:", opts.model, models)
        train_section = getattr(cfg, "train", None)
        if hasattr(train_section, "model"):  # so the run's config.yaml says which network it trains
            train_section.model = opts.model
    if opts.episodes is not None and opts.episodes < 1:
        raise BadInput(f"--episodes must be >= 1, got {opts.episodes}")
    ctx = Context(method=method.name, config=cfg, preset=preset, backend=backend, scene=scene, seed=opts.seed,
                  device=resolve_device(opts.device), workers=opts.workers, ray=opts.ray, model=opts.model,
                  task=opts.task, target=opts.target, episodes=opts.episodes, resume=opts.resume, quiet=opts.quiet)
    return method, ctx


# -- dataset ------------------------------------------------------------------------------------

def dataset_cache_dir(ctx: Context, splits: tuple[str, ...] | None = None) -> Path:
    """Where the dataset of ``ctx`` is cached; ``splits``: the cache of only those splits' shards."""
    section = getattr(ctx.config, "data", ctx.config)
    only = "-" + "+".join(sorted(splits)) if splits else ""
    name = f"{ctx.method}-{ctx.scene}-{ctx.backend}-{ctx.preset}-s{ctx.seed}-{configs.fingerprint(section)}{only}"
    return home() / "datasets" / name


def _generate_unit(method: Any, ctx: Context, unit: Unit) -> dict[str, Any]:
    """Make and write one shard (runs in a worker process; ``method`` travels pickled)."""
    t0 = time.perf_counter()
    arrays, stats = method.generate(ctx, unit)
    stats = {**stats, "seconds": time.perf_counter() - t0}
    return write_shard(ctx.data, unit.name, unit.split, arrays, stats)


def generate_dataset(method: Any, ctx: Context, out: Path, splits: tuple[str, ...] | None = None) -> dict[str, Any]:
    """Generate (or resume, or reuse) the dataset for ``ctx`` in ``out``; returns the manifest.

    ``splits`` (say ``("test",)``) makes only those splits' shards, the same shards the whole
    dataset would hold (every unit draws from its own seed).
    """
    out = check_writable(Path(out))
    ctx = ctx.with_(data=out)
    units = method.dataset_units(ctx)
    if splits:
        units = [u for u in units if u.split in splits]
    header = {"method": ctx.method, "scene": ctx.scene, "backend": ctx.backend, "preset": ctx.preset, "seed": ctx.seed,
              "config": configs.to_dict(ctx.config), "units": len(units), "plugin": method.plugin,
              "versions": versions("mujoco", "pybullet", "robosuite"), "machine": machine()}
    if splits:
        header["only_splits"] = sorted(splits)
    manifest = start_manifest(out, header)
    if manifest.get("status") == "complete":
        ctx.log(f"dataset {out} is already complete ({manifest.get('records')} records)")
        return manifest
    todo = [u for u in units if shard_done(out, u.name) is None]
    if len(todo) < len(units):
        ctx.log(f"resuming: {len(units) - len(todo)} of {len(units)} shards already done")
    t0 = time.perf_counter()
    made = ctx.map(functools.partial(_generate_unit, method), todo, description=f"{ctx.method} dataset ({ctx.backend})")
    seconds = time.perf_counter() - t0
    records = [shard_done(out, u.name) for u in units]
    if any(r is None for r in records):
        raise BadInput(f"dataset {out}: some shards are missing after generation; rerun to resume")
    stats = method.summarize_dataset(ctx, [r.get("stats", {}) for r in records])
    new_items = sum(r["count"] for r in made)
    stats["records_per_second"] = round(new_items / seconds, 3) if seconds > 0 and new_items else None
    stats["workers"] = ctx.workers
    return finish_manifest(out, manifest, records, stats, seconds)


def run_dataset(opts: Options) -> dict[str, Any]:
    method, ctx = make_context(opts)
    out = opts.out or dataset_cache_dir(ctx)
    t0 = time.perf_counter()
    manifest = generate_dataset(method, ctx, out)
    return {"verb": "dataset", "method": ctx.method, "backend": ctx.backend, "scene": ctx.scene, "preset": ctx.preset,
            "seed": ctx.seed, "path": str(Path(out).resolve()), "splits": manifest.get("splits"),
            "records": manifest.get("records"), "stats": manifest.get("stats"), "seconds": round(time.perf_counter() - t0, 3)}


def ensure_dataset(method: Any, ctx: Context, data: Path | None, splits: tuple[str, ...] | None = None) -> Path:
    """The dataset to train/evaluate on: ``--data``, or the cached one (generated once).

    ``splits`` names the only splits the caller reads (an evaluation's test set): the whole
    cached dataset serves when it exists, otherwise only those splits are generated, into a
    cache of their own (an all-shapes test set is a seventh of the all-shapes dataset).
    """
    if data is not None:
        read_manifest(Path(data), ctx.method)
        return Path(data)
    cached = dataset_cache_dir(ctx)
    if splits:
        try:
            read_manifest(cached, ctx.method)
            return cached
        except BadInput:
            cached = dataset_cache_dir(ctx, splits)
    rank = int(os.environ.get("RANK", "0"))
    if rank != 0:  # under torchrun, rank 0 generates; the others wait for it
        while True:
            try:
                read_manifest(cached, ctx.method)
                return cached
            except BadInput:
                time.sleep(1.0)
    try:
        read_manifest(cached, ctx.method)
    except BadInput:
        only = f" ({', '.join(splits)} split{'s' if len(splits) > 1 else ''} only)" if splits else ""
        ctx.log(f"no cached dataset for this configuration: generating {cached}{only}")
        generate_dataset(method, ctx, cached, splits)
    return cached


# -- train / eval / deploy ----------------------------------------------------------------------

@contextlib.contextmanager
def _discarded_on_bad_input(run: Run | None):
    """A run that a verb refused as bad input (before doing anything) is removed: its --out stays free."""
    try:
        yield
    except BadInput:
        if run is not None and run.trained_file is None and not run.checkpoint("last").exists():
            shutil.rmtree(run.path, ignore_errors=True)
        raise


def _wait_for_run(path: Path) -> Run:
    while not (path / "run.json").exists():
        time.sleep(0.5)
    return Run(path)


def run_train(opts: Options) -> dict[str, Any]:
    rank = int(os.environ.get("RANK", "0"))
    world = int(os.environ.get("WORLD_SIZE", "1"))
    resume_run = None
    base: dict[str, Any] = {}
    if opts.resume:
        resume_run = open_run(opts.run, opts.method, need_checkpoint=False) if opts.run else \
            latest_run(opts.method, "train", need_checkpoint=True)
        base = {**resume_run.info, "_config_file": resume_run.path / "config.yaml"}
        trained = (base.get("options") or {}).get("model")  # a run started with --model goes on with it
        if opts.model and trained and opts.model != trained:
            raise BadInput(f"--resume: {resume_run.path} trains model {trained!r}; --model {opts.model} cannot continue it")
        opts = replace(opts, model=opts.model or trained)
    method, ctx = make_context(opts, base)
    data = ensure_dataset(method, ctx, opts.data or (Path(base["data"]) if base.get("data") else None))
    manifest = read_manifest(data, ctx.method)
    scene, made_on = manifest.get("scene"), manifest.get("backend")
    if scene and scene != ctx.scene:  # a --data dataset says what scene the run is of
        if opts.scene:
            raise BadInput(f"--scene {opts.scene}, but the dataset {data} is of scene {scene}")
        ctx = ctx.with_(scene=scene)
    if made_on and made_on != ctx.backend and resume_run is None:  # ... and the backend it trains on
        if opts.backend:  # (a method's closed-loop validation runs on the training backend)
            raise BadInput(f"--backend {ctx.backend}, but the dataset {data} was made on {made_on}: train on "
                           f"{made_on}, then evaluate with --backend {ctx.backend}")
        ctx = ctx.with_(backend=made_on)
    ctx = ctx.with_(data=data)
    t0 = time.perf_counter()
    if resume_run is not None:
        run = resume_run
    elif world > 1:
        out = opts.out or home() / "runs" / ctx.method / f"torchrun-{os.environ.get('TORCHELASTIC_RUN_ID', 'job')}-train-{ctx.backend}"
        run = Run.create("train", ctx, configs.to_dict(ctx.config), out, extra={"world_size": world}) if rank == 0 \
            else _wait_for_run(Path(out))
    else:
        run = Run.create("train", ctx, configs.to_dict(ctx.config), opts.out)
    ctx = ctx.with_(run=run.path)
    seed_everything(ctx.seed)  # before the method builds its model: --seed sets the initial weights too
    with _discarded_on_bad_input(run if resume_run is None and world == 1 else None):
        metrics = method.train(ctx)
    if rank == 0:
        if run.trained_file is None:  # the contract: eval and deploy load what train saved
            raise RunFailure(f"method {ctx.method!r} (plugin {method.plugin!r}): train() returned without saving a "
                             f"trained model in {run.path}; save it with ctx.output().save_trained(...) or train "
                             f"with physint_cli.training.fit")
        run.finish(metrics)
    return {"verb": "train", "method": ctx.method, "backend": ctx.backend, "scene": ctx.scene, "preset": ctx.preset,
            "seed": ctx.seed, "run": str(run.path.resolve()), "data": str(Path(data).resolve()),
            "checkpoint": str(run.trained_file.resolve()) if run.trained_file else None, "metrics": metrics,
            "seconds": round(time.perf_counter() - t0, 3)}


def _trained(opts: Options, verb: str) -> tuple[Run | None, dict[str, Any]]:
    if opts.run:
        source = open_run(opts.run, opts.method)
    else:
        try:
            source = latest_run(opts.method, "train")
        except BadInput:
            if verb == "deploy" and get_plugins().method(opts.method).deploys_without_run:
                return None, {}  # agents that need no model (the method refuses the ones that do)
            raise
    info = source.info
    # evaluate with the config the model was trained with; --preset/--set/--backend still override
    base = {**info, "_config_file": source.path / "config.yaml", "_downstream": True}
    return source, base


def _run_verb(verb: str, opts: Options) -> dict[str, Any]:
    source, base = _trained(opts, verb)
    method, ctx = make_context(opts, base)
    section = getattr(ctx.config, verb, None)
    if opts.episodes is not None and hasattr(section, "episodes"):
        section.episodes = opts.episodes  # --episodes N is {verb}.episodes=N, so the run's config.yaml records it
    data = opts.data or (Path(base["data"]) if base.get("data") else None)
    ctx = ctx.with_(source_run=source.path if source else None, data=Path(data) if data else None)
    run = Run.create(verb, ctx, configs.to_dict(ctx.config), opts.out)
    ctx = ctx.with_(run=run.path)
    t0 = time.perf_counter()
    with _discarded_on_bad_input(run):
        result = getattr(method, "evaluate" if verb == "eval" else "deploy")(ctx)
    run.finish(result)
    return {"verb": verb, "method": ctx.method, "backend": ctx.backend, "scene": ctx.scene, "preset": ctx.preset,
            "seed": ctx.seed, "run": str(run.path.resolve()),
            "source_run": str(source.path.resolve()) if source else None,
            "metrics": result, "artifacts": run.artifacts(), "seconds": round(time.perf_counter() - t0, 3)}


def run_eval(opts: Options) -> dict[str, Any]:
    return _run_verb("eval", opts)


def run_deploy(opts: Options) -> dict[str, Any]:
    return _run_verb("deploy", opts)


def run_pipeline(opts: Options) -> dict[str, Any]:
    """dataset -> train -> eval -> deploy, each in its own directory under --out (or the home)."""
    t0 = time.perf_counter()
    root = Path(opts.out) if opts.out else None
    if root is not None:
        check_writable(root)
    ds = run_dataset(replace(opts, out=root / "dataset" if root else None))
    tr = run_train(replace(opts, data=Path(ds["path"]), out=root / "train" if root else None, resume=False))
    ev = run_eval(replace(opts, run=Path(tr["run"]), out=root / "eval" if root else None, preset=None, scene=None,
                          sets=[s for s in opts.sets]))
    de = run_deploy(replace(opts, run=Path(tr["run"]), out=root / "deploy" if root else None, preset=None, scene=None))
    return {"verb": "pipeline", "method": opts.method, "dataset": ds, "train": tr, "eval": ev, "deploy": de,
            "seconds": round(time.perf_counter() - t0, 3)}
