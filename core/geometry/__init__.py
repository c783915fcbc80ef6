"""Shared numerics on plain arrays (no model objects), one topic a module.

Numba kernels live in private ``_kernels`` modules beside the driver that uses
them and are compiled lazily on first use (``cache=True``).
"""
