"""Errors on the command line: one line on stderr, exit status 2, never a traceback.

An API error (:class:`svrobs_client.SvrobsError`) is shown as
``error: <field in plain words>: <message>``, e.g. ``error: invalid spec: reps: must
be >= 1`` for a bad spec (README, "The spec and the record").
"""

from __future__ import annotations

import re
import sys

import typer

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
    text = plain_message(exc) if isinstance(exc, SvrobsError) else str(exc)
    text = text.strip() or type(exc).__name__
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
