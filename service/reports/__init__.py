"""Reports in the service layer: the HTML page of a report (``html``) and the
reports of stored jobs (``stored``). The content itself comes from
:mod:`svrobs_core.report`; ``svrobs reproduce`` is :mod:`svrobs_cli.reproduce`."""
