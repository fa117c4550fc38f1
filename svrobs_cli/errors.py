"""Errors on the command line: one line on stderr, exit status 2, never a traceback.

An API error (:class:`svrobs_client.SvrobsError`) is shown as
``error: <field in plain words>: <message>``, e.g. ``error: invalid spec: reps: must
be >= 1`` for a bad spec (README, "The spec and the record"); a file that cannot be
read or written as ``error: cannot read <path>: <reason>`` (``cannot write``; an
OSError otherwise as ``error: <path>: <reason>``); a command line that does not parse
(an unknown option, a missing argument, a job id that is not a number) as
``error: <what is wrong> (see svrobs <command> --help)``.
"""

from __future__ import annotations

import re
import sys
from collections.abc import Iterator
from contextlib import contextmanager

import typer
from typer._click.exceptions import NoArgsIsHelpError, UsageError  # typer's own click
from typer.core import TyperGroup

from svrobs_client import SvrobsError


class CliError(Exception):
    """An error shown to the user as one line (exit status 2)."""


# pydantic's names for the branches of a union or a validator ("N.list[any]"): not a
# field a user wrote, so dropped from the field path
_VALIDATOR_PART = re.compile(
    r"\.(?:list|dict|tuple|set|frozenset|union|tagged-union|json-or-python|lax-or-strict"
    r"|is-instance|nullable|default|function-[a-z-]+|constrained-[a-z-]+)(?:\[[^\]]*\])?"
)


def plain_field(field: str | None) -> str | None:
    """The field path as the user wrote it (``N.list[any]`` -> ``N``)."""
    if not field:
        return None
    return _VALIDATOR_PART.sub("", field) or None


def plain_message(exc: SvrobsError) -> str:
    """``field: message`` (the message alone when the API names no field, or when the
    message already starts with it: ``job 5 is queued: ...``)."""
    field = plain_field(exc.field)
    if not field or exc.message.split(" ", 1)[0] == field:
        return exc.message
    return f"{field}: {exc.message}"


def one_line(exc: BaseException) -> str:
    if isinstance(exc, SvrobsError):
        text = plain_message(exc)
    elif isinstance(exc, OSError) and exc.strerror:  # without "[Errno 2]"
        text = f"{exc.filename}: {exc.strerror}" if exc.filename else exc.strerror
    else:
        text = str(exc)
    text = text.strip() or type(exc).__name__
    return " ".join(text.split())[:500]


@contextmanager
def _usage_in_one_line() -> Iterator[None]:
    """click's usage errors (printed as a box with the usage) as a :class:`CliError`."""
    try:
        yield
    except NoArgsIsHelpError:  # the help, as asked
        raise
    except UsageError as exc:
        ctx = exc.ctx
        hint = f" (see {ctx.command_path} --help)" if ctx is not None else ""
        raise CliError(exc.format_message().rstrip(".") + hint) from None


class OneLineGroup(TyperGroup):
    """A command group whose command lines that do not parse are one line too."""

    def make_context(self, *args, **kwargs):
        with _usage_in_one_line():
            return super().make_context(*args, **kwargs)

    def invoke(self, ctx):
        with _usage_in_one_line():
            return super().invoke(ctx)


class SvrobsTyper(typer.Typer):
    """A Typer app that turns every error into one line on stderr and exit status 2."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("cls", OneLineGroup)
        super().__init__(*args, **kwargs)

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
