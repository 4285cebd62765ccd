"""lfcore: pure light-field PIV computation: optics, rendering, weights, reconstruction,
correlation, vector post-processing, metrics, flows and the run format.

Arrays and frozen configurations in, arrays out: nothing here opens a file, port or camera (the
run store's format, :mod:`lfcore.runstore`, is the one exception, with :mod:`lfcore.files`, how
every file lfpiv writes is replaced whole). Warp kernels live in
:mod:`lfcore._kernels` behind the plain functions of these modules, which users import:
"""

__all__ = [
    "chief_ray",    # where a world point appears in a raw light-field image
    "correlate",    # 3D multi-grid cross-correlation
    "device",       # Warp devices and CPU threading
    "device_ops",   # image and volume operations on the device
    "errors",       # DeviceError, ComputeDeviceError
    "files",        # replacing a file whole: written beside, flushed, renamed
    "flows",        # the test flows and particle advection
    "matrix_free",  # the matrix-free DRT templates per depth and lenslet phase, and their operator
    "metrics",      # Q_recon, particle matching, diameters, velocity and divergence errors
    "mla",          # the microlens lattice and the sensor's pixel coordinates
    "operator",     # what reconstruction sees of a projection: the Operator and Projector protocols
    "particles",    # seeding and the laser sheet
    "pinhole",      # the pinhole (Tomo-PIV) camera model: projection, lines of sight, triangulation
    "pinhole_projector",  # pinhole cameras bound to a voxel grid: MLOS, line-of-sight weights (MLOS-SMART)
    "plan",         # the planner: which operator, weight cache and depth slabs, and why
    "projector",    # light-field cameras bound to a voxel grid on a device: elimination and their weights
    "reconstruct",  # DRT-MART, MART, MLOS-MART and MLOS-SMART
    "render",       # Monte-Carlo light-field particle images
    "rig",          # the rig description
    "runstore",     # the run store (zarr)
    "soloff",       # the third-order Soloff polynomial mapping
    "target",       # the calibration dot board
    "vectors",      # outliers, replacement, units, vorticity, divergence, Q-criterion
    "volume",       # the voxel grid
    "weight_build",  # the voxel-to-pixel weights (DRT and line of sight): built, and applied as an operator
    "weight_cache",  # weights traced once per voxel across frames
    "white",        # the white image of a plenoptic camera
    "world",        # seeded particles moving with a known flow
    "zarrstore",    # what the run and calibration stores share
]
