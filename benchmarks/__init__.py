"""Benchmarks of deliffas: every figure is a ratio measured in the same run (``make bench``)."""
