"""DaVis images in and vector sets out, on files written and read by LaVision's lvpyio (never by lfpiv's readers).

lvpyio cannot write a valid ``.imx`` (see lfpiv.formats.davis), so the image tests use ``.im7``.
"""

from __future__ import annotations

import sys
from dataclasses import replace

import numpy as np
import pytest

from lfcore.vectors import FLAG_OUTLIER, FLAG_REPLACED
from lfpiv.formats import FormatError
from lfpiv.formats.davis import davis_timing, read_davis_image, write_davis_set
from lfpiv.formats.images import image_files, inspect_image, pair_frames, read_pair

from .conftest import RATE_HZ, omega

lv = pytest.importorskip("lvpyio")

ROWS, COLS = 12, 16
DT_US = 250.0


def frame(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 4096, (ROWS, COLS), dtype=np.uint16)


def davis_buffer(frames: list[np.ndarray], t0_us: float):
    """A buffer as DaVis records a double-frame image: frame k at t0 + k * dt (``AcqTimeSeries``)."""
    buf = lv.arrays_to_buffer(frames)
    for k, f in enumerate(buf.frames):
        f.attributes["AcqTimeSeries"] = f"{t0_us + (k % 2) * DT_US:.0f} \u00b5s"
    return buf


def test_a_double_frame_im7_with_its_times(tmp_path):
    a, b = frame(1), frame(2)
    lv.write_buffer(davis_buffer([a, b], 5000.0), str(tmp_path / "B00001.im7"))
    img = read_davis_image(tmp_path / "B00001.im7")
    assert img.frames.dtype == np.uint16 and np.array_equal(img.frames, np.stack([a, b]))
    assert img.times_s == pytest.approx((5e-3, 5.25e-3))
    info = inspect_image(tmp_path / "B00001.im7")
    assert (info.format, info.frames, info.rows, info.columns, info.bits_per_sample) == ("davis", 2, ROWS, COLS, None)
    [pair] = pair_frames([tmp_path / "B00001.im7"], layout="double-frame", sensor_px=(COLS, ROWS))
    got_a, got_b = read_pair(pair, sensor_px=(COLS, ROWS), bit_depth=12)
    assert np.array_equal(got_a, a) and np.array_equal(got_b, b)


def test_a_recorded_set_its_timing_and_the_folder_left_as_it_was(tmp_path):
    frames = [(frame(10 + k), frame(20 + k)) for k in range(3)]
    period_us = 1e6 / 15.0  # 15 pairs per second
    lv.write_set([davis_buffer(list(f), k * period_us) for k, f in enumerate(frames)], str(tmp_path / "Rec"))
    before = {p.name: p.read_bytes() for p in (tmp_path / "Rec").iterdir()}
    files = image_files(tmp_path / "Rec.set")
    assert [p.name for p in files] == ["B00001.im7", "B00002.im7", "B00003.im7"]
    assert image_files(tmp_path / "Rec") == files
    pairs = pair_frames(files, layout="double-frame")
    for p, (a, b) in zip(pairs, frames, strict=True):
        got_a, got_b = read_pair(p)
        assert np.array_equal(got_a, a) and np.array_equal(got_b, b)
    timing = davis_timing([inspect_image(f) for f in files])
    assert timing.dt_s == pytest.approx(DT_US * 1e-6) and timing.rate_hz == pytest.approx(15.0, rel=1e-5)
    assert {p.name: p.read_bytes() for p in (tmp_path / "Rec").iterdir()} == before


def test_older_buffer_times_and_files_without_times(tmp_path):
    buf = lv.arrays_to_buffer([frame(3), frame(4)])
    buf.attributes["AcqTimeSeries0"] = "0 \u00b5s"
    buf.attributes["AcqTimeSeries1"] = "0.4 ms"
    lv.write_buffer(buf, str(tmp_path / "old.im7"))
    assert read_davis_image(tmp_path / "old.im7").times_s == pytest.approx((0.0, 4e-4))
    lv.write_buffer(lv.arrays_to_buffer([frame(5), frame(6)]), str(tmp_path / "bare.im7"))
    info = inspect_image(tmp_path / "bare.im7")
    timing = davis_timing([info])
    assert info.times_s is None and (timing.dt_s, timing.rate_hz) == (None, None)


def test_the_second_camera_of_a_two_camera_file(tmp_path):
    frames = [frame(30 + k) for k in range(4)]  # A, B of camera 1, then A, B of camera 2
    lv.write_buffer(lv.arrays_to_buffer(frames), str(tmp_path / "two.im7"))
    [pair] = pair_frames([tmp_path / "two.im7"], layout="double-frame", camera=1)
    a, b = read_pair(pair)
    assert np.array_equal(a, frames[2]) and np.array_equal(b, frames[3])
    with pytest.raises(FormatError) as e:
        pair_frames([tmp_path / "two.im7"], layout="double-frame", camera=2)
    assert "2 camera(s)" in str(e.value) and "\n" not in str(e.value)


def test_damaged_davis_files(tmp_path):
    lv.write_buffer(lv.arrays_to_buffer([frame(7), frame(8)]), str(tmp_path / "good.im7"), compress=False)
    raw = (tmp_path / "good.im7").read_bytes()
    (tmp_path / "cut.im7").write_bytes(raw[: len(raw) - 300])
    (tmp_path / "head.im7").write_bytes(raw[:100])
    (tmp_path / "junk.im7").write_bytes(bytes(range(256)) * 2)
    for name in ("cut.im7", "head.im7", "junk.im7"):
        with pytest.raises(FormatError) as e:
            inspect_image(tmp_path / name)
        msg = str(e.value)
        assert str(tmp_path / name) in msg and "damaged or truncated" in msg and "\n" not in msg


def test_without_lvpyio_the_error_says_how_to_install_it(tmp_path, monkeypatch):
    lv.write_buffer(lv.arrays_to_buffer([frame(9)]), str(tmp_path / "a.im7"))
    monkeypatch.setitem(sys.modules, "lvpyio", None)  # import lvpyio now fails
    with pytest.raises(FormatError, match="pip install lvpyio"):
        inspect_image(tmp_path / "a.im7")


# --- vector sets ------------------------------------------------------------------------
def test_a_vector_set_read_back_by_lvpyio(rotation, tmp_path):
    written = write_davis_set(tmp_path, rotation)
    assert written == [tmp_path / "vectors.set", tmp_path / "vectors"]
    s = lv.read_set(str(tmp_path / "vectors.set"))
    try:
        assert s.type_id == "SET_TYPE_ID_VECTOR" and len(s) == 2
        x, y, z = rotation.coords_m()
        for i, pair in enumerate(rotation.pairs):
            f = s[i][0]
            assert f.is_3c and len(f) == len(z) and f.shape == (len(y), len(x))
            # positions from the frame's scales, as lvpyio places them (the centre of vector i)
            for axis, c in (("x", x), ("y", y), ("z", z)):
                sc = getattr(f.scales, axis)
                assert sc.unit == "m"
                assert np.allclose(sc.offset + sc.slope * getattr(f.grid, axis) * (np.arange(len(c)) + 0.5), c)
            for k in range(len(z)):
                m = f.as_masked_array(plane=k)
                ok = ~np.ma.getmaskarray(m)["u"]
                for c, comp in enumerate("uvw"):
                    assert np.allclose(m[comp][ok], rotation.velocity[i, k][..., c][ok], atol=1e-6)
                vz = f.components["TS:vorticity_z"][k]
                assert np.allclose(vz, 2 * omega(pair), rtol=1e-5)
            t = f.attributes["AcqTimeSeries"]
            assert t.endswith("\u00b5s") and float(t.split()[0]) == pytest.approx(pair / RATE_HZ * 1e6)
        # pair 0 has an outlier left as it was (disabled), pair 2 one replaced (enabled, told by its flags)
        f0, f2 = s[0][0], s[1][0]
        assert f0.enabled[1][2, 3] == 0 and np.ma.getmaskarray(f0.as_masked_array(plane=1))["u"][2, 3]
        assert f0.components["TS:flags"][1][2, 3] == FLAG_OUTLIER
        flags2 = rotation.flags[1]
        k, j, i = np.argwhere(flags2 == (FLAG_OUTLIER | FLAG_REPLACED))[0]
        assert f2.enabled[k][j, i] == 1
        assert f2.components["TS:flags"][k][j, i] == FLAG_OUTLIER | FLAG_REPLACED
    finally:
        s.close()


def test_a_vector_set_replaces_an_earlier_export_and_keeps_foreign_files(rotation, tmp_path):
    write_davis_set(tmp_path, rotation)
    one = replace(rotation, pairs=[2], time_s=rotation.time_s[1:],
                  **{n: getattr(rotation, n)[1:] for n in ("velocity", "vorticity", "divergence", "q_criterion",
                                                           "flags", "peak_ratio")})
    write_davis_set(tmp_path, one)
    assert sorted(p.name for p in (tmp_path / "vectors").iterdir()) == ["B00001.vc7"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["vectors", "vectors.set"]  # no temporary folder left
    (tmp_path / "vectors" / "notes.txt").write_text("keep")
    with pytest.raises(FormatError) as e:
        write_davis_set(tmp_path, rotation)
    assert "notes.txt" in str(e.value) and "would be lost" in str(e.value)
    assert (tmp_path / "vectors" / "notes.txt").read_text() == "keep"
