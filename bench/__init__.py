"""Benchmarks of the arena (``make bench``): not part of the installed runtime."""
