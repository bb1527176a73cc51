"""Benchmark and reproduction scripts of torchrl_tels.

Each script is a module run from the repository root, ``python -m benchmarks.<script> --help``;
``benchmarks.harness`` holds what they share.
"""
