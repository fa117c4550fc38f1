"""Validation errors that name the offending field (SPEC section 10)."""

from __future__ import annotations


class SpecError(ValueError):
    """A bad experiment spec or system spec.

    ``field`` is a dotted path into the spec (``"systems[0].A"``, ``"gamma"``),
    so the service can answer HTTP 422 naming it and the CLI can print it.
    """

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message
