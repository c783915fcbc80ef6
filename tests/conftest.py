"""Shared pytest configuration: numba caches stay inside the checkout."""
