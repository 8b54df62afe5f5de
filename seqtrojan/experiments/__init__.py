"""Experiments built from the library: learning curves and the end-to-end reproduction of the paper."""
