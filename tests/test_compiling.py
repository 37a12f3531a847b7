"""Compilation of numba kernels as the commands see it (:mod:`replay.compiling`): timed apart from the work,
announced once on a terminal.

A cold cache is made here without touching the package's: a kernel defined inside the test (no disk cache)
is compiled at its first call, inside the run.
"""

from __future__ import annotations

import time
from pathlib import Path

from numba import njit

from pdr_mag.sinks import QuietSink
from replay import run as run_module
from replay.cli import main
from replay.compiling import NOTICE, CompileWatch
from replay.run import replay

ROOT = Path(__file__).resolve().parents[1]


def _fresh_kernel():
    """A kernel never compiled before (a new function object each call), that calls another one: nested
    compilations."""

    @njit
    def inner(x):
        return x * 2.0

    @njit
    def outer(x):
        return inner(x) + 1.0

    return outer


class CompilingSink(QuietSink):
    """Compiles a fresh kernel at its first output rows: a compilation in the middle of the run's work."""

    def __init__(self, kernel):
        self.kernel = kernel
        self.calls = 0

    def estimates(self, batch) -> None:
        self.calls += 1
        self.kernel(1.0)


def test_watch_times_nested_compilations_once_and_notices_once():
    said = []
    with CompileWatch(lambda: said.append(1)) as w:
        k = _fresh_kernel()
        assert k(1.0) == 3.0
        n, s = w.compilations, w.seconds
        assert k(2.0) == 5.0  # compiled already: nothing more
    assert n == 1 and s > 0 and said == [1]  # inner compiled inside outer's compilation: one, timed once
    assert (w.compilations, w.seconds) == (n, s)
    with CompileWatch() as w2:
        _fresh_kernel()(1.0)
    assert w2.compilations == 1 and w.compilations == 1  # a watch counts only while it is active


def test_replay_leaves_compile_time_out_of_the_work():
    rec = ROOT / "recordings" / "walk"
    replay(rec, progress=False)  # the pipeline's own kernels loaded or compiled: not this test's subject
    kernel = _fresh_kernel()
    t0 = time.perf_counter()
    s = replay(rec, sinks=[CompilingSink(kernel)], progress=False)
    wall = time.perf_counter() - t0
    assert s["compile_s"] > 0
    # the work's time and the compile time are apart: together no more than the call's wall time
    assert s["elapsed_s"] > 0 and s["elapsed_s"] + s["compile_s"] <= wall
    n = sum(s["n_samples"].values())
    assert s["samples_per_s"] == n / s["elapsed_s"]
    again = replay(rec, sinks=[CompilingSink(kernel)], progress=False)  # compiled now: nothing to compile
    assert again["compile_s"] == 0.0
    assert {k: v for k, v in s.items() if k not in ("elapsed_s", "compile_s", "samples_per_s")} == {
        k: v for k, v in again.items() if k not in ("elapsed_s", "compile_s", "samples_per_s")
    }


def test_the_command_says_once_on_a_terminal_that_it_compiles(monkeypatch, capsys, tmp_path):
    rec = str(ROOT / "recordings" / "walk")
    kernels = []

    class Sink(run_module.CsvSink):
        def open(self, meta):
            super().open(meta)
            kernels.append(_fresh_kernel())
            kernels[-1](1.0)
            _fresh_kernel()(1.0)  # a second compilation in the same run: still one notice

    monkeypatch.setattr("replay.commands.replay.CsvSink", Sink)
    for tty in (True, False):
        monkeypatch.setattr("sys.stderr.isatty", lambda tty=tty: tty)
        assert main(["replay", rec, "--out-csv", str(tmp_path / "h.csv")]) == 0
        out = capsys.readouterr()
        assert out.err.count(NOTICE) == (1 if tty else 0), out.err
        assert "compiling  " in out.out and "not in the throughput" in out.out
