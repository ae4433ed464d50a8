"""Many independent tasks on dask.distributed: a local cluster or one the user already runs.

Sweeps, Monte Carlo studies and the diagnose recognition study are the same job: a function over
a list of items, each result wanted as soon as it is ready. This module runs that job on
`dask.distributed <https://distributed.dask.org>`_, an engine users already operate, rather than a
home-made pool::

    from piezo_fmu.parallel import map_as_completed
    for i, result in map_as_completed(run_case, cases, scheduler="tcp://10.0.0.5:8786"):
        ...                                     # i: the item's position in ``cases``

* **Where.** Without a scheduler address, a :class:`distributed.LocalCluster` sized to the machine
  (one single-threaded worker process per core: the simulations hold the GIL); with one, the
  existing cluster, whose workers must have piezo-fmu installed. ``workers=0`` runs everything
  in this process, in order, without dask (for debugging and for the serial reference).
* **Batching.** A dask task costs a few milliseconds of scheduling and transfer (measured on a
  shared 2-core machine: 3-5 ms of CPU in the scheduler's process and about 3 ms in the worker);
  a compiled closed-loop run can take less. Items are therefore sent in batches sized from the
  measured time per item (median, so a worker's first call that compiles numba does not count)
  to take about ``target_task_s`` each, while a few batches per worker are kept in flight and the
  last ones shrink so that all workers finish together, but not below ``TAIL_FRACTION`` of
  ``target_task_s`` and leaving no smaller remainder (a tail of one-item tasks spent as much CPU
  on dask as on the items). Batches are formed in item order as workers ask, so results never
  depend on the number of workers: only on ``fn`` and the item.
* **Quiet local workers.** The local cluster runs with :data:`LOCAL_CLUSTER_CONFIG`: no
  statistical profiler (it samples each worker's stack every 10 ms for a dashboard that is not
  started) and slower housekeeping (event-loop watchdog, system and memory monitors). Idle, a
  2-worker cluster with dask's defaults burned about 50 ms of CPU per second in the scheduler's
  process and 35-40 ms per worker; with these settings about 10 and 3 ms (same machine). When
  the tasks keep every core busy, that CPU is taken from them. A setting the user made (dask
  config file, ``DASK_*`` variable: a value other than dask's default) is kept.
* **Worker loss.** Tasks are pure (same function and items: same result), so when a worker dies
  the scheduler runs its tasks again elsewhere. A batch that keeps killing workers (dask gives up
  after ``distributed.scheduler.allowed-failures`` deaths) is split into single items; an item
  that still fails is reported as :class:`TaskFailed` (``errors="return"``) or raised.
* **Shared data.** ``context`` (e.g. a model and its FMUs) is sent to every worker once and
  handed to ``fn(context, item)``; only the items travel with the tasks.
* **Shutdown.** :class:`Engine` is a context manager: leaving it (also on Ctrl-C) cancels what is
  still pending and closes the client and a cluster it started.
"""
from __future__ import annotations

import logging
import math
import os
import statistics
import time
from collections import deque

from .errors import UserError

__all__ = ["LOCAL_CLUSTER_CONFIG", "Engine", "TaskFailed", "local_workers", "map_as_completed"]

#: dask settings of the local cluster an :class:`Engine` starts (its scheduler, nannies and
#: workers), instead of dask's defaults given in the comments: housekeeping that serves the
#: dashboard or reacts within milliseconds costs CPU the tasks need.
LOCAL_CLUSTER_CONFIG = {
    "distributed.worker.profile.enabled": False,             # True: stack samples every 10 ms
    "distributed.admin.tick.interval": "1s",                 # 20ms: event-loop watchdog
    "distributed.admin.system-monitor.interval": "1s",       # 500ms: CPU/memory/network metrics
    "distributed.worker.memory.monitor-interval": "500ms",   # 100ms: the nanny's memory limit check
    # 65536: set in every worker's environment, it fixes glibc's trim threshold, which also turns
    # off glibc's adaptive mmap threshold, so every array over 128 KiB is a fresh mmap with its page
    # faults: a diagnosis (rig-004) took 60 s in a worker against 27 s in a plain process
    "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
}
TAIL_FRACTION = 0.1     # the smallest batch: this fraction of target_task_s
WORKERS_REFRESH_S = 1.0  # how often map asks the scheduler how many workers there are [s]


class TaskFailed(Exception):
    """An item whose task did not produce a result: ``fn`` raised (with ``errors="return"``), or
    the workers running it kept dying. ``str()`` says which."""


def local_workers() -> int:
    """Worker processes of a local cluster: the cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:          # not on Linux
        return max(1, os.cpu_count() or 1)


def local_cluster_config() -> dict:
    """:data:`LOCAL_CLUSTER_CONFIG` without the keys the user configured (dask config file,
    ``DASK_*`` environment variable or :func:`dask.config.set`: a value other than dask's
    default), which are kept."""
    import dask
    import distributed  # noqa: F401 - registers its defaults (importing inside config.set loses them)

    defaults = dask.config.merge(*dask.config.defaults)
    out = {}
    for key, value in LOCAL_CLUSTER_CONFIG.items():
        try:
            if dask.config.get(key) != dask.config.get(key, config=defaults):
                continue
        except KeyError:        # a key this version of distributed does not know: harmless
            pass
        out[key] = value
    return out


def _call(fn, context, item, has_context):
    return fn(context, item) if has_context else fn(item)


def _run_batch(fn, context, batch, has_context, catch):
    """Run ``fn`` on each ``(position, item)`` of ``batch`` in a worker.

    Returns ``[(position, result, seconds), ...]``; with ``catch`` an exception of one item becomes
    its :class:`TaskFailed` result instead of failing the whole batch."""
    out = []
    for pos, item in batch:
        t0 = time.perf_counter()
        if catch:
            try:
                res = _call(fn, context, item, has_context)
            except Exception as exc:  # noqa: BLE001 - returned to the caller, named
                res = TaskFailed(f"{type(exc).__name__}: {exc}")
        else:
            res = _call(fn, context, item, has_context)
        out.append((pos, res, time.perf_counter() - t0))
    return out


def _name(fn) -> str:
    return getattr(fn, "__name__", None) or getattr(getattr(fn, "func", None), "__name__", "task")


class Engine:
    """A dask.distributed client: a local cluster or an existing scheduler.

    Parameters
    ----------
    scheduler : str, optional
        Address of a running scheduler, e.g. ``"tcp://10.0.0.5:8786"``; ``None`` starts a local
        cluster.
    workers : int, optional
        Local cluster: the number of worker processes (default: :func:`local_workers`). Existing
        scheduler: wait until that many workers have joined. ``0``: no dask at all, every item
        runs in this process, in order.
    timeout : float
        Seconds to wait for the scheduler to answer (and for ``workers`` to join) [s].

    Examples
    --------
    >>> with Engine(workers=2) as engine:              # doctest: +SKIP
    ...     engine.warm(compile_kernels)               # once on every worker
    ...     for i, r in engine.map(fn, items, progress=print):
    ...         keep(i, r)
    """

    def __init__(self, scheduler=None, workers=None, timeout=30.0):
        self.scheduler = scheduler
        self.client = None
        self.cluster = None
        self.tasks = 0              # tasks submitted by map (batches), for measuring the overhead
        if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 0):
            raise UserError(f"--workers: must be a whole number >= 0, got {workers!r}")
        self.serial = workers == 0
        if self.serial:
            if scheduler:
                raise UserError("--workers 0 runs in this process; it cannot be combined with --scheduler")
            return
        try:
            from distributed import Client, LocalCluster
        except ImportError:       # pragma: no cover - a dependency of piezo-fmu
            raise UserError("dask.distributed is not installed (pip install 'dask[distributed]')") from None
        if scheduler:
            try:
                self.client = Client(scheduler, timeout=timeout, set_as_default=False)
            except (OSError, TimeoutError) as exc:
                raise UserError(f"--scheduler {scheduler}: cannot connect ({exc}); is `dask scheduler` "
                                "running there and the address tcp://HOST:PORT?") from None
            except (ValueError, TypeError) as exc:
                raise UserError(f"--scheduler {scheduler}: not a scheduler address ({exc}); "
                                "expected tcp://HOST:PORT") from None
            if workers:
                try:
                    self.client.wait_for_workers(workers, timeout=timeout)
                except TimeoutError:
                    n = self.n_workers
                    self.close()
                    raise UserError(f"--workers {workers}: only {n} worker(s) joined {scheduler} "
                                    f"within {timeout:g} s") from None
        else:
            import dask

            n = workers or local_workers()
            with dask.config.set(local_cluster_config()):     # read as the servers start
                self.cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                            dashboard_address=None, silence_logs=logging.ERROR)
                self.client = Client(self.cluster, set_as_default=False)

    # -- life cycle ----------------------------------------------------------------------------
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        """Close the client and the local cluster, if one was started (idempotent)."""
        client, cluster = self.client, self.cluster
        self.client = self.cluster = None
        if client is not None:
            try:
                client.close()
            except Exception:  # noqa: BLE001, S110 - closing a client whose scheduler is gone
                pass
        if cluster is not None:
            try:
                cluster.close()
            except Exception:  # noqa: BLE001, S110 - a cluster already gone
                pass

    @property
    def n_workers(self) -> int:
        """Workers connected now (1 in serial mode)."""
        if self.serial or self.client is None:
            return 1
        try:
            return len(self.client.scheduler_info(n_workers=-1)["workers"])
        except TypeError:        # older distributed: no n_workers argument
            return len(self.client.scheduler_info()["workers"])

    def describe(self) -> str:
        if self.serial:
            return "serial, in this process"
        where = self.scheduler or "local cluster"
        return f"dask.distributed, {where}, {self.n_workers} worker(s)"

    # -- work ------------------------------------------------------------------------------------
    def warm(self, fn, *args):
        """Run ``fn(*args)`` once on every connected worker (e.g. compile kernels) and wait.

        Workers that join later run it when their first task calls it, if ``fn`` is how tasks
        start; that is ``fn``'s business (make it idempotent and cheap the second time)."""
        if self.serial:
            fn(*args)
            return
        addrs = list(self.client.scheduler_info()["workers"])
        futs = [self.client.submit(fn, *args, workers=[a], allow_other_workers=False, pure=False)
                for a in addrs]
        self.client.gather(futs, errors="skip")

    def map(self, fn, items, *, context=None, progress=None, errors="raise", target_task_s=0.5,
            max_batch=256):
        """Yield ``(position, result)`` for every item as results complete (any order).

        Parameters
        ----------
        fn : callable
            ``fn(item)``, or ``fn(context, item)`` when ``context`` is given; must be picklable
            (a module-level function or a ``functools.partial`` of one) and pure: the same item
            gives the same result, wherever and however often it runs.
        items : sequence
            Picklable items; ``position`` is an item's index in it.
        context : object, optional
            Shared read-only data sent to each worker once (not with every task).
        progress : callable, optional
            ``progress(fraction, message)`` after each completed batch (fraction of the items).
        errors : {"raise", "return"}
            An exception of ``fn`` (or an item whose workers kept dying) is raised here, or
            yielded as a :class:`TaskFailed` result and the other items go on.
        target_task_s : float
            Aimed wall time of one task [s]: longer amortises dask's per-task cost (a few ms),
            shorter loses less work when a worker dies and balances better. The last batches
            shrink to balance the workers, down to ``TAIL_FRACTION * target_task_s``.
        max_batch : int
            Most items in one task.
        """
        if errors not in ("raise", "return"):
            raise ValueError(f"errors: 'raise' or 'return', got {errors!r}")
        items = list(items)
        total = len(items)
        has_context = context is not None
        catch = errors == "return"
        if total == 0:
            return
        if self.serial:
            yield from self._map_serial(fn, items, context, has_context, catch, progress)
            return
        yield from self._map_dask(fn, items, context, has_context, catch, progress, target_task_s,
                                  max_batch)

    def _map_serial(self, fn, items, context, has_context, catch, progress):
        for pos, item in enumerate(items):
            self.tasks += 1
            (_, res, _), = _run_batch(fn, context, [(pos, item)], has_context, catch)
            yield pos, res
            if progress is not None:
                progress((pos + 1) / len(items), f"{pos + 1}/{len(items)}")

    def _map_dask(self, fn, items, context, has_context, catch, progress, target_task_s, max_batch):
        from dask.base import tokenize
        from distributed import as_completed

        client = self.client
        total = len(items)
        ctx = client.scatter(context, broadcast=True, hash=False) if has_context else None
        ctx_token = tokenize(ctx.key if ctx is not None else None)
        prefix = _name(fn)
        todo = deque(range(total))          # positions not yet submitted, in order
        singles = deque()                   # positions of batches that failed, run one by one
        times = deque(maxlen=256)           # recent seconds per item
        done = 0
        ac = as_completed(loop=client.loop)
        pending = {}                        # key -> (future, positions)

        workers_seen = [0, -math.inf]       # workers, time.monotonic() when asked

        def n_workers():
            # the scheduler's answer lists every worker: asked at most every WORKERS_REFRESH_S
            now = time.monotonic()
            if now - workers_seen[1] >= WORKERS_REFRESH_S:
                workers_seen[:] = [max(1, self.n_workers), now]
            return workers_seen[0]

        def batch_size(n_workers):
            if not times:
                return 1
            per_item = max(statistics.median(times), 1e-6)
            size = int(target_task_s / per_item) or 1
            smallest = int(TAIL_FRACTION * target_task_s / per_item) or 1
            tail = max(math.ceil(len(todo) / (2 * n_workers)), smallest)    # the last batches shrink
            size = max(1, min(size, max_batch, tail))
            if len(todo) - size < smallest:             # no smaller remainder after this batch
                size = min(len(todo), max_batch)
            return size

        def submit(positions):
            batch = [(p, items[p]) for p in positions]
            key = f"{prefix}-{tokenize(fn, ctx_token, batch, has_context, catch)}"
            fut = client.submit(_run_batch, fn, ctx, batch, has_context, catch, key=key, pure=True)
            self.tasks += 1
            pending[fut.key] = (fut, positions)
            ac.add(fut)

        def fill():
            n = n_workers()
            while (todo or singles) and ac.count() < 2 * n:
                if singles:
                    submit([singles.popleft()])
                    continue
                size = batch_size(n)
                submit([todo.popleft() for _ in range(min(size, len(todo)))])

        try:
            fill()
            for fut in ac:
                positions = pending.pop(fut.key)[1]
                if fut.status == "finished":
                    results = fut.result()
                    fut.release()
                    for pos, res, seconds in results:
                        times.append(seconds)
                        done += 1
                        yield pos, res
                else:
                    status = fut.status
                    exc = fut.exception() if status == "error" else TaskFailed(f"task {status}")
                    fut.release()
                    lost = status != "error" or type(exc).__name__ in ("KilledWorker", "CommClosedError")
                    if lost and len(positions) > 1:
                        singles.extend(positions)          # find the item that kills workers
                    elif catch:
                        why = (f"the worker running it died repeatedly ({exc})" if lost
                               else f"{type(exc).__name__}: {exc}")
                        for pos in positions:
                            done += 1
                            yield pos, TaskFailed(why)
                    else:
                        raise exc
                if progress is not None:
                    progress(done / total, f"{done}/{total}, {n_workers()} worker(s)")
                fill()
        finally:
            if pending:
                client.cancel([f for f, _ in pending.values()])
            ac.clear()
            if ctx is not None:
                ctx.release()


def map_as_completed(fn, items, *, scheduler=None, workers=None, context=None, progress=None,
                     errors="raise", warm=None, **options):
    """Run ``fn`` over ``items`` on an :class:`Engine` opened for the purpose; yield
    ``(position, result)`` as results complete, then shut the engine down.

    ``warm``: a function run once on every worker before the items (see :meth:`Engine.warm`);
    other arguments as :class:`Engine` and :meth:`Engine.map`.

    Examples
    --------
    >>> results = dict(map_as_completed(abs, [-1, -2, 3], workers=0))
    >>> [results[i] for i in range(3)]
    [1, 2, 3]
    """
    with Engine(scheduler, workers) as engine:
        if warm is not None:
            engine.warm(warm)
        yield from engine.map(fn, items, context=context, progress=progress, errors=errors, **options)
