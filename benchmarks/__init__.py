"""Benchmarks and evaluation commands (``fourlegs bench ...``), kept out of the engine."""
