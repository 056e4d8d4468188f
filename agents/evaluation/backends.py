"""Where the groups of episodes run: the local process pool (the default) or a Ray cluster.

    bimp evaluate ... --backend ray                        # a local Ray instance on this machine's cores
    bimp evaluate ... --backend ray --address HOST:6379    # a running cluster (``ray start --head`` there)

A backend runs :func:`bimp.agents.evaluation.evaluate.run_group` over the groups of jobs and hands each record to
``write`` as its group finishes; everything else (what to run, resume, the lock, provenance, the summary) stays in
:func:`bimp.agents.evaluation.evaluate.evaluate`, in the driver process, whichever backend runs the episodes. Both
backends keep the same failure semantics: a group whose worker process dies is run again, and one that kills its worker
again is recorded as a ``WorkerDied`` error; never lost, never a hang. The local pool reruns every group in flight when
its pool breaks, each alone; on Ray each group is a task in its own worker, so a crash is the task's own and Ray retries
it once (``max_retries``: a dead worker or node).

Killed, even by SIGKILL, the driver leaves no worker running: a pool worker dies with its parent (:func:`die_with`),
and multiprocessing's resource tracker exits once they are gone. On Ray (2.60, observed): a driver's tasks and
their workers end within a few seconds of its death, on a cluster as on a local instance; a local instance's GCS
and raylet go at once, the raylet's two agent processes about a minute later, on their own.

Ray is an optional extra (``pip install -e ".[ray]"``); it is imported only here, and only when asked for. Every
worker runs one BLAS / torch / XLA thread: the workers are the parallelism. See ``docs/scaling.md``.
"""

from __future__ import annotations

import ctypes
import multiprocessing as mp
import os
import signal
import socket
import sys
import threading
import time
from collections import deque
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Callable

BACKENDS = ("local", "ray")
INSTALL_RAY = 'pip install -e ".[ray]"'
# One thread per worker process: spawned / Ray workers import numpy and JAX afresh and would otherwise each start
# a thread per core and fight over them.
THREADS = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
           "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"}


class BackendError(ValueError):
    """A backend that cannot run as asked (unknown name, Ray not installed, no cluster at the address)."""


def start_backend(backend: str, address: str | None = None, cpus: int | None = None) -> None:
    """Check a backend request before anything runs (:func:`check_backend`) and, for Ray, connect
    (:func:`connect_ray`): :class:`BackendError` naming what is wrong, Ray not installed, or an address where no
    cluster answers."""
    check_backend(backend, address, cpus)
    if backend == "ray":
        connect_ray(address, cpus)


def check_backend(backend: str, address: str | None = None, cpus: int | None = None) -> None:
    """The request alone, nothing started (what ``--dry-run`` checks): :class:`BackendError` naming an unknown
    backend, or Ray options without ``backend="ray"``."""
    if backend not in BACKENDS:
        raise BackendError(f"unknown backend {backend!r}; choose from {list(BACKENDS)}")
    if backend != "ray" and (address is not None or cpus is not None):
        raise BackendError(f"--address and --ray-cpus are for --backend ray, not {backend!r}")
    if cpus is not None and (address is not None or cpus < 1):
        raise BackendError(f"--ray-cpus {cpus}: the CPUs of a new local Ray instance (>= 1), not with --address")


def run_groups(groups: list, run: Callable, crashed: Callable, write: Callable, *, backend: str = "local",
               workers: int = 1, address: str | None = None, cpus: int | None = None) -> None:
    """Run ``run(group)`` for every group on ``backend`` and ``write`` every record as its group finishes; a group
    whose worker died twice is written as ``crashed(group, why)``. ``local``: a pool of ``workers`` processes (in
    this process when there is one worker or one group, on one thread as in a worker:
    :func:`bimp.agents.rollout.one_thread`); ``ray``: one task per group on the cluster."""
    if backend == "ray":
        run_ray(groups, run, crashed, write, address=address, cpus=cpus)
    elif workers > 1 and len(groups) > 1:
        run_local(groups, workers, run, crashed, write)
    else:
        for group in groups:
            for record in run(group):
                write(record)


def _ray():
    try:
        import ray
    except ImportError as err:
        raise BackendError(f"--backend ray needs Ray, which is not installed ({err}); install the extra with "
                           f"{INSTALL_RAY}") from None
    return ray


def init_worker() -> None:
    """What every worker process sets before it runs episodes (the environment variables of :data:`THREADS` must
    be set before numpy and JAX load: the pool's parent sets them, Ray's runtime environment does)."""
    import torch

    torch.set_num_threads(1)  # workers are the parallelism; oversubscribed threads only slow them down


def init_pool_worker(parent: int) -> None:
    """The local pool's initializer: the worker dies with ``parent`` (:func:`die_with`), then :func:`init_worker`."""
    die_with(parent)
    init_worker()


PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def die_with(parent: int) -> None:
    """End this process as soon as its parent process ``parent`` dies, however it dies (a pool worker outliving a
    SIGKILLed ``bimp evaluate`` would otherwise hold its memory under PID 1 until its group ends, or forever when
    idle: it holds both ends of its own call queue, so no EOF ever comes).

    Linux: the kernel sends SIGKILL when the parent *thread* that started this process exits
    (``PR_SET_PDEATHSIG``). That is safe for the pool: with the spawn context ``ProcessPoolExecutor`` starts its
    workers in ``submit``, i.e. in the thread running :func:`run_local`, which holds the pool until it shuts it down
    (only with ``max_tasks_per_child``, unused here, would its management thread start replacements). Elsewhere a
    daemon thread looks at ``os.getppid()`` every second: a process whose parent died is re-parented."""
    armed = False
    if sys.platform.startswith("linux"):
        try:
            armed = ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0
        except (OSError, AttributeError):  # no prctl in this libc: fall back to looking
            pass
    if os.getppid() != parent:  # it died before prctl ran, or before this look: no signal will come
        os._exit(1)
    if not armed:
        threading.Thread(target=_exit_when_orphaned, args=(parent,), name="die-with-parent", daemon=True).start()


def _exit_when_orphaned(parent: int) -> None:
    while os.getppid() == parent:
        time.sleep(1.0)
    os._exit(1)


# --- the local process pool ------------------------------------------------------------------------------------
def run_local(groups: list, workers: int, run: Callable, crashed: Callable, write: Callable) -> None:
    """Run ``run(group)`` for every group on ``workers`` spawned processes, at most ``workers`` groups in flight,
    and ``write`` each record it returns. When a worker dies, every group then in flight is a suspect: each is
    rerun alone on a fresh pool, and one that kills its worker alone is written as ``crashed(group, why)`` (never
    retried forever, never lost, never a hang)."""
    for var, value in THREADS.items():
        os.environ.setdefault(var, value)
    make = lambda: ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"),  # noqa: E731
                                       initializer=init_pool_worker, initargs=(os.getpid(),))
    # The workers die with this process however it ends (die_with), and multiprocessing's resource tracker, whose
    # pipe this process and the workers hold, then exits on its EOF: a killed `bimp evaluate` leaves nothing behind.
    # Groups travel with their place in the list: suspects rerun in that order, whatever order the broken pool's
    # futures were failed in.
    queue, suspects = deque(enumerate(groups)), []
    in_flight: dict = {}
    pool, broken = make(), False
    try:
        while queue or suspects or in_flight:
            if broken and not in_flight:
                pool.shutdown(wait=True, cancel_futures=True)
                pool, broken = make(), False
            try:
                if not broken and not any(alone for _, _, alone in in_flight.values()):
                    if suspects:  # a suspect runs alone: nothing else starts beside it, nor while others finish
                        if not in_flight:
                            future = pool.submit(run, suspects[0][1])  # raises before the group leaves its queue
                            in_flight[future] = (*suspects.pop(0), True)
                    else:
                        while queue and len(in_flight) < workers:
                            future = pool.submit(run, queue[0][1])
                            in_flight[future] = (*queue.popleft(), False)
            except BrokenProcessPool:  # it broke since the last look: the group stays queued
                broken = True
                if not in_flight:
                    continue
            done, _ = wait(in_flight, return_when=FIRST_COMPLETED)
            for future in [f for f in in_flight if f in done]:  # in the order submitted, not the set's
                index, group, alone = in_flight.pop(future)
                try:
                    for record in future.result():
                        write(record)
                except BrokenProcessPool:  # a group's first crash is always in company: alone is its second
                    broken = True
                    if alone:
                        for record in crashed(group, "the worker process running it died twice, the second time "
                                                     "running it alone"):
                            write(record)
                    else:
                        suspects.append((index, group))
                        suspects.sort(key=lambda suspect: suspect[0])
    finally:
        pool.shutdown(wait=False, cancel_futures=True)


# --- Ray ---------------------------------------------------------------------------------------------------------
def connect_ray(address: str | None = None, cpus: int | None = None):
    """The Ray module, connected: to the cluster at ``address`` (``HOST:PORT`` of its head, ``ray://HOST:PORT``
    for Ray Client, ``auto`` for a cluster started on this machine), else to a new local instance with ``cpus``
    CPUs (default: all). A process already connected (``ray.init`` by the caller, or an earlier evaluation) stays
    connected. :class:`BackendError` naming the address when no cluster answers there, before any episode runs."""
    ray = _ray()
    if ray.is_initialized():
        return ray
    if address not in (None, "auto"):
        _reachable(address)  # Ray itself waits minutes on an address where nothing listens
    try:
        if address is None:
            ray.init(address="local", num_cpus=cpus, include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address=address, log_to_driver=False)
    except (ConnectionError, ValueError, RuntimeError) as err:
        raise BackendError(f"--address {address!r}: cannot connect to a Ray cluster there ({err})") from None
    if ray.cluster_resources().get("CPU", 0) < 1:
        raise BackendError(f"the Ray cluster at {address or 'this machine'} has no CPU to run episodes on")
    return ray


def _reachable(address: str, timeout: float = 5.0) -> None:
    host, colon, port = address.removeprefix("ray://").rpartition(":")
    if not (colon and host and port.isdigit()):
        raise BackendError(f"--address {address!r}: expected HOST:PORT (the head's, from `ray start --head`), "
                           "ray://HOST:PORT or auto")
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as err:
        raise BackendError(f"--address {address!r}: no Ray cluster answers there ({err})") from None


def ray_options() -> dict:
    """Task options of every bimp task on Ray: one CPU, one retry after a dead worker or node, one thread."""
    return {"num_cpus": 1, "max_retries": 1, "runtime_env": {"env_vars": dict(THREADS)}}


def in_worker(function: Callable, *args):
    """``function(*args)`` in a Ray worker, after :func:`init_worker` (the body of every bimp task on Ray)."""
    init_worker()
    return function(*args)


def run_ray(groups: list, run: Callable, crashed: Callable, write: Callable, *, address: str | None = None,
            cpus: int | None = None) -> None:
    """Run ``run(group)`` for every group as a Ray task and ``write`` its records as each task finishes
    (``ray.wait``). A task whose worker (or node) dies is retried once by Ray; one that dies again, or fails in
    any other way Ray reports, is written as ``crashed(group, why)``. At most twice the cluster's CPUs are in
    flight: the rest wait in the driver, so a study of 10^4 groups does not hold 10^4 results in memory."""
    ray = connect_ray(address, cpus)
    task = ray.remote(in_worker).options(**ray_options())
    window = max(1, 2 * int(ray.cluster_resources().get("CPU", 1)))
    queue, in_flight = deque(groups), {}
    try:
        while queue or in_flight:
            while queue and len(in_flight) < window:
                group = queue.popleft()
                in_flight[task.remote(run, group)] = group
            (ref,), _ = ray.wait(list(in_flight), num_returns=1)
            group = in_flight.pop(ref)
            try:
                records = ray.get(ref)
            except ray.exceptions.RayError as err:  # WorkerCrashedError after the retry, NodeDiedError, ...
                records = crashed(group, f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}")
            for record in records:
                write(record)
    finally:
        for ref in in_flight:  # interrupted: nothing left running on the cluster for this driver
            ray.cancel(ref, force=True)


__all__ = ["BACKENDS", "BackendError", "connect_ray", "run_groups", "start_backend"]
