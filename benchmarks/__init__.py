"""Benchmark scripts of torchrl_tels: speed, the baseline grid and the paper's other experiments.

Each script is a module run from the repository root, ``python -m benchmarks.<script> --help``;
``benchmarks.harness`` holds what they share. The reproduction study lives in ``study/``.
"""
