"""The reproduction study's scripts: ``python -m benchmarks.reproduction.<script> --help``.

``run_choice`` trains one arm's run; the others read the results under ``results/``, and
``tables`` writes them into ``RESULTS.md``.
"""
