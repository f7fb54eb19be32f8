"""Errors of the perception package that callers handle without importing torch."""
from __future__ import annotations


class ModelLoadError(RuntimeError):
    """A CM-VAE weights file that is missing, unreadable or not a CM-VAE (one line, no traceback needed)."""
