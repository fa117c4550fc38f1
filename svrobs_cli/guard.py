"""Run a Python module as a child that cannot outlive its parent for long.

    python -m svrobs_cli.guard --parent PID --grace 10 -m celery -A worker.celery_app worker ...

``svrobs serve`` starts every child this way (:func:`svrobs_cli.processes.guarded`).
The module runs in this same process (``runpy``, as ``python -m`` would run it),
beside one daemon thread that watches the parent: when the parent is gone
(the kernel then also sends the parent-death signal, SIGTERM, which starts the
module's own shutdown: uvicorn's, Celery's warm shutdown), the thread waits
``grace`` seconds and then SIGKILLs the child's whole process group (a prefork
pool too). So a supervisor killed by SIGKILL leaves nothing running after
``grace`` seconds, even a worker whose shutdown hangs.
"""

from __future__ import annotations

import os
import runpy
import signal
import sys
import threading
import time

from svrobs_cli.processes import parent_death_signal

POLL_SECONDS = 0.2


def _watch(parent: int, grace: float, send_term: bool) -> None:
    while os.getppid() == parent:
        time.sleep(POLL_SECONDS)
    if send_term:  # no parent-death signal on this platform: start the shutdown here
        os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(grace)
    print(
        f"svrobs: parent {parent} gone and pid {os.getpid()} still running after {grace:g} s;"
        " killing its process group",
        file=sys.stderr,
        flush=True,
    )
    try:
        if os.getpgrp() == os.getpid():
            os.killpg(os.getpid(), signal.SIGKILL)
    finally:
        os.kill(os.getpid(), signal.SIGKILL)


USAGE = "usage: python -m svrobs_cli.guard --parent PID --grace SECONDS -m MODULE [ARGS...]"


def main(argv: list[str]) -> None:
    if len(argv) < 6 or argv[0] != "--parent" or argv[2] != "--grace" or argv[4] != "-m":
        sys.exit(USAGE)
    parent, grace, module, args = int(argv[1]), float(argv[3]), argv[5], argv[6:]
    # the parent passes its pid: a parent already gone when this starts is seen too
    send_term = not parent_death_signal()  # else the kernel sends it
    threading.Thread(
        target=_watch, args=(parent, grace, send_term), name="svrobs-guard", daemon=True
    ).start()
    sys.argv = [module, *args]
    runpy.run_module(module, run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main(sys.argv[1:])
