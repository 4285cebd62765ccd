"""``lfpiv import`` checks every entry before it writes anything (issue 50, part 3): dangling and
looping links, pipes and files whose names break the pattern are named (never passed over, which
would shift frames A and B of every later pair); signed images with negative counts and 1-bit
images are refused; LZW TIFFs read (imagecodecs); a compressed page that does not decode is found
before the store is made; a TIFF appended page by page is one stack; a file that changes during
the import is refused."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import tifffile

from lfcore.runstore import RunStore
from tests.conftest import EXAMPLES
from tests.conftest import run_cli as _run
from tests.helpers import one_error

TINY = str(EXAMPLES / "tiny.toml")
ROWS, COLS = 160, 192


def _frames(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(100, 4000, (n, ROWS, COLS)).astype(np.uint16)


def _folder(tmp_path: Path, frames: np.ndarray, name: str = "rec", **kw: object) -> Path:
    d = tmp_path / name
    d.mkdir()
    for i, f in enumerate(frames):
        tifffile.imwrite(d / f"img_{i:04d}.tif", f, **kw)
    return d


def _import(capsys: pytest.CaptureFixture, tmp_path: Path, pattern: object) -> tuple[int, str, str]:
    return _run(capsys, "import", "--rig", TINY, "--out", tmp_path / "run.zarr", "--frames", str(pattern),
                "--dt-us", "1000", "--quiet")


def _refused(capsys: pytest.CaptureFixture, tmp_path: Path, pattern: object, *said: str) -> str:
    rc, out, err = _import(capsys, tmp_path, pattern)
    assert rc == 2 and one_error(err), err
    assert all(s in err for s in said), err
    assert not (tmp_path / "run.zarr").exists()  # nothing written
    return err


@pytest.mark.parametrize("how", ["dangling", "loop", "pipe"])
def test_an_entry_that_is_not_a_file_is_named_never_skipped(tmp_path, capsys, how):
    d = _folder(tmp_path, _frames(6))
    link = d / "img_0002.tif"
    link.unlink()
    if how == "dangling":
        os.symlink(d / "gone.tif", link)
        said = "is a dangling symbolic link"
    elif how == "loop":
        os.symlink(link, link)
        said = "is a symbolic link that loops"
    else:
        os.mkfifo(link)
        said = "is a named pipe"
    _refused(capsys, tmp_path, d / "*.tif", str(link), said)
    _refused(capsys, tmp_path, d, str(link), said)  # the folder itself, too


def test_a_file_whose_name_breaks_the_pattern_is_named_with_the_fix(tmp_path, capsys):
    frames = _frames(4)
    d = _folder(tmp_path, frames)
    tifffile.imwrite(d / "background.tif", _frames(1, seed=9)[0])  # sorts first: it would shift every pair
    _refused(capsys, tmp_path, d / "*.tif", "background.tif", "not follow the names of the other 4 files",
             f"'{d / 'img_*.tif'}'")
    rc, _, err = _import(capsys, tmp_path, d / "img_*.tif")  # the pattern the message gives
    assert rc == 0, err
    run = RunStore.open(tmp_path / "run.zarr")
    assert np.array_equal(run.frames("cam0")[...].reshape(-1, ROWS, COLS), frames)  # frames A and B in place
    assert run.drops() == []


def test_names_of_two_patterns_a_and_b_are_one_recording(tmp_path, capsys):
    frames = _frames(4)
    d = tmp_path / "ab"
    d.mkdir()
    for i, f in enumerate(frames):
        tifffile.imwrite(d / f"B{i // 2 + 1:05d}_{'AB'[i % 2]}.tif", f)
    rc, _, err = _import(capsys, tmp_path, d / "*.tif")
    assert rc == 0, err
    assert np.array_equal(RunStore.open(tmp_path / "run.zarr").frames("cam0")[...].reshape(-1, ROWS, COLS), frames)


@pytest.mark.parametrize("compression", [None, "zlib"])
def test_signed_images_with_negative_counts_are_refused_never_wrapped(tmp_path, capsys, compression):
    frames = _frames(4).astype(np.int16) - 200  # background-subtracted: some counts negative
    d = _folder(tmp_path, frames, compression=compression)
    _refused(capsys, tmp_path, d / "*.tif", "img_0000.tif", "signed int16 values down to", "never negative")


def test_signed_images_of_counts_import_exactly(tmp_path, capsys):
    frames = _frames(4)
    d = _folder(tmp_path, frames.astype(np.int16))
    rc, _, err = _import(capsys, tmp_path, d / "*.tif")
    assert rc == 0, err
    assert np.array_equal(RunStore.open(tmp_path / "run.zarr").frames("cam0")[...].reshape(-1, ROWS, COLS), frames)


def test_lzw_tiffs_from_pillow_import_exactly(tmp_path, capsys):
    from PIL import Image

    frames = _frames(4)
    d = tmp_path / "lzw"
    d.mkdir()
    for i, f in enumerate(frames):
        Image.fromarray(f).save(d / f"img_{i:04d}.tif", compression="tiff_lzw")
    with tifffile.TiffFile(d / "img_0000.tif") as tf:
        assert tf.pages[0].compression == 5  # LZW
    rc, _, err = _import(capsys, tmp_path, d / "*.tif")
    assert rc == 0, err
    assert np.array_equal(RunStore.open(tmp_path / "run.zarr").frames("cam0")[...].reshape(-1, ROWS, COLS), frames)


def test_a_compressed_page_that_does_not_decode_is_found_before_anything_is_written(tmp_path, capsys):
    d = _folder(tmp_path, _frames(6), compression="zlib")
    last = d / "img_0005.tif"  # of the last pair: found only once pairs were committed, before
    with tifffile.TiffFile(last) as tf:
        offset, count = tf.pages[0].dataoffsets[0], tf.pages[0].databytecounts[0]
    raw = bytearray(last.read_bytes())
    raw[offset + 2:offset + count] = bytes(range(256)) * ((count - 2) // 256) + bytes((count - 2) % 256)
    last.write_bytes(bytes(raw))
    _refused(capsys, tmp_path, d / "*.tif", "img_0005.tif", "damaged or truncated")


def test_a_tiff_appended_page_by_page_is_one_stack(tmp_path, capsys):
    frames = _frames(4)
    (tmp_path / "s").mkdir()
    for f in frames:
        tifffile.imwrite(tmp_path / "s" / "stack.tif", f, append=True)
    with tifffile.TiffFile(tmp_path / "s" / "stack.tif") as tf:
        assert len(tf.series) == 4  # what tifffile makes of it: one series a page
    rc, _, err = _import(capsys, tmp_path, tmp_path / "s" / "stack.tif")
    assert rc == 0, err
    assert np.array_equal(RunStore.open(tmp_path / "run.zarr").frames("cam0")[...].reshape(-1, ROWS, COLS), frames)
    shutil.rmtree(tmp_path / "run.zarr")
    tifffile.imwrite(tmp_path / "s" / "stack.tif", frames[0, :80], append=True)  # a page of another size
    _refused(capsys, tmp_path, tmp_path / "s" / "stack.tif", "images of different sizes")


def test_1_bit_images_are_refused(tmp_path, capsys):
    d = _folder(tmp_path, _frames(4) > 2000)
    _refused(capsys, tmp_path, d / "*.tif", "img_0000.tif", "1-bit (bilevel")


def test_a_file_that_changes_during_the_import_is_refused(tmp_path, capsys, monkeypatch):
    import lfpiv.jobs.import_ as job

    d = _folder(tmp_path, _frames(6))
    real = job.read_sources

    def still_written(path, sources, **kw):
        if Path(path).name == "img_0004.tif":  # the camera software is still writing it
            with open(path, "ab") as fh:
                fh.write(b"\0" * 16)
        return real(path, sources, **kw)

    monkeypatch.setattr(job, "read_sources", still_written)
    monkeypatch.setattr(job, "cpu_threads", lambda: 1)
    rc, _, err = _import(capsys, tmp_path, d / "*.tif")
    assert rc == 2 and one_error(err) and "img_0004.tif changed during the import" in err, err
    if (tmp_path / "run.zarr").exists():  # the pairs before it are kept, marked aborted (none: nothing left)
        run = RunStore.open(tmp_path / "run.zarr")
        assert run.state == "aborted" and run.committed_pairs <= 2


def test_every_file_that_cannot_be_used_is_named(tmp_path, capsys):
    d = _folder(tmp_path, _frames(6))
    (d / "img_0002.tif").write_bytes(b"II*\x00" + bytes(300))  # a TIFF header, no image
    (d / "img_0004.tif").write_bytes(b"")
    _refused(capsys, tmp_path, d / "*.tif", "img_0002.tif", "and 1 more file(s) that cannot be used",
             str(d / "img_0004.tif"))
    (d / "img_0002.tif").unlink()
    (d / "img_0004.tif").unlink()
    os.symlink(d / "gone.tif", d / "img_0002.tif")
    os.symlink(d / "gone.tif", d / "img_0004.tif")
    _refused(capsys, tmp_path, d / "*.tif", "img_0002.tif is a dangling symbolic link", "and 1 more entry",
             str(d / "img_0004.tif"))
