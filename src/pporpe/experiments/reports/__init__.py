"""Reporting on a grid's results: what both reports share, and the online and batch reports.

``pporpe report`` is :func:`.report.write_report`, which sends a grid to
:mod:`.online.report` or :mod:`.batch.report`. Shared by both: the run folders read into
cells (:mod:`.results`), statistics over seeds (:mod:`.stats`), verdicts (:mod:`.verdicts`),
the tables' common parts (:mod:`.tables`), the common figures (:mod:`.plots`) and the
methods' labels and colours with the paper's analytic figures (:mod:`.figures`). Neither
:mod:`.online` nor :mod:`.batch` imports the other.
"""
