"""Benchmarks: speed and accuracy measurements (`fourlegs bench ...`), kept out of the engine."""
