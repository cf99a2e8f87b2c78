"""Figures drawn in forked worker processes: a report's figures split by weight between processes.

Each figure is drawn by one process from the run's data (inherited by ``os.fork``, not copied
or re-read) and the same code, so its bytes do not depend on which process drew it or how many
there were (``tests/experiments/test_report.py`` compares one and two processes). A job returns
a small picklable value (the HTML blocks and notes of its figures); the workers send theirs back
through a pipe. Drawing is CPU-bound Python (matplotlib), so threads would not help.

Only :func:`os.fork` is used (no ``multiprocessing`` start-up, no re-import): on a system without
it, with one core, or while other Python threads run (a fork copies no thread, so a lock one of
them holds would never be released in the child), every job runs in this process. The threads of
native pools (numpy's OpenBLAS, Arrow's, started by the imports and the Parquet reading) are
harmless: the children use neither pool's locks (OpenBLAS and Arrow reset them after a fork).
"""

from __future__ import annotations

import os
import pickle
import sys
import threading
import traceback
import warnings
from typing import Callable, TypeVar

T = TypeVar("T")


def available_workers(limit: int = 2) -> int:
    """Processes worth drawing in: the cores this process may run on, at most ``limit``."""
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        n = os.cpu_count() or 1
    return max(1, min(limit, n))


def split_by_weight(weights: list[float], n: int) -> list[list[int]]:
    """Job indices per process, heaviest job first to the least loaded process (ties: lower index);
    each list in job order. Deterministic: depends only on the weights."""
    bins: list[list[int]] = [[] for _ in range(n)]
    load = [0.0] * n
    for i in sorted(range(len(weights)), key=lambda i: (-weights[i], i)):
        b = min(range(n), key=lambda b: (load[b], b))
        bins[b].append(i)
        load[b] += weights[i]
    return [sorted(b) for b in bins]


def run_jobs(jobs: list[tuple[float, Callable[[], T]]], workers: int = 1) -> list[T]:
    """Run ``(weight, job)`` pairs; their results in job order.

    With ``workers`` > 1 (and :func:`os.fork`, more than one job and no other Python thread), the
    jobs are split by :func:`split_by_weight` between this process and ``workers - 1`` forked
    children. A job that raises in a child raises here (the same exception type when it pickles,
    with the child's traceback as a note), after every child has ended."""
    n = min(workers, len(jobs))
    if n <= 1 or not hasattr(os, "fork") or threading.active_count() > 1:
        return [job() for _, job in jobs]
    parts = split_by_weight([w for w, _ in jobs], n)
    sys.stdout.flush()  # a child must not write the parent's buffered output a second time
    sys.stderr.flush()
    children: list[tuple[int, int, list[int]]] = []  # (pid, read end of its pipe, its job indices)
    failure: BaseException | None = None
    try:
        for part in parts[1:]:
            r, w = os.pipe()
            with warnings.catch_warnings():
                # Python >= 3.12 warns on a fork while OS threads run (numpy's OpenBLAS and Arrow's
                # pools are started by then); the child only runs numpy, pandas and matplotlib on
                # inherited data, and both libraries re-initialize their pools after a fork.
                warnings.filterwarnings("ignore", r".*multi-threaded.*fork", DeprecationWarning)
                pid = os.fork()
            if pid == 0:  # child: run its jobs, send the results, exit without cleanup
                os.close(r)
                _child(w, [jobs[i][1] for i in part])
            os.close(w)
            children.append((pid, r, part))
        results: dict[int, T] = {i: jobs[i][1]() for i in parts[0]}
        for pid, r, part in children:
            status, value = _receive(r)
            if status == "ok":
                results.update(zip(part, value))
            elif failure is None:
                failure = value
    except BaseException:  # stop the children: never leave one behind
        for pid, _, _ in children:
            _kill(pid)
        raise
    finally:
        for pid, r, _ in children:
            os.close(r)
            os.waitpid(pid, 0)
    if failure is not None:
        raise failure
    return [results[i] for i in range(len(jobs))]


def _child(w: int, jobs: list[Callable[[], object]]) -> None:
    """In a forked child: run the jobs, write ``("ok", results)`` or ``("error", exception)`` to ``w``, exit."""
    code = 0
    try:
        try:
            payload = pickle.dumps(("ok", [job() for job in jobs]))
        except BaseException as exc:  # noqa: BLE001 - every failure goes back to the parent
            code = 1
            payload = pickle.dumps(("error", _portable(exc)))
        with os.fdopen(w, "wb") as fh:
            fh.write(payload)
        sys.stdout.flush()
        sys.stderr.flush()
    finally:
        os._exit(code)


def _portable(exc: BaseException) -> BaseException:
    """The exception if it pickles, else a RuntimeError with its text; the child's traceback as a note."""
    tb = "".join(traceback.format_exception(exc))
    try:
        pickle.loads(pickle.dumps(exc))
        out = exc
    except Exception:  # noqa: BLE001
        out = RuntimeError(f"{type(exc).__name__}: {exc}")
    out.add_note(f"raised in a report worker process (pid {os.getpid()}):\n{tb}")
    return out


def _receive(r: int) -> tuple[str, object]:
    with os.fdopen(r, "rb", closefd=False) as fh:
        data = fh.read()
    if not data:
        return "error", RuntimeError("a report worker process ended without sending its figures")
    return pickle.loads(data)


def _kill(pid: int) -> None:
    import signal

    try:
        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
