"""The reconstruction operator: what an algorithm sees of a projection, as protocols.

Geometry, operator and algorithm are separate objects (as in tomography toolkits):

- a **projector** (:class:`Projector`) binds cameras and a voxel grid on a device. It says which
  voxels can hold a particle (elimination) and makes the **operator** of a frame's active voxels;
- an **operator** (:class:`Operator`) is what the algorithms iterate over: its active voxels,
  the forward projection, the multiplicative (SMART) update, the scatter of its intensities into
  a dense volume, its bytes and device. :class:`lfcore.reconstruct.FrameReconstructor`,
  :class:`lfcore.slabs.SlabReconstructor` and the live path see nothing else;
- an **operator source** (:class:`OperatorSource`) gives a stream's frames their operators (from
  a weight cache, from templates, or by a per-frame choice between them).

The implementations are siblings, each named for what it is (:data:`OPERATOR_KINDS`): stored
sparse rows (:class:`lfcore.weight_build.Weights`: ray-traced DRT weights, light-field
line-of-sight weights, the templates' images, pinhole line-of-sight weights or a mixed rig's
joint rows) and the templates applied on the fly (:class:`lfcore.matrix_free.TemplateOperator`).
The projectors are :class:`lfcore.projector.LightFieldProjector`,
:class:`lfcore.pinhole_projector.PinholeProjector` and :class:`lfcore.pinhole_projector.JointProjector`.
Which of them serves a reconstruction is decided in one place, :mod:`lfcore.plan`, the one module
that imports them (an import contract in ``pyproject.toml``).

Pixels of all cameras are numbered globally: camera k's pixel (row, column) is
``pixel_offsets[k] + row * columns + column``; voxels by int32 flat (z, y, x) indices of the
projector's grid (a depth slab numbers its own from its first plane).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from lfcore.device import MemoryBudgetError, Rows, launch_rows, warp
from lfcore.volume import VolumeGrid

__all__ = ["ALL_KINDS", "INDEX_LIMIT", "JOINT", "LINE_OF_SIGHT", "MatrixFreeUnsupported", "OPERATOR_KINDS",
           "Operator", "OperatorSource", "PINHOLE", "PROJECTORS", "Projector", "STORAGE", "TEMPLATES",
           "TEMPLATE_IMAGES", "TRACED", "applied_by", "check_indexable", "from_templates", "gather", "log_ratio",
           "max_planes", "scatter_voxels"]

#: Voxels are numbered by int32 flat indices, so one projector numbers fewer than this many: a larger
#: box (the chapter's 5.5-G-voxel dual-camera one) is reconstructed in depth slabs, each numbering
#: its own voxels (:meth:`Projector.planes`).
INDEX_LIMIT = 2**31

#: What an operator is (:attr:`Operator.kind`): light-field DRT weights, ray traced and stored ...
TRACED = "traced weights"
#: ... light-field line-of-sight weights (the MART baseline's and MLOS-MART's), stored or partly
#: made again in every iteration ...
LINE_OF_SIGHT = "line-of-sight weights"
#: ... the matrix-free templates' images of the voxels, stored (no ray tracing) ...
TEMPLATE_IMAGES = "template images"
#: ... the matrix-free templates applied in every iteration ...
TEMPLATES = "templates"
#: ... pinhole (Tomo-PIV) cameras' line-of-sight weights (MLOS-SMART) ...
PINHOLE = "pinhole weights"
#: ... and a mixed rig's rows of both kinds joined.
JOINT = "joint weights"
#: Every kind, and the ones made from the templates.
ALL_KINDS = (TRACED, LINE_OF_SIGHT, TEMPLATE_IMAGES, TEMPLATES, PINHOLE, JOINT)
OPERATOR_KINDS = {TRACED: "ray-traced DRT weights, stored",
                  LINE_OF_SIGHT: "line-of-sight weights (stored, or made again in each iteration where they do "
                                 "not fit)",
                  TEMPLATE_IMAGES: "the matrix-free templates' images of the active voxels, stored",
                  TEMPLATES: "the matrix-free templates, applied in every iteration",
                  PINHOLE: "pinhole cameras' line-of-sight weights, stored",
                  JOINT: "a mixed rig's light-field and pinhole weights, joined row by row"}
_FROM_TEMPLATES = (TEMPLATE_IMAGES, TEMPLATES)

#: What may apply DRT-MART's operator (``ReconSettings.projector``, ``--projector``): ``auto`` (per
#: frame, :mod:`lfcore.plan`), ``stored`` (traced weights) or ``matrix-free`` (the templates).
PROJECTORS = ("auto", "stored", "matrix-free")
#: Where weights live (``ReconSettings.weight_storage``, ``--weight-storage``).
STORAGE = ("auto", "stored", "on-the-fly")


class MatrixFreeUnsupported(ValueError):
    """The geometry has no matrix-free form (pinhole cameras, alone or beside light-field ones)."""


def max_planes(grid: VolumeGrid) -> int:
    """The most planes of ``grid`` that one projector numbers (fewer than :data:`INDEX_LIMIT` voxels)."""
    return (INDEX_LIMIT - 1) // (grid.shape[1] * grid.shape[2])


def check_indexable(grid: VolumeGrid) -> None:
    """Raise :class:`MemoryBudgetError` (one line, with the fix) if ``grid`` has too many voxels
    for int32 voxel indices (:data:`INDEX_LIMIT`)."""
    if grid.shape[0] > max_planes(grid):
        raise MemoryBudgetError(f"a box of {grid.n_voxels:,} voxels is more than int32 voxel indices number in one "
                                "piece; reconstruct it in depth slabs (--slabs auto) or use a coarser --pvr")


@runtime_checkable
class Operator(Protocol):
    """The projection operator of one frame's active voxels: all an algorithm sees.

    Attributes
    ----------
    kind
        What it is, one of :data:`ALL_KINDS` (:data:`OPERATOR_KINDS` says it in words).
    device
        The Warp device its arrays live on.
    voxels
        (n,) int32 flat voxel indices of the operator's grid, on the device, in the order of the
        intensities ``e`` the methods take.
    n_voxels, nnz, nbytes
        Active voxels, stored weights (0 where none are stored) and device bytes held.
    n_on_the_fly
        Voxels whose weights are made again in every iteration instead of stored.

    Notes
    -----
    The sequential form (eq. 4.1 pixel by pixel) needs stored rows besides: ``transpose()`` and
    ``sweep(transposed, image, e, relaxation, floor)`` of :class:`lfcore.weight_build.Weights`
    (:class:`lfcore.reconstruct.ReconSettings` allows it only with stored weights).
    """

    kind: str

    @property
    def device(self) -> str: ...

    @property
    def voxels(self) -> object: ...

    @property
    def n_voxels(self) -> int: ...

    @property
    def nnz(self) -> int: ...

    @property
    def nbytes(self) -> int: ...

    @property
    def n_on_the_fly(self) -> int: ...

    def forward(self, e, *, out=None) -> object:
        """Project the voxels' intensities ``e`` (n,) to all pixels: ``out`` (n_pixels,) float32
        (zeroed first; None: a new array), returned."""

    def update(self, ratio, e, relaxation: float) -> None:
        """The multiplicative update ``E_v <- E_v exp(mu sum_i w_iv ratio_i)`` of ``e`` in place,
        ``ratio`` the (n_pixels,) log ratios of :func:`log_ratio`."""

    def scatter(self, e, *, out=None) -> object:
        """The dense (z, y, x) float32 volume of the grid with ``e`` at the voxels, zero elsewhere,
        on the device (``out`` zeroed and written; None: a new array)."""

    def restrict(self, rows, *, spend: bool = False) -> Operator:
        """The operator of some of its rows: ``rows`` (k,) int32 row indices (ascending, on the
        device) into :attr:`voxels`; a new operator whose row t is this one's ``rows[t]``.
        ``spend``: this operator's stored rows are let go as the kept ones are copied (piece by piece,
        so that the copy and the whole do not stand together), and it is not applied again."""


class Projector(Protocol):
    """Cameras bound to a voxel grid on a device: what makes a frame's :class:`Operator`.

    Implemented by :class:`lfcore.projector.LightFieldProjector`,
    :class:`lfcore.pinhole_projector.PinholeProjector` and
    :class:`lfcore.pinhole_projector.JointProjector`; chosen by :func:`lfcore.plan.projector_for`.

    Attributes
    ----------
    kind
        ``"light-field"``, ``"pinhole"`` or ``"joint"`` (a mixed rig).
    cameras, grid, box, z0
        The cameras; the grid (a depth slab of ``box`` starting at its plane ``z0`` on a projector
        from :meth:`planes`, else the box itself).
    device, wp
        The Warp device and the Warp module.
    n_pixels, pixel_offsets
        Pixels of all cameras, and where each camera's begin in the global numbering.
    """

    kind: str
    cameras: tuple
    grid: VolumeGrid
    box: VolumeGrid
    z0: int
    device: str
    n_pixels: int
    pixel_offsets: np.ndarray

    def eliminate(self, lit, *, min_seen: float = 0.5, max_dark: float = 0.05) -> object:
        """Voxels that can hold a particle: (n,) int32 flat indices, ascending."""

    def all_voxels(self) -> object:
        """Every voxel of the grid, (n,) int32."""

    def planes(self, z0: int, z1: int) -> Projector:
        """This projector on planes ``z0 .. z1 - 1`` of its grid, numbering its own voxels."""

    def precompute_checks(self, *, n_checks: int | None = None, budget_bytes: int | None = None) -> int:
        """Store the pixels elimination looks up; returns their bytes (0: none kept)."""

    def operator(self, voxels, *, method: str, min_weight: float = 1e-6, budget_bytes: int | None = None,
                 storage: str = "stored") -> Operator:
        """The stored-rows operator of ``voxels`` (``method`` ``"drt"`` or ``"los"``)."""


class OperatorSource(Protocol):
    """Where a stream of frames gets its operators: one object per stream, chosen by
    :mod:`lfcore.plan` (the weights from a cache, the templates, or a per-frame choice).

    Attributes
    ----------
    templates
        The matrix-free templates held for the next frames (None where none are held).
    """

    templates: object

    def operator(self, voxels, *, budget: Callable[[], int], host: np.ndarray | None = None) -> Operator:
        """The operator of a frame's ``voxels`` ((n,) int32 on the device; ``host`` the same on the
        host where the caller has them); ``budget()`` gives the bytes it may take, asked when they
        are needed (the device's free memory changes as the operator is built)."""

    def held_bytes(self, op: Operator) -> int:
        """Device bytes kept for the next frames beside ``op`` (the templates, a cache's pool)."""

    def prepare(self, *, budget: Callable[[], int]) -> None:
        """Build what the first frame would otherwise build in its own time (the templates)."""


def applied_by(op: object) -> str:
    """What applied ``op`` in the words recorded since the first matrix-free runs (the run store's
    ``volumes/`` attributes, :attr:`lfcore.reconstruct.ReconResult.projector`): ``"matrix-free"``
    for the templates and their images, ``"stored"`` for every other stored weights."""
    return "matrix-free" if getattr(op, "kind", None) in _FROM_TEMPLATES else "stored"


def from_templates(op: object) -> bool:
    """Whether ``op`` is made from the matrix-free templates (applied, or their images stored)."""
    return getattr(op, "kind", None) in _FROM_TEMPLATES


def log_ratio(image, proj, floor: float, out) -> object:
    """``out[i] = ln(max(image_i, floor) / proj_i)`` over all pixels, 0 where nothing projects
    onto pixel i (``proj_i`` 0): the ratio the multiplicative update (:meth:`Operator.update`)
    reads. ``image``, ``proj`` and ``out`` are (n_pixels,) float32 on one device; ``floor`` in
    counts, the least a pixel's measurement counts as. Returns ``out``."""
    from lfcore._kernels import mart as km

    wp = warp()
    wp.launch(km.log_ratio, dim=int(out.shape[0]), inputs=[image, proj, float(floor), out], device=str(out.device))
    return out


def scatter_voxels(voxels, e, shape: Sequence[int], *, device: str, out=None) -> object:
    """The dense (z, y, x) float32 volume of ``shape`` with intensities ``e`` (n,) at the flat
    indices ``voxels`` (n,) int32, zero elsewhere, on ``device``.

    ``out``: an (nz, ny, nx) float32 Warp array to write (zeroed first); None: a new one.
    """
    from lfcore._kernels import mart as km

    wp = warp()
    shape = tuple(int(s) for s in shape)
    if out is None:
        out = wp.zeros(shape, dtype=float, device=device)
    else:
        if tuple(out.shape) != shape:
            raise ValueError(f"the volume must be {shape} (z, y, x), got {out.shape}")
        out.zero_()
    n = int(voxels.shape[0])
    if n:
        flat = out.reshape(int(np.prod(shape)))
        launch_rows(km.scatter_volume, n, [Rows(voxels), Rows(e), flat], device)
    return out


def gather(src, rows) -> object:
    """``src[rows]`` on the device: ``src`` (n,) float32 or int32, ``rows`` (k,) int32; a new (k,) array
    of ``src``'s type (the intensities or voxel indices of the rows an operator keeps)."""
    from lfcore._kernels import mart as km

    wp = warp()
    k = int(rows.shape[0])
    device = str(src.device)
    out = wp.empty(max(k, 1), dtype=src.dtype, device=device)[:k]
    if k:
        launch_rows(km.gather_index if src.dtype == wp.int32 else km.gather, k, [src, Rows(rows), Rows(out)], device)
    return out
