"""Benchmarks and peers (Intel Embree through embreex). Uses jrt's public API only."""
