"""The ``svrobs`` command line: every command is registered in :mod:`svrobs_cli.app`.

Top of the layers: it may import ``service`` and ``svrobs_core``; nothing imports it
but the tests and the benches.
"""
