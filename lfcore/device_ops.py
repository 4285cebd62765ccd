"""Image and volume operations that keep the data on the Warp device.

The live pipeline uploads raw 16-bit frames once and brings back only what a person looks at
(projections, one slice) and the vectors; these classes do the steps in between on the device
with buffers allocated once. Their results equal the host versions
(:func:`lfcore.reconstruct.preprocess`, ``scipy.ndimage.gaussian_filter`` with
``mode="constant", truncate=3.0``, ``numpy.max``) to float32 rounding.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import ndimage

from lfcore._deprecation import keyword_options
from lfcore.device import RowOffset, launch_rows, resolve_device, warp
from lfcore.flatfield import FlatField
from lfcore.rig import Camera

__all__ = ["ImagePreprocessor", "VolumeOps", "gaussian_taps"]


def gaussian_taps(sigma: float, *, truncate: float = 3.0) -> np.ndarray:
    """Normalised 1-D Gaussian taps (2 r + 1,), r = int(truncate sigma + 0.5), as SciPy's."""
    radius = int(truncate * float(sigma) + 0.5)
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    taps = np.exp(-0.5 * (x / float(sigma)) ** 2)
    return (taps / taps.sum()).astype(np.float32)


class ImagePreprocessor:
    """Background subtraction and the lit mask of every camera's raw frame, on the device.

    Parameters
    ----------
    cameras
        The cameras, in the order their pixels are concatenated (the projector's order).
    device
        Warp device; None for the first GPU, else the CPU.

    Notes
    -----
    Inputs are flat uint16 arrays of all cameras' pixels (camera after camera, each row-major),
    ``n_pixels`` long. Outputs, into caller-provided arrays of the same length: the float32
    signal (raw minus the background level where that exceeds the threshold, zero elsewhere)
    and the uint8 lit mask, grown by ``grow`` pixels with a 3 x 3 square (pixels past the
    image border count as dark), exactly as :func:`lfcore.reconstruct.preprocess` without its
    ``hysteresis`` (:attr:`lfcore.reconstruct.ReconSettings.lit_hysteresis`, which the live pipeline
    refuses). With ``flats``
    (per camera a :class:`lfcore.flatfield.FlatField` or None) every frame is corrected first, as
    :func:`lfcore.flatfield.correct` does, its masked pixels given the signal
    :data:`lfcore.reconstruct.MASKED` and counted as lit.
    """

    @keyword_options("device", "flats", since="0.1.0")
    def __init__(self, cameras: Sequence[Camera], *, device: str | None = None,
                 flats: Sequence[FlatField | None] | None = None) -> None:
        from lfcore._kernels import images as ki

        self._k = ki
        self.wp = warp()
        self.device = resolve_device(device)
        self.shapes = [(int(c.sensor_px[1]), int(c.sensor_px[0])) for c in cameras]
        sizes = [r * c for r, c in self.shapes]
        self.offsets = [0, *np.cumsum(sizes).tolist()]
        self.n_pixels = int(self.offsets[-1])
        self._grown = self.wp.empty(self.n_pixels, dtype=self.wp.uint8, device=self.device)
        # per-pixel dark and 1 / gain of the cameras with a flat field (0: masked), on the device
        self._flat = None
        if flats is not None and any(f is not None for f in flats):
            dark = np.zeros(self.n_pixels, np.float32)
            inv = np.ones(self.n_pixels, np.float32)
            for i, f in enumerate(flats):
                if f is None:
                    continue
                if f.shape != self.shapes[i]:
                    raise ValueError(f"the flat field of camera '{cameras[i].name}' is {f.shape[0]} x {f.shape[1]} "
                                     f"px but its frames {self.shapes[i][0]} x {self.shapes[i][1]}")
                sl = slice(self.offsets[i], self.offsets[i + 1])
                dark[sl] = f.dark.ravel()
                inv[sl] = np.where(f.mask, 0.0, 1.0 / f.gain).ravel()
            self._flat = (self.wp.array(dark, dtype=float, device=self.device),
                          self.wp.array(inv, dtype=float, device=self.device))

    @keyword_options("grow", "stream", since="0.1.0")
    def __call__(self, raw, levels: Sequence[float], thresholds: Sequence[float], signal, lit, *, grow: int = 0,
                 stream=None) -> None:
        """Preprocess one frame of every camera.

        Parameters
        ----------
        raw
            (n_pixels,) uint16 Warp array on the device: the raw frames, in counts.
        levels, thresholds
            Per camera, the background level and the signal threshold above it, in counts.
        signal, lit
            (n_pixels,) float32 and uint8 Warp arrays written.
        grow
            Pixels by which the lit mask is widened.
        stream
            CUDA stream to launch on (None: the device's current stream).
        """
        wp, k, d = self.wp, self._k, self.device
        for i, (rows, cols) in enumerate(self.shapes):
            if self._flat is not None:  # every frame flat-field corrected (cameras without one: dark 0, gain 1)
                launch_rows(k.subtract_threshold_flat, rows * cols,
                            [raw, RowOffset(self.offsets[i]), *self._flat, float(levels[i]), float(thresholds[i]),
                             signal, lit], d, stream=stream)
                continue
            launch_rows(k.subtract_threshold, rows * cols,
                        [raw, RowOffset(self.offsets[i]), float(levels[i]), float(thresholds[i]), signal, lit], d,
                        stream=stream)
        for _ in range(int(grow)):
            for i, (rows, cols) in enumerate(self.shapes):
                launch_rows(k.dilate3x3, rows, [lit, self.offsets[i], rows, cols, RowOffset(0), self._grown], d,
                            rest=(cols,), stream=stream)
            wp.copy(lit, self._grown, stream=stream)


class VolumeOps:
    """Gaussian smoothing, maximum-intensity projections and slices of (z, y, x) volumes on the device.

    Parameters
    ----------
    shape
        (nz, ny, nx) of the volumes.
    device
        Warp device; None for the first GPU, else the CPU.
    """

    @keyword_options("device", since="0.1.0")
    def __init__(self, shape: tuple[int, int, int], *, device: str | None = None) -> None:
        from lfcore._kernels import volumes as kv

        self._k = kv
        self.wp = warp()
        self.device = resolve_device(device)
        self.shape = tuple(int(n) for n in shape)
        self._tmp: object | None = None
        self._taps: dict[float, object] = {}
        self._planes: dict[int, object] = {}  # per axis, one plane buffer (made on first use)

    def empty(self):
        """A new (z, y, x) float32 volume on the device (contents undefined)."""
        return self.wp.empty(self.shape, dtype=float, device=self.device)

    def smooth(self, vol, sigma: float) -> None:
        """Gaussian-smooth ``vol`` in place (sigma in voxels, every axis; zero outside).

        Equals ``scipy.ndimage.gaussian_filter(vol, sigma, mode="constant", truncate=3.0)``: on a GPU
        by three passes of a kernel, on the CPU (whose arrays are host memory) by that filter itself.
        """
        if sigma <= 0:
            return
        if self._tmp is None:
            self._tmp = self.empty()
        if self.device == "cpu":  # the array is host memory: SciPy's filter, about 8x less CPU than the kernels' passes
            host = vol.numpy()
            ndimage.gaussian_filter(host, float(sigma), mode="constant", truncate=3.0, output=self._tmp.numpy())
            np.copyto(host, self._tmp.numpy())
            return
        self._smooth_passes(vol, sigma)

    def _smooth_passes(self, vol, sigma: float) -> None:
        """:meth:`smooth` by three passes of the separable kernel (a GPU's way; any device runs it, so the
        CPU's tests check the kernels too)."""
        wp, d = self.wp, self.device
        if self._tmp is None:
            self._tmp = self.empty()
        taps = self._taps.get(float(sigma))
        if taps is None:
            taps = self._taps[float(sigma)] = wp.array(gaussian_taps(sigma), dtype=float, device=d)
        radius = (taps.shape[0] - 1) // 2
        # z into tmp, y back into vol, x into tmp, then tmp copied to vol
        src, dst = vol, self._tmp
        for axis in (0, 1, 2):
            launch_rows(self._k.convolve_axis, self.shape[0], [src, taps, radius, axis, RowOffset(0), dst], d,
                        rest=self.shape[1:])
            src, dst = dst, src
        wp.copy(vol, src)

    def _to_host(self, kernel, vol, axis: int, *args) -> np.ndarray:
        """Run a plane kernel (output: the volume's shape without ``axis``) and copy its plane to the host."""
        out = self._planes.get(axis)
        if out is None:
            dims = tuple(n for i, n in enumerate(self.shape) if i != axis)
            out = self._planes[axis] = self.wp.empty(dims, dtype=float, device=self.device)
        self.wp.launch(kernel, dim=out.shape, device=self.device, inputs=[vol, axis, *args, out])
        return out.numpy().copy()

    def projection(self, vol, axis: int) -> np.ndarray:
        """Maximum-intensity projection along array ``axis`` (0 z, 1 y, 2 x), on the host."""
        return self._to_host(self._k.max_along, vol, axis)

    def plane(self, vol, axis: int, index: int) -> np.ndarray:
        """The plane ``index`` normal to array ``axis``, on the host."""
        if not 0 <= index < self.shape[axis]:
            raise IndexError(f"slice {index} is outside the volume's {self.shape[axis]} planes along axis {axis}")
        return self._to_host(self._k.take_slice, vol, axis, int(index))
