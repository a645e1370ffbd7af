"""A tiny dask.distributed helper shared by the experiment scripts.

Usage inside a script::

    from _dask import add_dask_arguments, dask_client, map_tasks

    add_dask_arguments(parser)                 # --workers N, --scheduler ADDRESS
    with dask_client(args) as client:
        results = map_tasks(client, my_function, [dict(T=5, seed=1), dict(T=50, seed=1)],
                            desc="posterior runs")

``my_function(**params)`` runs on a worker with ``torch.set_num_threads(1)`` (one core per task,
so N workers keep N cores busy and nothing oversubscribes); results come back in the order of the
parameter list.  By default a :class:`distributed.LocalCluster` is started with ``--workers``
processes × 1 thread; ``--scheduler tcp://host:8786`` connects to a running cluster instead (the
experiment helper files are uploaded to its workers).  ``--workers 0`` runs the tasks in this
process, one after another (no dask at all: handy for debugging and profiling).
"""
from __future__ import annotations

import contextlib
import os
import sys
import time
from pathlib import Path

__all__ = ["add_dask_arguments", "dask_client", "map_tasks", "map_task_groups", "run_single_threaded"]

HERE = Path(__file__).resolve().parent


def add_dask_arguments(parser, default_workers: int = 2) -> None:
    """Add ``--workers`` and ``--scheduler`` to an argparse parser."""
    g = parser.add_argument_group("parallel execution (dask.distributed)")
    g.add_argument("--workers", type=int, default=default_workers,
                   help=f"LocalCluster worker processes, 1 thread each (default {default_workers}; "
                        "0 = run tasks in this process without dask)")
    g.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="connect to a running dask scheduler (e.g. tcp://127.0.0.1:8786) instead of "
                        "starting a LocalCluster")


def run_single_threaded(fn, params: dict):
    """Call ``fn(**params)`` with torch limited to one thread (what every task runs as)."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    if str(HERE) not in sys.path:  # helper modules of experiments/ importable on any worker
        sys.path.insert(0, str(HERE))
    import torch

    torch.set_num_threads(1)
    return fn(**params)


@contextlib.contextmanager
def dask_client(args, upload=()):
    """A ``distributed.Client`` per the parsed ``--workers``/``--scheduler`` (None for --workers 0).

    ``upload``: names of helper modules in experiments/ (e.g. ``("_laplace.py",)``) that tasks
    import; with ``--scheduler`` they are sent to the remote workers (``Client.upload_file``),
    with a LocalCluster the workers find them on their path.
    """
    if getattr(args, "scheduler", None):
        from distributed import Client

        client = Client(args.scheduler)
        for name in ("_dask.py", *upload):  # make the helpers importable on remote workers
            client.upload_file(str(HERE / name))
        try:
            yield client
        finally:
            client.close()
        return
    if int(getattr(args, "workers", 1)) <= 0:
        yield None
        return
    from distributed import Client, LocalCluster

    # Worker processes inherit the environment: one BLAS/OpenMP thread each, and experiments/ on
    # the path for the helper modules (spawned workers do not run the script's sys.path setup).
    os.environ["OMP_NUM_THREADS"] = "1"
    os.environ["MKL_NUM_THREADS"] = "1"
    paths = [str(HERE)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    os.environ["PYTHONPATH"] = os.pathsep.join(dict.fromkeys(paths))
    cluster = LocalCluster(n_workers=int(args.workers), threads_per_worker=1, processes=True,
                           dashboard_address=None, silence_logs=40)
    client = Client(cluster)
    try:
        yield client
    finally:
        client.close()
        cluster.close()


def map_tasks(client, fn, param_list: list[dict], desc: str = "tasks", progress: bool = True) -> list:
    """Run ``fn(**p)`` for every p in ``param_list`` (on the cluster, or here if ``client`` is
    None) and return the results in input order, showing a progress bar on stderr.

    Exceptions raised by a task are re-raised here with the failing parameters in the message.
    """
    return map_task_groups(client, [(fn, param_list)], desc=desc, progress=progress)[0]


def map_task_groups(client, groups, desc: str = "tasks", progress: bool = True) -> list[list]:
    """Several independent sweeps at once: ``groups`` is a list of ``(fn, param_list)``; every
    task of every group is submitted before any result is awaited (so the workers never idle
    between sweeps).  Returns one result list per group, each in input order."""
    from tqdm.auto import tqdm

    jobs = [(g, i, fn, p) for g, (fn, plist) in enumerate(groups) for i, p in enumerate(plist)]
    out = [[None] * len(plist) for _, plist in groups]
    bar = tqdm(total=len(jobs), desc=desc, disable=not progress, dynamic_ncols=True)
    t0 = time.perf_counter()
    try:
        if client is None:
            for g, i, fn, p in jobs:
                out[g][i] = run_single_threaded(fn, p)
                bar.update(1)
            return out
        from distributed import as_completed

        futures = [client.submit(run_single_threaded, fn, p, pure=False) for _, _, fn, p in jobs]
        where = {f.key: (g, i, p) for f, (g, i, _, p) in zip(futures, jobs)}
        for fut in as_completed(futures):
            g, i, p = where[fut.key]
            try:
                out[g][i] = fut.result()
            except Exception as exc:
                for f in futures:
                    f.cancel()
                raise RuntimeError(f"task {desc} (group {g}, #{i}) with {p} failed: {exc!r}") from exc
            bar.update(1)
        return out
    finally:
        bar.close()
        if progress:
            print(f"[{desc}] {len(jobs)} tasks in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
