"""``lfpiv import``: a run store made from image files recorded elsewhere (TIFF, PNG, BMP, DaVis)."""

from __future__ import annotations

import argparse

from lfpiv.commands import by_camera, positive_float, warn_optics
from lfpiv.errors import UsageError


def register(sub: argparse._SubParsersAction) -> None:
    from lfpiv.jobs.import_ import LAYOUTS

    s = sub.add_parser("import", help="make a run store of image files recorded elsewhere (TIFF, PNG, BMP, DaVis)",
                       description="Put the light-field images a camera's own software recorded into a new run "
                       "store of the same layout as a recorded run, ready for reconstruct, correlate, evaluate and "
                       "export. Each camera's files are a glob pattern (quote it), a folder or a DaVis set, in "
                       "natural order (img2 before img10). Every file is checked (size against the camera's "
                       "sensor_px, values against its bit_depth, compressed pages decoded) before anything is "
                       "written, and every entry that cannot be a frame (a dangling link, a file whose name breaks "
                       "the others') is named, never skipped; each source's path, "
                       "size and checksum go into the run's attributes; the files are only read.")
    s.add_argument("--rig", required=True, metavar="RIG", help="rig file (TOML) the files were recorded with")
    s.add_argument("--out", required=True, metavar="RUN", help="run store to create (a .zarr directory)")
    s.add_argument("--frames", action="append", default=[], metavar="CAM=PATTERN",
                   help="the files of camera CAM (once per camera; PATTERN alone for a one-camera rig)")
    s.add_argument("--frames-b", action="append", default=[], metavar="CAM=PATTERN",
                   help="--layout separate: the files of frames B of camera CAM")
    s.add_argument("--davis", action="append", default=[], metavar="[CAM=]PATH",
                   help="a DaVis set (.set or its folder) of double-frame images, read with LaVision's lvpyio; "
                   "dt and rate come from its frame times; PATH alone: every camera, in turn, from one set")
    s.add_argument("--layout", choices=LAYOUTS, default="interleaved",
                   help="interleaved (default: the files alternate frame A, frame B), double-frame (each file "
                   "holds both frames: two pages, or one image twice the sensor's height, A on top) or separate "
                   "(frames B from --frames-b)")
    s.add_argument("--dt-us", type=positive_float, default=None, metavar="US",
                   help="time between frames A and B in microseconds (required unless DaVis files carry it)")
    s.add_argument("--rate-hz", type=positive_float, default=None, metavar="HZ",
                   help="pairs per second (default: from DaVis files, else unknown)")
    s.add_argument("--checksum", choices=("crc32c", "sha256"), default="crc32c",
                   help="checksum of each source file kept with the run: crc32c (default; what zarr checks "
                   "chunks with, fast) or sha256 (what sha256sum prints, about six times slower)")
    s.add_argument("--overwrite", action="store_true", help="replace an existing run store at --out")
    s.add_argument("--skip-done", action="store_true",
                   help="go on with an interrupted import of the same files into --out")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from lfpiv.jobs.import_ import import_files
    from lfpiv.rigfile import load_rig

    rig = load_rig(args.rig)
    warn_optics(rig)
    names = [c.name for c in rig.camera]
    if not args.frames and not args.davis:
        raise UsageError("give the files: --frames CAM=PATTERN for each camera (or --davis PATH)")
    res = import_files(rig, args.out, frames=by_camera(args.frames, "--frames", names),
                       frames_b=by_camera(args.frames_b, "--frames-b", names) or None,
                       davis=by_camera(args.davis, "--davis", names, bare="every") or None, layout=args.layout,
                       dt_us=args.dt_us, rate_hz=args.rate_hz, overwrite=args.overwrite, skip_done=args.skip_done,
                       progress=not args.quiet, checksum=args.checksum)
    if res.imported == 0:
        print(f"every pair of {res.store.path} is imported already; nothing to do")
        return 0
    mb = res.bytes_read / 1e6
    t = res.timing
    rate = f", pairs at {t['rate_hz']:g} Hz" if t.get("rate_hz") else ", pair rate unknown"
    files = len(res.store.attrs["import"]["sources"])
    print(f"wrote {res.store.path}: {res.pairs} pair(s) x {len(names)} camera(s) from {files} file(s), {res.drops} "
          f"frame(s) lost (see drops/); dt {t['dt_s'] * 1e6:g} us{rate}; {mb:.0f} MB read in {res.seconds:.1f} s "
          f"({mb / max(res.seconds, 1e-9):.0f} MB/s)")
    return 0
