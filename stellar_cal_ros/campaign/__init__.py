"""Calibration campaigns: many simulate / replay / diagnose / budget runs on Dask.

:mod:`.spec` expands a YAML spec into runs, :mod:`.runs` executes one run (the only place
that calls the estimators), :mod:`.runner` schedules them on Dask distributed (resumable,
one Parquet table), :mod:`.summary` reports, :mod:`.command` is ``stellar-cal campaign``.
"""
