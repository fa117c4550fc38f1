"""Reports in the service layer: the HTML page of a report (``html``) and the
paper reproduction that writes tables, figures and reports to a folder
(``reproduce``). The content itself comes from :mod:`svrobs_core.report`."""
