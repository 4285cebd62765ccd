"""A run's pairs processed in parallel worker processes with Dask: on one machine or a cluster.

Reconstruction and correlation treat every pair on its own, so a run spreads over workers one
pair per task. Each worker builds its operator (projector and weight cache, or correlator) once
and keeps it for every pair it gets, writes its volumes or vectors straight into the run store
(distinct chunks, so workers never write the same file), and returns only a summary. The
coordinator, the process that runs the ``lfpiv`` command, alone records which pairs are done,
as their tasks finish: the run store's bookkeeping attributes are rewritten whole, so two
writers would lose each other's pairs. A worker that fails or a Ctrl-C leaves every finished
pair recorded and readable.

``--workers N`` starts N worker processes on this machine (one per GPU on a multi-GPU
workstation: ``--device cuda`` gives worker i the GPU i modulo the GPUs found; on the CPU the
cores are shared out among them). ``--scheduler ADDRESS`` uses the workers of a running Dask
cluster (``dask scheduler`` and ``dask worker ADDRESS`` on the nodes, or a job-queue cluster
on a batch system); every worker must see the run store at the same absolute path.
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import tempfile
import threading
import uuid
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any, TypeVar

from tqdm import tqdm

from lfpiv.errors import UsageError

__all__ = ["connect_timeout_s", "dask_client", "map_pairs", "new_token", "open_run_on_worker", "this_worker_device",
           "worker_device", "worker_state"]

T = TypeVar("T")

#: Seconds ``--scheduler`` waits for the scheduler to answer before giving up with an error.
CONNECT_TIMEOUT_S = 10.0

# Per worker process: the operator of the job it is working on, built by its first task and
# reused by the next ones of the same job (token), replaced when a new job arrives.
_STATE: dict[str, Any] = {}


def connect_timeout_s() -> float:
    """``LFPIV_DASK_TIMEOUT_S`` if set, else :data:`CONNECT_TIMEOUT_S`."""
    try:
        return float(os.environ.get("LFPIV_DASK_TIMEOUT_S", CONNECT_TIMEOUT_S))
    except ValueError:
        raise UsageError("LFPIV_DASK_TIMEOUT_S must be a number of seconds") from None


def new_token() -> str:
    """A name for one command's job, under which workers keep its operator."""
    return uuid.uuid4().hex


@contextmanager
def dask_client(workers: int | None = None, scheduler: str | None = None) -> Iterator[Any]:
    """A Dask client for ``--workers`` or ``--scheduler``, or None for neither (run in this process).

    Parameters
    ----------
    workers
        Start this many single-threaded worker processes on this machine.
    scheduler
        Address of a running Dask scheduler, e.g. ``tcp://head-node:8786``.

    Raises
    ------
    UsageError
        Both given, a worker count below 1, or a scheduler that does not answer.
    """
    if workers is not None and scheduler is not None:
        raise UsageError("give --workers (processes on this machine) or --scheduler (a running Dask cluster), not both")
    if workers is None and scheduler is None:
        yield None
        return
    from distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            client = Client(scheduler, timeout=connect_timeout_s())
        except (OSError, TimeoutError, ValueError) as exc:
            raise UsageError(f"--scheduler {scheduler}: no Dask scheduler answered ({exc}); start one ('dask "
                             f"scheduler' and 'dask worker {scheduler}' on the nodes) or use --workers N") from None
        with client:
            if not client.scheduler_info().get("workers"):
                raise UsageError(f"--scheduler {scheduler}: the scheduler has no workers; start some with "
                                 f"'dask worker {scheduler}'")
            yield client
        return
    if workers < 1:
        raise UsageError(f"--workers must be at least 1, got {workers}")
    from lfcore.device import cpu_threads

    # the cores shared out among the workers' CPU launches
    share = max(1, cpu_threads() // workers)
    # processes, not threads: each worker has its own Warp context (and GPU), and the Python
    # parts of a reconstruction do not hold each other up on the interpreter lock
    # a task's error comes back to this process and is reported there once, as one line: the
    # workers' own logs of it would repeat it with a traceback
    # the workers' scratch space (spill files, their lock files) in a folder of this command's own,
    # removed with the cluster: nothing is left in $TMPDIR/dask-scratch-space
    import dask

    scratch = tempfile.mkdtemp(prefix="lfpiv-dask-")
    try:
        with dask.config.set({"temporary-directory": scratch}):
            with _quiet_worker_processes():
                cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                       dashboard_address=None, silence_logs=logging.CRITICAL,
                                       env={"LFPIV_CPU_THREADS": str(share)}, local_directory=scratch)
            with cluster, Client(cluster) as client:
                yield client
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


@contextmanager
def _quiet_worker_processes() -> Iterator[None]:
    """Start worker processes with SIGINT ignored (they inherit it): Ctrl-C reaches every process
    of the terminal's group, and it is this process that should stop, record what finished and
    shut the workers down, not each worker with a traceback of its own. Multiprocessing's
    resource tracker, started with them, is told not to warn about the semaphores of workers
    shut down mid-task."""
    env = os.environ.get("PYTHONWARNINGS")
    os.environ["PYTHONWARNINGS"] = ",".join(filter(None, [env, "ignore:resource_tracker:UserWarning"]))
    main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
    try:
        yield
    finally:
        if main:
            signal.signal(signal.SIGINT, previous)
        if env is None:
            del os.environ["PYTHONWARNINGS"]
        else:
            os.environ["PYTHONWARNINGS"] = env


def worker_device(device: str | None, worker_name: object, cuda_devices: Sequence[str]) -> str | None:
    """The device one worker uses.

    ``cpu`` and an explicit ``cuda:N`` are used as given. ``cuda`` (or None, ``auto``) on a
    machine with GPUs gives a local worker, named by its number, the GPU of that number modulo
    the GPUs found, so N workers on N GPUs take one each; a worker of another cluster (named by
    the cluster) gets the first GPU its process sees, which batch systems usually choose.
    """
    if device not in (None, "auto", "cuda") or not cuda_devices:
        return device
    if isinstance(worker_name, int):
        return cuda_devices[worker_name % len(cuda_devices)]
    return device


def this_worker_device(device: str | None) -> str:
    """:func:`worker_device` for the worker process calling it, resolved to a Warp device name.

    Raises
    ------
    ComputeDeviceError
        If the worker has no such device, naming the worker.
    """
    from distributed import get_worker

    from lfcore.device import ComputeDeviceError, available_devices, resolve_device

    name = get_worker().name
    try:
        return resolve_device(worker_device(device, name, [d for d in available_devices() if d.startswith("cuda")]))
    except ComputeDeviceError as exc:
        raise ComputeDeviceError(f"Dask worker {name}: {exc}") from None


def open_run_on_worker(path: str, writer: str | None = None) -> Any:
    """The run store at ``path``, opened for writing by the worker process calling it.

    ``writer`` is the coordinator's :attr:`lfcore.runstore.RunStore.writer_token`: the
    coordinator holds the store's writer lock while its workers write distinct chunks, and a
    worker on another host of a cluster shows the token to share it.

    Raises
    ------
    RunStoreError
        If the worker cannot open it, naming the worker and the shared path it needs.
    """
    from distributed import get_worker

    from lfcore.runstore import RunStore, RunStoreError

    try:
        return RunStore.open(path, mode="r+", shared_with=writer)
    except RunStoreError as exc:
        raise RunStoreError(f"Dask worker {get_worker().name}: {exc} (every worker must see the run store at the "
                            "same absolute path: a shared file system)") from None


def worker_state(token: str, build: Callable[[], T]) -> T:
    """The operator of job ``token`` in this worker process, built on first use.

    A new token drops the previous job's operator first, so a worker holds one job's device
    memory at a time.

    Raises
    ------
    UsageError
        If the worker runs tasks on several threads, which would share the operator at once.
    """
    from distributed import get_worker

    worker = get_worker()
    if worker.state.nthreads > 1:
        # tasks on threads of one worker would share its operator's device buffers at once
        raise UsageError(f"Dask worker {worker.name} runs {worker.state.nthreads} threads; lfpiv needs workers of "
                         "one thread each: start them with 'dask worker ADDRESS --nthreads 1'")
    if _STATE.get("token") != token:
        _STATE.clear()
        _STATE["value"] = build()
        _STATE["token"] = token
    return _STATE["value"]


def map_pairs(client: Any, task: Callable[..., T], job: Any, pairs: Iterable[int], *,
              on_done: Callable[[int, T], None], desc: str, progress: bool = True,
              postfix: Callable[[int, T], dict[str, Any]] | None = None) -> None:
    """Run ``task(job, pair)`` on the cluster for every pair; ``on_done(pair, result)`` here, in
    the order the tasks finish, and the progress bar shows ``postfix(pair, result)`` (its fields)
    where it is given.

    No more tasks are given out than the cluster has worker threads, so after a failure the
    others given out are all under way: they are waited for, the pairs among them that succeed
    passed to ``on_done``, and then the first error is raised, as one line when it is the
    cluster's (a worker that died). Ctrl-C cancels them instead: local workers stop with the
    command, a cluster's worker finishes the pair it is on.

    Raises
    ------
    UsageError
        If the cluster lost a task (its worker died, the scheduler went away).
    Exception
        The first task's own error, with its type.
    """
    from distributed import as_completed

    todo = list(pairs)[::-1]
    given: dict[Any, int] = {}

    def give_out() -> list[Any]:
        # the cluster may grow or shrink while it works (an adaptive job-queue cluster)
        free = max(1, sum(client.nthreads().values())) - len(given)
        out = []
        for _ in range(min(free, len(todo))):
            p = todo.pop()
            fut = client.submit(task, job, p, key=f"{desc}-{p}-{uuid.uuid4().hex[:8]}", pure=False)
            given[fut] = p
            out.append(fut)
        return out

    first: BaseException | None = None
    try:
        with tqdm(total=len(todo), unit="pair", disable=not progress, desc=desc, leave=False) as bar:
            running = as_completed(give_out())
            for fut in running:
                p = given.pop(fut)
                try:
                    result = fut.result()  # a task's exception is raised here, with its type
                except Exception as exc:
                    if first is None:
                        first = _task_error(exc, p)
                    continue
                on_done(p, result)
                if postfix is not None:
                    bar.set_postfix(postfix(p, result), refresh=False)
                bar.update(1)
                if first is None:
                    running.update(give_out())
    finally:
        client.cancel(list(given))
        _forget_job(client, job)
    if first is not None:
        raise first


def _task_error(exc: Exception, pair: int) -> Exception:
    """A task's own error as it is; the cluster's (a lost worker or connection) as one line."""
    from concurrent.futures import CancelledError

    from distributed.comm.core import CommClosedError
    from distributed.scheduler import KilledWorker

    if isinstance(exc, KilledWorker | CommClosedError | CancelledError):
        return UsageError(f"pair {pair}: the Dask cluster lost its task ({type(exc).__name__}: {exc}); a worker that "
                          "died, often out of memory, is the usual cause: give the workers more memory, run fewer "
                          "per machine or use a coarser --pvr")
    return exc


def _forget_job(client: Any, job: Any) -> None:
    """Drop the job's operator (device memory) from workers that outlive the command."""
    token = getattr(job, "token", None)
    try:
        client.run(_forget_state, token, on_error="ignore")
    except Exception:  # a cluster going away has nothing left to free
        pass


def _forget_state(token: str | None) -> None:
    if _STATE.get("token") == token:
        _STATE.clear()
