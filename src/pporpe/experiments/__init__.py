"""The paper's experiments, in two rooms: running a grid (:mod:`.grids`) and reporting on it
(:mod:`.reports`).

* :mod:`.grids`: a grid's spec (methods x tasks x seeds, :mod:`.grids.spec`), its runs packed
  into jobs (:mod:`.grids.planning`), run on a local process pool or a Ray cluster
  (:mod:`.grids.backends`, :mod:`.grids.reproduce`: ``pporpe reproduce``), its progress
  (:mod:`.grids.progress`) and the ``grid.json`` / ``status.json`` its chunks merge into
  (:mod:`.grids.merge`); a spec's sweep and its stage-2 checks (:mod:`.grids.sweep`).
* :mod:`.reports`: ``pporpe report`` (:mod:`.reports.report`) and what it reads and writes:
  the statistics, verdicts, tables and figures both reports share, and what only the online
  report (:mod:`.reports.online`), only the batch report (:mod:`.reports.batch`) or only a
  sweep's report (:mod:`.reports.sweep`) computes; the paper's analytic figures
  (:mod:`.reports.figures`, ``pporpe figures``).
* :mod:`.sweep_terms`: what both rooms know of a sweep (a cell's folder name, the
  ``grid.json`` record, the words of a selection rule), importing neither.

The grids never import the reports, nor the reports the grids: a report reads only the run
folders and ``grid.json``.
"""
