"""The one error type of the data layer."""

from __future__ import annotations


class DataError(ValueError):
    """Bad input data: a one-line message naming the file (or folder) and the problem.

    Subclasses ValueError so that generic callers that catch ValueError still see it; the CLI catches it
    to print the message without a traceback.
    """
