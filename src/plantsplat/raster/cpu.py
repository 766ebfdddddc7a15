"""CPU backend. TEMPORARY in this commit: uses the pure-torch compositing (correct but slow) until
the numba tile kernels land."""

from __future__ import annotations

from .reference import composite_reference as composite_cpu  # noqa: F401
