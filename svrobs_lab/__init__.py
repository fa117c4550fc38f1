"""The application layer: the lab's use cases, under every front end.

REST routes (``service.api``), web pages (``service.web``), worker tasks
(``worker``) and the CLI (``svrobs_cli``) call these modules; they call the store
(``service.db``) and the pure core (``svrobs_core``). Errors are
:mod:`svrobs_lab.errors`, mapped to a response once per front end. See
``docs/architecture.md#layers``.
"""
