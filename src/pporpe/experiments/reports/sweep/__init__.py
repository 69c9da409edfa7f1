"""A sweep's report: stage 1 (tuning: sensitivity, selection, ``selected.toml``) and the
sections stage 2 (evaluation) adds to its grid's report.

It reads a sweep's run folders as the batch report does (its numbers per run,
:data:`..batch.results.METRICS`, normalised per task as :mod:`..batch.aggregate`), for a
sweep of batch or online runs alike; it never imports :mod:`..online`, and neither report
imports it: only :mod:`..report` sends a sweep here.
"""
