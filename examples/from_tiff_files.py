"""From a lab's TIFF files to a vorticity plot, in a few notebook cells.

Run it as a script (``python examples/from_tiff_files.py [TIFF_FOLDER] [--out DIR]``) or cell by
cell (``# %%``) in Jupyter, VS Code or Spyder. With a folder of TIFF files, it imports those:
name them so that they sort in recording order and alternate frame A, frame B (``img0001.tif``,
``img0002.tif``, ...), and give the rig file they were recorded with (``--rig``), the time
between the frames (``--dt-us``) and the pair rate (``--rate-hz``). Without one, it first writes
stand-in TIFF files as a camera's own software would (16-bit, one frame per file, with
``tifffile``), so the example runs anywhere; the tests (tests/functional/test_examples.py) run it that way.
"""

# %% The files, the rig and where the results go
import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only: no display needed
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import lfpiv  # noqa: E402

here = Path(__file__).resolve().parent
cli = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
cli.add_argument("tiffs", nargs="?", default=None, help="folder of TIFF files (default: make stand-in files)")
cli.add_argument("--rig", default=str(here / "tiny.toml"), help="the rig file the files were recorded with")
cli.add_argument("--dt-us", type=float, default=None, help="time between frames A and B (default: the rig's)")
cli.add_argument("--rate-hz", type=float, default=None, help="pairs per second (default: the rig's laser rate)")
cli.add_argument("--out", default="from-tiff-output", help="folder for the run store and the pictures")
args = cli.parse_args([] if "ipykernel" in sys.modules else None)  # in a notebook: the defaults

out = Path(args.out)
out.mkdir(parents=True, exist_ok=True)
rig = lfpiv.load_rig(args.rig)
dt_us = args.dt_us or rig.timing.dt_us
rate_hz = args.rate_hz or rig.laser.rate_hz

# %% Stand-in TIFF files, as a camera's software writes them (only without a folder of files)
if args.tiffs is None:
    import tifffile

    from lfpiv.jobs.synth import synthesize

    demo = synthesize(rig, out / "stand-in.zarr", flow="vortex-ring", pairs=2, seed=7, overwrite=True,
                      progress=False).store
    folder = out / "tiffs"
    folder.mkdir(exist_ok=True)
    frames = demo.frames(rig.camera[0].name)[...]  # (pairs, 2, rows, columns) uint16
    for i, image in enumerate(frames.reshape(-1, *frames.shape[2:])):
        tifffile.imwrite(folder / f"img{i + 1:04d}.tif", image)  # img0001 = pair 0 A, img0002 = pair 0 B, ...
else:
    folder = Path(args.tiffs)

# %% Import: a run store of the same layout as a recorded run (every file checked, none changed)
imported = lfpiv.import_files(rig, out / "run.zarr", frames={rig.camera[0].name: str(folder / "*.tif")},
                              dt_us=dt_us, rate_hz=rate_hz, overwrite=True, progress=False)
run = imported.store
print(f"imported {imported.pairs} pair(s) from {folder}, {imported.bytes_read / 1e6:.1f} MB")

# %% Reconstruct (DRT-MART) and correlate (3D multi-grid cross-correlation)
lfpiv.reconstruct(run, iterations=20, progress=False)
vectors = lfpiv.correlate(run, overlap=0.5, progress=False)
print(f"{len(vectors.pairs)} pair(s) of {' x '.join(map(str, vectors.grid.counts))} vectors, "
      f"{vectors.outliers} outlier(s) replaced")

# %% The vorticity of the middle z plane, with the in-plane vectors over it
v = lfpiv.open_run(out / "run.zarr").vectors()
x, y, z = v["x_mm"], v["y_mm"], v["z_mm"]
from lfcore.vectors import vorticity  # noqa: E402

u = np.stack([v[c][0] for c in "uvw"], axis=-1)  # pair 0: (z, y, x, 3) m/s
k = len(z) // 2
wz = vorticity(u, x, y, z)[k, ..., 2]
fig, ax = plt.subplots(figsize=(6, 5))
im = ax.imshow(wz, origin="lower", extent=(x[0], x[-1], y[0], y[-1]), cmap="RdBu_r", aspect="equal",
               vmin=-np.abs(wz).max(), vmax=np.abs(wz).max())
ax.quiver(x, y, u[k, ..., 0], u[k, ..., 1])
ax.set_xlabel("x (mm)")
ax.set_ylabel("y (mm)")
ax.set_title(f"pair 0, z = {z[k]:.2f} mm: (u, v) over the vorticity")
fig.colorbar(im, ax=ax, label="vorticity w_z (1/s)")
fig.savefig(out / "vorticity.png", dpi=100)
print(f"picture: {out / 'vorticity.png'}")

# %% And for ParaView, Tecplot, MATLAB or xarray: the fields in SI units
for fmt in ("netcdf", "vtk", "mat"):
    lfpiv.export(run, fmt, out / "field", overwrite=True)
print(f"exports in {out / 'field'}")
