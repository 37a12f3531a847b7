"""The MCAP sink's optional writer process (``McapSink(..., background=True)``).

The caller pickles each sink call into a pipe; a "spawn" child process runs an in-process
:class:`~pdr_mag.sinks.mcap.McapSink` on them in order.  The pipe blocks when the writer falls behind, so
memory stays bounded; an error in the child is reported back at ``close()``.
"""

from __future__ import annotations

from pathlib import Path


class WriterProcess:
    """A child process running an in-process :class:`McapSink`, fed ``(method, args)`` through a pipe."""

    def __init__(self, path: Path, compression: str, chunk_size: int):
        import multiprocessing as mp

        ctx = mp.get_context("spawn")  # not fork: the caller may have threads (rerun, the I/O thread)
        recv_end, self._conn = ctx.Pipe(duplex=False)
        self._result, result_end = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(
            target=_writer_main,
            args=(recv_end, result_end, str(path), compression, chunk_size),
            name="pdr_mag-mcap-sink",
            daemon=True,
        )
        self._proc.start()
        recv_end.close()
        result_end.close()

    def send(self, name: str, args: tuple) -> None:
        try:
            self._conn.send((name, args))
        except (BrokenPipeError, ConnectionResetError, EOFError) as exc:
            raise RuntimeError(f"McapSink writer process ended early ({self._error_or(exc)})") from None

    def _error_or(self, exc) -> str:
        if self._result.poll(1.0):
            return str(self._result.recv().get("error"))
        return f"{type(exc).__name__}; exit code {self._proc.exitcode}"

    def finish(self) -> dict:
        try:
            self._conn.send(("close", ()))
        except (BrokenPipeError, ConnectionResetError):
            pass
        self._conn.close()
        result = {"error": f"no answer from the writer process (exit code {self._proc.exitcode})"}
        try:
            result = self._result.recv()
        except EOFError:
            pass
        self._proc.join(timeout=60)
        return result


def _writer_main(conn, result, path: str, compression: str, chunk_size: int) -> None:
    """The writer process: apply the calls in order; after an error keep draining (no deadlock)."""
    from pdr_mag.sinks.mcap import McapSink

    sink = McapSink(path, compression=compression, chunk_size=chunk_size)
    error = None
    while True:
        try:
            name, args = conn.recv()
        except EOFError:  # the caller went away without close(): still finish the file
            name, args = "close", ()
        if error is None:
            try:
                getattr(sink, name)(*args)
            except BaseException as exc:  # noqa: BLE001 - reported to the caller
                error = f"{type(exc).__name__}: {exc}"
        if name == "close":
            break
    if error is not None and sink._writer is not None:
        try:
            sink.close()
        except BaseException:  # noqa: BLE001, S110 - the first error is the one to report
            pass
    result.send(
        {"counts": sink.counts, "time_offset_ns": sink._offset_ns, "clamped": sink._clamped, "error": error}
    )
