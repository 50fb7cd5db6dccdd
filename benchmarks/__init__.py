"""Benchmarks: heavy measurements behind `fourlegs bench …` (not imported by the engine)."""
