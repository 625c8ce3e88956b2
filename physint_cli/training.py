"""Training helpers shared by methods: devices, DistributedDataParallel, checkpoints, a fit loop.

Launched under ``torchrun`` (``WORLD_SIZE`` > 1) training runs with DistributedDataParallel,
on gloo for CPU and NCCL for CUDA; otherwise single-process. Only rank 0 writes the run.
"""

from __future__ import annotations

import contextlib
import os
import random
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .checkpoints import load_checkpoint, save_checkpoint  # noqa: F401  (plugins import them from here too)
from .errors import BadInput


def resolve_device(device: str) -> str:
    import torch

    if device not in ("auto", "cpu", "cuda") and not device.startswith("cuda:"):
        raise BadInput(f"--device {device!r} is not valid; use auto, cpu or cuda")
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise BadInput("--device cuda: no CUDA device is available here; use --device cpu or auto")
    return device


PRECISIONS = ("auto", "fp32", "bf16")


def resolve_precision(precision: str, device: str) -> str:
    """``fp32`` or ``bf16`` for ``device``. ``auto`` is bf16 where the hardware multiplies bf16 natively
    (CPUs with AMX tiles or AVX512-BF16, CUDA GPUs that support it) and fp32 elsewhere."""
    import torch

    if precision not in PRECISIONS:
        raise BadInput(f"precision {precision!r} is not valid; use {', '.join(PRECISIONS)}")
    if precision != "auto":
        return precision
    if device.startswith("cuda"):
        return "bf16" if torch.cuda.is_bf16_supported() else "fp32"
    cpu = torch.cpu
    native = getattr(cpu, "_is_amx_tile_supported", lambda: False)() or \
        getattr(cpu, "_is_avx512_bf16_supported", lambda: False)()
    # torch held to AVX2 or below (ATEN_CPU_CAPABILITY=avx2, as on an AVX2-only CPU) runs no AVX512 kernels
    held_below_avx512 = not torch.backends.cpu.get_cpu_capability().startswith("AVX512")
    return "bf16" if native and not held_below_avx512 else "fp32"


def autocast(device: str, precision: str):
    """The autocast context for a resolved precision (``bf16``), or a no-op one (``fp32``)."""
    import contextlib

    import torch

    if precision != "bf16":
        return contextlib.nullcontext()
    return torch.autocast("cuda" if device.startswith("cuda") else "cpu", dtype=torch.bfloat16)


def to_device(batch: dict[str, Any], device: str, channels_last: bool = False) -> dict[str, Any]:
    """Move a batch's tensors to ``device``; image batches (4-D) to channels-last layout if asked."""
    import torch

    out = {}
    for k, v in batch.items():
        if hasattr(v, "to"):
            v = v.to(device)
            if channels_last and v.dim() == 4:
                v = v.contiguous(memory_format=torch.channels_last)
        out[k] = v
    return out


@contextlib.contextmanager
def torch_threads(n: int):
    """Run with ``n`` intra-op threads. One thread is fastest for the small batches of control on a
    2-core machine, and makes closed-loop results the same whatever the worker count: float sums
    split over a different number of threads differ in the last bit, and a closed loop amplifies it."""
    import torch

    saved = torch.get_num_threads()
    if saved != n:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        if saved != n:
            torch.set_num_threads(saved)


def adamw_cosine(model, *, lr: float, weight_decay: float, epochs: int, warmup_epochs: int = 1):
    """AdamW and a per-epoch schedule: a linear warm-up over ``warmup_epochs``, then the learning
    rate follows a half cosine from ``lr`` down to 0, which it reaches as the last epoch ends
    (call ``scheduler.step()`` once per epoch: ``fit`` does). The solver of the CPU presets."""
    import math

    import torch

    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=weight_decay)
    epochs, warm = max(1, int(epochs)), max(0, int(warmup_epochs))

    def factor(epoch: int) -> float:
        if epoch < warm:
            return (epoch + 1) / (warm + 1)
        t = (epoch - warm) / max(1, epochs - warm)
        return 0.5 * (1 + math.cos(math.pi * min(t, 1.0)))

    return opt, torch.optim.lr_scheduler.LambdaLR(opt, factor)


def seed_everything(seed: int) -> None:
    import torch

    random.seed(seed)
    np.random.seed(seed % (2**32))
    torch.manual_seed(seed)


@dataclass
class Dist:
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def enabled(self) -> bool:
        return self.world_size > 1


def init_distributed(device: str) -> Dist:
    """Join the torchrun process group if launched under torchrun."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return Dist()
    import torch.distributed as dist

    if not dist.is_initialized():
        dist.init_process_group(backend="nccl" if device.startswith("cuda") else "gloo")
    local = int(os.environ.get("LOCAL_RANK", "0"))
    if device.startswith("cuda"):
        import torch

        torch.cuda.set_device(local)
    return Dist(rank=dist.get_rank(), world_size=dist.get_world_size(), local_rank=local)


def barrier(d: Dist) -> None:
    if d.enabled:
        import torch.distributed as dist

        dist.barrier()


def unwrap(model):
    return model.module if hasattr(model, "module") else model


CHECKPOINT_SECONDS = 300.0
"""Within an epoch ``fit`` also saves its ``last`` checkpoint this often, so an interrupted
training resumes at the batch it had reached and loses at most this much work."""


class EpochOrder:
    """The order of one epoch's training samples: a permutation drawn from (seed, epoch) alone
    (or a ``DistributedSampler``'s share of it), so an epoch interrupted part-way is drawn the
    same way again on resume and continues from the sample it had reached. A torch ``Sampler``;
    ``data`` may grow between epochs."""

    def __init__(self, data, seed: int, distributed=None):
        self.data, self.seed, self.distributed = data, int(seed), distributed
        self.epoch, self.start = 0, 0

    def set_epoch(self, epoch: int, start: int = 0) -> None:
        """Draw ``epoch``'s order and leave out its first ``start`` samples (already trained on)."""
        self.epoch, self.start = int(epoch), int(start)
        if self.distributed is not None:
            self.distributed.set_epoch(epoch)

    def _order(self) -> list[int]:
        if self.distributed is not None:
            return list(self.distributed)
        import torch

        seed = int(np.random.SeedSequence([self.seed, self.epoch]).generate_state(1)[0])
        return torch.randperm(len(self.data), generator=torch.Generator().manual_seed(seed)).tolist()

    def __iter__(self):
        return iter(self._order()[self.start:])

    def __len__(self) -> int:
        return max(0, (len(self.distributed) if self.distributed is not None else len(self.data)) - self.start)


class _HeldInterrupts:
    """Within ``with``, Ctrl-C (SIGINT) and SIGTERM arriving inside ``held()`` (one optimiser step,
    which cannot be saved half-applied) take effect when it ends; anywhere else they interrupt at
    once. Outside the main thread (where Python handles signals) it does nothing."""

    def __init__(self):
        self.holding, self.pending, self.previous = False, False, {}

    def __enter__(self) -> "_HeldInterrupts":
        if threading.current_thread() is threading.main_thread():
            # only signals that would raise KeyboardInterrupt now (not ones ignored, as in a background job)
            self.previous = {s: signal.signal(s, self._handle) for s in (signal.SIGINT, signal.SIGTERM)
                             if signal.getsignal(s) is signal.default_int_handler}
        return self

    def __exit__(self, *exc) -> None:
        for s, handler in self.previous.items():
            signal.signal(s, handler)

    def _handle(self, signum, frame) -> None:
        if not self.holding:
            raise KeyboardInterrupt
        self.pending = True

    @contextlib.contextmanager
    def held(self):
        self.holding, self.pending = True, False
        try:
            yield
        finally:
            self.holding = False
        if self.pending:
            raise KeyboardInterrupt


@dataclass
class FitResult:
    epochs: int
    best_metric: float
    history: list[dict[str, float]]


def fit(model, train_set, val_set, *, run, epochs: int, batch_size: int, lr: float, loss_fn: Callable,
        metric_fn: Callable, device: str = "cpu", resume: bool = False, optimizer: str = "adam",
        weight_decay: float = 0.0, num_workers: int = 0, seed: int = 0, higher_is_better: bool = False,
        meta: dict[str, Any] | None = None, log: Callable[[str], None] = print,
        make_optimizer: Callable[[Any], tuple[Any, Any]] | None = None, precision: str = "fp32",
        channels_last: bool = False, batch_transform: Callable[[dict[str, Any]], dict[str, Any]] | None = None,
        before_epoch: Callable[[int, Any], None] | None = None, progress: bool = False) -> FitResult:
    """Supervised training with checkpoints every epoch (and every ``CHECKPOINT_SECONDS`` within
    one), resume from where it stopped, and DDP.

    ``loss_fn(model, batch) -> scalar loss``; ``metric_fn(model, loader) -> float`` on validation.
    ``precision`` (``fp32``, ``bf16``, ``auto``: see :func:`resolve_precision`) runs the forward
    passes under autocast (weights and optimiser stay fp32); ``channels_last`` stores the model and
    image batches channels-last (with bf16 on CPUs with AMX, about 4x faster convolutions).
    ``batch_transform(batch) -> batch`` runs on each collated training batch (batched augmentation,
    much cheaper than per record on a CPU).
    ``meta`` is saved in every checkpoint (e.g. the model name and its constructor arguments).
    ``make_optimizer(model) -> (optimizer, scheduler or None)`` replaces the built-in optimizers;
    the scheduler is stepped once per epoch.
    ``before_epoch(epoch, model)`` runs before each epoch (0-based; also the first one after a
    resume) and may grow ``train_set`` (single process only: a distributed sampler's length is fixed).
    ``progress`` shows a bar over each epoch's batches on stderr (a terminal only; logs stay clean).
    Each epoch's log line and history point carry its wall time, and the line an estimate of the
    time left (the mean epoch of this process times the epochs to go).
    """
    import torch
    from torch.utils.data import DataLoader, DistributedSampler

    d = init_distributed(device)
    seed_everything(seed + d.rank)
    asked, precision = precision, resolve_precision(precision, device)
    why = " (auto: this CPU, or the vector capability torch is held to, has neither AMX nor AVX512-BF16 to " \
          "multiply bf16 natively; training takes " \
          "several times as long as on one that has)" if asked == "auto" and precision == "fp32" and \
        not device.startswith("cuda") else ""
    log(f"training on {device} in {precision}{', channels-last' if channels_last else ''}{why}")
    model = model.to(device)
    if channels_last:
        model = model.to(memory_format=torch.channels_last)
    if d.enabled:
        model = torch.nn.parallel.DistributedDataParallel(model)
    params = [p for p in model.parameters() if p.requires_grad]
    scheduler = None
    if make_optimizer is not None:
        opt, scheduler = make_optimizer(model)
    else:
        optimizers = {"adam": torch.optim.Adam, "rmsprop": torch.optim.RMSprop, "sgd": torch.optim.SGD}
        if optimizer not in optimizers:
            raise BadInput(f"optimizer {optimizer!r} is not known; valid: {', '.join(optimizers)}")
        opt = optimizers[optimizer](params, lr=lr, weight_decay=weight_decay)
    start_epoch, start_batch, partial, best, history = 0, 0, (0.0, 0), None, []
    last = run.checkpoint("last")
    if resume and last.exists():
        state = load_checkpoint(last, device)
        unwrap(model).load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        if scheduler is not None and state.get("scheduler"):
            scheduler.load_state_dict(state["scheduler"])
        start_epoch, best, history = state["epoch"], state.get("best"), state.get("history", [])
        start_batch, partial = state.get("batch", 0), tuple(state.get("partial", (0.0, 0)))
        torch.set_rng_state(state["torch_rng"])
        within = f", {start_batch} batches into epoch {start_epoch + 1}" if start_batch else ""
        log(f"resumed from {last} at epoch {start_epoch}{within}")
    order = EpochOrder(train_set, seed, DistributedSampler(train_set, shuffle=True, seed=seed) if d.enabled else None)
    generator = torch.Generator().manual_seed(seed)
    loader = DataLoader(train_set, batch_size=batch_size, sampler=order, num_workers=num_workers,
                        generator=generator, drop_last=False)
    val_loader = DataLoader(val_set, batch_size=batch_size, shuffle=False, num_workers=num_workers)
    if before_epoch is not None and d.enabled:
        raise BadInput("this training grows its data between epochs, which needs a single process (not torchrun)")

    def state_now(**progress) -> dict[str, Any]:
        return dict(model=unwrap(model).state_dict(), optimizer=opt.state_dict(), best=best,
                    scheduler=scheduler.state_dict() if scheduler is not None else None, history=history,
                    torch_rng=torch.get_rng_state(), meta=meta or {}, **progress)

    epoch_seconds: list[float] = []
    for epoch in range(start_epoch, epochs):
        started = time.monotonic()
        skip = start_batch if epoch == start_epoch else 0
        order.set_epoch(epoch, skip * batch_size)
        if before_epoch is not None:
            before_epoch(epoch, unwrap(model))
        model.train()
        total, count = partial if skip else (0.0, 0)
        saved, done, saved_done = time.monotonic(), skip, skip  # batches of this epoch trained on / in `last`
        try:
            with _HeldInterrupts() as interrupts, \
                    _epoch_bar(progress and d.is_main, f"epoch {epoch + 1}/{epochs}", len(loader), skip) as advance:
                for i, batch in enumerate(loader, start=skip + 1):
                    with interrupts.held():
                        if batch_transform is not None:
                            batch = batch_transform(batch)
                        batch = to_device(batch, device, channels_last)
                        with autocast(device, precision):
                            loss = loss_fn(model, batch)
                        opt.zero_grad(set_to_none=True)
                        loss.backward()
                        opt.step()
                        total += float(loss.detach()) * len(next(iter(batch.values())))
                        count += len(next(iter(batch.values())))
                        done = i
                    advance()
                    if d.is_main and time.monotonic() - saved >= CHECKPOINT_SECONDS:  # part of an epoch: i batches done
                        save_checkpoint(last, **state_now(epoch=epoch, batch=i, partial=(total, count)))
                        saved, saved_done = time.monotonic(), i
        except KeyboardInterrupt:  # Ctrl-C or SIGTERM: keep every finished batch, then stop
            if d.is_main and done > saved_done:
                save_checkpoint(last, **state_now(epoch=epoch, batch=done, partial=(total, count)))
            raise
        if scheduler is not None:
            scheduler.step()
        model.eval()
        with torch.no_grad(), autocast(device, precision):
            val = float(metric_fn(unwrap(model), val_loader))
        epoch_seconds.append(time.monotonic() - started)
        point = {"epoch": epoch + 1, "train_loss": total / max(count, 1), "val_metric": val,
                 "seconds": round(epoch_seconds[-1], 1)}  # this process's wall time for the epoch
        history.append(point)
        improved = best is None or (val > best if higher_is_better else val < best)
        if improved:
            best = val
        if d.is_main:
            run.log_metrics(epoch + 1, **point)
            state = state_now(epoch=epoch + 1, batch=0)
            if improved:
                run.save_trained(**state)
            save_checkpoint(last, **state)
            left = float(np.mean(epoch_seconds)) * (epochs - epoch - 1)
            log(f"epoch {epoch + 1}/{epochs}: train loss {point['train_loss']:.4f}, val {val:.4f} "
                f"({_duration(epoch_seconds[-1])}{f'; about {_duration(left)} to go' if left else ''})")
        barrier(d)
    return FitResult(epochs=epochs, best_metric=float(best) if best is not None else float("nan"), history=history)


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 90 else f"{seconds / 60:.1f} min"


@contextlib.contextmanager
def _epoch_bar(shown: bool, description: str, total: int, done: int):
    """A transient bar over one epoch's batches on stderr (a terminal only); yields ``advance()``."""
    from .parallel import progress_bar

    with progress_bar(quiet=not shown, transient=True) as bar:
        task = bar.add_task(description, total=total, completed=done)
        yield lambda: bar.advance(task)


# -- registered models ------------------------------------------------------------------------

def registered_model(method: str, name: str):
    """The ``ModelInfo`` a plugin registered for ``method`` under ``name``; unknown names exit 2."""
    from .plugins import get_plugins

    return get_plugins().model(method, name)


def load_trained_model(run_dir, method: str, what: str, device: str = "cpu"):
    """The best checkpoint of a trained run of ``method`` (its meta names the registered model and
    its constructor arguments), in eval mode, and that meta. Anything else exits 2, naming ``what``
    was expected."""
    from .plugins import get_plugins
    from .runs import Run

    run = Run(Path(run_dir))
    state = run.load_trained(device)
    path = run.trained_file
    meta = state.get("meta", {})
    if meta.get("method") != method or meta.get("model") not in get_plugins().models_for(method):
        raise BadInput(f"checkpoint {path} is not a {what} (method {meta.get('method')!r}, model {meta.get('model')!r})")
    model = registered_model(method, meta["model"]).build(**meta["kwargs"])
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as exc:  # saved by a version whose layers differ
        first = str(exc).splitlines()[0]
        raise BadInput(f"checkpoint {path} does not fit this version's {meta['model']!r} model ({first}); "
                       f"train it again") from None
    return model.to(device).eval(), meta
