"""A real light-field camera's images (tests/data/napari_lf_guv, see its README.md): the lattice
fitted to its white image against what the authors report, the perspective views and a refocused
plane of its raw light field, and the checks before recording."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import tifffile

import lfpiv
from calibration.store import CalibrationStore
from lfcore.camera_checks import background_noise, micro_image_fill
from lfcore.views import Lattice, sample_views
from tests.conftest import run_cli

DATA = Path(__file__).resolve().parents[1] / "data" / "napari_lf_guv"
#: The authors' lenslet pitch on the sensor: 100 um lenslets, relayed 1:1, on 6.5 um pixels.
PITCH_PX = 100.0 / 6.5


@pytest.fixture(scope="module")
def calibration(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from lfpiv.cli import main

    out = tmp_path_factory.mktemp("real") / "cal.zarr"
    assert main(["calibrate", "mla", "--rig", str(DATA / "rig.toml"), "--white", f"lfm={DATA / 'white.tif'}",
                 "--out", str(out)]) == 0
    return out


def _lattice(store: CalibrationStore) -> Lattice:
    g = store.grid("lfm")
    return Lattice(origin_px=g.origin_px, basis_px=np.asarray(g.basis_px), grid=g.grid)


def test_the_lattice_is_the_authors(calibration: Path) -> None:
    g = CalibrationStore.open(calibration).grid("lfm")
    assert g.grid == "square"
    assert g.pitch_px == pytest.approx(PITCH_PX, rel=0.002)
    assert abs(g.rotation_deg) < 0.5
    assert g.rms_px < 0.2
    # every micro-image wholly inside the 320 x 320 crop: 320 / 15.4 = 20.8 per side
    assert g.n_lenslets >= 20 * 20 and g.inliers.all()


def test_the_micro_images_fill_the_pitch(calibration: Path) -> None:
    # matched image-side and lenslet f-numbers (f/25 both): discs about a pitch across
    store = CalibrationStore.open(calibration)
    white = tifffile.imread(DATA / "white.tif").astype(np.float32)
    lat = _lattice(store)
    fill = micro_image_fill(sample_views(white, lat, radius_px=0.6 * lat.pitch_px))
    assert 0.85 <= fill <= 1.05


def test_views_show_the_vesicle_as_a_ring(calibration: Path, tmp_path: Path, capsys) -> None:
    res = lfpiv.views(image=DATA / "lightfield.tif", calibration=calibration, depths_mm=[0.0], out=tmp_path / "v",
                      every_view=False)
    assert "fitted grid" in res.lattice_source
    for img in (res.centre_view, res.plane_images()[0]):
        rows, cols = img.shape
        r = np.hypot(*np.meshgrid(np.arange(cols) - cols / 2 + 0.5, np.arange(rows) - rows / 2 + 0.5))
        ring = np.percentile(img[(r > 0.3 * cols) & (r < 0.5 * cols)], 90)
        inside = np.median(img[r < 0.2 * cols])
        assert ring > 2.0 * inside  # the membrane's bright ring around the darker interior
    assert (tmp_path / "v" / "views.png").is_file() and (tmp_path / "v" / "mosaic.png").is_file()
    rc, text, _ = run_cli(capsys, "views", "--image", DATA / "lightfield.tif", "--calibration", calibration,
                          "--depths", "0", "--no-each-view", "--out", tmp_path / "w")
    assert rc == 0 and "20 x 20 lenslets" in text


def test_dark_frame_and_saturation(calibration: Path) -> None:
    raw = tifffile.imread(DATA / "lightfield.tif").astype(np.float64)
    dark = tifffile.imread(DATA / "dark.tif").astype(np.float64)
    white = tifffile.imread(DATA / "white.tif").astype(np.float64)
    b, s = background_noise(dark)
    assert b == pytest.approx(dark.mean(), abs=3 * dark.std())
    # the micro-images' discs (pi / 4 of a square cell) stand above the dark level, and the light
    # field lies under the white image (some of its gap pixels read below the dark frame: as recorded)
    assert np.mean(raw > b + 3 * s) > np.pi / 4 and np.mean(white > raw) > 0.99
    checks, notes = lfpiv.check_camera(DATA / "rig.toml", images={"lfm": DATA / "lightfield.tif"},
                                       calibration=calibration)
    assert checks[0].saturated_fraction == 0.0 and not notes  # the calibration's lattice, no note
    assert checks[0].histogram.sum() == raw.size
