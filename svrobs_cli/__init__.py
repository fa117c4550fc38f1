"""The ``svrobs`` command line: every command is registered in :mod:`svrobs_cli.app`.

Top of the layers: it may import ``service``, ``svrobs_core`` and ``svrobs_client``
(every REST command goes through the client); nothing imports it but the tests and
the benches.
"""
