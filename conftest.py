"""Puts the project root on sys.path so tests can use benchmarks.peers (Embree)."""
