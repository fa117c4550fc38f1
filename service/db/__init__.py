"""The DB package shared by the API, the worker and beat, one module per thing it manages.

``models`` (tables) and ``session`` (engines, transactions); ``jobs`` (create,
cancel, look up); ``units`` (claim, heartbeat, complete, fail a work unit; the
job's summaries); ``results_store`` (records <-> ``results`` rows); ``outbox``
(units to (re)publish); ``schedules`` (cron validation, due times, scheduled
jobs); ``accounts`` (teams, users, API keys); ``provenance``; ``errors`` (the
domain errors the API maps to responses); ``migrate`` (Alembic).
"""
