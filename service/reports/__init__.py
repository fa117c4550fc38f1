"""The paper reproduction that writes tables, figures and reports to a folder
(``reproduce``), a CLI command (``svrobs reproduce``). The content comes from
:mod:`svrobs_core.report`; a stored job's HTML report is :mod:`svrobs_lab.reports`."""
