"""Plan a batch and run its tasks on Dask: a local cluster of processes, an existing cluster's scheduler, or
a client the caller brings.

:func:`plan` turns the inputs into the fleet table's rows in their final order: rows of recordings that
cannot be processed (:mod:`replay.batch.inputs`), rows stored with complete outputs (resumed, unless
``force``), and a :class:`~replay.batch.tasks.Task` for each of the others. :func:`execute` submits the
tasks, one Dask task per recording, and collects their rows as they finish, with a progress bar.

Failures stay rows: a task's own failure comes back as its row (:func:`~replay.batch.tasks.run_task`); a
task whose worker died is rescheduled by Dask on another worker, and after
``distributed.scheduler.allowed-failures`` deaths (a recording that kills its worker) it is an ``error``
row too. Interrupted (Ctrl-C), the batch cancels the tasks not finished: the recordings in flight have no
output folder and the next run does them.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import sys
import threading
import time
import uuid
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, field
from multiprocessing import resource_tracker
from pathlib import Path

from replay.batch.inputs import find_recordings
from replay.batch.table import error_row
from replay.batch.tasks import OPTIONS, Task, completed_row, run_task
from replay.errors import InputError


@dataclass
class Plan:
    """A batch before it runs.

    Attributes
    ----------
    command : str
    out_dir : Path
        Absolute.
    rows : list of dict or None
        The fleet table in its final order; None where a task's row goes.
    tasks : list of Task
        The recordings to process.
    slots : list of int
        ``rows`` index of each task's row.
    n_resumed : int
        Rows taken from complete outputs of an earlier run.
    """

    command: str
    out_dir: Path
    rows: list = field(default_factory=list)
    tasks: list = field(default_factory=list)
    slots: list = field(default_factory=list)
    n_resumed: int = 0

    def table(self, task_rows) -> list[dict]:
        """The complete table, with ``task_rows`` (one per task, in task order) in their places."""
        rows = list(self.rows)
        for slot, row in zip(self.slots, task_rows, strict=True):
            rows[slot] = row
        return rows


def plan(command: str, inputs, out_dir, options: dict | None = None, calibration=None,
         force: bool = False) -> Plan:
    """Plan a batch of ``command`` over ``inputs`` into ``out_dir``.

    Parameters
    ----------
    command : str
        ``replay``, ``calibrate`` or ``diagnose``.
    inputs : sequence of path
        Recordings, folders and manifests (:mod:`replay.batch.inputs`).
    out_dir : path
        The output folder (created).
    options : dict, optional
        The command's options (:data:`replay.batch.tasks.OPTIONS`; unknown names are a ValueError).
    calibration : path, optional
        ``replay``: the calibration file of the recordings for which a manifest gives none.
    force : bool
        Redo recordings whose outputs are complete.
    """
    if command not in OPTIONS:
        raise ValueError(f"command: expected one of {sorted(OPTIONS)}, got {command!r}")
    opts = dict(OPTIONS[command])
    for k, v in (options or {}).items():
        if k not in opts:
            raise ValueError(f"options: {command} has no option {k!r} (known: {sorted(opts)})")
        opts[k] = v
    out = Path(os.path.abspath(out_dir))
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(out_dir, f"cannot create the output folder ({exc.strerror})") from None
    p = Plan(command, out)
    for item in find_recordings(inputs, skip=[out]):
        if item.error is not None:
            p.rows.append(error_row(item.label, item.error))
            continue
        cal = item.calibration if item.calibration is not None else calibration
        cal = None if command != "replay" or cal is None else str(cal)
        task = Task(command, item.label, item.path, item.key, str(out), opts, cal,
                    None if cal is None else os.path.abspath(cal))
        done = None if force else completed_row(task)
        if done is not None:
            p.rows.append(done)
            p.n_resumed += 1
        else:
            p.slots.append(len(p.rows))
            p.rows.append(None)
            p.tasks.append(task)
    return p


def default_workers() -> int:
    """The cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        return os.cpu_count() or 1


#: The port Dask's dashboard usually has; a local cluster's dashboard takes it when it is free.
DASHBOARD_PORT = 8787


def _dashboard_address() -> str:
    """``:8787`` when that port is free here, else ``:0`` (a free port the system picks): Dask would otherwise
    warn that the port is in use (another cluster's dashboard) before taking another one."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("", DASHBOARD_PORT))
        except OSError:
            return ":0"
    return f":{DASHBOARD_PORT}"


@contextmanager
def dask_client(workers: int | None = None, scheduler: str | None = None, dashboard: bool = False):
    """A ``distributed.Client``: of the cluster at ``scheduler``, else of a local cluster of ``workers``
    single-threaded worker processes (default :func:`default_workers`), started here and stopped on exit.

    A local cluster has a dashboard only when asked (``dashboard``: on port :data:`DASHBOARD_PORT` if free,
    else on any free port; ``client.dashboard_link`` says where). Without one, the scheduler's HTTP endpoints
    (health checks) listen on a free port of the loopback interface: no port is taken that another
    cluster's dashboard might hold, and nothing is said about it.
    """
    from distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            client = Client(scheduler, timeout="10s")
        except (OSError, TimeoutError, ValueError) as exc:
            raise InputError(scheduler, f"cannot connect to the Dask scheduler ({exc})") from None
        try:
            yield client
        finally:
            client.close()
        return
    log = logging.getLogger("distributed")
    level = log.level
    log.setLevel(logging.CRITICAL)  # the cluster is ours: its logs (also at shutdown) are noise here
    cluster = client = None
    try:
        # The worker processes inherit an ignored SIGINT: Ctrl-C on the terminal reaches the whole process
        # group, and it is this process that stops the batch and the cluster (the workers go with it).
        # (Signal handlers can only be set from the main thread; elsewhere the workers keep the default.)
        main = threading.current_thread() is threading.main_thread()
        handler = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
        _quiet_resource_tracker()
        try:
            http = {"dashboard_address": _dashboard_address()} if dashboard else {
                "dashboard_address": None, "scheduler_kwargs": {"dashboard_address": "127.0.0.1:0"}}
            cluster = LocalCluster(n_workers=workers or default_workers(), threads_per_worker=1,
                                   processes=True, silence_logs=logging.CRITICAL, **http)
        finally:
            if main:
                signal.signal(signal.SIGINT, handler)
        client = Client(cluster)
        yield client
    finally:
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()
        log.setLevel(level)


def _running(client) -> int:
    """Tasks executing now: those assigned to each worker, up to its thread count (a worker also holds
    tasks queued for it)."""
    threads = client.nthreads()
    return sum(min(len(keys), threads.get(w, 1)) for w, keys in client.processing().items())


class Interrupted(KeyboardInterrupt):
    """Ctrl-C during :func:`execute`: ``n_done`` of ``n_tasks`` recordings had finished (their outputs are
    complete; a next run skips them)."""

    def __init__(self, n_done: int, n_tasks: int):
        super().__init__(f"interrupted after {n_done} of {n_tasks} recordings")
        self.n_done = n_done
        self.n_tasks = n_tasks


def _quiet_resource_tracker() -> None:
    """Start multiprocessing's resource tracker (if not running) with its stderr on /dev/null.

    When a worker process dies (killed, out of memory) and the nanny starts another, the tracker prints
    ``KeyError`` tracebacks about semaphores it no longer knows (a CPython quirk with spawned processes);
    the batch itself handles the death (the recording is rescheduled), so they are noise on the terminal.
    """
    if getattr(resource_tracker._resource_tracker, "_fd", None) is not None:
        return
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):  # no real stderr (captured): nothing to protect
        return
    saved = os.dup(fd)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), fd)
            resource_tracker.ensure_running()
    finally:
        os.dup2(saved, fd)
        os.close(saved)


def _row_of(future, task: Task) -> dict:
    """A finished future's row; a task that did not return one (its workers died, the scheduler cancelled
    it) is an error row saying so."""
    try:
        return future.result()
    except Exception as exc:  # noqa: BLE001 — a lost task is a row, never the batch's end
        name = type(exc).__name__
        why = "its worker died while processing it" if name == "KilledWorker" else "it did not finish"
        return error_row(task.label, f"{task.label}: {why} ({name}: {exc})")


class _Progress:
    """A bar over recordings: done, failed, running, ETA (tqdm on stderr), or nothing."""

    def __init__(self, total: int, desc: str, enabled: bool | None):
        if enabled is None:
            enabled = sys.stderr.isatty()
        self.bar = None
        if enabled and total:
            from tqdm import tqdm

            self.bar = tqdm(total=total, desc=desc, unit="rec", leave=False, dynamic_ncols=True)

    def update(self, n_new: int, n_ok: int, n_failed: int, n_running: int) -> None:
        if self.bar is not None:
            self.bar.set_postfix_str(f"ok {n_ok}, failed {n_failed}, running {n_running}", refresh=False)
            self.bar.update(n_new)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def execute(tasks, client=None, workers: int | None = None, scheduler: str | None = None,
            progress: bool | None = None, desc: str = "batch",
            dashboard: Callable[[str], None] | None = None) -> list[dict]:
    """Run ``tasks`` on Dask and return their rows, in task order.

    Parameters
    ----------
    tasks : sequence of Task
    client : distributed.Client, optional
        The caller's client (a backend's): used as it is, not closed.
    workers, scheduler :
        Without ``client``: :func:`dask_client`'s (a local cluster, or the cluster at ``scheduler``).
    progress : bool or None
        Progress bar on stderr (None: when stderr is a terminal).
    dashboard : callable, optional
        Without ``client``: ask for the local cluster's dashboard and give its address (or, with
        ``scheduler``, that cluster's) to this callable once the cluster is up. None: no dashboard.
    """
    tasks = list(tasks)
    if not tasks:
        return []
    if client is None:
        n = min(workers or default_workers(), len(tasks))
        with dask_client(n, scheduler, dashboard=dashboard is not None) as own:
            if dashboard is not None:
                dashboard(own.dashboard_link)
            return execute(tasks, client=own, progress=progress, desc=desc)
    from distributed import as_completed

    token = uuid.uuid4().hex[:8]
    keys = [f"pdr-mag-{t.command}-{i}-{token}" for i, t in enumerate(tasks)]
    futures = client.map(run_task, tasks, key=keys, pure=False)
    slot = {f.key: i for i, f in enumerate(futures)}
    rows: list = [None] * len(tasks)
    bar = _Progress(len(tasks), desc, progress)
    n_ok = n_failed = 0
    ac = as_completed(futures)
    try:
        while not ac.is_empty():
            finished = ac.next_batch(block=False)
            for f in finished:
                i = slot[f.key]
                rows[i] = _row_of(f, tasks[i])
                if rows[i].get("status") == "ok":
                    n_ok += 1
                else:
                    n_failed += 1
                f.release()
            bar.update(len(finished), n_ok, n_failed, _running(client) if bar.bar is not None else 0)
            if not finished:
                time.sleep(0.2)
    except KeyboardInterrupt:
        client.cancel([f for f in futures if not f.done()])
        raise Interrupted(sum(r is not None for r in rows), len(rows)) from None
    except BaseException:
        client.cancel([f for f in futures if not f.done()])
        raise
    finally:
        bar.close()
    return rows
