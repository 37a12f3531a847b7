"""The numba kernels' compilation as the commands see it: when it starts, and how long it takes.

pdr_mag's per-sample kernels are compiled by numba at their first call and kept in its on-disk cache
(``cache=True``), so only a run that finds the cache cold — the first after installing, or the first after a
kernel's source changed — compiles them (20–30 s); later runs load them (well under a second). numba
broadcasts a ``numba:compile`` event around each compilation, never around a load from the cache
(``numba.core.event``); :class:`CompileWatch` listens to those events, so that a command can say once that
the kernels are being compiled, and ``replay`` can leave the compile time out of the work it reports.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable

from numba.core import event
from tqdm import tqdm

#: What a command says on a terminal when it has to compile the kernels.
NOTICE = "pdr-mag: compiling the numba kernels (first run only: later runs load them from the cache)…"


class CompileWatch(event.Listener):
    """Time spent compiling numba kernels while the watch is active (a context manager).

    Compilations nest (a kernel compiles the kernels it calls while it is typed): only the outermost ones
    are timed, so ``seconds`` is wall time, each second counted once.

    Parameters
    ----------
    notice : callable, optional
        Called (without arguments) when the first compilation starts, once: a command's message that the
        kernels are being compiled.

    Attributes
    ----------
    seconds : float
        Wall time spent compiling so far, s.
    compilations : int
        Outermost compilations so far (0: every kernel came from the cache, or was already loaded).
    """

    def __init__(self, notice: Callable[[], None] | None = None):
        self.notice = notice
        self.seconds = 0.0
        self.compilations = 0
        self._depth = 0
        self._started = 0.0
        self._installed = None

    def on_start(self, ev) -> None:
        if self._depth == 0:
            self._started = time.perf_counter()
            if self.compilations == 0 and self.notice is not None:
                self.notice()
        self._depth += 1

    def on_end(self, ev) -> None:
        self._depth -= 1
        if self._depth == 0:
            self.seconds += time.perf_counter() - self._started
            self.compilations += 1

    def __enter__(self) -> CompileWatch:
        self._installed = event.install_listener("numba:compile", self)
        self._installed.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self._installed.__exit__(*exc)
        self._installed = None


def announced() -> CompileWatch:
    """The watch a command runs its work in: on a terminal it says :data:`NOTICE` once on stderr when the
    first compilation starts (above a progress bar, if one is showing); elsewhere (a pipe, a log, a test)
    it stays silent."""
    return CompileWatch(_say if sys.stderr.isatty() else None)


def _say() -> None:
    tqdm.write(NOTICE, file=sys.stderr)
