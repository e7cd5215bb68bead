"""Launching a run's shards: one local process per worker or device, or a SLURM array
(submitit). Each shard is an ordinary run (runner.run_benchmark with shard=(K, N)); the
last to finish merges (run/shards.py)."""

from __future__ import annotations

import os
from dataclasses import replace

import pandas as pd
from rich.console import Console

from ..reporting.tables import print_summary
from .folder import RunFolder
from .stage import MatchOptions


WORKER_BYTES = 2 << 30  # memory one local CPU worker may take (torch, a backbone, two images' pyramids)


def threads_per_worker(workers: int) -> int:
    return max(1, (os.cpu_count() or 1) // workers)


def max_cpu_workers() -> tuple[int, str]:
    """How many local CPU workers this machine holds: one per core, and WORKER_BYTES of
    available memory each; with the reason, for the message."""
    from ..devices import available_host_memory

    cores = os.cpu_count() or 1
    free = available_host_memory()
    by_memory = cores if free is None else max(1, free // WORKER_BYTES)
    why = f"{cores} cores" + ("" if free is None else f", {free / 2**30:.1f} GiB available at about {WORKER_BYTES / 2**30:.0f} GiB each")
    return max(1, min(cores, by_memory)), why


def check_workers(workers: int) -> None:
    """A one-line ValueError for a --workers the machine cannot hold."""
    if workers < 0:
        raise ValueError(f"--workers must be 0 (one process) or more, got {workers}")
    bound, why = max_cpu_workers()
    if workers > bound:
        raise ValueError(f"--workers {workers}: this machine holds at most {bound} ({why}); "
                         "for more, run shards on more machines (--shard K/N or --launcher slurm)")


def _die_with_parent(parent: int) -> None:
    """In a worker: end when the process that started it ends (Linux: the kernel sends SIGTERM;
    a killed parent otherwise leaves its workers running on)."""
    import signal

    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:  # the parent died before the line above took effect
        os._exit(1)


def worker_pool(n: int):
    """N fresh worker processes (spawned: no torch state shared across fork) that die with this one."""
    import concurrent.futures
    import multiprocessing

    return concurrent.futures.ProcessPoolExecutor(max_workers=n, mp_context=multiprocessing.get_context("spawn"),
                                                  initializer=_die_with_parent, initargs=(os.getpid(),))


def run_shard_job(kwargs: dict) -> dict:
    """One shard in this process (what a local worker or a SLURM array task runs)."""
    import torch

    from ..runner import run_benchmark  # in the worker: a shard loads the models

    threads = kwargs.pop("threads", None)
    if threads:
        torch.set_num_threads(threads)
    summary = run_benchmark(console=Console(quiet=kwargs.pop("quiet", False)), **kwargs)
    return summary.iloc[0].to_dict()


def run_shards(kwargs: dict, n: int, devices: list[str] | None = None, launcher: str = "local",
               console: Console | None = None, slurm: dict | None = None) -> list:
    """Run the N shards of one run: `launcher` local (one process each, at most len(devices)
    at once, torch threads divided among them on a CPU) or slurm (a submitit array; runs
    locally, one process per shard, where no SLURM is found). Returns each shard's summary
    (local) or the submitted jobs (slurm)."""
    console = console or Console()
    devices = devices or ["cpu"]
    jobs = []
    for k in range(1, n + 1):
        device = devices[(k - 1) % len(devices)]
        threads = threads_per_worker(len(devices)) if device == "cpu" else None
        job = {**kwargs, "shard": (k, n), "device": device, "threads": threads, "quiet": True}
        options = kwargs.get("options") or MatchOptions()
        if launcher == "local" and device == "cpu" and options.feature_cache_mb is None:
            from ..matchers.feature_cache import auto_cache_mb

            # local CPU workers share the host's memory: each gets its part of the default budget
            job["options"] = replace(options, feature_cache_mb=auto_cache_mb("cpu") / sum(d == "cpu" for d in devices))
        jobs.append(job)
    if launcher == "slurm":
        try:
            import submitit
        except ImportError:
            raise ValueError("--launcher slurm needs submitit: pip install 'e3cm-bench[cluster]'") from None
        executor = submitit.AutoExecutor(folder=RunFolder(kwargs["out"]).shards_dir / "slurm")
        params = {"timeout_min": 24 * 60, "slurm_array_parallelism": n, **(slurm or {})}
        if executor.cluster != "slurm":
            params = {k: v for k, v in params.items() if not k.startswith("slurm_")}
        executor.update_parameters(**params)
        submitted = executor.map_array(run_shard_job, jobs)
        console.print(f"submitted {n} shard(s) to {executor.cluster}: job {submitted[0].job_id.split('_')[0]}; "
                      f"they merge when the last one finishes (or: e3cm-bench merge {kwargs['out']})", markup=False)
        if executor.cluster == "slurm":
            return submitted
        return [job.result() for job in submitted]
    with worker_pool(len(devices)) as pool:
        futures = [pool.submit(run_shard_job, job) for job in jobs]
        results = []
        for k, future in enumerate(futures, start=1):
            results.append(future.result())
            console.print(f"shard {k}-of-{n} done", markup=False)
    merged = RunFolder(kwargs["out"]).summary_path
    if merged.is_file():  # the last worker merged; show what a single run would have shown
        summary = pd.read_csv(merged).iloc[0].to_dict()
        print_summary(summary, f"{n} shards merged -> {kwargs['out']}", console=console)
    return results

