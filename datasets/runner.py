"""Running units of work: in this process, on a local Dask cluster or on an existing
scheduler (:class:`RunOptions`), retried, counted and reported (:class:`JobReport`).
The target database's render and feature jobs (:mod:`prism3d.datasets.jobs.database_jobs`), the
simulated field batches and the survey's dense pairs all run through :func:`run_tasks`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import psutil

from prism3d.errors import DatasetError
from prism3d.progress import ProgressFn
from prism3d.reconstruct.survey.run import dense_pair
from prism3d.reconstruct.survey.model import PairRequest, PairResult

__all__ = [
    "SCHEDULER_TIMEOUT_S", "JobReport", "RunOptions", "Task", "check_scheduler", "execute_tasks", "run_survey_pairs",
    "run_tasks",
]

log = logging.getLogger(__name__)


@dataclass
class JobReport:
    """Outcome of a job run: unit counts (``total``, ``skipped`` = resumed,
    ``done`` = run now), ``failed`` (``unit``, ``what``, ``error``), per-unit ``stats``.
    """

    job: str
    total_units: int = 0
    skipped_units: int = 0
    done_units: int = 0
    failed: list[dict[str, str]] = field(default_factory=list)
    stats: list[Any] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return not self.failed

    @property
    def exit_code(self) -> int:
        """0 when every unit is done, 1 when a unit failed."""
        return 0 if self.ok else 1

    def failure_line(self) -> str:
        """One line for a job with failed units: how many, the first error, how to resume."""
        first = self.failed[0] if self.failed else {"unit": "-", "error": "-"}
        return (f"job {self.job}: {len(self.failed)} of {self.total_units} units failed (first: "
                f"{first['unit']}: {first['error']}); finished units are kept, run the same "
                "command again to resume")

    def summary(self) -> str:
        head = (
            f"job {self.job}: {self.skipped_units + self.done_units}/{self.total_units} units done "
            f"({self.done_units} now, {self.skipped_units} resumed), {len(self.failed)} failed, "
            f"{self.seconds:.1f} s"
        )
        lines = [head]
        lines += [f"  FAILED {f['unit']} ({f['what']}): {f['error']}" for f in self.failed]
        return "\n".join(lines)


Task = tuple[str, str, Callable[..., Any], tuple]


#: A local Dask worker is a process of its own: about this much memory before any work.
WORKER_BASE_MIB = 400
#: At most this many local workers per core (more only wait for the cores).
WORKERS_PER_CORE = 4


def max_local_workers() -> int:
    """The most local Dask workers this machine can hold: :data:`WORKERS_PER_CORE` a core,
    and each with :data:`WORKER_BASE_MIB` of the memory available now (at least 1)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    mem = int(psutil.virtual_memory().available) // (WORKER_BASE_MIB * 2**20)
    return max(1, min(WORKERS_PER_CORE * cores, mem))


@dataclass(frozen=True)
class RunOptions:
    """Where and how job units run."""

    workers: int = 0
    """0: units run in this process (debugging); N: a local Dask cluster of N processes."""
    scheduler: str | None = None
    """Address of an existing Dask scheduler (``tcp://HOST:PORT``); overrides ``workers``."""
    retries: int = 2
    """Retries of a failing unit before it is reported."""
    progress: ProgressFn | None = None
    """Progress callback ``(done, total, label)``."""

    def __post_init__(self) -> None:
        w, r = self.workers, self.retries
        if isinstance(w, bool) or not isinstance(w, int) or w < 0:
            raise DatasetError(f"workers: expected an integer >= 0, got {w!r}")
        sch = self.scheduler
        if sch is None and w > 1 and w > (cap := max_local_workers()):
            raise DatasetError(f"workers: {w} local workers is more than this machine holds (at most {cap}: "
                               f"{WORKERS_PER_CORE} a core, {WORKER_BASE_MIB} MiB each); give fewer, or --scheduler")
        if sch is not None and not (isinstance(sch, str) and "://" in sch):
            raise DatasetError(f"scheduler: expected an address like tcp://HOST:PORT, got {sch!r}")
        if isinstance(r, bool) or not isinstance(r, int) or r < 0:
            raise DatasetError(f"retries: expected an integer >= 0, got {r!r}")


class _Tally:
    """Counts finished tasks into a :class:`JobReport` and reports progress."""

    def __init__(self, report: JobReport, n: int, progress: ProgressFn | None) -> None:
        self.report, self.n, self.progress, self.done = report, n, progress, 0
        if progress is not None:
            progress(0, n, report.job)

    def __call__(self, unit_id: str, what: str, res: Any, err: BaseException | None) -> None:
        self.done += 1
        if err is None:
            self.report.done_units += 1
            self.report.stats.append(res)
        else:
            # INFO, shown with -v: the report carries every failure and each job's caller
            # reports them once (JobReport.summary / failure_line); a warning here printed
            # a second line before the command's own error
            log.info("unit %s (%s) failed: %s", unit_id, what, err)
            self.report.failed.append(
                {"unit": unit_id, "what": what, "error": f"{type(err).__name__}: {err}"}
            )
        if self.progress is not None:
            self.progress(self.done, self.n, unit_id)


def execute_tasks(tasks: list[Task], report: JobReport, run: RunOptions) -> None:
    """Run ``(unit_id, what, fn, args)`` tasks into a ``report`` the caller made (a job
    that resumed some units has counted them already); never raises for a unit."""
    finish = _Tally(report, len(tasks), run.progress)
    if not tasks:
        return
    if run.scheduler is None and run.workers == 0:
        _run_local(tasks, run.retries, finish)
    else:
        _run_dask(tasks, report.job, run, finish)


def run_tasks(job: str, tasks: Sequence[Task], run: RunOptions | None = None) -> JobReport:
    """Run independent tasks ``(unit_id, what, fn, args)`` (``fn`` importable, ``args``
    picklable) in this process or on Dask as ``run`` says, with its retries and progress;
    each task's return value lands in the report's ``stats`` (completion order), and one
    task's failure is reported, never raised."""
    t0 = time.perf_counter()
    run = RunOptions() if run is None else run
    check_scheduler(run.scheduler)
    report = JobReport(job=job, total_units=len(tasks))
    execute_tasks(list(tasks), report, run)
    report.seconds = time.perf_counter() - t0
    return report


def run_survey_pairs(reqs: Sequence[PairRequest], run: RunOptions,
                     progress: ProgressFn | None = None) -> list[PairResult]:
    """A survey's dense pairs (:func:`prism3d.reconstruct.survey.run.dense_pair`), one unit
    each, where ``run`` says; a pair that fails (not one skipped with a reason) stops the
    survey with its error."""
    report = run_tasks("survey dense", [(f"pair {r.i}-{r.j}", f"{Path(r.path_i).name}+{Path(r.path_j).name}",
                                         _dense_pair, (r,)) for r in reqs],
                       replace(run, progress=progress))
    if not report.ok:
        raise DatasetError(f"survey: {report.failure_line()}")
    return list(report.stats)


def _dense_pair(req: PairRequest) -> PairResult:
    return dense_pair(req)


def _run_local(tasks: list[Task], retries: int, finish: _Tally) -> None:
    for unit_id, what, fn, args in tasks:
        err: BaseException | None = None
        res = None
        for _attempt in range(retries + 1):
            try:
                res = fn(*args)
                err = None
                break
            except Exception as exc:  # noqa: BLE001 - one unit's failure must not stop the job
                err = exc
        finish(unit_id, what, res, err)


#: Seconds to reach a Dask scheduler before a job gives up (it writes nothing then).
SCHEDULER_TIMEOUT_S = 5.0


def check_scheduler(address: str | None, timeout_s: float = SCHEDULER_TIMEOUT_S) -> None:
    """DatasetError unless a TCP connection to the scheduler ``tcp://HOST:PORT`` opens
    within ``timeout_s`` (None: no scheduler, nothing to check)."""
    import socket

    if address is None:
        return
    host, _, port = address.removeprefix("tcp://").rpartition(":")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            pass
    except (OSError, ValueError) as exc:
        raise DatasetError(f"scheduler {address}: cannot connect ({exc}); is it running?") from None


def _dask_config() -> dict[str, Any]:
    import dask

    # one core per worker process: numba's parallel kernels would otherwise start one
    # thread per core in every worker and the workers would fight for the cores
    environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}))
    environ.setdefault("NUMBA_NUM_THREADS", 1)
    environ.setdefault("PRISM3D_NUM_THREADS", 1)  # Open3D ray casting (capture.render)
    environ.setdefault("OMP_NUM_THREADS", 1)
    return {
        "distributed.worker.multiprocessing-method": "spawn",
        "distributed.nanny.pre-spawn-environ": environ,
    }


@contextlib.contextmanager
def _environ_restored() -> Iterator[None]:
    """Undo what a local cluster's nannies set in this process's environment: they set
    the workers' variables (``NUMBA_NUM_THREADS=1``...) here before spawning, and a later
    numba config reload in the caller's process would then fail."""
    saved = dict(os.environ)
    try:
        yield
    finally:
        for k in set(os.environ) - set(saved):
            del os.environ[k]
        os.environ.update(saved)


@contextlib.contextmanager
def _cluster_log_quiet() -> Iterator[None]:
    """The cluster's own INFO lines (scheduler start, workers registering: ~25 per run)
    only when prism3d's log shows INFO too (-v); its warnings and errors always."""
    dlog = logging.getLogger("distributed")
    old = dlog.level
    if not log.isEnabledFor(logging.INFO):
        dlog.setLevel(logging.WARNING)
    try:
        yield
    finally:
        dlog.setLevel(old)


def _run_dask(tasks: list[Task], job: str, run: RunOptions, finish: _Tally) -> None:
    import dask
    from distributed import Client, LocalCluster, as_completed

    # the workers' scratch space is ours and goes with the run (Dask's default,
    # $TMPDIR/dask-scratch-space, would stay behind after every run)
    with tempfile.TemporaryDirectory(prefix="prism3d-dask-") as scratch, \
            dask.config.set({**_dask_config(), "temporary-directory": scratch}), _environ_restored(), \
            _cluster_log_quiet():
        if run.scheduler is not None:
            cluster = None
            client = Client(run.scheduler, timeout=SCHEDULER_TIMEOUT_S)
        else:
            cluster = LocalCluster(
                n_workers=run.workers,
                threads_per_worker=1,
                local_directory=scratch,
                processes=True,
                host="127.0.0.1",  # scheduler and workers reachable from this machine only
                dashboard_address="127.0.0.1:0",  # a free local port: never clash, never exposed
                silence_logs=logging.ERROR,
            )
            client = Client(cluster)
        try:
            futs = []
            names: dict[str, tuple[str, str]] = {}
            for unit_id, what, fn, args in tasks:
                key = f"{job}-{unit_id}-{time.time_ns()}"
                futs.append(client.submit(fn, *args, key=key, retries=run.retries, pure=False))
                names[key] = (unit_id, what)
            for fut in as_completed(futs):
                unit_id, what = names[fut.key]
                try:
                    res = fut.result()
                    finish(unit_id, what, res, None)
                except Exception as exc:  # noqa: BLE001 - reported per unit
                    finish(unit_id, what, None, exc)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
