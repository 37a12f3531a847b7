"""The one exception type of the application layer: bad input, reported as one line, exit code 2."""

from __future__ import annotations


class InputError(ValueError):
    """Bad input: a file that cannot be used as it is.

    ``str(err)`` is the one line the command prints: ``FILE[:LINE]: problem``.
    """

    def __init__(self, path, problem: str, line: int | None = None):
        self.path = str(path)
        self.problem = problem
        self.line = line
        where = self.path if line is None else f"{self.path}:{line}"
        super().__init__(f"{where}: {problem}")
