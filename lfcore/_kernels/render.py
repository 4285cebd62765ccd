"""Monte-Carlo ray tracing of point particles through a plenoptic camera, and sensor exposure.

Paraxial thin-lens optics in the camera frame (see :mod:`lfcore.rig`). A ray leaves the
particle E, passes the main lens at aperture point A with transverse slope
s_in = (A - E_xy) / (so - E_z), and is bent to s_out = s_in - A / F. It reaches the MLA at
q = A + si * s_out, enters the lenslet whose cell contains q (centre c), and that lenslet,
one focal length f_ml in front of the sensor, sends it to c + f_ml * s_out: every pixel under a
lenslet corresponds to one direction, i.e. one sub-aperture of the main lens.
"""

from __future__ import annotations

import warp as wp

from lfcore._kernels.optics import CameraParams, lenslet_centre
from lfcore.device import warp as _init

_init()
wp.set_module_options({"enable_backward": False})

#: Fixed-point scale of the accumulation buffer: one count is 2**20 quanta. Integer atomics
#: make the sum independent of thread order, so a seed gives identical images on the GPU too.
QUANTA_PER_COUNT = float(2**20)

@wp.func
def box_muller(u1: float, u2: float) -> wp.vec2:
    """Two independent standard normal samples from two uniform ones.

    (Takes the uniforms rather than the RNG state: a Warp function gets its own copy of a
    state argument, so drawing inside it would not advance the caller's state.)
    """
    r = wp.sqrt(-2.0 * wp.log(wp.max(u1, 1.0e-12)))
    t = 6.283185307179586 * u2
    return wp.vec2(r * wp.cos(t), r * wp.sin(t))


@wp.kernel
def trace_particles(
    cam: CameraParams,
    points: wp.array(dtype=wp.vec3),
    quanta_per_ray: wp.array(dtype=wp.int64),
    radius: float,
    rays_per_particle: int,
    rays_per_thread: int,
    chunks: int,
    seed: int,
    tid0: int,
    image: wp.array2d(dtype=wp.int64),
):
    """One thread traces ``rays_per_thread`` rays of one particle (camera-frame points, mm).

    The launch covers threads ``tid0 + tid`` (a thread's random stream depends on that index
    only, so a launch split into blocks draws the same rays).
    """
    tid = wp.tid() + tid0
    ip = tid // chunks
    first = (tid - ip * chunks) * rays_per_thread
    n = wp.min(rays_per_thread, rays_per_particle - first)
    state = wp.rand_init(seed, tid)
    centre = points[ip]
    w = quanta_per_ray[ip]
    for _k in range(n):
        e = centre
        if radius > 0.0:
            e = centre + radius * wp.sample_unit_sphere(state)
        a = cam.aperture_r * wp.sample_unit_disk(state)
        inv_so = 1.0 / (cam.so - e[2])
        sx = (a[0] - e[0]) * inv_so - a[0] * cam.inv_f
        sy = (a[1] - e[1]) * inv_so - a[1] * cam.inv_f
        qx = a[0] + cam.si * sx
        qy = a[1] + cam.si * sy
        if cam.sigma_mla > 0.0:
            g = box_muller(wp.randf(state), wp.randf(state))
            qx += cam.sigma_mla * g[0]
            qy += cam.sigma_mla * g[1]
        c = lenslet_centre(cam, qx, qy)
        x = c[0] + cam.f_ml * sx
        y = c[1] + cam.f_ml * sy
        if cam.sigma_sensor > 0.0:
            g = box_muller(wp.randf(state), wp.randf(state))
            x += cam.sigma_sensor * g[0]
            y += cam.sigma_sensor * g[1]
        col = 0.5 * float(cam.ncols) - x / cam.pixel
        row = 0.5 * float(cam.nrows) + y / cam.pixel
        # bounds in floating point: a ray from a point far off the axis lands beyond any int,
        # whose conversion is undefined (it gave negative indices and a crash)
        if col >= 0.0 and row >= 0.0 and col < float(cam.ncols) and row < float(cam.nrows):
            wp.atomic_add(image, int(row), int(col), w)


@wp.kernel
def expose(
    quanta: wp.array2d(dtype=wp.int64),
    count_per_quantum: float,
    background: float,
    gain: float,
    shot_noise: int,
    read_noise: float,
    full_scale: float,
    seed: int,
    r0: int,
    out: wp.array2d(dtype=wp.uint16),
):
    """Irradiance (fixed-point counts) to digital numbers: shot and read noise, saturation.

    The launch covers rows ``r0 + r``; each pixel's noise depends on its own index only.
    """
    r, c = wp.tid()
    r += r0
    mean = float(quanta[r, c]) * count_per_quantum + background
    state = wp.rand_init(seed, r * out.shape[1] + c)
    v = mean
    if shot_noise != 0:
        v = float(wp.poisson(state, mean * gain)) / gain
    if read_noise > 0.0:
        v += read_noise * wp.randn(state)
    v = wp.clamp(wp.round(v), 0.0, full_scale)
    out[r, c] = wp.uint16(v)


@wp.kernel
def expose_response(
    quanta: wp.array2d(dtype=wp.int64),
    count_per_quantum: float,
    response: wp.array2d(dtype=float),
    dark: wp.array2d(dtype=float),
    gain: float,
    shot_noise: int,
    read_noise: float,
    full_scale: float,
    seed: int,
    r0: int,
    out: wp.array2d(dtype=wp.uint16),
):
    """:func:`expose` through a camera's per-pixel response: the light times ``response`` (lens
    fall-off, micro-image vignetting, dust) on the per-pixel ``dark`` offset, then the same noise."""
    r, c = wp.tid()
    r += r0
    mean = float(quanta[r, c]) * count_per_quantum * response[r, c] + dark[r, c]
    state = wp.rand_init(seed, r * out.shape[1] + c)
    v = mean
    if shot_noise != 0:
        v = float(wp.poisson(state, wp.max(mean, 0.0) * gain)) / gain
    if read_noise > 0.0:
        v += read_noise * wp.randn(state)
    v = wp.clamp(wp.round(v), 0.0, full_scale)
    out[r, c] = wp.uint16(v)


@wp.kernel
def quanta_to_counts(quanta: wp.array2d(dtype=wp.int64), count_per_quantum: float, out: wp.array2d(dtype=float)):
    r, c = wp.tid()
    out[r, c] = float(quanta[r, c]) * count_per_quantum
