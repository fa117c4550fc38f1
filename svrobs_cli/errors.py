"""Errors on the command line: one line on stderr, exit status 2, never a traceback."""

from __future__ import annotations

import sys

import typer


class CliError(Exception):
    """An error shown to the user as one line (exit status 2)."""


def one_line(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return " ".join(text.split())[:500]


class SvrobsTyper(typer.Typer):
    """A Typer app that turns every error into one line on stderr and exit status 2."""

    def __call__(self, *args, **kwargs):
        try:
            return super().__call__(*args, **kwargs)
        except SystemExit:
            raise
        except KeyboardInterrupt:
            print("interrupted", file=sys.stderr)
            sys.exit(130)
        except Exception as exc:  # noqa: BLE001 - the one place errors become a line
            print(f"error: {one_line(exc)}", file=sys.stderr)
            sys.exit(2)
