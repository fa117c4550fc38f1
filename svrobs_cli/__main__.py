"""``python -m svrobs_cli`` and the ``svrobs`` console script (:func:`main`)."""

import sys


def main() -> None:
    """Run the command line; for ``serve``, stop signals are kept from the start
    (:mod:`svrobs_cli.signals`), before the imports. BLAS is pinned to one thread and
    one kernel before numpy loads (:mod:`svrobs_core.threads`): ``svrobs reproduce``
    computes in this process and its forks."""
    from svrobs_core.threads import single_thread_env

    single_thread_env()
    from svrobs_cli.signals import COMPUTING, exit_on_sigterm, record_early

    if sys.argv[1:2] == ["serve"]:
        record_early()
    elif sys.argv[1:2] not in ([c] for c in COMPUTING):
        exit_on_sigterm()
    from svrobs_cli.app import app

    app()


if __name__ == "__main__":
    main()
