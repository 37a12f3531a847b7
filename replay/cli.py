"""``pdr-mag``: simulate, calibrate, replay, diagnose, batch.  Thin: parses, calls, prints.

Every command lives in ``replay/commands/<name>.py`` as a ``click`` command named ``command``.
Bad input ends with exit code 2 and one line on stderr (``pdr-mag: FILE[:LINE]: problem``), never a
traceback.
"""

from __future__ import annotations

import importlib
import sys

import click

from replay.errors import InputError

COMMANDS = ("simulate", "calibrate", "replay", "diagnose", "batch")


class _Commands(click.Group):
    """The subcommands, each imported when it is used (``replay.commands.<name>``'s ``command``): a command
    loads only its own dependencies (``simulate`` needs neither the compiled pipeline nor the model check)."""

    def list_commands(self, ctx) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx, name: str):
        if name not in COMMANDS:
            return None
        return importlib.import_module(f"replay.commands.{name}").command


@click.group(cls=_Commands, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="pdr_mag")
def cli() -> None:
    """pdr_mag — magnetometer calibration and heading for pedestrian navigation with phones."""


def _fail(message: str) -> int:
    one_line = " ".join(message.split("\n"))
    click.echo(f"pdr-mag: {one_line}", err=True)
    return 2


def main(argv: list[str] | None = None) -> int:
    """Entry point of the console script and of ``python -m pdr_mag``; returns the exit code."""
    try:
        rv = cli.main(args=argv, prog_name="pdr-mag", standalone_mode=False)
    except InputError as exc:
        return _fail(str(exc))
    except click.exceptions.Exit as exc:
        return exc.exit_code
    except click.Abort:
        return _fail("aborted")
    except click.ClickException as exc:
        return _fail(exc.format_message().replace("\n", " "))
    except BrokenPipeError:
        return 1
    except OSError as exc:
        if exc.filename is None:  # not about a file the user named: a bug or the machine, keep the traceback
            raise
        return _fail(f"{exc.filename}: {exc.strerror or exc}")
    return rv if isinstance(rv, int) else 0


def run() -> None:
    """Console-script wrapper: exit with :func:`main`'s code."""
    sys.exit(main())


if __name__ == "__main__":
    run()
