"""Many recordings at once on Dask (``pdr-mag batch``): the Python API underneath the command.

A backend with its own ``distributed.Client`` submits the same tasks the command does::

    from replay.batch import plan, execute, write_table

    p = plan("replay", ["/data/week-42"], "/results/week-42", options={"mcap": True})
    rows = p.table(execute(p.tasks, client=my_client))   # or client.map(run_task, p.tasks) yourself
    write_table(rows, p.out_dir)

* :func:`plan` — find the recordings (:mod:`replay.batch.inputs`), skip those whose outputs are complete,
  make a picklable :class:`Task` for each of the others;
* :func:`run_task` — process one recording with the single command's own code, write its files atomically
  and return its fleet-table row (:mod:`replay.batch.tasks`); a plain function a worker imports from
  ``replay.batch.tasks``;
* :func:`execute` — submit tasks to a client (a local cluster of processes, or the cluster at a scheduler
  address, when none is given) and collect their rows with a progress bar (:mod:`replay.batch.engine`);
* :func:`write_table`, :data:`COLUMNS`, :func:`headline` — the fleet table (:mod:`replay.batch.table`).

The library :mod:`pdr_mag` never imports Dask; only this package does.
"""

from replay.batch.engine import Plan, dask_client, default_workers, execute, plan
from replay.batch.inputs import Item, find_recordings
from replay.batch.table import COLUMNS, headline, read_csv, worst_first, write_table
from replay.batch.tasks import OPTIONS, ROW_FILE, Task, completed_row, run_task

__all__ = [
    "COLUMNS",
    "OPTIONS",
    "ROW_FILE",
    "Item",
    "Plan",
    "Task",
    "completed_row",
    "dask_client",
    "default_workers",
    "execute",
    "find_recordings",
    "headline",
    "plan",
    "read_csv",
    "run_task",
    "worst_first",
    "write_table",
]
