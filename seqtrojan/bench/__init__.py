"""Throughput benchmarks (printed figures, never timed tests)."""
