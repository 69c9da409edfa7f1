"""Running a grid: its spec, its jobs, where they run, its progress and its merged status.

``pporpe reproduce`` is :func:`.reproduce.reproduce`; a spec is read by
:func:`.spec.load_spec`. Nothing here imports :mod:`pporpe.experiments.reports`.
"""
