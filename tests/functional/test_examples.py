"""The examples users copy run as written: ``examples/from_tiff_files.py`` from stand-in TIFF files
to a vorticity picture and exports that other readers open."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from tests.conftest import EXAMPLES


def test_from_tiff_files_runs_as_a_script(tmp_path: Path) -> None:
    out = tmp_path / "out"
    done = subprocess.run([sys.executable, str(EXAMPLES / "from_tiff_files.py"), "--out", str(out)],
                          capture_output=True, text=True, timeout=600, cwd=Path(__file__).resolve().parents[2])
    assert done.returncode == 0, done.stderr[-2000:]
    assert "imported 2 pair(s)" in done.stdout
    picture = out / "vorticity.png"
    assert picture.stat().st_size > 10_000  # a drawn figure, not an empty canvas
    import matplotlib.image

    pixels = matplotlib.image.imread(picture)
    assert np.ptp(pixels[..., :3]) > 0.5  # colours, not a blank page
    # the netCDF export opens in xarray with the flow in SI units
    import xarray as xr

    nc = sorted((out / "field").glob("*.nc"))
    assert nc, sorted(p.name for p in (out / "field").iterdir())
    with xr.open_dataset(nc[0]) as ds:
        assert ds["u"].attrs.get("units") == "m s-1"
        assert np.isfinite(ds["u"].values).all()
        assert 0 < float(np.abs(ds["u"]).max()) < 10.0  # the stand-in vortex ring: metres per second, not mm
