"""Readers of images recorded elsewhere, on files written by tifffile, Pillow and imageio (never by lfpiv)."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import tifffile
from PIL import Image

from lfpiv.formats import FormatError
from lfpiv.formats.images import (
    FrameSource,
    bit_depth,
    image_files,
    inspect_image,
    natural_sort,
    pair_frames,
    read_frame,
    read_image,
    read_pair,
    source_file,
)

ROWS, COLS = 12, 16
SENSOR = (COLS, ROWS)  # the rig's sensor_px: (columns, rows)


def frame(seed: int, bits: int = 12) -> np.ndarray:
    """A frame of ``bits``-bit counts in a uint16 array, with the top value present."""
    a = np.random.default_rng(seed).integers(0, 1 << bits, (ROWS, COLS), dtype=np.uint16)
    a[0, 0] = (1 << bits) - 1
    return a


def one_line_error(excinfo: pytest.ExceptionInfo, *names: str | Path) -> str:
    msg = str(excinfo.value)
    assert "\n" not in msg, msg
    for n in names:
        assert str(n) in msg, msg
    return msg


# --- names ------------------------------------------------------------------------------
def test_natural_sort_puts_img2_before_img10():
    names = ["img10.tif", "img2.tif", "IMG1.tif", "img1_b.tif", "img1_a.tif", "a/img3.tif"]
    assert [p.name for p in natural_sort(names)] == ["img3.tif", "IMG1.tif", "img1_a.tif", "img1_b.tif", "img2.tif",
                                                      "img10.tif"]
    assert natural_sort(["run9/f1.tif", "run10/f1.tif", "run10/f0.tif"]) == [
        Path("run9/f1.tif"), Path("run10/f0.tif"), Path("run10/f1.tif")]


def test_image_files_from_a_glob_a_folder_and_a_set(tmp_path):
    for i in (10, 2, 1):
        tifffile.imwrite(tmp_path / f"img{i}.tif", frame(i))
    (tmp_path / "notes.txt").write_text("not an image")
    assert [p.name for p in image_files(tmp_path / "img*.tif")] == ["img1.tif", "img2.tif", "img10.tif"]
    assert [p.name for p in image_files(tmp_path)] == ["img1.tif", "img2.tif", "img10.tif"]
    with pytest.raises(FormatError) as e:
        image_files(tmp_path / "cam2_*.tif")
    assert "no file matches" in one_line_error(e, "cam2_*.tif")
    (tmp_path / "gone.set").write_text("// set file")
    with pytest.raises(FormatError) as e:
        image_files(tmp_path / "gone.set")
    assert "folder" in one_line_error(e, "gone")
    (tmp_path / "vec").mkdir()
    (tmp_path / "vec" / "B00001.vc7").write_bytes(b"x")
    with pytest.raises(FormatError) as e:
        image_files(tmp_path / "vec")
    assert "vector fields" in one_line_error(e, "vec")


# --- pixels back exactly ------------------------------------------------------------------
def test_tifffile_images_come_back_exactly(tmp_path):
    a, b = frame(1), frame(2)
    tifffile.imwrite(tmp_path / "one.tif", a)
    tifffile.imwrite(tmp_path / "two.tif", np.stack([a, b]))  # a two-page TIFF
    tifffile.imwrite(tmp_path / "eight.tif", (a >> 4).astype(np.uint8))
    info = inspect_image(tmp_path / "two.tif")
    assert (info.format, info.frames, info.rows, info.columns, info.dtype, info.bits_per_sample) == (
        "tiff", 2, ROWS, COLS, "uint16", 16)
    assert np.array_equal(read_image(tmp_path / "one.tif"), a[None])
    assert np.array_equal(read_image(tmp_path / "two.tif"), np.stack([a, b]))
    assert np.array_equal(read_image(tmp_path / "two.tif", frame=1), b)
    eight = read_image(tmp_path / "eight.tif", frame=0)
    assert eight.dtype == np.uint16 and np.array_equal(eight, a >> 4)
    assert inspect_image(tmp_path / "eight.tif").bits_per_sample == 8


def test_pillow_tiffs_come_back_exactly(tmp_path):
    a, b = frame(3), frame(4)
    Image.fromarray(a).save(tmp_path / "pil.tif")  # 16-bit greyscale ("I;16")
    Image.fromarray(a).save(tmp_path / "stack.tif", save_all=True, append_images=[Image.fromarray(b)])
    assert np.array_equal(read_image(tmp_path / "pil.tif", frame=0), a)
    assert inspect_image(tmp_path / "stack.tif").frames == 2
    assert np.array_equal(read_image(tmp_path / "stack.tif"), np.stack([a, b]))


def test_png_and_bmp_from_imageio_come_back_exactly(tmp_path):
    a = frame(5)
    iio.imwrite(tmp_path / "a.png", a)
    iio.imwrite(tmp_path / "a8.png", (a >> 4).astype(np.uint8))
    iio.imwrite(tmp_path / "a.bmp", (a >> 4).astype(np.uint8))
    assert np.array_equal(read_image(tmp_path / "a.png", frame=0), a)
    assert inspect_image(tmp_path / "a.png").bits_per_sample == 16
    assert inspect_image(tmp_path / "a8.png").bits_per_sample == 8
    assert np.array_equal(read_image(tmp_path / "a.bmp", frame=0), a >> 4)
    assert np.array_equal(read_image(tmp_path / "a8.png", frame=0), a >> 4)


def test_bit_depth_declared_and_held(tmp_path):
    tifffile.imwrite(tmp_path / "twelve.tif", frame(6, bits=12))  # 12-bit data in a 16-bit container
    tifffile.imwrite(tmp_path / "ten.tif", frame(7, bits=10))
    d = bit_depth(tmp_path / "twelve.tif")
    assert (d.declared, d.largest, d.needed) == (16, 4095, 12)
    assert bit_depth(tmp_path / "ten.tif").needed == 10


# --- layouts ------------------------------------------------------------------------------
def test_interleaved_files_alternate_a_and_b(tmp_path):
    frames = [frame(10 + k) for k in range(4)]
    for k, f in enumerate(frames):
        tifffile.imwrite(tmp_path / f"img{k + 1}.tif", f)
    pairs = pair_frames(image_files(tmp_path / "img*.tif"), layout="interleaved", sensor_px=SENSOR)
    assert [(p.a.path.name, p.b.path.name) for p in pairs] == [("img1.tif", "img2.tif"), ("img3.tif", "img4.tif")]
    a, b = read_pair(pairs[1], sensor_px=SENSOR, bit_depth=12)
    assert np.array_equal(a, frames[2]) and np.array_equal(b, frames[3])


def test_interleaved_pages_of_one_stack(tmp_path):
    frames = np.stack([frame(20 + k) for k in range(6)])
    tifffile.imwrite(tmp_path / "stack.tif", frames)
    pairs = pair_frames([tmp_path / "stack.tif"], layout="interleaved")
    assert [(p.a.frame, p.b.frame) for p in pairs] == [(0, 1), (2, 3), (4, 5)]
    a, b = read_pair(pairs[2])
    assert np.array_equal(a, frames[4]) and np.array_equal(b, frames[5])


def test_double_frame_two_pages_and_one_tall_image(tmp_path):
    a, b = frame(30), frame(31)
    tifffile.imwrite(tmp_path / "p1.tif", np.stack([a, b]))  # two pages
    Image.fromarray(np.concatenate([a, b])).save(tmp_path / "p2.tif")  # A above B, twice the sensor's height
    pairs = pair_frames([tmp_path / "p1.tif", tmp_path / "p2.tif"], layout="double-frame", sensor_px=SENSOR)
    for p in pairs:
        got_a, got_b = read_pair(p, sensor_px=SENSOR, bit_depth=12)
        assert np.array_equal(got_a, a) and np.array_equal(got_b, b)
    assert (pairs[1].a.half, pairs[1].b.half) == (0, 1)
    assert np.array_equal(read_frame(pairs[1].b, sensor_px=SENSOR), b)


def test_separate_patterns_for_a_and_b(tmp_path):
    for k in range(3):
        iio.imwrite(tmp_path / f"A_{k}.png", frame(40 + k))
        iio.imwrite(tmp_path / f"B_{k}.png", frame(50 + k))
    pairs = pair_frames(image_files(tmp_path / "A_*.png"), layout="separate", files_b=image_files(tmp_path / "B_*.png"))
    a, b = read_pair(pairs[2])
    assert np.array_equal(a, frame(42)) and np.array_equal(b, frame(52))
    with pytest.raises(FormatError) as e:
        pair_frames(image_files(tmp_path / "A_*.png"), layout="separate", files_b=image_files(tmp_path / "B_[01].png"))
    assert "3 frames" in one_line_error(e) and "2" in str(e.value)


# --- errors: one line, naming the file and the fix ------------------------------------------
def test_corrupt_and_truncated_files(tmp_path):
    tifffile.imwrite(tmp_path / "good.tif", frame(60))
    raw = (tmp_path / "good.tif").read_bytes()
    (tmp_path / "half.tif").write_bytes(raw[: len(raw) // 2])  # cut in the pixel data
    (tmp_path / "head.tif").write_bytes(raw[:200])  # cut in the tags
    (tmp_path / "junk.tif").write_bytes(b"II*\x00" + bytes(range(256)) * 2)
    (tmp_path / "noise.tif").write_bytes(os.urandom(300))
    iio.imwrite(tmp_path / "good.png", frame(61))
    png = (tmp_path / "good.png").read_bytes()
    (tmp_path / "half.png").write_bytes(png[: len(png) // 2])
    for name in ("half.tif", "head.tif", "junk.tif", "noise.tif", "half.png"):
        with pytest.raises(FormatError) as e:
            inspect_image(tmp_path / name)
        assert "damaged or truncated" in one_line_error(e, tmp_path / name)
    with pytest.raises(FormatError) as e:
        read_image(tmp_path / "half.png")
    one_line_error(e, tmp_path / "half.png")


def test_frames_not_of_the_sensor_size(tmp_path):
    tifffile.imwrite(tmp_path / "small.tif", frame(62)[:, :8])
    with pytest.raises(FormatError) as e:
        pair_frames([tmp_path / "small.tif"] * 2, layout="interleaved", sensor_px=SENSOR)
    assert "8 x 12 px" in one_line_error(e, tmp_path / "small.tif") and "sensor_px is [16, 12]" in str(e.value)
    with pytest.raises(FormatError) as e:
        read_frame(FrameSource(tmp_path / "small.tif"), sensor_px=SENSOR)
    one_line_error(e, tmp_path / "small.tif")
    # one tall image given as one frame: the message points to the double-frame layout
    tifffile.imwrite(tmp_path / "tall.tif", np.concatenate([frame(1), frame(2)]))
    with pytest.raises(FormatError) as e:
        pair_frames([tmp_path / "tall.tif"] * 2, layout="interleaved", sensor_px=SENSOR)
    assert "double-frame layout" in one_line_error(e, tmp_path / "tall.tif")


def test_more_bits_than_the_camera(tmp_path):
    tifffile.imwrite(tmp_path / "fourteen.tif", frame(63, bits=14))
    with pytest.raises(FormatError) as e:
        read_frame(FrameSource(tmp_path / "fourteen.tif"), bit_depth=12)
    msg = one_line_error(e, tmp_path / "fourteen.tif")
    assert "16383 (14 bits)" in msg and "bit_depth of 12" in msg
    tifffile.imwrite(tmp_path / "shifted.tif", frame(64, bits=12) << 4)  # 12-bit data aligned to the top bits
    with pytest.raises(FormatError) as e:
        read_frame(FrameSource(tmp_path / "shifted.tif"), bit_depth=12)
    assert "shifted left by 4 bits" in one_line_error(e, tmp_path / "shifted.tif")
    assert read_frame(FrameSource(tmp_path / "shifted.tif"), bit_depth=16).max() == 4095 << 4


def test_unreadable_files(tmp_path):
    (tmp_path / "empty.tif").write_bytes(b"")
    (tmp_path / "dir.tif").mkdir()
    (tmp_path / "notes.txt").write_text("x")
    cases = {"missing.tif": "does not exist", "empty.tif": "empty", "dir.tif": "is a folder",
             "notes.txt": "not an image file lfpiv reads"}
    for name, what in cases.items():
        with pytest.raises(FormatError) as e:
            inspect_image(tmp_path / name)
        assert what in one_line_error(e, tmp_path / name)
    with pytest.raises(FormatError) as e:
        source_file(tmp_path / "missing.tif")
    one_line_error(e, tmp_path / "missing.tif")


def test_pixels_that_are_not_camera_counts(tmp_path):
    tifffile.imwrite(tmp_path / "float.tif", frame(65).astype(np.float32))
    iio.imwrite(tmp_path / "rgb.png", np.zeros((ROWS, COLS, 3), np.uint8))
    tifffile.imwrite(tmp_path / "rgb.tif", np.zeros((ROWS, COLS, 3), np.uint8), photometric="rgb")
    for name, what in (("float.tif", "floating-point"), ("rgb.png", "colour"), ("rgb.tif", "colour")):
        with pytest.raises(FormatError) as e:
            inspect_image(tmp_path / name)
        assert what in one_line_error(e, tmp_path / name)


def test_a_set_of_mixed_sizes(tmp_path):
    tifffile.imwrite(tmp_path / "f1.tif", frame(66))
    tifffile.imwrite(tmp_path / "f2.tif", frame(67))
    tifffile.imwrite(tmp_path / "f3.tif", frame(68)[:8])
    tifffile.imwrite(tmp_path / "f4.tif", frame(69)[:8])
    with pytest.raises(FormatError) as e:
        pair_frames(image_files(tmp_path / "f*.tif"), layout="interleaved")
    assert "mixed sizes" in one_line_error(e, tmp_path / "f3.tif")
    tifffile.imwrite(tmp_path / "odd.tif", np.stack([frame(1), frame(2), frame(3)]), photometric="minisblack")
    with pytest.raises(FormatError) as e:
        pair_frames([tmp_path / "odd.tif"], layout="interleaved")
    assert "odd number" in one_line_error(e, tmp_path / "odd.tif")
    with pytest.raises(FormatError) as e:
        pair_frames([tmp_path / "odd.tif"], layout="double-frame")
    assert "interleaved layout" in one_line_error(e, tmp_path / "odd.tif")
    with pytest.raises(FormatError) as e:
        pair_frames([tmp_path / "f1.tif"], layout="stacked")
    assert "interleaved, double-frame, separate" in one_line_error(e)


# --- provenance, and the sources left as they were ------------------------------------------
def test_source_file_records_path_size_and_sha256(tmp_path):
    tifffile.imwrite(tmp_path / "a.tif", frame(70))
    raw = (tmp_path / "a.tif").read_bytes()
    rec = source_file(tmp_path / "a.tif", block=100)  # streamed in blocks smaller than the file
    assert rec.size == len(raw) and rec.sha256 == hashlib.sha256(raw).hexdigest()
    assert rec.path == str((tmp_path / "a.tif").resolve())
    assert rec.to_dict() == {"path": rec.path, "size": rec.size, "sha256": rec.sha256}


def test_sources_are_never_modified_moved_or_locked(tmp_path):
    src = tmp_path / "rec"
    src.mkdir()
    tifffile.imwrite(src / "s.tif", np.stack([frame(71), frame(72)]))
    iio.imwrite(src / "a.png", frame(73))
    iio.imwrite(src / "b.png", frame(74))
    for p in src.iterdir():
        p.chmod(0o444)
    before = {p.name: (p.read_bytes(), p.stat().st_mtime_ns, p.stat().st_mode) for p in src.iterdir()}
    for p in pair_frames([src / "s.tif"], layout="double-frame") + pair_frames(
            [src / "a.png", src / "b.png"], layout="interleaved"):
        read_pair(p)
    for p in src.iterdir():
        bit_depth(p)
        source_file(p)
    after = {p.name: (p.read_bytes(), p.stat().st_mtime_ns, p.stat().st_mode) for p in src.iterdir()}
    assert after == before
    for p in src.iterdir():  # nothing holds them: they can be renamed and removed at once
        p.rename(p.with_suffix(p.suffix + ".moved"))
    assert sorted(p.name for p in src.iterdir()) == ["a.png.moved", "b.png.moved", "s.tif.moved"]
