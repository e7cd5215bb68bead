"""Launching a run's shards: one local process per worker or device, or a SLURM array
(submitit). Each shard is an ordinary run (runner.run_benchmark of a RunRequest with shard=(K, N));
the last to finish merges (pipeline/shards.py)."""

from __future__ import annotations

import os
from dataclasses import replace

import pandas as pd
from rich.console import Console

from e3cm_bench.matchers.user_module import no_folder_on_path
from e3cm_bench.reporting.tables import print_summary
from e3cm_bench.storage.folder import RunFolder


WORKER_BYTES = 2 << 30  # memory one local CPU worker may take (torch, a backbone, two images' pyramids)


def threads_per_worker(workers: int) -> int:
    return max(1, (os.cpu_count() or 1) // workers)


def max_cpu_workers() -> tuple[int, str]:
    """How many local CPU workers this machine holds: one per core, and WORKER_BYTES of
    available memory each; with the reason, for the message."""
    from e3cm_bench.ground.devices import available_host_memory

    cores = os.cpu_count() or 1
    free = available_host_memory()
    by_memory = cores if free is None else max(1, free // WORKER_BYTES)
    why = f"{cores} cores" + (
        "" if free is None else f", {free / 2**30:.1f} GiB available at about {WORKER_BYTES / 2**30:.0f} GiB each"
    )
    return max(1, min(cores, by_memory)), why


LAUNCHERS = ("local", "slurm")  # --launcher: this machine's processes, or a SLURM array (submitit)


def check_launcher(launcher: str) -> None:
    """A one-line ValueError for a --launcher that is not one of LAUNCHERS."""
    if launcher not in LAUNCHERS:
        raise ValueError(f"--launcher {launcher!r}: choose one of {', '.join(LAUNCHERS)}")


def check_workers(workers: int, option: str | None = None) -> None:
    """A one-line ValueError for a --workers the machine cannot hold."""
    if workers < 0:
        raise ValueError(f"--workers must be 0 (one process) or more, got {workers}")
    bound, why = max_cpu_workers()
    if workers > bound:
        raise ValueError(f"{option or f'--workers {workers}'}: this machine holds at most {bound} ({why}); "
                         "for more, run shards on more machines (--shard K/N or --launcher slurm)")


def check_slurm(shards: int) -> None:
    """--launcher slurm --shards N, checked before anything starts: N from 1 to MAX_SHARDS; where
    no srun is found, submitit runs the N tasks as local processes, so the machine must hold them
    as it must --workers N; where srun is found, a SLURM controller must answer (sinfo)."""
    import shutil
    import subprocess

    from e3cm_bench.pipeline.shards import MAX_SHARDS

    if not 1 <= shards <= MAX_SHARDS:
        raise ValueError(f"--shards must be from 1 to {MAX_SHARDS:,}, got {shards}")
    if shutil.which("srun") is None:
        check_workers(
            shards, f"--launcher slurm --shards {shards} (no srun here: submitit starts them as local processes)"
        )
        return
    try:
        done = subprocess.run(["sinfo", "-h"], capture_output=True, text=True, timeout=30)
        why = (
            None if done.returncode == 0 else (done.stderr.strip().splitlines() or [f"exit code {done.returncode}"])[-1]
        )
    except (OSError, subprocess.TimeoutExpired) as error:
        why = f"{type(error).__name__}: {error}"
    if why is not None:
        raise ValueError(f"--launcher slurm: srun is on PATH but no SLURM controller answers (sinfo -h: {why[:200]}); "
                         "start the controller, or use --workers N here")


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


def run_shard_job(job: dict) -> dict:
    """One shard in this process (what a local worker or a SLURM array task runs): job holds its
    RunRequest ("request") and how it was launched (argv, threads, quiet)."""
    import torch

    from e3cm_bench.pipeline.runner import run_benchmark  # in the worker: a shard loads the models

    _as_launched(job.get("argv"))
    method = job["request"].method
    if method is not None and ":" in method.matcher:
        from e3cm_bench.matchers import get_matcher

        # a package.module:factory named by --matcher was imported in the process that launched
        # this one; a worker or an array task is a new interpreter and imports it again
        get_matcher(method.matcher, allow_import=True)
    if job.get("threads"):
        torch.set_num_threads(job["threads"])
    summary = run_benchmark(job["request"], console=Console(quiet=job.get("quiet", False)))
    return summary.iloc[0].to_dict()


def run_experiment_shard_job(job: dict) -> None:
    """Shard K/N of every method of an experiment (reproduce), in this process (a SLURM array task):
    job holds the config, its RunRequest and reproduce's own choices (run_experiment_shards)."""
    from e3cm_bench.pipeline.experiments import reproduce

    _as_launched(job.get("argv"))
    reproduce(job["config_path"], job["request"], console=Console(quiet=job.get("quiet", False)), **job["choices"])


def _as_launched(argv: list[str] | None) -> None:
    """In a worker or an array task: the command line that launched the shards, with this
    shard's own options, as sys.argv; each shard records from it the command that reruns it
    (pipeline/shards.shard_command). sys.argv here is otherwise the worker's or submitit's own."""
    import sys

    if argv:
        sys.argv = list(argv)


def launched_argv(shard: tuple[int, int], device: str | None = None) -> list[str] | None:
    """sys.argv of the shard K/N of this command: --shard K/N (and --device) for the launch options."""
    import shlex
    import sys

    from e3cm_bench.pipeline.shards import shard_command

    command = shard_command(shard, device=device)
    if command is None:
        return None
    # shard_command gave "cd DIR && e3cm-bench ARGS"; a shard records the same from this argv
    return [sys.argv[0], *shlex.split(command.split(" && ", 1)[1])[1:]]


def submit_array(function, jobs: list[dict], folder, console: Console, out, slurm: dict | None = None) -> list:
    """Submit function(job) for each job as one SLURM array (submitit); where no SLURM is found,
    submitit runs them as local processes and this waits for them. Returns the submitted
    jobs (SLURM) or their results (local).

    The sbatch options of the script submitit writes (FOLDER/<job>_submission.sh; docs/cluster.md):
    --array=0-(N-1)%N, --time=1440 (24 h), --job-name=e3cm-bench, --nodes=1, --signal=USR2@90,
    --open-mode=append, --output/--error FOLDER/%A_%a_0_log.{out,err}, --wckey=submitit; no
    partition, CPUs, memory or GPUs: the cluster's defaults. The environment (the virtual
    environment, PYTHONPATH) goes with the tasks (sbatch's --export=ALL). SBATCH_* environment
    variables (SBATCH_PARTITION, SBATCH_TIMELIMIT, SBATCH_GRES, ...) override the script's
    #SBATCH lines: a cluster's partition and limits need no option here."""
    try:
        import submitit
    except ImportError:
        raise ValueError("--launcher slurm needs submitit: pip install 'e3cm-bench[cluster]'") from None
    n = len(jobs)
    executor = submitit.AutoExecutor(folder=folder)
    params = {"timeout_min": 24 * 60, "name": "e3cm-bench", "slurm_array_parallelism": n, **(slurm or {})}
    if executor.cluster != "slurm":
        params = {k: v for k, v in params.items() if not k.startswith("slurm_")}
    executor.update_parameters(**params)
    with no_folder_on_path():  # the tasks (sbatch exports this environment) import nothing from the current folder
        submitted = executor.map_array(function, jobs)
    job_id = submitted[0].job_id.split("_")[0]
    console.print(f"submitted {n} shard(s) to {executor.cluster}: job {job_id}; "
                  f"they merge when the last one finishes (or: e3cm-bench merge {out})", markup=False)
    if executor.cluster == "slurm":
        console.print(f"watch: squeue -j {job_id}; logs: {folder}/{job_id}_*_log.*", markup=False)
        return submitted
    return [job.result() for job in submitted]


def run_experiment_shards(config_path, request, choices: dict, n: int, console: Console | None = None,
                          slurm: dict | None = None) -> list:
    """reproduce --launcher slurm --shards N: a SLURM array of N tasks; task K runs shard K/N of
    every method (experiments.reproduce with request.shard=(K, N)); the last to finish writes
    the table (or: e3cm-bench merge OUT). choices: reproduce's keyword arguments."""
    console = console or Console()
    jobs = [{"config_path": config_path, "request": request.but(shard=(k, n)), "choices": choices, "quiet": True,
             "argv": launched_argv((k, n))} for k in range(1, n + 1)]
    folder = RunFolder(request.out).shards_dir / "slurm"
    return submit_array(run_experiment_shard_job, jobs, folder, console, request.out, slurm)


def run_shards(request, n: int, devices: list[str] | None = None, launcher: str = "local",
               console: Console | None = None, slurm: dict | None = None) -> list:
    """Run the N shards of one run (a RunRequest): `launcher` local (one process each, at most
    len(devices) at once, torch threads divided among them on a CPU) or slurm (a submitit array;
    runs locally, one process per shard, where no SLURM is found). Returns each shard's summary
    (local) or the submitted jobs (slurm)."""
    console = console or Console()
    devices = devices or ["cpu"]
    jobs = []
    for k in range(1, n + 1):
        device = devices[(k - 1) % len(devices)]
        # local CPU workers divide the cores; a SLURM task keeps torch's default, the CPUs it was given
        threads = threads_per_worker(len(devices)) if device == "cpu" and launcher == "local" else None
        shard = request.but(shard=(k, n), device=device)
        if launcher == "local" and device == "cpu" and request.options.feature_cache_mb is None:
            from e3cm_bench.matchers.feature_cache import auto_cache_mb

            # local CPU workers share the host's memory: each gets its part of the default budget
            budget = auto_cache_mb("cpu") / sum(d == "cpu" for d in devices)
            shard = shard.but(options=replace(request.options, feature_cache_mb=budget))
        jobs.append({"request": shard, "threads": threads, "quiet": True,
                     "argv": launched_argv((k, n), None if device == "cpu" else device)})
    if launcher == "slurm":
        return submit_array(run_shard_job, jobs, RunFolder(request.out).shards_dir / "slurm", console,
                            request.out, slurm)
    with no_folder_on_path(), worker_pool(len(devices)) as pool:  # workers import nothing from the current folder
        futures = [pool.submit(run_shard_job, job) for job in jobs]
        results = []
        for k, future in enumerate(futures, start=1):
            results.append(future.result())
            console.print(f"shard {k}-of-{n} done", markup=False)
    merged = RunFolder(request.out).summary_path
    if merged.is_file():  # the last worker merged; show what a single run would have shown
        summary = pd.read_csv(merged).iloc[0].to_dict()
        print_summary(summary, f"{n} shards merged -> {request.out}", console=console)
    return results
