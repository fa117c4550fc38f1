"""``python -m svrobs_cli``: the ``svrobs`` console script."""

from svrobs_cli.app import app

app()
