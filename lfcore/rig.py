"""The rig description: frozen, validated configuration objects.

A rig file (TOML, see ``examples/``) is parsed by the application into a plain dict and
validated here with :meth:`Rig.from_dict`. Every table rejects unknown keys, and every
impossible value is an error that names its key. The objects are immutable; derived optical
quantities are exposed as properties so they can never drift from the inputs.

Conventions (docs/reference/conventions.md): millimetres in the world, micrometres for sensor and lenslet pitches,
seconds for time. A camera's pose is its rotation and the world point its focal plane is
centred on; the rotation R = Rz(rz) Ry(ry) Rx(rx) maps camera-frame vectors to world vectors.
In the camera frame the optical axis is +z, the main lens sits at ``z = so`` looking toward -z,
and depth ``dz`` is positive toward the camera.

A camera is of one of two kinds (``kind`` in its ``[[camera]]`` table): a plenoptic
:class:`Camera` (``"lightfield"``, the default) or a conventional Tomo-PIV :class:`PinholeCamera`
(``"pinhole"``). Both share the pose, the sensor and the thin-lens distances; only the
light-field camera has a microlens array, and code that needs one refuses a pinhole camera with
a one-line :class:`NotLightFieldError` naming it.
"""

from __future__ import annotations

import difflib
import functools
import json
import math
import re
from collections.abc import Sequence
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    TypeAdapter,
    ValidationError,
    field_validator,
    model_validator,
)

from lfcore._deprecation import keyword_options

__all__ = [
    "MAX_RAYS_PER_PARTICLE",
    "AnyCamera",
    "Camera",
    "NotLightFieldError",
    "PinholeCamera",
    "LaserConfig",
    "PulseGeneratorConfig",
    "RenderConfig",
    "Rig",
    "RigError",
    "StageConfig",
    "TargetConfig",
    "TimingConfig",
    "VolumeConfig",
    "camera_from_dict",
    "is_pinhole",
    "require_lightfield",
    "rotation_angle_deg",
    "rotation_matrix",
    "voxel_shape_warnings",
]

def _within(lo: float, hi: float, *, above: bool = False) -> Any:
    """A finite float in the physical range [lo, hi] of a rig value (``(lo, hi]`` with ``above``):
    a value finite but far outside it (a dt of 1e-300 us, a PVR of 1e308) is a slip, and would
    make a meaningless run rather than an error."""
    bound = {"gt": lo} if above else {"ge": lo}
    return Annotated[float, Field(le=hi, allow_inf_nan=False, **bound)]


#: An angle in degrees: a turn either way at most
Angle = _within(-360.0, 360.0)
#: A world position, mm: within a million km of the origin (a focus or centre beyond is a slip of
#: units; a merely far one the rig's own checks name)
Position = _within(-1e12, 1e12)
AngleVec3 = tuple[Angle, Angle, Angle]
PositionVec3 = tuple[Position, Position, Position]
def _visible(m: float) -> float:
    if m > -1e-6:
        raise ValueError(f"a magnification of {m:g} images a pixel onto more than a metre; |M| must be at least 1e-6")
    return m


#: A lateral magnification: negative (a real, inverted image), |M| from 1e-6 to 1000
Magnification = Annotated[float, Field(lt=0, ge=-1000.0, allow_inf_nan=False), AfterValidator(_visible)]
#: A length in mm, up to 100 m
LengthMm = _within(0.0, 1e5, above=True)
#: A time in microseconds, up to 100 s
TimeUs = _within(0.0, 1e8, above=True)
#: A rate in Hz, up to 1 MHz
RateHz = _within(0.0, 1e6, above=True)

#: Names a camera may not take because the run store uses them for its own groups.
RESERVED_NAMES = frozenset({"drops", "truth", "volumes", "vectors"})

#: Relative mismatch between the main lens' image-side f-number and the lenslets' f-number
#: above which :meth:`Camera.optics_warnings` warns.
F_NUMBER_TOLERANCE = 0.05

#: Angle (degrees) between two cameras' lines of sight from which each sees, across its view,
#: the depth the other resolves poorly (the chapter's optimum is 90).
CROSSED_VIEWS_DEG = 45.0

#: Fewest lenslets across either sensor axis before :meth:`Camera.optics_warnings` suspects a
#: slipped unit (below one lenslet the rig is refused).
MIN_LENSLETS = 4

#: Pixels per lenslet above which :meth:`Camera.optics_warnings` suspects a slipped unit.
MANY_PIXELS_PER_LENSLET = 60.0

#: Ratio of a voxel's longest to its shortest edge from which :func:`voxel_shape_warnings` warns.
DEEP_VOXEL_RATIO = 2.0


class RigError(ValueError):
    """A rig description that cannot be used; the message is one line naming the key."""


class NotLightFieldError(ValueError):
    """Light-field optics (microlens array, white image, DRT weights) asked of a pinhole camera;
    one line naming the camera."""


class _NoSuchOptics(NotLightFieldError, AttributeError):
    """A light-field attribute read from a pinhole camera (an AttributeError too, so ``hasattr``
    and ``getattr(..., default)`` keep working)."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=False)


def rotation_matrix(rotation_deg: tuple[float, float, float]) -> np.ndarray:
    """Camera-to-world rotation from ``[rx, ry, rz]`` in degrees.

    Parameters
    ----------
    rotation_deg
        Rotations about the world x, y and z axes, applied x first: R = Rz Ry Rx.

    Returns
    -------
    numpy.ndarray
        (3, 3) float64 matrix mapping camera-frame vectors to world vectors.
    """
    rx, ry, rz = (math.radians(a) for a in rotation_deg)
    cx, sx, cy, sy, cz, sz = (math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry),
                              math.cos(rz), math.sin(rz))
    r_x = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    r_y = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    r_z = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return r_z @ r_y @ r_x


def rotation_angle_deg(a_deg: tuple[float, float, float], b_deg: tuple[float, float, float]) -> float:
    """Angle (degrees) of the rotation that takes pose ``a_deg`` to pose ``b_deg`` (both
    ``[rx, ry, rz]`` as :func:`rotation_matrix`).

    Near ry = +-90 degrees rx and rz turn about almost the same axis (gimbal lock), so the Euler
    angles of two nearly equal poses can differ by tens of degrees; this angle cannot.
    """
    r = rotation_matrix(a_deg).T @ rotation_matrix(b_deg)
    # atan2 of the axis part against the trace part stays accurate at small angles, where
    # arccos((trace - 1) / 2) loses half its digits
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    return float(np.degrees(math.atan2(0.5 * np.linalg.norm(axis), 0.5 * (np.trace(r) - 1.0))))


def _check_name(v: str) -> str:
    if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]{0,31}", v):
        raise ValueError("must be 1-32 letters, digits, '_' or '-', starting with a letter")
    if v in RESERVED_NAMES:
        raise ValueError(f"'{v}' is reserved by the run store; choose another name")
    return v


class _Posed:
    """What every kind of camera derives alike from its pose, sensor and thin-lens distances.

    Thin lens of focal length F (:attr:`lens_focal_length_mm`) at magnification M < 0: image
    distance si = F (1 - M), object distance so = si / (-M). The camera frame has its origin at
    the focus point, +z toward the lens (which sits at z = so).
    """

    # each kind declares the fields used here: sensor_px, pixel_pitch_um, magnification,
    # rotation_deg and focus_mm (annotations here would become fields, first in every dump)

    @property
    def lens_focal_length_mm(self) -> float:  # pragma: no cover - each kind defines it
        raise NotImplementedError

    @property
    def image_distance_mm(self) -> float:
        """si = F (1 - M): lens to the image plane (the MLA, or a pinhole camera's sensor)."""
        return self.lens_focal_length_mm * (1.0 - self.magnification)

    @property
    def object_distance_mm(self) -> float:
        """so = si / (-M): lens to the focal plane."""
        return self.image_distance_mm / -self.magnification

    @property
    def pixel_mm(self) -> float:
        return self.pixel_pitch_um * 1e-3

    @property
    def object_pixel_mm(self) -> float:
        """Size of one pixel projected onto the focal plane, pixel pitch / |M|."""
        return self.pixel_mm / abs(self.magnification)

    @property
    def sensor_size_mm(self) -> tuple[float, float]:
        """(width, height) of the sensor."""
        return (self.sensor_px[0] * self.pixel_mm, self.sensor_px[1] * self.pixel_mm)

    @property
    def field_of_view_mm(self) -> tuple[float, float]:
        """(width, height) of the focal plane seen by the sensor."""
        w, h = self.sensor_size_mm
        m = abs(self.magnification)
        return (w / m, h / m)

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) camera-to-world rotation matrix."""
        return rotation_matrix(self.rotation_deg)

    @property
    def optical_axis(self) -> np.ndarray:
        """World direction from the focal plane toward the camera (camera +z)."""
        return self.rotation[:, 2].copy()

    @property
    def lens_centre_mm(self) -> np.ndarray:
        """(3,) world position of the lens centre (a pinhole camera's projection centre)."""
        return np.asarray(self.focus_mm, dtype=np.float64) + self.object_distance_mm * self.optical_axis

    def world_to_camera(self, points_mm: np.ndarray) -> np.ndarray:
        """World points to the camera frame (origin at the focus point, +z toward the lens).

        Parameters
        ----------
        points_mm
            (..., 3) world coordinates in mm, last axis (x, y, z).

        Returns
        -------
        numpy.ndarray
            (..., 3) camera-frame coordinates in mm; the last component is the depth dz.
        """
        p = np.asarray(points_mm, dtype=np.float64) - np.asarray(self.focus_mm)
        return p @ self.rotation  # row-vector form of R^T p

    def camera_to_world(self, points_mm: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`world_to_camera`."""
        p = np.asarray(points_mm, dtype=np.float64)
        return p @ self.rotation.T + np.asarray(self.focus_mm)


class Camera(_Posed, _Strict):
    """One unfocused plenoptic (light-field) camera: main lens, microlens array, sensor.

    Thin-lens model: main-lens focal length F, magnification M < 0, image distance
    si = F (1 - M), object distance so = si / (-M), aperture D = F / N. The MLA sits at si
    behind the main lens, the sensor one lenslet focal length f_ml behind the MLA.
    """

    #: ``"lightfield"``, the default kind of a ``[[camera]]`` table (see :class:`PinholeCamera`)
    kind: Literal["lightfield"] = "lightfield"
    #: 1-32 letters, digits, '_' or '-', starting with a letter: the camera's group in the run store and its CAM= in
    #: options (not drops, truth, volumes or vectors, which the run store uses)
    name: str
    # up to 32768 a side: the largest scientific sensors are about 14,000 px wide
    #: Sensor size in pixels, [columns, rows]
    sensor_px: tuple[Annotated[int, Field(ge=8, le=32768)], Annotated[int, Field(ge=8, le=32768)]]
    #: Pixel pitch of the sensor, micrometres
    pixel_pitch_um: _within(0.0, 1000.0, above=True)
    #: Lattice of the microlens array: "hex" (rows along sensor x, alternate rows shifted half a pitch) or "square"
    mla_grid: Literal["hex", "square"]
    #: Lenslet pitch p_ml, micrometres; at least two pixels
    mla_pitch_um: _within(0.0, 1e5, above=True)
    #: Lenslet focal length f_ml, micrometres: the sensor sits this far behind the microlens array; matched optics have
    #: f_ml / p_ml = N (1 - M)
    mla_focal_length_um: _within(0.0, 1e6, above=True)
    #: Main-lens focal length F, mm
    main_focal_length_mm: LengthMm
    #: The main lens' own f-number N = F / D; the light converging on the lenslets has the image-side N (1 - M), which
    #: should match f_ml / p_ml (more than 5% off is a warning naming the matching N)
    f_number: _within(0.0, 1000.0, above=True)
    #: Lateral magnification M of the main lens, negative (a real, inverted image): -1 images 1:1; |M| at least 1e-6
    magnification: Magnification
    #: Camera pose: rotations [rx, ry, rz] about the world axes in degrees, x first (R = Rz Ry Rx maps camera-frame
    #: vectors to world vectors); [0, 0, 0] puts the camera on world +z looking toward -z
    rotation_deg: AngleVec3 = (0.0, 0.0, 0.0)
    #: World point [x, y, z] in mm that the focal plane is centred on
    focus_mm: PositionVec3 = (0.0, 0.0, 0.0)
    #: In-plane rotation of the microlens array on the sensor, degrees (`calibrate mla` measures it, `calibrate fit`
    #: fits it)
    mla_rotation_deg: Angle = 0.0
    #: In-plane shift [x, y] of the microlens array from the sensor centre, micrometres (measured as mla_rotation_deg)
    mla_offset_um: tuple[_within(-1e5, 1e5), _within(-1e5, 1e5)] = (0.0, 0.0)
    #: GenICam serial number of the real camera (hardware = "real"; `lfpiv devices` lists them); required when the rig
    #: has several cameras
    serial: str | None = None
    #: Bits per pixel of the real sensor: its full scale (2**bit_depth - 1) judges clipping of
    #: white images and the values of imported frames; apart from [render]'s synthetic images.
    bit_depth: Annotated[int, Field(ge=8, le=16)] = 16

    @field_validator("name")
    @classmethod
    def _name_ok(cls, v: str) -> str:
        return _check_name(v)

    @model_validator(mode="after")
    def _optics_possible(self) -> Camera:
        if self.mla_pitch_um < 2 * self.pixel_pitch_um:
            raise ValueError("mla_pitch_um must cover at least 2 pixels (pixel_pitch_um)")
        across = self.lenslets_across
        if min(across) < 1.0:
            # a pitch given in millimetres or nanometres leaves the sensor a lenslet or two wide
            raise ValueError(
                f"the sensor is only {across[0]:.3g} x {across[1]:.3g} lenslets "
                f"(sensor_px x pixel_pitch_um / mla_pitch_um); check the units: both pitches are in "
                "micrometres (e.g. pixel_pitch_um = 5.5, mla_pitch_um = 77)"
            )
        if self.mla_focal_length_um >= 1000 * self.image_distance_mm:
            raise ValueError("mla_focal_length_um must be much shorter than the image distance")
        return self

    # --- derived optics (mm unless the name says otherwise) -----------------------------
    @property
    def lens_focal_length_mm(self) -> float:
        """F of the thin lens that forms the image: the main lens."""
        return self.main_focal_length_mm

    @property
    def lenslets_across(self) -> tuple[float, float]:
        """Lenslets across the sensor (columns, rows): sensor_px x pixel_pitch_um / mla_pitch_um."""
        cols, rows = self.sensor_px
        return cols / self.pixels_per_lenslet, rows / self.pixels_per_lenslet

    @property
    def aperture_mm(self) -> float:
        """Main-lens aperture diameter D = F / N."""
        return self.main_focal_length_mm / self.f_number

    @property
    def image_side_f_number(self) -> float:
        """Working f-number si / D of the cone converging on the MLA."""
        return self.image_distance_mm / self.aperture_mm

    @property
    def lenslet_f_number(self) -> float:
        """f_ml / p_ml; matched optics have this equal to :attr:`image_side_f_number`."""
        return self.mla_focal_length_um / self.mla_pitch_um

    @property
    def mla_pitch_mm(self) -> float:
        return self.mla_pitch_um * 1e-3

    @property
    def mla_focal_length_mm(self) -> float:
        return self.mla_focal_length_um * 1e-3

    @property
    def pixels_per_lenslet(self) -> float:
        return self.mla_pitch_um / self.pixel_pitch_um

    @property
    def depth_per_lenslet_mm(self) -> float:
        """Defocus |dz| at which a point's blur on the MLA spans one lenslet pitch.

        The blur diameter on the MLA grows as D M^2 |dz| / si for small |dz| (longitudinal
        magnification M^2), so one pitch is reached at p_ml si / (D M^2).
        """
        return self.mla_pitch_mm * self.image_side_f_number / self.magnification**2

    def optics_warnings(self) -> list[str]:
        """Human-readable warnings about optics that work but are not as intended."""
        out = []
        across = self.lenslets_across
        if min(across) < MIN_LENSLETS:
            out.append(
                f"camera '{self.name}': the sensor is only {across[0]:.3g} x {across[1]:.3g} lenslets; check that "
                "pixel_pitch_um and mla_pitch_um are both in micrometres"
            )
        if self.pixels_per_lenslet > MANY_PIXELS_PER_LENSLET:
            out.append(
                f"camera '{self.name}': each lenslet spans {self.pixels_per_lenslet:.0f} pixels (light-field PIV "
                "cameras use about 10-20); check that pixel_pitch_um and mla_pitch_um are both in micrometres"
            )
        n_img, n_ml = self.image_side_f_number, self.lenslet_f_number
        mismatch = n_img / n_ml - 1.0
        if abs(mismatch) > F_NUMBER_TOLERANCE:
            matched = n_ml / (1.0 - self.magnification)
            what = ("the sub-aperture images overlap their neighbours (crosstalk)" if mismatch < 0
                    else "the sub-aperture images leave pixels unused")
            out.append(
                f"camera '{self.name}': the main lens' image-side f-number N(1-M) = {n_img:.2f} "
                f"does not match the lenslets' f_ml/p_ml = {n_ml:.2f} ({mismatch:+.0%}), so {what}; "
                f"set f_number = {matched:.3g} to match"
            )
        return out


class PinholeCamera(_Posed, _Strict):
    """One conventional (Tomo-PIV) camera: a thin lens imaging the volume onto the sensor,
    modelled as a pinhole with lens distortion (``kind = "pinhole"``).

    Same pose and distances as :class:`Camera`: focal length F, magnification M < 0 (or, in the
    rig file, ``object_distance_mm`` so instead, M = -F / (so - F)), image distance
    si = F (1 - M) from the lens (the projection centre, :attr:`lens_centre_mm`) to the sensor.
    The depth of field is taken to hold the whole volume (a Tomo-PIV lens stopped down for it).

    The image of a point is the pinhole image moved by the Brown-Conrady distortion of
    OpenCV's model, ``k1``, ``k2`` (radial) and ``p1``, ``p2`` (tangential), applied to the
    normalised image coordinates (x, y) = ((column - cx) / f_px, (row - cy) / f_px), x to the
    right and y down the image as OpenCV has them; f_px = si / pixel pitch, and (cx, cy) the
    sensor centre plus ``principal_point_px``. Coefficients from an OpenCV calibration of the
    same camera therefore carry over. See :mod:`lfcore.pinhole` for the projection and the line
    of sight of a pixel.
    """

    #: "pinhole": a conventional Tomo-PIV camera (required in its table; the default kind is "lightfield")
    kind: Literal["pinhole"]
    #: 1-32 letters, digits, '_' or '-', starting with a letter: the camera's group in the run store and its CAM= in
    #: options (not drops, truth, volumes or vectors, which the run store uses)
    name: str
    #: Sensor size in pixels, [columns, rows]
    sensor_px: tuple[Annotated[int, Field(ge=8, le=32768)], Annotated[int, Field(ge=8, le=32768)]]
    #: Pixel pitch of the sensor, micrometres
    pixel_pitch_um: _within(0.0, 1000.0, above=True)
    #: Focal length F of the lens, mm
    focal_length_mm: LengthMm
    #: Lateral magnification M, negative, |M| at least 1e-6; or give object_distance_mm instead (lens to focal plane,
    #: mm, beyond F), from which M = -F / (so - F)
    magnification: Magnification
    #: Camera pose: rotations [rx, ry, rz] about the world axes in degrees, x first (R = Rz Ry Rx maps camera-frame
    #: vectors to world vectors); [0, 0, 0] puts the camera on world +z looking toward -z
    rotation_deg: AngleVec3 = (0.0, 0.0, 0.0)
    #: World point [x, y, z] in mm that the focal plane is centred on
    focus_mm: PositionVec3 = (0.0, 0.0, 0.0)
    #: where the optical axis meets the sensor, from the sensor centre, (columns, rows) pixels
    principal_point_px: tuple[_within(-32768.0, 32768.0), _within(-32768.0, 32768.0)] = (0.0, 0.0)
    #: OpenCV's first radial distortion coefficient (on normalised image coordinates)
    k1: _within(-1000.0, 1000.0) = 0.0
    #: OpenCV's second radial distortion coefficient
    k2: _within(-1000.0, 1000.0) = 0.0
    #: OpenCV's first tangential distortion coefficient
    p1: _within(-1000.0, 1000.0) = 0.0
    #: OpenCV's second tangential distortion coefficient
    p2: _within(-1000.0, 1000.0) = 0.0
    #: GenICam serial number of the real camera (hardware = "real"; `lfpiv devices` lists them); required when the rig
    #: has several cameras
    serial: str | None = None
    #: Bits per pixel of the real sensor (full scale 2**bit_depth - 1); a simulated pinhole
    #: camera saturates there too (or at ``[render]``'s bit depth, whichever is lower).
    bit_depth: Annotated[int, Field(ge=8, le=16)] = 16

    @field_validator("name")
    @classmethod
    def _name_ok(cls, v: str) -> str:
        return _check_name(v)

    @model_validator(mode="before")
    @classmethod
    def _from_object_distance(cls, data: Any) -> Any:
        """``object_distance_mm`` (the lens-to-focal-plane distance a Tomo-PIV user measures)
        in place of ``magnification``: M = -F / (so - F)."""
        if not isinstance(data, dict):
            return data
        # validation goes on in Python mode after this, where strict tuples refuse JSON's lists
        data = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
        if "object_distance_mm" not in data:
            return data
        so = data.pop("object_distance_mm")
        if "magnification" in data:
            raise ValueError("give magnification or object_distance_mm, not both")
        f = data.get("focal_length_mm")
        if isinstance(so, int | float) and isinstance(f, int | float) and f > 0:
            if not (math.isfinite(so) and so > f):
                raise ValueError(f"object_distance_mm must be beyond the focal length ({f:g} mm), got {so:g}")
            data["magnification"] = -f / (so - f)
        return data

    @property
    def lens_focal_length_mm(self) -> float:
        """F of the lens."""
        return self.focal_length_mm

    @property
    def main_focal_length_mm(self) -> float:
        """F of the lens (the name the light-field camera gives it)."""
        return self.focal_length_mm

    @property
    def focal_length_px(self) -> float:
        """si / pixel pitch: the pinhole's focal length in pixels (OpenCV's fx = fy)."""
        return self.image_distance_mm / self.pixel_mm

    @property
    def principal_point(self) -> tuple[float, float]:
        """(cx, cy): continuous (column, row) pixel coordinates of the principal point."""
        (dx, dy), (cols, rows) = self.principal_point_px, self.sensor_px
        return (0.5 * cols + dx, 0.5 * rows + dy)

    @property
    def distortion(self) -> tuple[float, float, float, float]:
        """(k1, k2, p1, p2), OpenCV's order."""
        return (self.k1, self.k2, self.p1, self.p2)

    def optics_warnings(self) -> list[str]:
        """Human-readable warnings about optics that work but are not as intended."""
        out = []
        w, h = self.sensor_px
        if abs(self.principal_point_px[0]) > 0.5 * w or abs(self.principal_point_px[1]) > 0.5 * h:
            out.append(f"camera '{self.name}': the principal point is off the sensor (principal_point_px = "
                       f"{list(self.principal_point_px)} from its centre); check the sign and the units (pixels)")
        return out

    def __getattr__(self, item: str) -> Any:
        if item in _lightfield_only():
            raise _NoSuchOptics(f"camera '{self.name}' is a pinhole camera: it has no {item} (light-field optics); "
                                "use a light-field camera here, or leave this camera out")
        return super().__getattr__(item)


@functools.cache
def _lightfield_only() -> frozenset[str]:
    """Public attributes of a light-field camera that a pinhole camera lacks."""
    return frozenset(n for n in dir(Camera) if not n.startswith("_") and not hasattr(PinholeCamera, n)) | frozenset(
        n for n in Camera.model_fields if n not in PinholeCamera.model_fields)


#: A camera of either kind.
AnyCamera = Camera | PinholeCamera


def is_pinhole(camera: Any) -> bool:
    """Whether ``camera`` is a pinhole (Tomo-PIV) camera."""
    return getattr(camera, "kind", "lightfield") == "pinhole"


def require_lightfield(camera: Any, what: str) -> Camera:
    """``camera``, if it is a light-field camera.

    Parameters
    ----------
    camera
        A camera of either kind.
    what
        What needs the light-field optics, for the message (e.g. ``"a white image"``).

    Raises
    ------
    NotLightFieldError
        A pinhole camera, in one line naming it and ``what``.
    """
    if is_pinhole(camera):
        raise NotLightFieldError(f"camera '{camera.name}' is a pinhole camera: {what} needs a light-field camera "
                                 "(microlens array)")
    return camera


def _camera_kind(value: Any) -> str:
    """The tag of a ``[[camera]]`` table or camera object: its ``kind``, light-field by default."""
    if isinstance(value, dict):
        kind = value.get("kind", "lightfield")
        return kind if isinstance(kind, str) else repr(kind)
    return getattr(value, "kind", "lightfield")


_KINDS = "kind must be 'lightfield' (the default) or 'pinhole'"
_CameraOfKind = Annotated[Annotated[Camera, Tag("lightfield")] | Annotated[PinholeCamera, Tag("pinhole")],
                          Discriminator(_camera_kind, custom_error_type="camera_kind", custom_error_message=_KINDS)]
_CAMERA_ADAPTER: TypeAdapter = TypeAdapter(_CameraOfKind)


def camera_from_dict(data: dict[str, Any]) -> AnyCamera:
    """A camera of either kind from its ``[[camera]]`` table (as :meth:`Rig.to_dict` writes it).

    Raises
    ------
    pydantic.ValidationError
        A table that is not a valid camera.
    """
    return _CAMERA_ADAPTER.validate_python(data)


class VolumeConfig(_Strict):
    """The measurement volume, an axis-aligned box in world coordinates."""

    #: World position [x, y, z] of the volume's centre, mm (the world origin by default)
    centre_mm: PositionVec3 = (0.0, 0.0, 0.0)
    #: Edge lengths [x, y, z] of the measurement volume, mm
    size_mm: tuple[LengthMm, LengthMm, LengthMm]
    #: Pixel-voxel ratio per axis [x, y, z]: a voxel's edge is pvr times the first camera's pixel on its focal plane
    #: (pixel pitch / |M|); a plenoptic camera resolves depth coarsely, hence 10 in z
    pvr: tuple[_within(0.0, 1000.0, above=True), _within(0.0, 1000.0, above=True),
                _within(0.0, 1000.0, above=True)] = (2.0, 2.0, 10.0)

    @property
    def bounds_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi): the box's lowest and highest corners, (3,) world (x, y, z) mm each."""
        half = 0.5 * np.asarray(self.size_mm)
        return np.asarray(self.centre_mm) - half, np.asarray(self.centre_mm) + half


class LaserConfig(_Strict):
    """The double-pulsed laser and the light sheet it forms."""

    #: Laser wavelength, nm: the diffraction blur of rendered images
    wavelength_nm: _within(100.0, 20000.0) = 532.0
    #: Pair rate of `acquire` and `monitor`: double pulses per second, at most max_rate_hz
    rate_hz: RateHz = 10.0
    #: The laser's highest pair rate; a higher rate_hz is refused
    max_rate_hz: RateHz = 15.0
    #: Width of each flashlamp trigger pulse, microseconds
    flashlamp_width_us: TimeUs = 10.0
    #: Width of each Q-switch trigger pulse, microseconds
    qswitch_width_us: TimeUs = 10.0
    #: Light-sheet profile across sheet_axis, centred on the volume: "uniform" (everything lit alike), "gaussian" or
    #: "top-hat" (both need sheet_thickness_mm)
    sheet_profile: Literal["uniform", "gaussian", "top-hat"] = "uniform"
    #: World axis across the light sheet (its thickness direction)
    sheet_axis: Literal["x", "y", "z"] = "z"
    #: Sheet thickness, mm: a Gaussian's full width at 1/e^2 of the peak, a top-hat's full width; required for those
    #: profiles
    sheet_thickness_mm: LengthMm | None = None

    @model_validator(mode="after")
    def _thickness_given(self) -> LaserConfig:
        if self.sheet_profile != "uniform" and self.sheet_thickness_mm is None:
            raise ValueError(f"sheet_thickness_mm is required for sheet_profile = '{self.sheet_profile}'")
        if self.rate_hz > self.max_rate_hz:
            raise ValueError(
                f"rate_hz = {self.rate_hz} is above the laser's max_rate_hz = {self.max_rate_hz}; "
                "lower rate_hz or correct max_rate_hz"
            )
        return self


class TimingConfig(_Strict):
    """Timing of a double-frame pair (frame straddling).

    ``qswitch_delay_us`` is the laser's flashlamp-to-Q-switch delay (full energy near 180 us
    for a typical Nd:YAG); ``camera_exposure_us`` the exposure of frame A, which ends just after
    the first pulse; ``camera_interframe_us`` the camera's dead time between frames A and B,
    the shortest possible ``dt``; ``camera_max_fps`` the camera's frame rate limit (two frames
    per pair).
    """

    #: Time between the two laser pulses of a pair, microseconds (at least camera_interframe_us)
    dt_us: _within(1e-3, 1e8) = 2000.0
    #: The laser's flashlamp-to-Q-switch delay, microseconds
    qswitch_delay_us: TimeUs = 180.0
    #: Exposure of frame A, microseconds; it ends just after the first pulse
    camera_exposure_us: TimeUs = 20.0
    #: The camera's dead time between frames A and B, microseconds: the shortest dt
    camera_interframe_us: _within(0.0, 1e8) = 1.0
    #: The camera's highest frame rate, frames per second (a pair takes two frames)
    camera_max_fps: RateHz = 60.0


class StageConfig(_Strict):
    """The motorised calibration stage (serial, Zaber ASCII protocol).

    ``device`` is the controller's address on the daisy chain and ``axis`` its axis (both as
    the Zaber Console shows them).

    ``microstep_um`` is deprecated and optional: the driver reads the product (``deviceid``, or
    ``peripheral.id`` on a controller) and its ``resolution`` from the stage and works out the
    size of one native step itself. Set it only for a product missing from
    ``acquisition.stage.ZABER_PRODUCTS`` (the size of one microstep as the device is set up,
    as Zaber Launcher shows it); for a known product a value that disagrees with the device is
    reported in a warning and not used.
    """

    #: Serial port of the stage (e.g. /dev/ttyUSB0 or COM3), which `calibrate volume` needs with hardware = "real";
    #: the simulated lab uses its own
    port: str | None = None
    #: Serial baud rate, bit/s (Zaber's ASCII protocol: 115200)
    baud: Annotated[int, Field(gt=0)] = 115200
    #: The controller's address on the daisy chain, as Zaber Console shows it
    device: Annotated[int, Field(ge=1, le=99)] = 1
    #: The axis of that controller that carries the target
    axis: Annotated[int, Field(ge=1, le=9)] = 1
    #: Deprecated: the size of one microstep, micrometres, only for a product lfpiv does not know
    microstep_um: _within(0.0, 1e6, above=True) = 0.1


#: Which output of the pulse generator drives what, unless the rig file says otherwise.
DEFAULT_CHANNELS = {"flashlamp1": 1, "qswitch1": 2, "flashlamp2": 3, "qswitch2": 4, "camera": 5}


class PulseGeneratorConfig(_Strict):
    """The pulse generator that fires the laser and triggers the cameras (serial).

    ``channels`` maps each role (flashlamp1, qswitch1, flashlamp2, qswitch2, camera) to an
    output number, 1-based (A = 1). Both cameras share the camera output.
    """

    #: Serial port of the pulse generator (e.g. /dev/ttyUSB0 or COM3), required with hardware = "real"; the
    #: simulated lab uses its own
    port: str | None = None
    #: Serial baud rate, bit/s
    baud: Annotated[int, Field(gt=0)] = 115200
    #: Output of each role, 1-based (A = 1): flashlamp1, qswitch1, flashlamp2, qswitch2 and camera, each its own output;
    #: every camera shares the camera output
    channels: dict[str, Annotated[int, Field(ge=1, le=8)]] = dict(DEFAULT_CHANNELS)

    @field_validator("channels")
    @classmethod
    def _roles(cls, v: dict[str, int]) -> dict[str, int]:
        if set(v) != set(DEFAULT_CHANNELS):
            missing = sorted(set(DEFAULT_CHANNELS) - set(v))
            extra = sorted(set(v) - set(DEFAULT_CHANNELS))
            what = f"missing {missing}" if missing else f"unknown {extra}"
            raise ValueError(f"{what}; give exactly {sorted(DEFAULT_CHANNELS)}")
        if len(set(v.values())) != len(v):
            raise ValueError("two roles share one output; give each role its own channel")
        return v


#: Most rays per particle a rendering may trace: the default 10,000 already gives smooth images,
#: and a million takes a hundred times as long.
MAX_RAYS_PER_PARTICLE = 1_000_000


class RenderConfig(_Strict):
    """How synthetic and simulated light-field images are rendered.

    Intensities are in sensor counts (digital numbers). ``particle_counts`` is the total
    signal one particle at the laser-sheet peak deposits through the whole aperture.
    """

    #: Rays traced per particle through the main lens and the lenslets (10,000 look smooth)
    rays_per_particle: Annotated[int, Field(ge=1, le=MAX_RAYS_PER_PARTICLE)] = 10000
    #: counts a particle deposits in all: beyond 1e9 (16-bit pixels saturate at 65535) a frame is
    #: white, and the integer accumulation of the renderer overflows
    particle_counts: Annotated[float, Field(gt=0, le=1e9, allow_inf_nan=False)] = 50000.0
    #: Physical particle diameter, micrometres (0: a point source)
    particle_diameter_um: _within(0.0, 1e5) = 0.0
    #: Diameter (at 1/e^2 of the peak) of a particle's Gaussian image on a pinhole camera's
    #: sensor, pixels: Tomo-PIV's usual 2-3 px, what diffraction at the working f-number gives
    #: (light-field cameras trace their rays instead and ignore it)
    particle_image_px: Annotated[float, Field(gt=0, le=64, allow_inf_nan=False)] = 3.0
    #: Blur the images by diffraction at the main lens' image-side f-number and at the lenslets' (sigma
    #: 0.42 lambda N each)
    diffraction: bool = True
    #: Mean background added to every pixel, counts
    background_counts: _within(0.0, 1e6) = 100.0
    #: Photoelectrons per count, which sets the shot noise
    gain_e_per_count: _within(1e-6, 1e6) = 1.0
    #: Add Poisson shot noise of the photoelectrons
    shot_noise: bool = True
    #: Standard deviation of the Gaussian read noise, counts
    read_noise_counts: _within(0.0, 1e6) = 3.0
    #: Bits per pixel of synthetic and simulated images: they saturate at 2**bit_depth - 1
    bit_depth: Annotated[int, Field(ge=8, le=16)] = 16
    #: A light-field camera's response (all off by default: today's images). Main-lens fall-off:
    #: the fraction of light lost at the sensor corner, following a cos^4 profile about the sensor
    #: centre (0.4: the corners get 60%)
    lens_falloff: Annotated[float, Field(ge=0, lt=1, allow_inf_nan=False)] = 0.0
    #: Micro-image vignetting: the fraction of light lost at the rim of every micro-image, falling
    #: off with the square of the distance from its centre (each lenslet's own cos^4)
    micro_vignetting: Annotated[float, Field(ge=0, lt=1, allow_inf_nan=False)] = 0.0
    #: Dust shadows on the microlens array, at places drawn with ``response_seed``
    dust_spots: Annotated[int, Field(ge=0, le=1000)] = 0
    #: Light a dust shadow takes at its centre (1: black)
    dust_opacity: Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)] = 0.7
    #: Radius of a dust shadow (at 1/e of its depth), pixels
    dust_radius_px: Annotated[float, Field(gt=0, le=4096, allow_inf_nan=False)] = 8.0
    #: Fixed-pattern noise of the dark offset: the standard deviation, counts, of a per-pixel offset
    #: added to ``background_counts`` that is the same in every frame (what a dark frame measures)
    dark_fpn_counts: Annotated[float, Field(ge=0, le=10000, allow_inf_nan=False)] = 0.0
    #: Seed of the dust places and the fixed pattern (each camera draws its own from it)
    response_seed: Annotated[int, Field(ge=0)] = 0

    @property
    def has_response(self) -> bool:
        """Whether any of the camera-response keys is on (else images are today's)."""
        return bool(self.lens_falloff or self.micro_vignetting or self.dust_spots or self.dark_fpn_counts)


class TargetConfig(_Strict):
    """The calibration plate (``[target]``), so that a lab's own dot plate can serve.

    Every key is optional: what is not given is the default board's (see
    :func:`calibration.board.default_board`). ``dot_pitch_mm`` is the distance between
    neighbouring dot centres, ``dot_diameter_mm`` a dot's diameter, ``marker_diameter_mm`` the
    diameter of the larger marker dot at the plate's origin (0: no marker), ``tilt_deg`` the
    plate's rotation about world y, and ``level_step_mm`` the depth of a two-level plate's second
    level (its odd columns) behind the first (0: one level).
    """

    #: Distance between neighbouring dot centres, mm (not set: the default board's)
    dot_pitch_mm: LengthMm | None = None
    #: Diameter of a dot, mm (not set: the default board's)
    dot_diameter_mm: LengthMm | None = None
    #: Diameter of the larger marker dot at the plate's origin, mm; 0: no marker
    marker_diameter_mm: _within(0.0, 1e5) | None = None
    #: The plate's rotation about world y, degrees (not set: the default board's)
    tilt_deg: Angle | None = None
    #: Depth of a two-level plate's second level (its odd columns) behind the first, mm; 0: one level
    level_step_mm: _within(0.0, 1e5) = 0.0


class Rig(_Strict):
    """A whole LF-PIV rig: the volume, one or more cameras, laser, timing and devices."""

    #: "sim": the simulated lab (emulated pulse generator and stage on pseudo-terminals, simulated cameras); "real": the
    #: devices this file names
    hardware: Literal["sim", "real"] = "sim"
    #: GenTL producer files (.cti) that give access to the real cameras; when empty, the
    #: standard GENICAM_GENTL64_PATH environment variable is searched.
    gentl_producers: tuple[str, ...] = ()
    #: The measurement volume ([volume])
    volume: VolumeConfig
    #: The cameras, one [[camera]] table each, light-field or pinhole (at least one)
    camera: Annotated[tuple[_CameraOfKind, ...], Field(min_length=1)]
    #: The laser and its light sheet ([laser])
    laser: LaserConfig = LaserConfig()
    #: The timing of a double-frame pair ([timing])
    timing: TimingConfig = TimingConfig()
    #: The calibration stage ([stage])
    stage: StageConfig = StageConfig()
    #: The pulse generator ([pulse_generator])
    pulse_generator: PulseGeneratorConfig = PulseGeneratorConfig()
    #: How synthetic and simulated images are rendered ([render])
    render: RenderConfig = RenderConfig()
    #: The calibration plate ([target])
    target: TargetConfig = TargetConfig()

    @model_validator(mode="after")
    def _consistent(self) -> Rig:
        names = [c.name for c in self.camera]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"camera names must be unique; '{dup[0]}' appears twice")
        # a voxel (pvr times the first camera's pixel on its focal plane, as VolumeGrid.from_rig)
        # as wide as the volume reconstructs a box of one voxel: at least two along every axis
        voxel = np.asarray(self.volume.pvr, dtype=np.float64) * self.camera[0].object_pixel_mm
        for axis, size, v, pvr in zip("xyz", self.volume.size_mm, voxel, self.volume.pvr, strict=True):
            if np.rint(size / v) < 2:
                raise ValueError(
                    f"volume.pvr: {pvr:g} along {axis} makes voxels of {v:.4g} mm, which the volume "
                    f"({size:g} mm along {axis}) holds fewer than two of; lower volume.pvr or enlarge volume.size_mm"
                )
        corners = np.array(np.meshgrid(*[[-0.5, 0.5]] * 3, indexing="ij")).reshape(3, -1).T
        corners = np.asarray(self.volume.centre_mm) + corners * np.asarray(self.volume.size_mm)
        for cam in self.camera:
            nearest = cam.object_distance_mm - cam.world_to_camera(corners)[:, 2].max()
            if nearest <= cam.lens_focal_length_mm:
                raise ValueError(
                    f"the volume reaches within the focal length of camera '{cam.name}' "
                    f"(nearest point {nearest:.1f} mm from its lens, F = {cam.lens_focal_length_mm} mm); "
                    "shrink volume.size_mm or move the camera back"
                )
            # a focus farther from every point of the volume than the camera's object distance
            # leaves the particles blurred to nothing (a typo in focus_mm, not a rig)
            depth = cam.world_to_camera(corners)[:, 2]
            off = 0.0 if depth.min() <= 0.0 <= depth.max() else float(np.abs(depth).min())
            if off > cam.object_distance_mm:
                raise ValueError(
                    f"the volume lies {off:.4g} mm from the focal plane of camera '{cam.name}', more than its object "
                    f"distance ({cam.object_distance_mm:.4g} mm); set its focus_mm inside or near the volume"
                )
        return self

    @property
    def cameras(self) -> tuple[AnyCamera, ...]:
        return self.camera

    @property
    def lightfield_cameras(self) -> tuple[Camera, ...]:
        """The light-field cameras, in rig order."""
        return tuple(c for c in self.camera if not is_pinhole(c))

    @property
    def pinhole_cameras(self) -> tuple[PinholeCamera, ...]:
        """The pinhole (Tomo-PIV) cameras, in rig order."""
        return tuple(c for c in self.camera if is_pinhole(c))

    def camera_named(self, name: str) -> AnyCamera:
        for cam in self.camera:
            if cam.name == name:
                return cam
        raise KeyError(name)

    @classmethod
    @keyword_options("source", since="0.1.0")
    def from_dict(cls, data: dict[str, Any], *, source: str = "rig") -> Rig:

        """Validate a parsed rig file.

        Values are checked strictly, as the file's own types: a quoted number
        (``pixel_pitch_um = "5.5"``) or a fractional count (``sensor_px = [2048.5, 2048]``) is
        an error rather than being converted, since it usually means a slip elsewhere in the
        line; a whole number written as a float (``rays_per_particle = 4e3``) is a whole number.

        Raises
        ------
        RigError
            One line naming the first offending key, e.g.
            ``rig.toml: camera[1].f_number: must be greater than 0 (got -2)``. A misspelt key is
            named before the required key it leaves missing, with the closest known key.
        """
        try:
            # through JSON so that strict mode reads arrays as tuples, as a TOML file writes them
            text = json.dumps(_whole_numbers(data), default=_plain)
        except (TypeError, ValueError) as exc:
            raise RigError(f"{source}: cannot be read as a rig: {exc}") from None
        try:
            return cls.model_validate_json(text, strict=True)
        except ValidationError as exc:
            raise RigError(f"{source}: {_first_error(exc)}") from None

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible dict with every default filled in (round-trips through from_dict)."""
        return self.model_dump(mode="json")

    def optics_warnings(self) -> list[str]:
        return [w for cam in self.camera for w in cam.optics_warnings()]


def voxel_shape_warnings(cameras: Sequence[Camera], pvr: Sequence[float]) -> list[str]:
    """Warn when cameras that view the volume from crossed directions share deep voxels.

    A plenoptic camera resolves depth far more coarsely than the lateral axes, hence its
    default PVR of (2, 2, 10). A second camera about 90 degrees away sees that depth across its
    view at its full lateral resolution, so voxels several times longer than wide throw away
    what it adds; the chapter reconstructs its dual-camera cases on equal PVRs (3:1 in all three
    directions). On the two-camera case of ``benchmarks/recon.py`` (M's optics, 0.5 PPM) Q_recon
    was 0.834 at PVR (2, 2, 10) and 0.871 at (3, 3, 3).

    Parameters
    ----------
    cameras
        The cameras reconstructed together.
    pvr
        The pixel-voxel ratio (x, y, z) of the reconstruction.

    Returns
    -------
    list of str
        One line naming the first crossed pair and the fix, or nothing.
    """
    pvr = tuple(float(v) for v in pvr)
    ratio = max(pvr) / min(pvr)
    if ratio < DEEP_VOXEL_RATIO:
        return []
    for i, a in enumerate(cameras):
        for b in cameras[i + 1:]:
            # the angle between the lines of sight: facing cameras share their depth axis
            cos = min(1.0, abs(float(np.dot(a.optical_axis, b.optical_axis))))
            angle = math.degrees(math.acos(cos))
            if angle >= CROSSED_VIEWS_DEG:
                even = ",".join([f"{min(pvr):g}"] * 3)
                return [f"cameras '{a.name}' and '{b.name}' view the volume {angle:.0f} degrees apart, so each "
                        f"resolves the other's depth, but the voxels are {ratio:.3g}x longer than wide (PVR "
                        f"{', '.join(f'{v:g}' for v in pvr)}), which throws that away; use equal PVRs, e.g. "
                        f"--pvr {even} (the chapter's dual-camera cases use 3,3,3)"]
    return []


def _whole_numbers(value: Any) -> Any:
    """``value`` with every float that is a whole number made an int (strict int keys accept
    ``4e3``; strict float keys accept ints)."""
    if isinstance(value, float) and value.is_integer():
        return int(value)
    if isinstance(value, dict):
        return {k: _whole_numbers(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_whole_numbers(v) for v in value]
    return value


def _plain(value: Any) -> Any:
    """JSON form of what json cannot write: numpy scalars and arrays as numbers and lists."""
    if isinstance(value, np.generic | np.ndarray):
        return _whole_numbers(value.tolist())
    return str(value)  # e.g. a TOML date, refused as a string where a number is due


#: The tables of a rig file and the model of each, to suggest the key a misspelt one meant.
_TABLES: dict[str, type[BaseModel]] = {
    "camera": Camera, "lightfield": Camera, "pinhole": PinholeCamera, "volume": VolumeConfig, "laser": LaserConfig,
    "timing": TimingConfig, "stage": StageConfig, "pulse_generator": PulseGeneratorConfig, "render": RenderConfig,
}


def _where(loc: tuple[int | str, ...]) -> str:
    parts: list[str] = []
    for k, item in enumerate(loc):
        if isinstance(item, int):
            if parts:
                parts[-1] += f"[{item}]"
            continue
        if k and isinstance(loc[k - 1], int) and item in ("lightfield", "pinhole"):
            continue  # the camera's kind (the union's tag), not a key
        parts.append(str(item))
    return ".".join(parts)


def _model_at(loc: tuple[int | str, ...]) -> type[BaseModel] | None:
    """The model of the table that holds key ``loc`` (the last element is the key)."""
    names = [str(item) for item in loc[:-1] if not isinstance(item, int)]
    return _TABLES.get(names[-1]) if names else Rig


def _first_error(exc: ValidationError) -> str:
    errors = exc.errors(include_url=False)
    # a misspelt key also leaves its intended key missing; name the misspelling, which is
    # what the user has to change
    unknown = [e for e in errors if e["type"] == "extra_forbidden"]
    err = unknown[0] if unknown else errors[0]
    where = _where(err["loc"])
    kind = err["type"]
    if kind == "extra_forbidden":
        model = _model_at(err["loc"])
        key = str(err["loc"][-1])
        if model is PinholeCamera and key in Camera.model_fields:
            return (f"{where}: a pinhole camera (kind = \"pinhole\") has no {key}; remove it, or set kind = "
                    "\"lightfield\" for a light-field camera")
        if model is Camera and key in PinholeCamera.model_fields | {"object_distance_mm": None}:
            return (f"{where}: {key} is a key of pinhole cameras; set kind = \"pinhole\" for a Tomo-PIV camera, or "
                    "remove it")
        known = list(model.model_fields) if model is not None else []
        close = difflib.get_close_matches(str(err["loc"][-1]), known, n=1, cutoff=0.6)
        hint = (f"did you mean {close[0]}?" if close else
                "check its spelling against examples/ and the user guide's rig-file reference")
        return f"{where}: unknown key ({hint})"
    if kind == "missing":
        return f"{where}: required key is missing"
    if where == "camera" and kind in ("tuple_type", "list_type") and isinstance(err.get("input"), dict):
        return "camera: write each camera as an array of tables, [[camera]], not [camera]"
    msg = err["msg"]
    msg = msg.removeprefix("Value error, ")
    msg = msg[0].lower() + msg[1:] if msg else msg
    got = err.get("input")
    if isinstance(got, int) and not isinstance(got, bool) and abs(got) >= 10**16:
        got = float(got)  # 1e308 written in the file, read as a whole number: shown as written
    shown = "" if isinstance(got, dict) or kind.startswith("value_error") else f" (got {got!r})"
    if isinstance(got, str) and kind in ("float_type", "float_parsing", "int_type", "int_parsing", "bool_type"):
        shown += "; write numbers and true/false without quotes"
    return f"{where}: {msg}{shown}" if where else f"{msg}{shown}"
