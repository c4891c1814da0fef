"""Peers run side by side in the benchmarks (each in its own environment where it must be)."""
