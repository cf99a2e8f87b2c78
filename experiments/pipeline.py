"""Estimators in worker processes beside the frame source (``coloc run --workers N``, N >= 1), and
the batches every run steps its estimators in.

A coupled run is open loop: SUMO and the coupler never read an estimate, so frame k + 1 can be
made while the estimators work on frame k. :class:`EstimatorPool` spreads the config's estimators over
the runner's process and ``N`` worker processes (spawned, so SUMO's process is never forked) and hands
their results back to the runner in step order and in the config's method order, so the runner logs
exactly what it logs when it steps them itself: the same estimates.parquet, association.parquet and
summary numbers, byte for byte (``tests/experiments/test_pipeline.py``), only the wall time changes.

Every loop (the runner's own, each worker's, the pool's local one) steps one estimator through
:data:`BATCH` consecutive frames before the next estimator runs (:func:`step_batch`): each estimator
sees its frames in order, so its results are those of a frame-by-frame loop, and its arrays and code
(and SUMO's between batches) stay in the caches.

Where each method steps (:func:`assign_methods`): light methods (the registry's ``Method.light``: GNSS,
whose step costs a tenth of icp_known_da's) beside SUMO; the others heaviest first (``Method.cost``) to
the least loaded process, the runner's counting the frame synthesis (:data:`FRAME_COST`). Each worker
builds its estimators from the registry's parameters (as the runner does) and steps them on the
batches it is sent, frames without truth; the known-association bound is sent the true association of
the rows with it, by the runner, as in the serial loop. At most :data:`LOOKAHEAD` batches wait for
their results, so memory stays bounded. Workers that would get no method are not started.

What it costs: each frame is pickled once per worker (about 140 kB for the arterial's ~400 rows),
each result once, and each worker imports the estimators once (in parallel with SUMO's start-up). What
it gains on 2 cores (docs/performance.md, "Estimators beside the traffic"): the TLR hour of
``gnss,icp_known_da,icp_da_lc`` takes 10.9-11.3 s with one worker (icp_da_lc there, icp_known_da beside
SUMO) against 14.8-15.0 s in one process.
"""

from __future__ import annotations

import multiprocessing
import os
import queue
import socket
import sys
import threading
import time
import traceback
import types
from collections import deque
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from coloc.core.frame import Frame, StepEstimate

#: Frames an estimator steps through before the next estimator runs (in the runner's loop and in each
#: worker), and frames per message to a worker. Stepping one estimator over consecutive frames keeps its
#: arrays and code, and SUMO's, in the caches: the TLR hour of gnss + icp_known_da + icp_da_lc in one
#: process took 19.9-20.7 s frame by frame, 17.0-17.4 s in batches of 8 and 15.9-16.3 s in batches of
#: 32 (docs/performance.md, "Estimators beside the traffic"). Results are the same whatever the batch:
#: each estimator sees its frames in order.
BATCH = 32

#: batches sent ahead of the oldest batch whose results the runner has not taken yet
LOOKAHEAD = 2

#: The frame synthesis (SUMO and the coupler) in units of the registry's ``Method.cost``: on the TLR
#: hour 3.0 s against icp_known_da's 5.1 s. The runner's process is a slot for the estimators too
#: (:func:`assign_methods`), loaded with this much.
FRAME_COST = 0.6


@dataclass(frozen=True)
class StepResult:
    """One estimator's output for one frame, as the runner logs it."""

    name: str
    estimate: StepEstimate
    sent: object  # coloc.inference.comm.CommCount | None (:func:`step_comm`)
    seconds: float  # the estimator's step, measured in its worker


def step_comm(est):
    """What the estimator's vehicles sent in its last step (a :class:`coloc.inference.comm.CommCount`,
    the estimator's ``last_comm`` or its step info's ``comm``); None: the method does not count it."""
    comm = getattr(est, "last_comm", None)
    if comm is None:
        comm = getattr(getattr(est, "last", None), "comm", None)
    return comm


def estimator_stats(est) -> dict | None:
    """An estimator's end-of-run counters (the infrastructure methods' ``stats``), None if it has none."""
    return dict(est.stats) if hasattr(est, "stats") else None


def step_result(est, known: bool, blind: Frame, association) -> StepResult:
    """Step one estimator on a frame without truth (``known``: the known-association bound, told
    ``association``, the frame's true association of its rows) and time it."""
    t0 = time.perf_counter()
    res = est.step_with_association(blind, association) if known else est.step(blind)
    return StepResult(est.name, res, step_comm(est), time.perf_counter() - t0)


def step_batch(estimators: list, known: list[bool], batch: list) -> list[list[StepResult]]:
    """Step each estimator over ``batch`` ((frame without truth, association) pairs, in step order)
    before the next one runs (:data:`BATCH`); returns, per frame, its :class:`StepResult` list in
    ``estimators`` order."""
    out = [[None] * len(estimators) for _ in batch]
    for j, (est, told) in enumerate(zip(estimators, known)):
        for f, (blind, association) in enumerate(batch):
            out[f][j] = step_result(est, told, blind, association)
    return out


def assign_methods(methods: list[str], n_workers: int) -> tuple[list[int], list[list[int]]]:
    """Where each method steps with ``n_workers`` worker processes: (indices in the runner's process,
    indices per worker), each list in config order.

    Light methods (``Method.light``) stay in the runner's process. The others are spread by their
    ``Method.cost`` over the runner's process, loaded with the frame synthesis (:data:`FRAME_COST`),
    and the workers: heaviest first, each to the least loaded process (longest processing time
    first; a tie goes to the earlier process, the runner's first). Only workers that get a method are
    started, and each of those gets at least the first. On the arterial with one worker: icp_da_lc
    (1.3) goes to the worker, icp_known_da (1.0) beside SUMO (0.6 + 0.1 for GNSS)."""
    from coloc.methods.registry import METHODS

    def cost(i: int) -> float:
        m = METHODS.get(methods[i])
        return float(m.cost) if m is not None else 1.0

    local = [i for i, m in enumerate(methods) if getattr(METHODS.get(m), "light", False)]
    heavy = sorted((i for i in range(len(methods)) if i not in local), key=lambda i: (-cost(i), i))
    n = min(max(int(n_workers), 0), len(heavy))
    slots: list[list[int]] = [list(local)] + [[] for _ in range(n)]
    loads = [FRAME_COST + sum(cost(i) for i in local)] + [0.0] * n
    for k, i in enumerate(heavy):
        s_min = 1 + k if k < n else min(range(n + 1), key=lambda s: (loads[s], s))
        slots[s_min].append(i)
        loads[s_min] += cost(i)
    return sorted(slots[0]), [sorted(g) for g in slots[1:]]


def _worker_main(conn, methods: list[str], params, indices: list[int]) -> None:
    """Worker process: build the estimators ``indices`` of ``methods`` from ``params`` (the registry's
    :class:`coloc.methods.registry.MethodParams`), then step them on every batch of (frame without
    truth, association) received until None (:func:`step_batch`); reply per batch with the frames'
    :class:`StepResult` lists, at the end with each estimator's ``stats`` (infrastructure methods'
    counters) or None. It imports the registry, not the runner.

    After its last reply the process ends at once (``os._exit``): everything it had to say is sent,
    and the interpreter's teardown of the estimators and numba took 0.45 s that the runner waited
    for in :meth:`EstimatorPool.close`."""
    finished = False
    try:
        from coloc.methods.registry import METHODS, build_method

        estimators = [build_method(methods[i], params) for i in indices]
        known = [METHODS[e.name].known_association for e in estimators]
        conn.send(("ready", None))
        while True:
            msg = conn.recv()
            if msg is None:
                break
            conn.send(("step", step_batch(estimators, known, msg)))
        conn.send(("stats", [estimator_stats(est) for est in estimators]))
        finished = True
    except BaseException as exc:  # noqa: BLE001 - the runner raises it in the main process
        try:
            conn.send(("error", worker_error(exc)))
        except (BrokenPipeError, OSError):
            pass
    finally:
        conn.close()
    if finished:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)


@contextmanager
def _parent_main_not_imported():
    """Start spawned workers without importing the parent's ``__main__`` again.

    multiprocessing's spawn start method runs the parent's main script in every child (as
    ``__mp_main__``) so that functions defined there can be targets. The workers' target lives in
    this module and the methods in the registry, so that import only costs time: for ``coloc`` and
    the benches it is everything the runner imports (0.3-1 s a worker, measured by ``bench/startup.py``). While a worker
    starts, ``__main__`` is an empty module: the child then imports only this module and what
    unpickling its arguments needs."""
    main = sys.modules.get("__main__")
    sys.modules["__main__"] = types.ModuleType("__main__")
    try:
        yield
    finally:
        if main is None:
            del sys.modules["__main__"]
        else:
            sys.modules["__main__"] = main


def _drain(conn, replies: queue.Queue) -> None:
    """Move a worker's replies from its pipe to ``replies`` until its last one ("stats" or "error")."""
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            replies.put(("eof", None))
            return
        replies.put(msg)
        if msg[0] in ("stats", "error"):
            return


class EstimatorWorkerError(RuntimeError):
    """An estimator failed in its worker process: one line naming the worker, its methods and the
    error's type and message; the worker's traceback in ``worker_traceback`` (the command line prints
    it only with ``COLOC_DEBUG`` set)."""

    def __init__(self, message: str, worker_traceback: str | None = None):
        super().__init__(message)
        self.worker_traceback = worker_traceback


def worker_error(exc: BaseException) -> dict:
    """What a worker sends back about an exception: plain values (any exception, libsumo's too, and
    without the classes of the worker's modules); an :class:`couplers.errors.InputError` keeps its
    file, field and message."""
    from couplers.errors import InputError

    text = " ".join(str(exc).split())  # one line
    out = {"type": type(exc).__name__, "message": text, "traceback": traceback.format_exc()}
    if isinstance(exc, InputError):
        out["input"] = (exc.path, exc.field, exc.message)
    return out


def raise_worker_error(where: str, payload) -> None:
    """Raise in the runner what a worker reported (:func:`worker_error`): the InputError as it was,
    anything else as an :class:`EstimatorWorkerError` of one line."""
    from couplers.errors import InputError

    if payload.get("input") is not None:
        raise InputError(*payload["input"])
    text = f"{payload['type']}: {payload['message']}" if payload["message"] else payload["type"]
    raise EstimatorWorkerError(f"{where} failed: {text}", payload.get("traceback"))


class EstimatorPool:
    """The config's estimators in worker processes and beside the frame source; results in step and
    method order.

    ``submit(frame)`` takes a frame (with truth: the pool strips it, keeping the true association for
    the known-association bound); every :data:`BATCH` frames it sends the batch to the workers and steps
    the runner's own methods over it (:func:`assign_methods`). It returns the finished steps as
    (frame, [StepResult, ...]) in order, at most :data:`LOOKAHEAD` batches behind; ``finish()``
    returns the rest and ends the workers.
    """

    def __init__(self, methods: list[str], params, n_workers: int, lookahead: int = LOOKAHEAD,
                 batch: int = BATCH):
        from coloc.methods.registry import METHODS, build_method

        self.methods = list(methods)
        local, self.groups = assign_methods(self.methods, n_workers)
        self.local = local
        self._local_estimators = [build_method(self.methods[i], params) for i in local]
        self._local_known = [METHODS[self.methods[i]].known_association for i in local]
        self._needs_truth = [any(getattr(METHODS.get(self.methods[i]), "known_association", False) for i in g)
                             for g in self.groups]
        self.lookahead = max(1, int(lookahead))
        self.batch = max(1, int(batch))
        self._filling: list[Frame] = []  # frames of the batch not sent yet
        self._pending: deque[tuple[list[Frame], list[list[StepResult]]]] = deque()
        self.stats: dict[str, dict | None] = {}
        ctx = multiprocessing.get_context("spawn")
        self._conns, self._procs, self._replies, self._drains = [], [], [], []
        for group in self.groups:
            parent, child = ctx.Pipe()
            proc = ctx.Process(target=_worker_main, args=(child, self.methods, params, group), daemon=True)
            with _parent_main_not_imported():
                proc.start()
            child.close()
            # A thread per worker takes its replies off the pipe as they come: a worker never blocks on
            # a full pipe while the runner is blocked sending it the next batch.
            replies: queue.Queue = queue.Queue()
            drain = threading.Thread(target=_drain, args=(parent, replies), daemon=True)
            drain.start()
            self._drains.append(drain)
            self._conns.append(parent)
            self._procs.append(proc)
            self._replies.append(replies)

    def _where(self, w: int) -> str:
        return f"estimator worker {w} ({', '.join(self.methods[i] for i in self.groups[w])})"

    def _receive(self, w: int, kind: str):
        tag, payload = self._replies[w].get()
        if tag == "eof":
            code = self._procs[w].exitcode if w < len(self._procs) else None
            ended = f" (exit code {code})" if code is not None else ""
            raise EstimatorWorkerError(f"{self._where(w)} ended without a reply{ended}")
        if tag == "error":
            raise_worker_error(self._where(w), payload)
        if tag != kind:
            raise EstimatorWorkerError(f"{self._where(w)}: expected {kind!r}, got {tag!r}")
        return payload

    def _send(self, w: int, msg) -> None:
        """Send to worker ``w``; a worker that is gone (it failed and ended) is reported by its own
        error, which its drain thread has or is about to have (not as the runner's broken pipe)."""
        try:
            self._conns[w].send(msg)
        except OSError:  # BrokenPipeError, ConnectionResetError: the worker has ended
            while True:  # its error, or the end of its pipe, comes from the drain thread after its last results
                try:
                    tag, payload = self._replies[w].get(timeout=30.0)
                except queue.Empty:
                    raise EstimatorWorkerError(f"{self._where(w)} stopped reading and sent no reply") from None
                if tag in ("error", "eof"):
                    self._replies[w].put((tag, payload))
                    self._receive(w, "error")  # raises

    def wait_ready(self) -> None:
        for w in range(len(self._conns)):
            self._receive(w, "ready")

    def _dispatch(self) -> None:
        """Send the filling batch to the workers, then step the runner's methods over it."""
        frames, self._filling = self._filling, []
        blind = [f.without_truth() for f in frames]
        truth = [np.asarray(f.truth.v2f_feature) if f.truth is not None else None for f in frames]
        for w in range(len(self._conns)):
            self._send(w, [(b, a if self._needs_truth[w] else None) for b, a in zip(blind, truth)])
        self._pending.append((frames, step_batch(self._local_estimators, self._local_known, list(zip(blind, truth)))))

    def _collect_oldest(self) -> list[tuple[Frame, list[StepResult]]]:
        frames, local = self._pending.popleft()
        results: list[list[StepResult | None]] = [[None] * len(self.methods) for _ in frames]
        for f, res in enumerate(local):
            for i, r in zip(self.local, res):
                results[f][i] = r
        for w, group in enumerate(self.groups):
            for f, res in enumerate(self._receive(w, "step")):
                for i, r in zip(group, res):
                    results[f][i] = r
        return list(zip(frames, results))

    def submit(self, frame: Frame) -> list[tuple[Frame, list[StepResult]]]:
        self._filling.append(frame)
        done = []
        if len(self._filling) >= self.batch:
            self._dispatch()
            while len(self._pending) > self.lookahead:
                done.extend(self._collect_oldest())
        return done

    def finish(self) -> list[tuple[Frame, list[StepResult]]]:
        if self._filling:
            self._dispatch()
        done = []
        while self._pending:
            done.extend(self._collect_oldest())
        for w in range(len(self._conns)):
            self._send(w, None)
        for w, group in enumerate(self.groups):
            for i, stats in zip(group, self._receive(w, "stats")):
                self.stats[self.methods[i]] = stats
        for i, est in zip(self.local, self._local_estimators):
            self.stats[self.methods[i]] = estimator_stats(est)
        self.close()
        return done

    def close(self) -> None:
        """End the workers (also after an error: nothing is left running).

        The connections are shut down before they are closed: a worker still stepping and the thread
        draining its replies both see the end of the stream (a connection closed under a thread that
        reads it would raise there instead)."""
        for conn in self._conns:
            try:
                with socket.socket(fileno=os.dup(conn.fileno())) as sock:
                    sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        for drain in self._drains:
            drain.join(timeout=5.0)
        for conn in self._conns:
            try:
                conn.close()
            except OSError:
                pass
        for proc in self._procs:
            proc.join(timeout=5.0)
            if proc.is_alive():
                proc.terminate()
                proc.join()
        self._conns, self._procs, self._drains = [], [], []
        self._local_estimators = []  # their state is not needed after the loop (the PF's kept matrices: 2 GB)

    def __enter__(self) -> "EstimatorPool":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
