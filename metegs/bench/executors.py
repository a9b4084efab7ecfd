"""Where a suite's jobs run: one after the other in this process (`LocalExecutor`, the default), or as tasks of a
Ray cluster (`RayExecutor`, ``metegs-bench suite FILE --executor ray``; ``pip install -e ".[ray]"``).

Both run the same `SuiteRunner.perform` on the same jobs and read and write the same suite folder, so a suite
started with one finishes with the other: a run whose ``metrics.json`` and ``bench.json`` exist is reused, an
interrupted one resumes from its latest checkpoint or starts again (``metrics.json`` is written last and atomically:
a killed run is never counted). On Ray each job is a task with the ``resources`` the suite asks for, and the
synthesis and restoration of a condition's photos are tasks the runs depend on; the suite folder must be a path
every worker reaches (one machine, or a shared file system).
"""

from __future__ import annotations

import os
import socket
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from metegs.errors import ConfigError

if TYPE_CHECKING:
    from metegs.bench.suite import Job, JobResult, SuiteRunner

EXECUTORS = ("local", "ray")
"""Names ``metegs-bench suite --executor`` takes."""

RAY_INSTALL = 'pip install -e ".[ray]"'
"""How to install the Ray executor's extra."""


class LocalExecutor:
    """The jobs one after the other in this process, in plan order."""

    def run(self, runner: SuiteRunner, jobs: list[Job]) -> dict[str, JobResult]:
        outputs: dict[str, JobResult] = {}
        for job in jobs:
            out = runner.perform(job, {d: outputs[d].value for d in job.deps})
            for record in out.records + out.support:
                runner.announce(record)
            outputs[job.key] = out
        return outputs


def job_log(output: Path, job: Job) -> Path:
    """Where a job run on a worker writes what it prints: ``<suite>/logs/<key with / as __>.log``."""
    return Path(output) / "logs" / (job.key.replace("/", "__") + ".log")


def job_threads(runner: SuiteRunner, job: Job) -> int:
    """Torch and kernel threads of a job on a worker: the suite's ``threads``, else the CPUs it asked for."""
    return runner.suite.threads or max(1, int(job.resources.get("cpus", 1)))


def perform_on_worker(runner: SuiteRunner, job: Job, *needed: JobResult) -> JobResult:
    """A Ray task: `SuiteRunner.perform` with the job's console written to its log file."""
    from rich.console import Console

    log = job_log(runner.output, job)
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a", encoding="utf-8") as stream:
        runner.console = Console(file=stream, width=120, soft_wrap=True)
        runner.console.print(f"{job.key}: started on {socket.gethostname()} (pid {os.getpid()})", highlight=False)
        stream.flush()  # the driver counts the job as running from here
        out = runner.perform(job, {d: r.value for d, r in zip(job.deps, needed)}, threads=job_threads(runner, job))
    for record in out.records + out.support:
        if record.get("status") == "failed":
            record["log"] = str(log.relative_to(runner.output))
    return out


class RayExecutor:
    """Every job a Ray task (``address``: ``auto``, ``ray://host:10001``, or None to start Ray on this machine;
    a Ray already initialised in this process is used as it is)."""

    def __init__(self, address: str | None = None, max_retries: int = 2):
        self.address = address
        self.max_retries = max_retries
        """How often a job whose worker died (killed, out of memory) is started again; it resumes from its
        checkpoint."""

    def run(self, runner: SuiteRunner, jobs: list[Job]) -> dict[str, JobResult]:
        try:
            import ray
        except ImportError:
            raise ConfigError(f"--executor ray needs Ray: {RAY_INSTALL}") from None
        started = False
        if not ray.is_initialized():
            local = {"include_dashboard": False} if self.address is None else {}  # a cluster keeps its dashboard
            ray.init(address=self.address, log_to_driver=False, **local)
            started = True
        try:
            return self._run(ray, runner, jobs)
        finally:
            if started:
                ray.shutdown()

    @staticmethod
    def _result(ray, ref, job: Job, runner: SuiteRunner) -> JobResult:
        """A finished task's result; a task that raised (its worker died, or a job it needs failed) is recorded as
        failed with the error and its log."""
        try:
            return ray.get(ref)
        except Exception as exc:  # noqa: BLE001 - whatever the worker or Ray raised
            log = job_log(runner.output, job)
            reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            return runner.job_failed(
                job,
                f"{type(exc).__name__} on the Ray worker: {reason}",
                str(log.relative_to(runner.output)) if log.is_file() else None,
            )

    def _run(self, ray, runner: SuiteRunner, jobs: list[Job]) -> dict[str, JobResult]:
        task = ray.remote(perform_on_worker)
        shared = ray.put(runner)
        refs: dict[str, Any] = {}
        by_ref: dict[Any, Job] = {}
        since = time.time()
        for job in jobs:  # plan order: a job's inputs are submitted before it
            ref = task.options(
                num_cpus=float(job.resources.get("cpus", 1)),
                num_gpus=float(job.resources.get("gpus", 0)),
                max_retries=self.max_retries,
                retry_exceptions=False,
                name=job.key,
            ).remote(shared, job, *(refs[d] for d in job.deps))
            refs[job.key] = ref
            by_ref[ref] = job
        outputs: dict[str, JobResult] = {}
        runs = [j for j in jobs if j.action in RUN_ACTIONS]
        ended = {"done": 0, "failed": 0}
        columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
        with Progress(*columns, console=runner.console, transient=True) as progress:
            bar = progress.add_task("runs on Ray", total=len(runs))
            pending = list(refs.values())
            while pending:
                done, pending = ray.wait(pending, num_returns=1, timeout=1.0)
                for ref in done:
                    job = by_ref[ref]
                    out = self._result(ray, ref, job, runner)
                    for record in out.records + out.support:
                        runner.announce(record)
                    for record in out.records:
                        ended["failed" if record["status"] == "failed" else "done"] += 1
                    outputs[job.key] = out
                    if job.action in RUN_ACTIONS:
                        progress.advance(bar)
                running = sum(
                    1 for r in pending if by_ref[r].action in RUN_ACTIONS and started(runner, by_ref[r], since)
                )
                left = len(runs) - sum(1 for j in runs if j.key in outputs)
                progress.update(
                    bar,
                    description=f"runs on Ray: {left - running} queued, {running} running, {ended['done']} done, "
                    f"{ended['failed']} failed",
                )
        return outputs


RUN_ACTIONS = ("clean", "run", "peer")
"""Jobs that make a row of the results (the others prepare photos)."""


def started(runner: SuiteRunner, job: Job, since: float) -> bool:
    """Whether ``job`` has begun on a worker since ``since`` (its log was written to)."""
    log = job_log(runner.output, job)
    return log.is_file() and log.stat().st_mtime >= since


def make_executor(name: str, address: str | None = None) -> LocalExecutor | RayExecutor:
    """The executor ``metegs-bench suite --executor NAME`` asks for."""
    if name == "local":
        if address is not None:
            raise ConfigError("--address goes with --executor ray")
        return LocalExecutor()
    if name == "ray":
        return RayExecutor(address)
    raise ConfigError(f"--executor {name!r}: expected one of {', '.join(EXECUTORS)}")
