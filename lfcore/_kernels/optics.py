"""Camera optics shared by the Warp kernels: the camera's parameters and the MLA lattice.

Sensor-plane coordinates are the camera frame's transverse (x, y) in mm (see
:mod:`lfcore.mla`, which is the NumPy twin of :func:`lenslet_centre`).
"""

from __future__ import annotations

import math

import warp as wp

from lfcore.device import warp as _init
from lfcore.rig import Camera

_init()
wp.set_module_options({"enable_backward": False})

HEX_ROW = 0.8660254037844386


@wp.struct
class CameraParams:
    so: float  # main lens to focal plane, mm
    inv_f: float  # 1 / F, 1/mm
    si: float  # main lens to MLA, mm
    f_ml: float  # MLA to sensor, mm
    aperture_r: float  # D / 2, mm
    pitch: float  # lenslet pitch, mm
    hex: int  # 1 for a hexagonal grid, 0 for square
    cos_t: float  # MLA rotation
    sin_t: float
    off_x: float  # MLA offset, mm
    off_y: float
    pixel: float  # pixel pitch, mm
    ncols: int
    nrows: int
    sigma_mla: float  # main-lens diffraction blur on the MLA (Gaussian sigma), mm
    sigma_sensor: float  # lenslet diffraction blur on the sensor, mm


@wp.func
def lenslet_centre(cam: CameraParams, qx: float, qy: float) -> wp.vec2:
    """Centre (sensor-plane mm) of the lenslet cell containing (qx, qy)."""
    dx = qx - cam.off_x
    dy = qy - cam.off_y
    u = cam.cos_t * dx + cam.sin_t * dy
    v = -cam.sin_t * dx + cam.cos_t * dy
    p = cam.pitch
    cu = float(0.0)
    cv = float(0.0)
    if cam.hex == 0:
        cu = wp.round(u / p) * p
        cv = wp.round(v / p) * p
    else:
        h = p * HEX_ROW
        j0 = wp.floor(v / h)
        best = float(1.0e30)
        for k in range(2):
            j = j0 + float(k)
            shift = float(0.0)
            if wp.abs(j - 2.0 * wp.floor(j * 0.5)) > 0.5:
                shift = 0.5 * p
            au = wp.round((u - shift) / p) * p + shift
            av = j * h
            d2 = (u - au) * (u - au) + (v - av) * (v - av)
            if d2 < best:
                best = d2
                cu = au
                cv = av
    return wp.vec2(cam.cos_t * cu - cam.sin_t * cv + cam.off_x, cam.sin_t * cu + cam.cos_t * cv + cam.off_y)


def camera_params(camera: Camera, sigma_mla_mm: float = 0.0, sigma_sensor_mm: float = 0.0) -> CameraParams:
    """The kernel-side description of ``camera`` (diffraction blurs as Gaussian sigmas in mm)."""
    t = math.radians(camera.mla_rotation_deg)
    p = CameraParams()
    p.so = camera.object_distance_mm
    p.inv_f = 1.0 / camera.main_focal_length_mm
    p.si = camera.image_distance_mm
    p.f_ml = camera.mla_focal_length_mm
    p.aperture_r = 0.5 * camera.aperture_mm
    p.pitch = camera.mla_pitch_mm
    p.hex = 1 if camera.mla_grid == "hex" else 0
    p.cos_t, p.sin_t = math.cos(t), math.sin(t)
    p.off_x, p.off_y = (v * 1e-3 for v in camera.mla_offset_um)
    p.pixel = camera.pixel_mm
    p.ncols, p.nrows = camera.sensor_px
    p.sigma_mla = sigma_mla_mm
    p.sigma_sensor = sigma_sensor_mm
    return p
