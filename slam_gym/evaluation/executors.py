"""Run many jobs in parallel, resumably, writing one ``results.jsonl`` row per finished run.

:func:`run_jobs` is generic over the run function: any picklable callable ``run_fn(job) -> dict``
(a module-level function) whose dict holds the metrics of
:data:`slam_gym.evaluation.results.RESULT_KEYS`. Executors:

- ``"process"`` (default): :class:`concurrent.futures.ProcessPoolExecutor` with the ``spawn``
  start method (safe with threads, torch and BLAS pools), at most ``workers`` jobs in flight;
- ``"ray"``: the same function through ``ray.remote`` on a local Ray instance (or the cluster at
  ``ray_address``); an optional dependency, ``pip install slam-gym[ray]``;
- ``"serial"``: in this process, one after the other (debugging, profiling).

Guarantees (docs/ARCHITECTURE.md, "The command line and its output files"):

- resumable: jobs whose key already has a row in ``out_dir/results.jsonl`` are skipped, and each
  row is appended, flushed and ``fsync`` -ed as its run finishes, so killing the benchmark (even
  with SIGKILL) loses only the runs in progress; a partial last line is cut off on the next start;
- a run that raises becomes a row with ``status="error"``, ``error="Type: message"``, the
  traceback under ``traceback`` and every metric null; the other runs go on. A worker process that
  dies (killed, out of memory, a crash in native code) breaks a process pool: the jobs that were in
  flight are rerun one at a time in a fresh single-worker pool, so the one that kills its worker
  is recorded as an error and the innocent ones complete;
- a run that takes longer than ``run_timeout_s`` becomes an error row saying so (``RunTimeout``):
  with the process executor its worker is stopped and the pool replaced (the other runs in flight
  are started again), in the serial and Ray executors the run is interrupted by a timer signal in
  the process running it; the other runs go on;
- a row's key holds a user policy's digest (``policy_sha256``): recorded rows of the same run of
  other code (same key but for :data:`~slam_gym.evaluation.jobs.VERSION_OPTIONS`) are never
  reported; ok rows among them make :func:`run_jobs` refuse (:class:`ChangedCodeError`, naming
  the policies) unless ``rerun_changed``, which drops them and runs the jobs again; error rows
  among them (a policy that raised, since fixed) are dropped and run again in any case;
- Ctrl-C (``KeyboardInterrupt``) cancels the pending work, terminates the workers, leaves a valid
  file and raises :class:`RunsInterrupted` (a ``KeyboardInterrupt`` saying how many runs are kept
  and how to resume).
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import pickle
import signal
import sys
import threading
import time
import traceback
from collections import Counter, deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures import TimeoutError as FutureTimeoutError
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

from tqdm import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from filters.validation import require
from slam_gym.evaluation.jobs import VERSION_OPTIONS, Job
from slam_gym.evaluation.results import (
    RESULTS_FILENAME,
    STATUS_ERROR,
    ResultsWriter,
    code_identity,
    make_row,
    row_key,
    validate_result,
)

logger = logging.getLogger(__name__)

EXECUTORS = ("process", "ray", "serial")

RunFn = Callable[[Job], Mapping[str, Any]]
Outcome = dict[str, Any]

RAY_MISSING_MESSAGE = (
    "executor='ray' needs the optional dependency Ray: pip install slam-gym[ray] "
    "(or pip install ray), or use executor='process'"
)


class ChangedCodeError(ValueError):
    """Recorded rows of these jobs were run with other code or options of a user policy."""


class RunsInterrupted(KeyboardInterrupt):
    """Ctrl-C during :func:`run_jobs`; its message says which runs are kept and how to resume."""


class RunTimeout(BaseException):
    """A run exceeded its time limit (a ``BaseException``: a policy's ``except Exception`` must
    not swallow it)."""


def _timeout_failure(timeout_s: float, how: str, wall_time_s: float) -> Outcome:
    outcome = _failure(RunTimeout(
        f"the run took longer than the per-run limit of {timeout_s:g} s (run_timeout_s, "
        f"--run-timeout-s); {how}"))
    outcome["traceback"] = None
    outcome["wall_time_s"] = wall_time_s
    return outcome


@contextlib.contextmanager
def _time_limit(timeout_s: float | None):
    """Raise :class:`RunTimeout` in this thread after ``timeout_s`` (a real-time timer signal;
    only in the main thread of a process, where signals are delivered: elsewhere no limit)."""
    usable = (timeout_s is not None and hasattr(signal, "setitimer")
              and threading.current_thread() is threading.main_thread())
    if not usable:
        yield
        return

    def expire(signum, frame):
        raise RunTimeout(timeout_s)

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, timeout_s)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        signal.signal(signal.SIGALRM, previous)


def _failure(exc: BaseException, tb: str | None = None) -> Outcome:
    return {
        "result": None,
        "error": f"{type(exc).__name__}: {exc}",
        "traceback": tb if tb is not None else "".join(traceback.format_exception(exc)),
        "wall_time_s": 0.0,
    }


def execute_job(run_fn: RunFn, job: Job, timeout_s: float | None = None) -> Outcome:
    """Run one job and validate its result; runs inside the worker.

    Never raises ``Exception``: an exception of ``run_fn`` or an invalid result becomes an error
    outcome (with the traceback as text, since exceptions do not always pickle), and so does a
    run stopped after ``timeout_s`` (:func:`_time_limit`; None: no limit).
    ``KeyboardInterrupt`` and ``SystemExit`` pass through.
    """
    t0 = time.perf_counter()
    try:
        with _time_limit(timeout_s):
            result = validate_result(run_fn(job))
    except RunTimeout:
        return _timeout_failure(timeout_s, "it was interrupted", time.perf_counter() - t0)
    except Exception as exc:
        outcome = _failure(exc, traceback.format_exc())
        outcome["wall_time_s"] = time.perf_counter() - t0
        return outcome
    return {
        "result": result,
        "error": None,
        "traceback": None,
        "wall_time_s": time.perf_counter() - t0,
    }


PARENT_POLL_S = 0.5
"""How often a pool worker checks that the process that started it is still alive."""


def _init_worker(parent_pid: int) -> None:
    """Pool-worker initializer: Ctrl-C is handled by the parent, which terminates the workers;
    and a worker ends by itself when its parent dies (even by SIGKILL, which leaves the parent
    no chance to stop it): a daemon thread watches the parent's pid and exits the process once
    the worker has been re-parented."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)

    def watch_parent() -> None:
        while os.getppid() == parent_pid:
            time.sleep(PARENT_POLL_S)
        os._exit(1)

    threading.Thread(target=watch_parent, name="parent-watch", daemon=True).start()


def _terminate_pool(pool: ProcessPoolExecutor) -> None:
    """Cancel pending futures and stop the worker processes now (not after their current job)."""
    processes = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in processes:
        if proc.is_alive():
            proc.terminate()
    for proc in processes:
        proc.join(timeout=5.0)
    pool.shutdown(wait=True)


def _run_pool_until_broken(
    ctx: Any,
    queue: deque[Job],
    run_fn: RunFn,
    workers: int,
    on_outcome: Callable[[Job, Outcome], None],
    timeout_s: float | None = None,
) -> list[Job]:
    """Run ``queue`` on a pool of ``workers``; return the jobs in flight if the pool broke.

    A job still running ``timeout_s`` after it was handed to a worker (at most ``workers`` are
    in flight, so it started then) becomes a timeout error; the pool is then terminated, which
    stops that worker, and the other jobs in flight go back to the front of ``queue`` for the
    next pool."""
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_init_worker,
                               initargs=(os.getpid(),))
    in_flight: dict[Future, Job] = {}
    started: dict[Future, float] = {}
    broken: list[Job] = []
    pool_broken = False
    try:
        while (queue and not pool_broken) or in_flight:
            while queue and not pool_broken and len(in_flight) < workers:
                job = queue.popleft()
                try:
                    fut = pool.submit(execute_job, run_fn, job)
                except BrokenProcessPool:
                    queue.appendleft(job)  # never started: goes to the next pool
                    pool_broken = True
                    continue
                in_flight[fut] = job
                started[fut] = time.monotonic()
            if not in_flight:
                break
            wait_s = None
            if timeout_s is not None:
                wait_s = max(0.0, min(started[f] for f in in_flight) + timeout_s
                             - time.monotonic())
            done, _ = wait(in_flight, timeout=wait_s, return_when=FIRST_COMPLETED)
            if not done and timeout_s is not None:
                now = time.monotonic()
                late = [f for f in in_flight if now - started[f] >= timeout_s]
                if late:
                    for fut in late:
                        on_outcome(in_flight.pop(fut), _timeout_failure(
                            timeout_s, "its worker process was stopped and replaced",
                            now - started.pop(fut)))
                    queue.extendleft(reversed(list(in_flight.values())))  # started again
                    in_flight.clear()
                    pool_broken = True
                    break
            for fut in done:
                started.pop(fut, None)
                job = in_flight.pop(fut)
                try:
                    outcome = fut.result()
                except BrokenProcessPool:
                    broken.append(job)
                    pool_broken = True
                    continue
                except Exception as exc:  # e.g. the job or its result failed to pickle
                    outcome = _failure(exc)
                on_outcome(job, outcome)
    except BaseException:
        _terminate_pool(pool)
        raise
    if pool_broken:
        _terminate_pool(pool)
    else:
        pool.shutdown(wait=True)
    return broken


def _run_isolated(ctx: Any, run_fn: RunFn, job: Job, timeout_s: float | None = None) -> Outcome:
    """Run one job alone in a fresh single-worker pool; a dead worker, or one still running after
    ``timeout_s``, becomes an error outcome."""
    pool = ProcessPoolExecutor(max_workers=1, mp_context=ctx, initializer=_init_worker,
                               initargs=(os.getpid(),))
    t0 = time.perf_counter()
    try:
        fut = pool.submit(execute_job, run_fn, job)
        try:
            return fut.result(timeout=timeout_s)
        except FutureTimeoutError:
            _terminate_pool(pool)
            return _timeout_failure(timeout_s, "its worker process was stopped and replaced",
                                    time.perf_counter() - t0)
        except BrokenProcessPool:
            outcome = _failure(
                BrokenProcessPool(
                    "the worker process running this job died (killed, out of memory or a crash "
                    "in native code); it was rerun alone and died again"
                )
            )
            outcome["wall_time_s"] = time.perf_counter() - t0
            return outcome
        except Exception as exc:
            return _failure(exc)
    except BaseException:
        _terminate_pool(pool)
        raise
    finally:
        pool.shutdown(wait=True)


def _run_process(
    jobs: Sequence[Job], run_fn: RunFn, workers: int, on_outcome: Callable[[Job, Outcome], None],
    timeout_s: float | None = None,
) -> None:
    ctx = multiprocessing.get_context("spawn")
    queue = deque(jobs)
    n_done = 0
    stalls = 0

    def counted(job: Job, outcome: Outcome) -> None:
        nonlocal n_done
        n_done += 1
        on_outcome(job, outcome)

    while queue:
        before = n_done
        suspects = _run_pool_until_broken(ctx, queue, run_fn, workers, counted, timeout_s)
        if suspects:
            logger.warning(
                "a worker process died; rerunning the %d job(s) in flight one at a time",
                len(suspects),
            )
        for job in suspects:
            counted(job, _run_isolated(ctx, run_fn, job, timeout_s))
        stalls = stalls + 1 if n_done == before else 0
        if stalls >= 3:
            raise RuntimeError(
                "the process pool broke three times in a row before finishing any job; "
                "check that the worker processes can start (a script needs "
                "'if __name__ == \"__main__\":' with the spawn start method)"
            )


def _import_ray() -> Any:
    try:
        import ray
    except ImportError as exc:
        raise ImportError(RAY_MISSING_MESSAGE) from exc
    return ray


def _run_ray(
    jobs: Sequence[Job],
    run_fn: RunFn,
    workers: int,
    ray_address: str | None,
    on_outcome: Callable[[Job, Outcome], None],
    timeout_s: float | None = None,
) -> None:
    ray = _import_ray()
    started = False
    if not ray.is_initialized():
        kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
        if ray_address:
            kwargs["address"] = ray_address  # the cluster decides its CPUs
        else:
            # A local instance: workers import what this process imports (tests, scripts).
            paths = [p for p in (os.getcwd(), *sys.path) if p and os.path.isdir(p)]
            kwargs["num_cpus"] = workers
            kwargs["_node_ip_address"] = "127.0.0.1"  # a local instance talks over loopback only
            kwargs["runtime_env"] = {"env_vars": {"PYTHONPATH": os.pathsep.join(paths)}}
        ray.init(**kwargs)
        started = True
    refs: dict[Any, Job] = {}
    try:
        remote = ray.remote(num_cpus=1, max_retries=0)(execute_job)
        fn_ref = ray.put(run_fn)
        refs = {remote.remote(fn_ref, job, timeout_s): job for job in jobs}
        while refs:
            done, _ = ray.wait(list(refs), num_returns=1)
            for ref in done:
                job = refs.pop(ref)
                try:
                    outcome = ray.get(ref)
                except Exception as exc:  # worker crashed, task cancelled, ...
                    outcome = _failure(exc)
                on_outcome(job, outcome)
    except BaseException:
        for ref in refs:
            ray.cancel(ref, force=True)
        raise
    finally:
        if started:
            ray.shutdown()


def _run_serial(
    jobs: Sequence[Job], run_fn: RunFn, on_outcome: Callable[[Job, Outcome], None],
    timeout_s: float | None = None,
) -> None:
    for job in jobs:
        on_outcome(job, execute_job(run_fn, job, timeout_s))


def run_jobs(
    jobs: Iterable[Job],
    run_fn: RunFn,
    out_dir: str | os.PathLike,
    *,
    workers: int | None = None,
    executor: str = "process",
    ray_address: str | None = None,
    progress: bool = True,
    retry_errors: bool = False,
    rerun_changed: bool = False,
    run_timeout_s: float | None = None,
) -> list[dict[str, Any]]:
    """Run every job not yet in ``out_dir/results.jsonl`` and append one row per finished run.

    ``run_fn(job)`` must return a dict with (at least) the keys of ``RESULT_KEYS``; for the
    ``process`` and ``ray`` executors it must pickle (a module-level function or a
    ``functools.partial`` of one). ``workers`` defaults to ``os.cpu_count()`` (for ``ray`` with
    ``ray_address`` the cluster decides). With ``retry_errors`` the error rows of these jobs are
    removed from the file and the jobs are run again. Rows of these jobs run with another
    version of a user policy (the key differs only by :data:`VERSION_OPTIONS`) raise
    :class:`ChangedCodeError` naming the policies, or with ``rerun_changed`` are removed and
    their jobs run again. ``run_timeout_s`` (None: no limit) is the time limit of one run (module
    docstring).

    Returns the rows of ``jobs`` (already there or new), in the order of ``jobs``.

    With the ``process`` executor the workers are started with ``spawn``: a script that calls
    ``run_jobs`` must do so under ``if __name__ == "__main__":``, as for any spawn pool.
    """
    jobs = list(jobs)
    for i, job in enumerate(jobs):
        require(isinstance(job, Job), f"jobs[{i}]", job, "a slam_gym.evaluation.Job")
    keys = [job.key for job in jobs]
    dupes = sorted(k for k, count in Counter(keys).items() if count > 1)
    require(not dupes, "jobs", dupes[:3], "distinct jobs (these keys repeat)")
    require(executor in EXECUTORS, "executor", executor, f"one of {EXECUTORS}")
    require(callable(run_fn), "run_fn", run_fn, "a callable run_fn(job) -> dict")
    if workers is None:
        workers = os.cpu_count() or 1
    require(
        isinstance(workers, int) and not isinstance(workers, bool) and workers >= 1,
        "workers",
        workers,
        "an int >= 1",
    )
    if executor != "serial":
        try:
            pickle.dumps(run_fn)
        except Exception as exc:
            raise ValueError(
                f"run_fn={run_fn!r} is invalid: must pickle for executor={executor!r} (define it "
                f"at module level, not as a lambda or closure): {exc}"
            ) from exc
    require(ray_address is None or executor == "ray", "ray_address", ray_address,
            "given only with executor='ray' (the other executors do not use it)")
    require(run_timeout_s is None or (isinstance(run_timeout_s, (int, float))
                                      and not isinstance(run_timeout_s, bool)
                                      and 0 < run_timeout_s < float("inf")),
            "run_timeout_s", run_timeout_s, "None or a number of seconds > 0")
    if executor == "ray":
        _import_ray()  # fail before touching the output directory

    path = Path(out_dir) / RESULTS_FILENAME
    wanted = set(keys)
    code = code_identity()  # every row says which code made it
    with ResultsWriter(path) as writer:
        existing = writer.existing
        stale = _changed_rows(existing, jobs, wanted)
        stale_ok = [r for r in stale if r.get("status") != STATUS_ERROR]
        if stale_ok and not rerun_changed:  # error rows of old code hold no result to lose
            raise ChangedCodeError(_changed_message(stale_ok, path))
        stale_ids = {id(r) for r in stale}
        kept = [
            r for r in existing
            if not (retry_errors and r.get("status") == STATUS_ERROR and row_key(r) in wanted)
            and id(r) not in stale_ids
        ]
        if len(kept) != len(existing):
            if stale:
                logger.warning("%s", _changed_message(stale, path, replacing=True))
            if retry_errors and len(existing) - len(stale) != len(kept):
                logger.info("retrying %d errored run(s)", len(existing) - len(stale) - len(kept))
            writer.rewrite(kept)
            existing = writer.existing
        rows_by_key = {row_key(r): r for r in existing if row_key(r) in wanted}
        pending = [job for job in jobs if job.key not in rows_by_key]
        n_errors = sum(r.get("status") == STATUS_ERROR for r in rows_by_key.values())
        if rows_by_key:
            logger.info(
                "%s: %d of %d runs already done, %d to run",
                path,
                len(rows_by_key),
                len(jobs),
                len(pending),
            )
        bar = tqdm(
            total=len(jobs),
            initial=len(rows_by_key),
            desc="runs",
            unit="run",
            disable=not progress,
            dynamic_ncols=True,
        )

        def on_outcome(job: Job, outcome: Outcome) -> None:
            nonlocal n_errors
            row = make_row(
                job,
                outcome["result"],
                error=outcome["error"],
                traceback_text=outcome["traceback"],
                wall_time_s=outcome["wall_time_s"],
                code=code,
            )
            writer.write(row)
            rows_by_key[job.key] = row
            if row["status"] == STATUS_ERROR:
                n_errors += 1
                logger.warning("run %s failed: %s", job.key, row["error"])
            bar.set_postfix(errors=n_errors, refresh=False)
            bar.update(1)

        redirect = logging_redirect_tqdm() if progress else contextlib.nullcontext()
        try:
            with redirect:  # log lines are printed above the bar, not through it
                if pending:
                    n_workers = min(workers, len(pending))
                    if executor == "process":
                        _run_process(pending, run_fn, n_workers, on_outcome, run_timeout_s)
                    elif executor == "ray":
                        _run_ray(pending, run_fn, n_workers, ray_address, on_outcome,
                                 run_timeout_s)
                    else:
                        _run_serial(pending, run_fn, on_outcome, run_timeout_s)
        except KeyboardInterrupt as exc:
            raise RunsInterrupted(
                f"interrupted: the {len(rows_by_key)} finished run(s) of {len(jobs)} are kept in "
                f"{path}; rerun the same command (same output directory) to run the other "
                f"{len(jobs) - len(rows_by_key)}") from exc
        finally:
            bar.close()
    return [rows_by_key[k] for k in keys]


def _changed_rows(existing: Sequence[Mapping[str, Any]], jobs: Sequence[Job],
                  wanted: set[str]) -> list[Mapping[str, Any]]:
    """Recorded rows that are runs of these jobs with another version of a user policy's code."""
    identities = {job.identity for job in jobs if dict(job.options).keys() & set(VERSION_OPTIONS)}
    if not identities:
        return []
    stale = []
    for row in existing:
        if row_key(row) in wanted:
            continue
        try:
            identity = Job.from_row(row).identity
        except (ValueError, KeyError, TypeError):
            continue
        if identity in identities:
            stale.append(row)
    return stale


def _changed_message(stale: Sequence[Mapping[str, Any]], path: Path,
                     replacing: bool = False) -> str:
    counts = Counter(next((r[k] for k in ("policy", "system", "training") if r.get(k)), "?")
                     for r in stale)
    names = ", ".join(f"{name!r} ({n} run(s))" for name, n in sorted(counts.items()))
    what = (f"the code or options of policy {names} changed since its runs in {path} were "
            "made")
    if replacing:
        return f"{what}: those rows are dropped and the runs made again"
    return (f"{what}; their rows are not reused. Rerun with --rerun-changed (rerun_changed=True) "
            "to drop them and run again, or use a new --out")
