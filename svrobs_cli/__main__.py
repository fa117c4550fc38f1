"""``python -m svrobs_cli`` and the ``svrobs`` console script (:func:`main`)."""

import sys


def main() -> None:
    """Run the command line; for ``serve``, stop signals are kept from the start
    (:mod:`svrobs_cli.signals`), before the imports."""
    if sys.argv[1:2] == ["serve"]:
        from svrobs_cli.signals import record_early

        record_early()
    from svrobs_cli.app import app

    app()


if __name__ == "__main__":
    main()
