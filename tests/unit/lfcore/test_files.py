"""lfcore.files: a file is replaced whole or not at all."""

from __future__ import annotations

import errno
import os

import pytest

from lfcore.files import partial_path, replace_file, replacing


def test_a_complete_write_replaces_the_file(tmp_path):
    path = tmp_path / "a.txt"
    path.write_text("old")
    assert replace_file(path, "new") == path and path.read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]


@pytest.mark.parametrize("fault", [KeyboardInterrupt, OSError])
def test_a_write_cut_short_leaves_the_old_file_and_no_partial_one(tmp_path, fault):
    path = tmp_path / "a.png"
    path.write_bytes(b"good")
    with pytest.raises(fault), replacing(path) as tmp:
        tmp.write_bytes(b"stub")
        raise fault(errno.ENOSPC, "No space left on device") if fault is OSError else fault()
    assert path.read_bytes() == b"good" and not partial_path(path).exists()


def test_an_error_names_the_final_path_not_the_partial_one(tmp_path):
    path = tmp_path / "a.png"
    with pytest.raises(OSError) as err, replacing(path) as tmp:
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp))
    assert err.value.filename == str(path) and err.value.errno == errno.ENOSPC
    with pytest.raises(OSError) as err, replacing(path):
        raise OSError(errno.ENOSPC, "No space left on device")  # zarr's writes name no file
    assert err.value.filename == str(path)


def test_a_symbolic_link_is_replaced_not_written_through(tmp_path):
    target = tmp_path / "target.txt"
    target.write_text("keep")
    link = tmp_path / "link.txt"
    os.symlink(target, link)
    replace_file(link, "new")
    assert target.read_text() == "keep" and link.read_text() == "new" and not link.is_symlink()


def test_a_folder_in_the_way_is_an_error_naming_it(tmp_path):
    path = tmp_path / "a.png"
    path.mkdir()
    with pytest.raises(OSError) as err:
        replace_file(path, b"x")
    assert str(path) in str(err.value.filename) and not partial_path(path).exists()
