"""Issue 50: rig values finite but meaningless are refused, each naming its rig key, and a rig
value is never reported as an option that was never given."""

from __future__ import annotations

import pytest

from lfcore.rig import Rig, RigError
from lfcore.volume import VolumeGrid


def _refused(tiny_rig: Rig, table: str, key: str, value, index: int | None = None) -> str:
    d = tiny_rig.to_dict()
    t = d[table][0] if table == "camera" else d[table]
    if index is None:
        t[key] = value
    else:
        t[key] = list(t[key])
        t[key][index] = value
    with pytest.raises(RigError) as err:
        Rig.from_dict(d, source="rig.toml")
    msg = str(err.value)
    assert msg.startswith("rig.toml: ") and "\n" not in msg
    return msg


@pytest.mark.parametrize(("table", "key", "value", "index", "named"), [
    ("timing", "dt_us", 1e-300, None, "timing.dt_us: input should be greater than or equal to 0.001 (got 1e-300)"),
    ("timing", "dt_us", 5e-324, None, "timing.dt_us: input should be greater than or equal to 0.001"),
    ("timing", "dt_us", 1e300, None, "timing.dt_us: input should be less than or equal to"),
    ("volume", "pvr", 1e308, 0, "volume.pvr[0]: input should be less than or equal to 1000 (got 1e+308)"),
    ("volume", "size_mm", 1e300, 2, "volume.size_mm[2]: input should be less than or equal to"),
    ("volume", "centre_mm", 1e300, 1, "volume.centre_mm[1]: input should be less than or equal to"),
    ("camera", "rotation_deg", 1e300, 0, "camera[0].rotation_deg[0]: input should be less than or equal to 360"),
    ("camera", "rotation_deg", -1e300, 2, "camera[0].rotation_deg[2]: input should be greater than or equal to -360"),
    ("camera", "mla_rotation_deg", 1e300, None, "camera[0].mla_rotation_deg: input should be less than or equal"),
    ("camera", "magnification", -1e-300, None, "camera[0].magnification: a magnification of -1e-300"),
    ("camera", "pixel_pitch_um", 1e300, None, "camera[0].pixel_pitch_um: input should be less than or equal"),
    ("laser", "rate_hz", 1e300, None, "laser.rate_hz: input should be less than or equal"),
    ("laser", "wavelength_nm", 1e-300, None, "laser.wavelength_nm: input should be greater than or equal to 100"),
])
def test_finite_but_meaningless_values_name_their_key(tiny_rig, table, key, value, index, named):
    assert named in _refused(tiny_rig, table, key, value, index)


def test_a_pvr_that_leaves_one_voxel_along_an_axis_is_refused(tiny_rig):
    """pvr = 1e308 reconstructed a 1 x 1 x 1 box; a PVR within range whose voxels are wider than
    the volume is named too."""
    msg = _refused(tiny_rig, "volume", "pvr", 500.0, 0)
    assert "volume.pvr: 500 along x makes voxels of" in msg and "lower volume.pvr or enlarge volume.size_mm" in msg


def test_every_value_in_range_still_makes_a_grid(tiny_rig):
    grid = VolumeGrid.from_rig(tiny_rig)
    assert min(grid.shape) >= 2


def test_a_rig_dt_is_never_reported_as_the_dt_ms_option(tiny_rig, tmp_path):
    """dt_us = 5e-324 was reported as "--dt-ms must be positive", an option never given: the rig
    now refuses it, naming timing.dt_us, and --dt-ms given is checked against the same range."""
    from lfpiv.errors import UsageError
    from lfpiv.jobs.synth import synthesize

    assert "timing.dt_us" in _refused(tiny_rig, "timing", "dt_us", 5e-324)
    with pytest.raises(UsageError, match=r"--dt-ms must be from 1e-06 \(a nanosecond\) to 1e\+05 \(100 s\), got "):
        synthesize(tiny_rig, tmp_path / "s.zarr", pairs=1, dt_s=1e-323)


def test_an_imported_dt_is_checked_against_the_same_range_naming_where_it_came_from():
    """import took --dt-us 5e-324 (positive) and named --dt-us for a time the files carried."""
    from lfpiv.errors import UsageError
    from lfpiv.jobs.import_ import _timing

    with pytest.raises(UsageError, match=r"^--dt-us 4.94066e-324 is not a time between frames A and B"):
        _timing(5e-324, None, {"dt_s": None, "rate_hz": None})
    with pytest.raises(UsageError, match=r"^the files' time between frames A and B \(1e-300 s\) .*; give --dt-us$"):
        _timing(None, None, {"dt_s": 1e-300, "rate_hz": None})
    assert _timing(2000.0, 10.0, {"dt_s": None, "rate_hz": None})["dt_s"] == pytest.approx(2e-3)
