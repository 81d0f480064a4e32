"""Where tap tasks run: local processes or a Ray cluster, results yielded as they finish.

Both executors run the tasks they are given (``Tasks``: ``scenes.generate.TASKS``, whose
tap task returns a sample's record and its files' encoded bytes and writes nothing); the
caller (the driver) writes every file. The plugin's
large shared inputs reach each worker process once: through the pool's initializer
locally, through Ray's object store (``ray.put`` once, the ObjectRef passed to every
task) on a cluster. Ray is imported here only, and only for ``executor="ray"``.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import socket
from collections.abc import Callable, Iterable, Iterator
from typing import Any, NamedTuple

EXECUTORS = ("local", "ray")
#: Seconds to wait for a Ray head's port to accept a connection before calling it unreachable.
CONNECT_TIMEOUT_S = 5.0
#: Tap tasks in flight per CPU of the cluster: enough to keep every worker busy while the
#: driver writes files, few enough that results never pile up in the object store.
TASKS_PER_CPU = 2
#: Options of every Ray render task: a CPU each, spread over the cluster's nodes (a short
#: render would otherwise stay on the driver's node while another node's worker is still
#: starting; seen on a loaded machine).
RAY_TASK = {"num_cpus": 1, "scheduling_strategy": "SPREAD"}
#: Taps a local pool process takes at a time.
LOCAL_CHUNK = 4
#: Environment of every worker process. Mesa's software rasteriser starts a thread per
#: core in each process; with one process per core they only contend.
WORKER_ENV = {"LP_NUM_THREADS": "1"}
RAY_INSTALL = "pip install 'tactile-sim[ray]'"

#: One (kind, value) per result: ("tap", the tap task's dict) or ("background", image).
Results = Iterator[tuple[str, object]]


class Tasks(NamedTuple):
    """What an executor runs: module-level functions, so that they reach every worker by
    reference (``scenes.generate.TASKS``)."""

    #: (job, tap, shared) -> the tap's result (``scenes.generate.run_tap``).
    tap: Callable[[Any, Any, Any], dict]
    #: (job, shared) -> (H, W, 3) float image, the no-contact frame (``scenes.generate.no_contact``).
    no_contact: Callable[[Any, Any], Any]


def make_executor(executor: str, workers: int, address: str | None = None):
    """The executor called ``executor``, its inputs checked before any work.

    Parameters
    ----------
    executor : ``"local"`` or ``"ray"``.
    workers : local processes; for ``"ray"``, the CPUs of a cluster started on this
        machine (unused with ``address``: the cluster's own CPUs count).
    address : ``HOST:PORT`` of a running Ray cluster's head (``ray start --head``), or
        None to start one here. Only with ``"ray"``.
    """
    if executor not in EXECUTORS:
        raise ValueError(f"executor must be one of {EXECUTORS}, got {executor!r}")
    if address is not None and executor != "ray":
        raise ValueError(f"address is for executor 'ray' only, got address {address!r} with executor {executor!r}")
    if executor == "local":
        return LocalExecutor(workers)
    try:
        import ray
    except ImportError:
        raise ValueError(f"executor 'ray' needs Ray, which is not installed: {RAY_INSTALL}") from None
    if address is not None:
        if ray.is_initialized():
            raise ValueError(f"address {address!r}: this process is already connected to a Ray cluster; call "
                             "ray.shutdown() first, or leave address unset to use that connection")
        check_reachable(address)
    return RayExecutor(workers, address)


def check_reachable(address: str, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
    """Raise ValueError unless ``address`` (``HOST:PORT``, ``ray://HOST:PORT`` or
    ``auto``) accepts a TCP connection within ``timeout_s``.

    Ray itself retries an unreachable head for many minutes; this fails at once.
    """
    if address == "auto":
        return
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        raise ValueError(f"address must be HOST:PORT of a Ray head, e.g. 10.0.0.5:6379, got {address!r}")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except OSError as exc:
        raise ValueError(f"address {address!r} cannot be reached within {timeout_s:g} s ({exc}); start the head "
                         f"with 'ray start --head' and pass its HOST:6379") from None


# --- Local processes -------------------------------------------------------------------------

_TASKS: Tasks | None = None
_JOB = None
_SHARED = None


def _init_process(tasks: Tasks, job, shared) -> None:
    global _TASKS, _JOB, _SHARED
    for key, value in WORKER_ENV.items():
        os.environ.setdefault(key, value)
    _TASKS, _JOB, _SHARED = tasks, job, shared


def _pool_tap(tap):
    return _TASKS.tap(_JOB, tap, _SHARED)


def _pool_no_contact(_=None):
    return _TASKS.no_contact(_JOB, _SHARED)


class LocalExecutor:
    """Tap tasks in a spawn pool of ``workers`` processes, or in this one for a single worker."""

    def __init__(self, workers: int):
        self.workers = workers

    def run(self, tasks: Tasks, job, taps: list, shared=None, background: bool = False) -> Results:
        """``tasks`` of ``job`` on ``taps``, with the no-contact image if ``background``."""
        if self.workers == 1 or len(taps) <= 1:
            if background:
                yield "background", tasks.no_contact(job, shared)
            for tap in taps:
                yield "tap", tasks.tap(job, tap, shared)
            return
        ctx = multiprocessing.get_context("spawn")  # EGL contexts must not cross a fork
        with ctx.Pool(self.workers, initializer=_init_process, initargs=(tasks, job, shared)) as pool:
            image = pool.apply_async(_pool_no_contact) if background else None
            for result in pool.imap_unordered(_pool_tap, taps, chunksize=LOCAL_CHUNK):
                yield "tap", result
            if image is not None:
                yield "background", image.get()


# --- Ray -------------------------------------------------------------------------------------


class RayExecutor:
    """Tap tasks on a Ray cluster: the one at ``address``, or one started here with
    ``workers`` CPUs. A connection this process already has (``ray.init`` by the caller)
    is used as it is and left open."""

    def __init__(self, workers: int, address: str | None = None):
        self.workers = workers
        self.address = address

    def _connect(self) -> bool:
        """Connect (or start a local cluster); True when this call did, and must shut down."""
        import ray

        if ray.is_initialized():
            return False
        common = {"runtime_env": {"env_vars": WORKER_ENV}, "logging_level": logging.WARNING}
        if self.address is None:
            # "local": a new cluster here, even where RAY_ADDRESS or 'ray start' names another.
            ray.init(address="local", num_cpus=self.workers, include_dashboard=False, **common)
            return True
        try:
            ray.init(address=self.address, **common)
        except ConnectionError as exc:
            raise ValueError(f"address {self.address!r}: no Ray cluster answers there ({exc})") from None
        return True

    def run(self, tasks: Tasks, job, taps: Iterable, shared=None, background: bool = False) -> Results:
        """``tasks`` of ``job`` on ``taps``, with the no-contact image if ``background``."""
        import ray

        owned = self._connect()
        try:
            shared_ref = ray.put(shared)  # once; every task gets the same ObjectRef
            tap_task = ray.remote(**RAY_TASK)(tasks.tap)
            pending = {}
            if background:
                pending[ray.remote(**RAY_TASK)(tasks.no_contact).remote(job, shared_ref)] = "background"
            limit = TASKS_PER_CPU * max(1, int(ray.cluster_resources().get("CPU", self.workers)))
            for tap in taps:
                pending[tap_task.remote(job, tap, shared_ref)] = "tap"
                if len(pending) >= limit:  # bounded: results are recorded as they come
                    yield from self._some(pending)
            while pending:
                yield from self._some(pending)
        finally:
            if owned:
                ray.shutdown()

    @staticmethod
    def _some(pending: dict) -> Results:
        """Wait for at least one pending task; yield every finished one, forgetting it."""
        import ray

        done, _ = ray.wait(list(pending), num_returns=1)
        for ref in done:
            yield pending.pop(ref), ray.get(ref)
