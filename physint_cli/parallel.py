"""Running work units inline, in local processes (``--workers N``) or on Ray (``--ray ADDRESS``).

``fn(context, unit)`` must be a module-level function so it can travel to other processes;
results come back in unit order. Ctrl-C stops the pool; finished units have already been
written by their workers, so rerunning resumes.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import sys
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Callable

from .errors import BadInput, RunFailure


def progress_bar(quiet: bool = False, transient: bool = False):
    """A rich bar on stderr. A transient one disappears when done and is shown on a terminal only; the
    others also leave their final state in a log file."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    console = Console(stderr=True)
    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    TimeRemainingColumn(), console=console, transient=transient,
                    disable=quiet or (transient and not console.is_terminal))


_RAY_ADDRESS: str | None = None


def _check_reachable(address: str) -> None:
    """Fail fast on an address where no Ray head listens (ray.init would retry for minutes)."""
    import socket

    host, _, port = address.removeprefix("ray://").rpartition(":")
    try:
        with socket.create_connection((host or "127.0.0.1", int(port)), timeout=5):
            pass
    except (OSError, ValueError) as exc:
        raise BadInput(f"--ray {address}: cannot connect to a Ray cluster there ({exc}); "
                       "start one with `ray start --head` or use --ray local") from None


def _worker_init() -> None:
    # the parent handles Ctrl-C and stops the pool; workers must not print tracebacks for it
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # N worker processes are the parallelism: one math thread each, or they oversubscribe the cores
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def _apply(fn, ctx, unit):
    return fn(ctx, unit)


def map_units(fn: Callable[[Any, Any], Any], ctx: Any, units: list[Any], description: str = "working") -> list[Any]:
    if not units:
        return []
    if ctx.ray:
        return _map_ray(fn, ctx, units, description)
    workers = max(1, int(ctx.workers or 1))
    results: list[Any] = [None] * len(units)
    with progress_bar(ctx.quiet) as progress:
        task = progress.add_task(description, total=len(units))
        if workers == 1 or len(units) == 1:
            for i, unit in enumerate(units):
                results[i] = fn(ctx, unit)
                progress.advance(task)
            return results
        pool = ProcessPoolExecutor(max_workers=min(workers, len(units)), mp_context=multiprocessing.get_context("spawn"),
                                   initializer=_worker_init)
        try:
            pending = {pool.submit(fn, ctx, unit): i for i, unit in enumerate(units)}
            while pending:
                done, _ = wait(pending, return_when=FIRST_COMPLETED)
                for fut in done:
                    try:
                        results[pending.pop(fut)] = fut.result()
                    except BrokenProcessPool:
                        raise RunFailure("a worker process died (killed, out of memory, or a simulator crash); "
                                         "finished units are kept: rerun the same command to resume") from None
                    progress.advance(task)
        except BaseException:
            processes = list((getattr(pool, "_processes", None) or {}).values())  # before shutdown clears them
            pool.shutdown(wait=False, cancel_futures=True)
            for proc in processes:
                proc.terminate()
            raise
        pool.shutdown(wait=True)
    return results


def _map_ray(fn, ctx, units, description):
    try:
        import ray
    except ImportError:
        raise BadInput("--ray needs Ray: pip install 'physint[ray]'") from None
    global _RAY_ADDRESS
    address = None if ctx.ray in ("local", "") else ctx.ray
    if address and address != "auto":
        _check_reachable(address)
    try:
        if ray.is_initialized() and _RAY_ADDRESS != ctx.ray:
            ray.shutdown()
        if not ray.is_initialized():
            os.environ.setdefault("RAY_gcs_rpc_server_connect_timeout_s", "10")
            ray.init(address=address, log_to_driver=False, include_dashboard=False, configure_logging=False)
            _RAY_ADDRESS = ctx.ray
    except Exception as exc:
        raise BadInput(f"--ray {ctx.ray}: cannot connect to a Ray cluster ({str(exc).splitlines()[0]})") from None
    remote = ray.remote(_apply)
    refs = [remote.remote(fn, ctx, unit) for unit in units]
    results: list[Any] = [None] * len(units)
    index = {ref: i for i, ref in enumerate(refs)}
    with progress_bar(ctx.quiet) as progress:
        task = progress.add_task(f"{description} (ray)", total=len(units))
        pending = list(refs)
        try:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                for ref in done:
                    results[index[ref]] = ray.get(ref)
                    progress.advance(task)
        except KeyboardInterrupt:
            for ref in pending:
                ray.cancel(ref, force=True)
            raise
    print(f"ran {len(units)} units on Ray at {ctx.ray}", file=sys.stderr)
    return results
