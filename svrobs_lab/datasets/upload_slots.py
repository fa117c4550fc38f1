"""Uploads read at once in one API process (docs/datasets.md#limits): at most
``per_team`` of one team and ``at_once`` in all, each held from the first byte of
the body read until the dataset is stored or refused. A file can take several times
its size in memory while it is parsed, so beyond either bound the upload is refused
at once with :class:`~svrobs_lab.errors.RateLimited` (429, Retry-After: the last
upload's duration), before its body is read (:class:`svrobs_lab.slots.TeamSlots`).
"""

from __future__ import annotations

from ..slots import TeamSlots


class UploadSlots(TeamSlots):
    """Counted upload slots per team and in all, for one process."""

    def __init__(self, *, per_team: int, at_once: int):
        super().__init__(
            per_team=per_team,
            at_once=at_once,
            what="uploads being read",
            settings=("SVROBS_UPLOADS_PER_TEAM", "SVROBS_UPLOADS_AT_ONCE"),
        )
