"""Reporting on a grid's results: what the reports share, the online and batch reports, a sweep's.

``pporpe report`` is :func:`.report.write_report`, which sends a grid to
:mod:`.online.report` or :mod:`.batch.report`, and a sweep's stage 1 to
:mod:`.sweep.report` (a stage 2 gets its grid's report with the sweep's sections). Shared
by all: the run folders read into cells (:mod:`.results`), statistics over seeds
(:mod:`.stats`), verdicts (:mod:`.verdicts`), the tables' common parts (:mod:`.tables`),
the common figures (:mod:`.plots`) and the methods' labels and colours with the paper's
analytic figures (:mod:`.figures`). Neither
:mod:`.online` nor :mod:`.batch` imports the other; :mod:`.sweep` reads runs as the batch
report does and imports it, never :mod:`.online`, and neither imports :mod:`.sweep`.
"""
