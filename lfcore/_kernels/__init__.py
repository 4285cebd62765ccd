"""Warp kernels, kept at module scope so Warp can cache their compiled code.

Nothing here validates its inputs: the public functions elsewhere in :mod:`lfcore` do that and
define the API.
"""
