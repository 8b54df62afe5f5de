"""Defenses: the online state monitor, offline detection from weights, and mitigation."""
