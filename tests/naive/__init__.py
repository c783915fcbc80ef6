"""Brute-force reference implementations the fast kernels are tested against.

One module per topic (``naive.spacetime``, ``naive.raycast`` ...); they favour
obviousness over speed and are only run at small sizes.
"""
