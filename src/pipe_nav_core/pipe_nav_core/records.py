"""Flat records of the compiled kernels: consecutive fields of one array, each declared once
with its size, their starts derived.

A record's fields are module-level int constants (``start = fields(size)``), which numba
freezes as compile-time constants: reading a field costs what a literal index costs.
"""

from __future__ import annotations


class Fields:
    """The fields of one flat record, in order: each call declares the next field of
    ``size`` elements and returns its start; ``size`` is the record's length so far."""

    def __init__(self) -> None:
        self.size = 0

    def __call__(self, size: int = 1) -> int:
        if size < 1:
            raise ValueError(f"a field has at least one element, not {size}")
        start = self.size
        self.size += size
        return start
