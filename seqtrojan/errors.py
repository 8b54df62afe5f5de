"""Errors raised by seqtrojan. Every one names the offending value so that bad input is easy to fix."""

from __future__ import annotations


class SeqTrojanError(Exception):
    """Base class of all seqtrojan errors."""


class ConfigError(SeqTrojanError, ValueError):
    """A configuration value is invalid (wrong range, unknown name, inconsistent fields)."""


class LayoutError(SeqTrojanError, ValueError):
    """No solvable grid layout exists, or none was found within the allowed number of tries."""


class ShapeError(SeqTrojanError, ValueError):
    """A tensor or array passed in has the wrong shape, dtype or value range."""


class CheckpointError(SeqTrojanError, ValueError):
    """A model file is missing, corrupt, pickled, or does not match its card."""
