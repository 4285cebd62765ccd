"""``lfpiv views``: the perspective views and refocused planes of a raw light-field frame."""

from __future__ import annotations

import argparse
import re

from lfpiv.commands import positive_int


def depth_list(text: str) -> list[float]:
    """argparse type of ``--depths``: 'Z1,Z2,...' or 'START:STOP:STEP' (STOP included), mm."""
    m = re.fullmatch(r"\s*([-+.\deE]+)\s*:\s*([-+.\deE]+)\s*:\s*([-+.\deE]+)\s*", text)
    try:
        if m:
            start, stop, step = (float(g) for g in m.groups())
            if step <= 0 or stop < start:
                raise ValueError
            n = int((stop - start) / step + 1e-9) + 1
            if n > 1000:
                raise argparse.ArgumentTypeError(f"'{text}' gives {n} planes; at most 1000")
            return [start + i * step for i in range(n)]
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not depths in mm: Z1,Z2,... or START:STOP:STEP with "
                                         "STEP > 0") from None


def register(sub: argparse._SubParsersAction) -> None:
    v = sub.add_parser("views", help="perspective views and refocused planes of a raw light-field frame",
                       description="Sample a raw light-field frame at the same offset from every micro-image "
                       "centre: one perspective (sub-aperture) view per offset, on the microlens lattice fitted to "
                       "the white image (lfpiv calibrate mla) where --calibration gives it, else the rig file's "
                       "nominal one. Shift the views by the parallax of a plane (from the camera's optics: the "
                       "calibration's fitted model where it has one) and average them: the frame refocused on that "
                       "plane. Writes into --out a mosaic of every view (mosaic.png), the central view, one file "
                       "per view and per refocused plane, and a figure (views.png). The frame is a run's "
                       "(RUN --pair --frame --camera) or a raw image file (--image FILE with --calibration STORE, "
                       "or --rig RIG for the nominal lattice).")
    v.add_argument("run", nargs="?", default=None, metavar="RUN", help="run store (a .zarr directory)")
    v.add_argument("--pair", type=int, default=0, metavar="N", help="the run's pair (default: 0)")
    v.add_argument("--frame", choices=("A", "B"), default="A", help="frame A or B of the pair (default: A)")
    v.add_argument("--camera", default=None, metavar="NAME", help="the light-field camera (default: the only one)")
    v.add_argument("--image", default=None, metavar="FILE",
                   help="a raw image file (PNG, TIFF, BMP; 8 or 16 bit) instead of a run's frame")
    v.add_argument("--calibration", default=None, metavar="STORE",
                   help="calibration store with the camera's fitted microlens grid (and white image, fitted model)")
    v.add_argument("--rig", default=None, metavar="RIG",
                   help="rig file of --image when there is no calibration store (nominal lattice)")
    v.add_argument("--depths", type=depth_list, default=None, metavar="Z",
                   help="planes to refocus on, z in the rig's frame in mm: Z1,Z2,... or START:STOP:STEP "
                   "(default: 5 planes through the rig's volume)")
    v.add_argument("--upsample", type=positive_int, default=1, metavar="N",
                   help="samples per microlens of the refocused planes (default: 1)")
    v.add_argument("--out", default="views", metavar="DIR", help="folder for the files (default: views)")
    v.add_argument("--format", choices=("png", "tiff"), default="png",
                   help="png: 16-bit pictures stretched for display; tiff: the float32 values (default: png)")
    v.add_argument("--no-each-view", action="store_true", help="write the mosaic but not one file per view")
    v.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from lfpiv.jobs.views import views

    res = views(run=args.run, pair=args.pair, frame=args.frame, image=args.image, calibration=args.calibration,
                rig=args.rig, camera=args.camera, depths_mm=args.depths, upsample=args.upsample, out=args.out,
                fmt=args.format, every_view=not args.no_each_view)
    for note in res.notes:
        print(f"lfpiv: note: {note}")
    n2, n1 = res.views.inside.shape
    print(f"camera {res.camera}: {len(res.views.offsets_px)} perspective views of {n1} x {n2} lenslets "
          f"(lattice: {res.lattice_source})")
    if len(res.depths_mm):
        print(f"refocused at z = {', '.join(f'{z:g}' for z in res.depths_mm)} mm")
    print(f"wrote {len(res.files)} files to {args.out} (figure: {args.out}/views.png)")
    return 0
