"""The reproduction study of the TELS paper: ``python -m study.<script> --help``, from the repository root.

``README.md`` indexes the scripts. ``run_choice`` trains one arm's run; the others read the results
under ``results/``, and ``tables`` writes them into ``RESULTS.md``. The study imports what it shares
with the benchmarks (``benchmarks.harness``, ``benchmarks.baselines``, ``benchmarks.run_grid``) from
there; nothing under ``benchmarks/`` imports the study.
"""
