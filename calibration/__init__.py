"""Calibration: the microlens grid from a white image, and the volumetric calibration of each
camera's model from the dot target through the stage planes (the pure fit, and the runner that
drives the stage and cameras), kept in the calibration store.
"""

__all__ = [
    "board",     # the default dot board of a rig and its spacing limits
    "dots",      # the target's dots in a raw light-field image
    "fit",       # a camera model fitted to the named dots
    "mla_grid",  # every micro-image centre of a white image and the lattice through them
    "pinhole",   # a pinhole camera's model and Soloff mapping fitted to the dots
    "planes",    # one camera's plane images to its fitted model
    "runner",    # camera-only triggering and the plane run
    "selfcal",   # volume self-calibration of pinhole cameras (Wieneke 2008)
    "store",     # the calibration store (zarr)
]
