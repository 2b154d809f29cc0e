"""The engine of catalog runs: any per-job function over many jobs, here, in a process pool or on dask.

    apply(jobs, work, on_done, workers=2)                 # a local pool of two processes
    apply(jobs, work, on_done, scheduler="tcp://h:8786")  # a dask.distributed cluster

``work(job)`` is any picklable function of one job (a tile with its buffer, a chunk: plain data);
``on_done(job, result, error)`` receives each outcome in the calling process, in completion order,
and may return a job to run again (a retry).  A job's exception is an outcome, never fatal;
:class:`~.errors.Cancelled` (and Ctrl-C) stops everything at once, terminating the workers.  The
executors know nothing of tiles, LAS or GeoPackages (Sylva, not in the papers; the role of lidR's
LAScatalog engine, ``catalog_apply``).
"""
from __future__ import annotations

import os
import sys
from collections import deque
from dataclasses import replace
from pathlib import Path
from typing import Optional

from .errors import Cancelled, InputError, SylvaError
from .progress import CancelCheck, check


def apply(jobs, work, on_done, workers: int = 1, scheduler=None, cancelled: CancelCheck = None,
          idle=lambda: False, progress_of=lambda job: None) -> None:
    """Run ``work`` over ``jobs``: on ``scheduler`` (dask) if given, else in ``workers`` processes
    (1 = in this process, with ``progress_of(job)`` as each job's progress callback).

    ``idle()`` is called while the pool or the scheduler has nothing finished yet (background work
    of the caller, such as merging results; it returns False when it had nothing to do).
    """
    if scheduler is not None:
        run_dask(jobs, work, scheduler, on_done, cancelled, idle=idle)
    elif workers > 1:
        run_pool(jobs, work, workers, on_done, cancelled, idle=idle)
    else:
        run_serial(jobs, work, on_done, cancelled, progress_of)


def _task_key(job) -> str:
    """A dask task key unique to a job and its attempt."""
    return f"sylva-{getattr(job, 'name', id(job))}-{getattr(job, 'attempt', 1)}-{getattr(job, 'checksum', '')}"


def run_serial(jobs, work, on_done, cancelled: CancelCheck = None, progress_of=lambda job: None) -> None:
    """Run ``work(job, progress=..., cancelled=...)`` for each job in this process, in order.

    ``on_done(job, result, error)`` gets every outcome; a job it returns (a retry) runs next.
    ``progress_of(job)`` gives the job's progress callback.
    """
    queue = deque(jobs)
    while queue:
        job = queue.popleft()
        check(cancelled)
        try:
            result, err = work(job, progress=progress_of(job), cancelled=cancelled), None
        except Cancelled:
            raise
        except Exception as error:  # noqa: BLE001 — a job's failure is reported, never fatal
            result, err = None, error
        retry = on_done(job, result, err)
        if retry is not None:
            queue.appendleft(retry)


def pool_context():
    import multiprocessing as mp

    from .io.las import reading

    # fork is fast, but not safe once QGIS (Qt threads) is running in this process, nor once lazrs's
    # thread pool has (io.las.reading.PARALLEL_LAZ_USED: forked workers would wait for its threads): spawn then
    if sys.platform.startswith("linux") and "qgis.core" not in sys.modules and not reading.PARALLEL_LAZ_USED:
        return mp.get_context("fork")
    ctx = mp.get_context("spawn")
    exe = Path(sys.exec_prefix) / ("python.exe" if os.name == "nt" else "bin/python3")
    if exe.exists() and not Path(sys.executable).name.lower().startswith("python"):
        ctx.set_executable(str(exe))   # inside QGIS sys.executable is QGIS itself
    return ctx


class WorkerDied(SylvaError):
    """The process working on a tile died (killed for memory, or a crash in native code)."""


def run_pool(jobs, work, workers: int, on_done, cancelled: CancelCheck = None, idle=lambda: False) -> None:
    """Run ``work(job)`` in a process pool, at most ``workers`` jobs in flight (``work`` must pickle).

    ``on_done(job, result, error)`` gets every outcome in the main process; a job it returns (a
    retry) is queued first.

    A worker that dies breaks the whole pool (``BrokenProcessPool`` for every
    tile in flight): those tiles are then rerun one at a time in a pool of
    their own, which finds the culprit — reported as :class:`WorkerDied`, not
    retried — and clears the innocent; the other tiles go on in a new pool.
    ``idle()`` is called while no tile has finished (it returns False when it had nothing to do).
    """
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool

    queue, suspects = deque(jobs), deque()
    while queue or suspects:
        alone = bool(suspects)
        source, size = (suspects, 1) if alone else (queue, workers)
        pending = {}
        with ProcessPoolExecutor(max_workers=size, mp_context=pool_context()) as pool:
            try:
                broken = False
                while pending or (source and not broken):
                    while source and not broken and len(pending) < size:
                        job = source.popleft()
                        pending[pool.submit(work, job)] = job
                    done, _ = wait(list(pending), timeout=0 if idle() else 0.5, return_when=FIRST_COMPLETED)
                    check(cancelled)
                    for fut in done:
                        job = pending.pop(fut)
                        err = fut.exception()
                        if isinstance(err, BrokenProcessPool):
                            broken = True
                            if alone:
                                on_done(replace(job, attempt=max(job.attempt, 2)), None, WorkerDied(
                                    f"{job.path}: the process working on this tile died (out of memory, "
                                    "or a crash in a native library)"))
                            else:
                                suspects.append(job)
                            continue
                        retry = on_done(job, None if err else fut.result(), err)
                        if retry is not None:
                            source.appendleft(retry)
            except BaseException:
                for fut in pending:
                    fut.cancel()
                terminate(pool)   # a cancel (Ctrl-C, SIGTERM) must not wait for the tiles in flight
                raise


def terminate(pool) -> None:
    """Stop a ProcessPoolExecutor's workers now (their .part files are removed by the run)."""
    processes = dict(getattr(pool, "_processes", None) or {})
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in processes.values():
        try:
            proc.terminate()
        except Exception:  # noqa: BLE001 — already gone
            pass
    for proc in processes.values():
        try:
            proc.join(5)
            if proc.is_alive():
                proc.kill()
                proc.join(5)
        except Exception:  # noqa: BLE001
            pass


#: The address schemes a SCHEDULER may use: given explicitly, over the network only.
SCHEDULER_SCHEMES = ("tcp://", "tls://")


def connect_scheduler(address: str, timeout_s: Optional[float] = None):
    """A dask.distributed Client for ``address`` (tcp:// or tls:// only), or one line why not.

    A scheduler is trusted code execution: dask sends tasks and results pickled both ways, so a
    scheduler (or a worker) one does not control can run any code in this process.  Only
    addresses written out with an explicit tcp:// or tls:// scheme are accepted (no inproc://,
    ucx:// or a bare host name that dask would complete), and the connection times out instead
    of hanging (Sylva, not in the papers).  Restricting the client's deserializers to dask's
    pickle-free families does not close the hole: the client still unpickles the exceptions and
    tracebacks workers report (distributed 2026.8.0), so it is not done.
    """
    try:
        from distributed import Client
    except ImportError:
        raise InputError("the SCHEDULER option needs dask.distributed: pip install 'dask[distributed]'") from None
    if timeout_s is None:   # SYLVA_SCHEDULER_TIMEOUT_S: seconds to wait for the scheduler (default 20)
        try:
            timeout_s = float(os.environ.get("SYLVA_SCHEDULER_TIMEOUT_S", "20"))
        except ValueError:
            timeout_s = 20.0
    text = str(address).strip()
    if not text.lower().startswith(SCHEDULER_SCHEMES) or len(text) <= 6:
        raise InputError(f"SCHEDULER={text!r}: give the scheduler's address with its scheme, "
                         "tcp://HOST:PORT or tls://HOST:PORT")
    try:
        return Client(text, timeout=timeout_s, set_as_default=False)
    except (OSError, TimeoutError) as err:
        raise InputError(f"SCHEDULER={text}: cannot reach the dask scheduler within {timeout_s:g} s "
                         f"({type(err).__name__}: {' '.join(str(err).split())[:200]})") from None
    except ValueError as err:
        raise InputError(f"SCHEDULER={text}: not a usable scheduler address ({err})") from None


def run_dask(jobs, work, scheduler, on_done, cancelled: CancelCheck = None, idle=lambda: False) -> None:
    """Run ``work(job)`` on a ``dask.distributed`` scheduler (an address or a Client); as :func:`run_pool`."""
    client = scheduler if hasattr(scheduler, "submit") else connect_scheduler(scheduler)
    from distributed import wait
    pending = {}
    try:
        pending = {client.submit(work, job, pure=False, key=_task_key(job)): job
                   for job in jobs}
        while pending:
            try:
                done = wait(list(pending), timeout=0 if idle() else 0.5, return_when="FIRST_COMPLETED").done
            except TimeoutError:
                done = ()
            check(cancelled)
            for fut in done:
                job = pending.pop(fut)
                if fut.status == "error":
                    retry = on_done(job, None, fut.exception())
                else:
                    retry = on_done(job, fut.result(), None)
                if retry is not None:
                    pending[client.submit(work, retry, pure=False, key=_task_key(retry))] = retry
    except BaseException:
        client.cancel(list(pending))
        raise
    finally:
        if client is not scheduler:
            client.close()
