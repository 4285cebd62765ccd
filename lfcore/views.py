"""Perspective (sub-aperture) views and refocused planes of a raw light-field image.

Physics. Behind an unfocused MLA each lenslet images the main-lens pupil onto the sensor: the
pixel at offset d (sensor-plane mm) from a micro-image centre sees the light that crossed the
lenslet centre c from the pupil point A with c + f_ml (c - A) / si = k c + d, i.e.
``A = -si d / f_ml`` (k = 1 + f_ml / si, :mod:`lfcore.white`), the same A for every lenslet. So
the samples of all micro-images at one offset d form an image through one small part of the
aperture: a perspective view, one sample per lenslet. A point E is seen in the view through A
where its ray through A meets the MLA (:func:`lfcore.chief_ray.project` with ``pupil_mm=A``),
which moves with A in proportion to its defocus ``si (1 / d_E - 1 / so)``: parallax. Shifting
every view back by the parallax of a plane and averaging them (shift-and-add) brings the
points of that plane into register and blurs the others: a refocused image of the plane.

The lattice is the micro-image lattice in raw pixels: measured from a white image
(:mod:`calibration.mla_grid` fits it; the application passes its origin and basis) or, without
a calibration, the camera's nominal one (:func:`nominal_lattice`). Views are indexed by the
lattice indices (n1, n2) along its basis vectors, so a hexagonal lattice is sampled on its own
(sheared) grid; :func:`view_display` shears each row back for a picture.

Pixel coordinates are continuous (column, row) as in :mod:`lfcore.mla`: pixel ``[r, c]`` covers
``c <= column < c + 1``, so its centre is (c + 0.5, r + 0.5).

Pure computation: arrays and frozen configs in, arrays out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lfcore.chief_ray import project
from lfcore.mla import HEX_ROW
from lfcore.rig import Camera, require_lightfield
from lfcore.white import micro_image_scale

__all__ = ["Lattice", "Views", "depth_point", "focus_measure", "nominal_lattice", "refocus", "refocus_stack",
           "sample_views",
           "view_display", "view_mosaic", "view_offsets", "view_pupil_mm", "view_shifts_px"]


@dataclass(frozen=True)
class Lattice:
    """The micro-image lattice of a raw image, in pixels.

    Attributes
    ----------
    origin_px
        (column, row) of lattice node (0, 0).
    basis_px
        (2, 2): rows are the basis vectors a1, a2 in (column, row) pixels; node (n1, n2) is at
        ``origin + n1 a1 + n2 a2``.
    grid
        "hex" or "square".
    """

    origin_px: tuple[float, float]
    basis_px: np.ndarray = field(repr=False)
    grid: str = "hex"

    def __post_init__(self) -> None:
        b = np.array(self.basis_px, dtype=np.float64)
        if b.shape != (2, 2) or abs(np.linalg.det(b)) < 1e-9:
            raise ValueError(f"basis_px must be two independent 2-vectors, got {self.basis_px!r}")
        b.flags.writeable = False
        object.__setattr__(self, "basis_px", b)
        if self.grid not in ("hex", "square"):
            raise ValueError(f"grid must be 'hex' or 'square', got {self.grid!r}")

    @property
    def pitch_px(self) -> float:
        """Distance between neighbouring micro-image centres, pixels."""
        return float(np.hypot(*self.basis_px[0]))

    def nodes(self, shape: tuple[int, int], *, margin_px: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every lattice node of an index rectangle that covers an image, and which lie inside it.

        Parameters
        ----------
        shape
            (rows, columns) of the raw image.
        margin_px
            A node is inside when its centre is at least this far from every image edge.

        Returns
        -------
        n1, n2 : numpy.ndarray
            (N1,) and (N2,) int64 index ranges (the views' columns and rows).
        inside : numpy.ndarray
            (N2, N1) bool.
        """
        rows, cols = shape
        corners = np.array([[0.0, 0.0], [cols, 0.0], [0.0, rows], [cols, rows]]) - np.asarray(self.origin_px)
        idx = corners @ np.linalg.inv(self.basis_px)
        lo, hi = np.floor(idx.min(axis=0)).astype(int), np.ceil(idx.max(axis=0)).astype(int)
        n1, n2 = np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1)
        c = self.centres(n1, n2)
        inside = ((c[..., 0] >= margin_px) & (c[..., 0] <= cols - margin_px)
                  & (c[..., 1] >= margin_px) & (c[..., 1] <= rows - margin_px))
        # trim index rows and columns with no node inside
        keep2, keep1 = inside.any(axis=1), inside.any(axis=0)
        return n1[keep1], n2[keep2], inside[np.ix_(keep2, keep1)]

    def centres(self, n1: np.ndarray, n2: np.ndarray) -> np.ndarray:
        """(N2, N1, 2) (column, row) of the nodes of index ranges ``n1`` (columns) and ``n2`` (rows)."""
        b = self.basis_px
        return (np.asarray(self.origin_px) + np.asarray(n1, dtype=np.float64)[None, :, None] * b[0]
                + np.asarray(n2, dtype=np.float64)[:, None, None] * b[1])


def nominal_lattice(camera: Camera) -> Lattice:
    """The micro-image lattice the camera's nominal MLA (pitch, rotation, offset) gives.

    Micro-image centres are the lenslet centres scaled by k = 1 + f_ml / si about the optical
    axis (:mod:`lfcore.white`); lenslet centres are ``R(rotation) (i a1 + j a2) + offset`` in the
    sensor plane (:mod:`lfcore.mla`), and pixels mirror x.
    """
    cam = require_lightfield(camera, "a microlens lattice")
    k = micro_image_scale(cam)
    p = cam.mla_pitch_mm
    a = np.array([[p, 0.0], [0.5 * p, p * HEX_ROW]]) if cam.mla_grid == "hex" else np.array([[p, 0.0], [0.0, p]])
    t = math.radians(cam.mla_rotation_deg)
    rot = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    a_xy = a @ rot.T * k  # basis in the sensor plane at the micro-images, mm
    to_px = np.array([-1.0, 1.0]) / cam.pixel_mm  # sensor mm -> pixel offsets (x mirrored)
    nc, nr = cam.sensor_px
    off = k * np.asarray(cam.mla_offset_um) * 1e-3
    origin = (0.5 * nc + off[0] * to_px[0], 0.5 * nr + off[1] * to_px[1])
    return Lattice(origin_px=(float(origin[0]), float(origin[1])), basis_px=a_xy * to_px, grid=cam.mla_grid)


def view_offsets(lattice: Lattice, *, radius_px: float | None = None) -> np.ndarray:
    """The whole-pixel offsets (column, row) from the micro-image centre of every view.

    Parameters
    ----------
    lattice
        The micro-image lattice.
    radius_px
        Largest offset kept, pixels (default: half a pitch less half a pixel, the disc of a
        camera with matched f-numbers; views beyond the micro-image disc are dark).

    Returns
    -------
    numpy.ndarray
        (n_views, 2) int64 offsets (du, dv), in row-major order of (dv, du).
    """
    r = 0.5 * lattice.pitch_px - 0.5 if radius_px is None else float(radius_px)
    m = int(math.floor(r))
    dv, du = np.meshgrid(np.arange(-m, m + 1), np.arange(-m, m + 1), indexing="ij")
    keep = du**2 + dv**2 <= r * r + 1e-9
    return np.stack([du[keep], dv[keep]], axis=1).astype(np.int64)


@dataclass(frozen=True)
class Views:
    """The perspective views of one raw image.

    Attributes
    ----------
    images
        (n_views, N2, N1) float32: view v's sample at lattice node (n1[j], n2[i]) is
        ``images[v, i, j]``; 0 where the node is outside the image.
    offsets_px
        (n_views, 2) int64 offsets (du, dv) from the micro-image centre, pixels.
    n1, n2
        The lattice index ranges of the columns and rows.
    inside
        (N2, N1) bool: nodes whose micro-image lies wholly in the image.
    lattice
        The lattice they were sampled on.
    """

    images: np.ndarray = field(repr=False)
    offsets_px: np.ndarray
    n1: np.ndarray = field(repr=False)
    n2: np.ndarray = field(repr=False)
    inside: np.ndarray = field(repr=False)
    lattice: Lattice

    def view(self, du: int, dv: int) -> np.ndarray:
        """The view at offset (du, dv), (N2, N1)."""
        hit = np.flatnonzero((self.offsets_px[:, 0] == du) & (self.offsets_px[:, 1] == dv))
        if not len(hit):
            raise KeyError(f"no view at offset ({du}, {dv}); offsets reach {int(np.abs(self.offsets_px).max())} px")
        return self.images[hit[0]]

    @property
    def centre(self) -> np.ndarray:
        """The central view (offset (0, 0)), (N2, N1)."""
        return self.view(0, 0)

    def picture(self, image: np.ndarray, *, upsample: int = 1) -> np.ndarray:
        """A view, or a plane refocused from these views, as an upright picture (:func:`view_display`)."""
        return view_display(image, self.lattice, self.n2, inside=self.inside, upsample=upsample)


def sample_views(image: np.ndarray, lattice: Lattice, *, radius_px: float | None = None,
                 white: np.ndarray | None = None, min_white: float = 0.2) -> Views:
    """Every perspective view of a raw image: the pixels at one offset from every micro-image centre.

    View (du, dv) at node n is the raw image at ``centre(n) + (du, dv)`` (bilinear: the centres
    are sub-pixel, the offsets whole pixels, so each node's four weights serve every view).

    Parameters
    ----------
    image
        (rows, columns) raw image, counts (any real dtype).
    lattice
        The micro-image lattice (calibrated, or :func:`nominal_lattice`).
    radius_px
        Largest offset, pixels (see :func:`view_offsets`).
    white
        (rows, columns) white image of the same camera, or None. Given, each view is divided by
        the same view of the white image (a display normalisation of each micro-image's
        vignetting), and samples where the white view is below ``min_white`` of its 99th
        percentile are 0.
    min_white
        See ``white``.

    Returns
    -------
    Views
    """
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"a raw image is a 2-D array, got shape {img.shape}")
    offsets = view_offsets(lattice, radius_px=radius_px)
    reach = float(np.abs(offsets).max(initial=0)) + 1.0
    n1, n2, inside = lattice.nodes(img.shape, margin_px=reach + 0.5)
    if not inside.any():
        raise ValueError(f"no micro-image lies wholly inside the {img.shape[1]} x {img.shape[0]} image; "
                         "is the lattice this camera's?")
    out = _gather(img, lattice, offsets, n1, n2, inside)
    if white is not None:
        w = np.asarray(white)
        if w.shape != img.shape:
            raise ValueError(f"the white image is {w.shape[1]} x {w.shape[0]} px but the raw image "
                             f"{img.shape[1]} x {img.shape[0]}")
        wv = _gather(w, lattice, offsets, n1, n2, inside)
        floor = min_white * float(np.percentile(wv[:, inside], 99))
        ok = wv > max(floor, 1e-12)
        out = np.where(ok, out / np.where(ok, wv, 1.0), 0.0).astype(np.float32)
    return Views(images=out, offsets_px=offsets, n1=n1, n2=n2, inside=inside, lattice=lattice)


def _gather(img: np.ndarray, lattice: Lattice, offsets: np.ndarray, n1: np.ndarray, n2: np.ndarray,
            inside: np.ndarray) -> np.ndarray:
    rows, cols = img.shape
    c = lattice.centres(n1, n2)[inside]  # (n, 2) (column, row)
    # the image value at continuous (column, row) p is that of pixel centre p - 0.5
    p = c - 0.5
    p0 = np.floor(p).astype(np.int64)
    f = (p - p0).astype(np.float32)
    w00, w01 = (1 - f[:, 0]) * (1 - f[:, 1]), f[:, 0] * (1 - f[:, 1])
    w10, w11 = (1 - f[:, 0]) * f[:, 1], f[:, 0] * f[:, 1]
    base = p0[:, 1] * cols + p0[:, 0]
    flat = np.ascontiguousarray(img).reshape(-1)
    if flat.dtype != np.float32:
        flat = flat.astype(np.float32)
    out = np.zeros((len(offsets), *inside.shape), dtype=np.float32)
    sel = np.flatnonzero(inside.reshape(-1))
    view = np.empty(inside.size, dtype=np.float32)
    for v, (du, dv) in enumerate(offsets):
        i = base + (dv * cols + du)
        view[:] = 0.0
        view[sel] = w00 * flat[i] + w01 * flat[i + 1] + w10 * flat[i + cols] + w11 * flat[i + cols + 1]
        out[v] = view.reshape(inside.shape)
    return out


def view_pupil_mm(camera: Camera, offsets_px: np.ndarray) -> np.ndarray:
    """The main-lens pupil point each view looks through, camera-frame (x, y) mm.

    A pixel at sensor-plane offset d from its micro-image centre sees the ray through the lenslet
    centre from the pupil point A = -si d / f_ml (module docstring).

    Parameters
    ----------
    camera
        The camera (image distance, lenslet focal length, pixel pitch).
    offsets_px
        (..., 2) offsets (column, row) from the micro-image centre, pixels.

    Returns
    -------
    numpy.ndarray
        (..., 2) pupil points (x, y), mm.
    """
    cam = require_lightfield(camera, "perspective views")
    o = np.asarray(offsets_px, dtype=np.float64)
    d = np.stack([-o[..., 0], o[..., 1]], axis=-1) * cam.pixel_mm  # pixels -> sensor mm (x mirrored)
    return -cam.image_distance_mm * d / cam.mla_focal_length_mm


def depth_point(camera: Camera, depth_mm: float) -> np.ndarray:
    """Where the camera's optical axis crosses the rig's plane z = ``depth_mm`` (world mm, (3,)).

    Raises
    ------
    ValueError
        The camera's axis runs along the plane (it looks across the rig's z axis).
    """
    axis = camera.optical_axis
    if abs(axis[2]) < 0.1:
        raise ValueError(f"camera '{camera.name}' looks across the rig's z axis (its axis is "
                         f"{np.round(axis, 3).tolist()}); planes of constant z are edge-on to it")
    focus = np.asarray(camera.focus_mm, dtype=np.float64)
    return focus + (depth_mm - focus[2]) / axis[2] * axis


def view_shifts_px(camera: Camera, offsets_px: np.ndarray, depth_mm: float) -> np.ndarray:
    """The parallax of a plane in every view: where its points appear relative to the central view.

    For the point where the camera's axis crosses the rig's plane z = ``depth_mm``, the raw-image
    position in each view (:func:`lfcore.chief_ray.project` through the view's pupil point,
    :func:`view_pupil_mm`) minus its position in the central view. The shift depends on the
    point's depth along the camera's axis only (si A (1 / d - 1 / so), times k on the sensor),
    not on where it lies across the field: the plane refocused is the one through that point
    square to the camera's axis (the rig's plane itself for a camera looking along z).

    Parameters
    ----------
    camera
        The camera.
    offsets_px
        (n_views, 2) view offsets (column, row), pixels.
    depth_mm
        The plane's z in the rig's frame, mm.

    Returns
    -------
    numpy.ndarray
        (n_views, 2) shifts (column, row) in raw pixels; 0 on the focal plane.
    """
    e = depth_point(camera, depth_mm)
    ref = project(camera, e)
    pupils = view_pupil_mm(camera, offsets_px)
    return np.array([project(camera, e, pupil_mm=(float(a[0]), float(a[1]))) - ref for a in pupils]).reshape(-1, 2)


def _rolled(img: np.ndarray, d1: int, d2: int) -> np.ndarray:
    """``img`` read at (n1 + d1, n2 + d2) for whole d1, d2 (0 beyond the edges), same shape."""
    rows, cols = img.shape
    out = np.zeros_like(img)
    r0, r1 = max(0, -d2), min(rows, rows - d2)
    c0, c1 = max(0, -d1), min(cols, cols - d1)
    if r1 > r0 and c1 > c0:
        out[r0:r1, c0:c1] = img[r0 + d2:r1 + d2, c0 + d1:c1 + d1]
    return out


def _upsampled(img: np.ndarray, s: int, p1: int, p2: int) -> np.ndarray:
    """``img`` interpolated linearly onto a grid ``s`` times finer, read ``p1``, ``p2`` fine steps on.

    Fine sample f = n s + t stands for coarse position n + (t + p) / s.
    """
    rows, cols = img.shape

    def axis(a: np.ndarray, n: int, p: int, ax: int) -> np.ndarray:
        pos = (np.arange(n * s) + p) / s
        i0 = np.floor(pos).astype(np.int64)
        f = (pos - i0).astype(np.float32)
        pad = np.concatenate([a, np.zeros_like(a.take([0], axis=ax))], axis=ax)
        lo = np.take(pad, np.clip(i0, 0, n), axis=ax)
        hi = np.take(pad, np.clip(i0 + 1, 0, n), axis=ax)
        shape = [1, 1]
        shape[ax] = -1
        f = f.reshape(shape)
        return (1 - f) * lo + f * hi

    return axis(axis(img, cols, p1, 1), rows, p2, 0)


def refocus(views: Views, camera: Camera, depth_mm: float, *, upsample: int = 1) -> np.ndarray:
    """The image refocused on the rig's plane z = ``depth_mm``: the views shifted back by its parallax and averaged.

    Each view is shifted by the parallax (:func:`view_shifts_px`) rounded to 1 / ``upsample`` of
    a lattice step: the views of one sub-step phase are added at whole lattice steps, and each
    phase's sum is interpolated linearly onto the finer grid once. Every depth therefore gets
    the same interpolation blur, so sharpness compares fairly across depths.

    Parameters
    ----------
    views
        The perspective views (:func:`sample_views`).
    camera
        The camera (its optics give the parallax, :func:`view_shifts_px`).
    depth_mm
        The plane's z in the rig's frame, mm.
    upsample
        Samples per lattice step of the result (1: one per lenslet; more resolves the sub-lenslet
        parallax of planes near the focal plane).

    Returns
    -------
    numpy.ndarray
        (N2 upsample, N1 upsample) float32: fine sample (i, j) stands for lattice position
        (n1[0] + j / upsample, n2[0] + i / upsample); the mean over the views that reach it (0
        where fewer than a quarter of them do).
    """
    s = int(upsample)
    if s < 1:
        raise ValueError(f"upsample must be a whole number >= 1, got {upsample}")
    shifts = view_shifts_px(camera, views.offsets_px, depth_mm)
    dn = shifts @ np.linalg.inv(views.lattice.basis_px)  # raw pixels -> lattice indices
    q = np.rint(dn * s).astype(np.int64)  # fine steps
    whole = np.floor_divide(q, s)
    phase = q - whole * s
    inside = views.inside.astype(np.float32)
    fine_acc = np.zeros((inside.shape[0] * s, inside.shape[1] * s), dtype=np.float32)
    fine_hits = np.zeros_like(fine_acc)
    for p1, p2 in sorted({(int(a), int(b)) for a, b in phase}):
        members = np.flatnonzero((phase[:, 0] == p1) & (phase[:, 1] == p2))
        acc = np.zeros_like(inside)
        hits = np.zeros_like(inside)
        for v in members:
            # a point of the plane seen at node n in the central view is at n + dn in this view
            acc += _rolled(views.images[v], int(whole[v, 0]), int(whole[v, 1]))
            hits += _rolled(inside, int(whole[v, 0]), int(whole[v, 1]))
        fine_acc += _upsampled(acc, s, p1, p2) if s > 1 else acc
        fine_hits += _upsampled(hits, s, p1, p2) if s > 1 else hits
    # nodes that few views reach (at the edges) average too little light to show
    enough = fine_hits >= max(0.25 * len(views.offsets_px), 0.5)
    out = np.where(enough, fine_acc / np.maximum(fine_hits, 1e-6), 0.0)
    return out.astype(np.float32)


def refocus_stack(views: Views, camera: Camera, depths_mm: np.ndarray, *, upsample: int = 1) -> np.ndarray:
    """:func:`refocus` at every depth: (n_depths, N2 upsample, N1 upsample) float32."""
    return np.stack([refocus(views, camera, float(z), upsample=upsample) for z in np.atleast_1d(depths_mm)])


def focus_measure(planes: np.ndarray) -> np.ndarray:
    """How sharp each refocused plane is: the variance of its samples over the nodes every plane reaches.

    A plane through particles gathers each particle's light from all views into one spot, which
    raises the variance; planes before and behind spread it. The nodes near the edges that some
    planes leave empty (0, :func:`refocus`) are left out of every plane, so the edges do not
    decide.

    Parameters
    ----------
    planes
        (n_depths, rows, columns) refocused planes (:func:`refocus_stack`).

    Returns
    -------
    numpy.ndarray
        (n_depths,) float64 variances; the sharpest plane has the largest.
    """
    p = np.asarray(planes, dtype=np.float64)
    common = np.all(p != 0, axis=0)
    if not common.any():
        return np.zeros(len(p))
    return p[:, common].var(axis=1)


def view_display(image: np.ndarray, lattice: Lattice, n2: np.ndarray, *, inside: np.ndarray | None = None,
                 upsample: int = 1) -> np.ndarray:
    """A view (or refocused image) on the lattice's nodes as a picture on a rectangular grid.

    A hexagonal lattice's index grid is sheared (each row is half a pitch along from the last);
    each row is moved back by whole columns so the picture is upright (rows then alternate by
    half a sample, as any hexagonal image shown on square pixels), and turned so that columns
    and rows run as the raw image's do. Square lattices are only turned.

    Parameters
    ----------
    image
        (N2 upsample, N1 upsample) samples on the nodes of index rows ``n2`` (``upsample`` per
        lattice step, as :func:`refocus` gives them).
    lattice
        The lattice.
    n2
        (N2,) the rows' lattice indices.
    inside
        (N2, N1) bool, the nodes inside the image (:attr:`Views.inside`): the columns the shear
        leaves without any are trimmed. None: nothing is trimmed.
    upsample
        Samples per lattice step of ``image``.

    Returns
    -------
    numpy.ndarray
        (rows, columns) float32 picture.
    """
    img = np.asarray(image, dtype=np.float32)
    up = int(upsample)
    b = lattice.basis_px
    # the a2 component along a1, in pitches: how far along each row starts from the last
    step = float(b[1] @ b[0]) / float(b[0] @ b[0])
    mask = None if inside is None else np.kron(np.asarray(inside, dtype=bool), np.ones((up, up), dtype=bool))
    if abs(step) < 1e-6:
        return _upright(img if mask is None else _trim(img, mask), b)
    rows = float(np.asarray(n2)[0]) + np.arange(img.shape[0]) / up
    shift = np.floor(rows * step * up + 1e-9).astype(int)
    shift -= shift.min()
    width = img.shape[1] + int(shift.max())
    out = np.zeros((img.shape[0], width), dtype=np.float32)
    keep = np.zeros(out.shape, dtype=bool)
    for r, s in enumerate(shift):
        out[r, s:s + img.shape[1]] = img[r]
        if mask is not None:
            keep[r, s:s + img.shape[1]] = mask[r]
    return _upright(out if mask is None else _trim(out, keep), b)


def _trim(img: np.ndarray, keep: np.ndarray) -> np.ndarray:
    cols = np.flatnonzero(keep.any(axis=0))
    return img[:, cols[0]:cols[-1] + 1] if len(cols) else img


def _upright(img: np.ndarray, b: np.ndarray) -> np.ndarray:
    # index n1 may run toward smaller columns (the readout mirrors x), n2 toward smaller rows
    if b[0, 0] < 0:
        img = img[:, ::-1]
    if b[1, 1] < 0:
        img = img[::-1, :]
    return np.ascontiguousarray(img)


def view_mosaic(views: Views) -> np.ndarray:
    """Every view in one picture, tiled by offset: tile (dv, du) is view (du, dv) (:func:`view_display`).

    Returns
    -------
    numpy.ndarray
        (tiles * h, tiles * w) float32, 0 between and where there is no view.
    """
    tiles = [view_display(v, views.lattice, views.n2, inside=views.inside) for v in views.images]
    h, w = tiles[0].shape
    m = int(np.abs(views.offsets_px).max(initial=0))
    n = 2 * m + 1
    gap = 1
    out = np.zeros((n * (h + gap) - gap, n * (w + gap) - gap), dtype=np.float32)
    for t, (du, dv) in zip(tiles, views.offsets_px, strict=True):
        r, c = (dv + m) * (h + gap), (du + m) * (w + gap)
        out[r:r + h, c:c + w] = t
    return out
