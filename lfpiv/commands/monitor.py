"""``lfpiv monitor``: arm the rig, record every pair and watch the newest reconstructed live."""

from __future__ import annotations

import argparse
import math
import os
import signal
import sys
import time
from contextlib import ExitStack
from pathlib import Path

from lfpiv.commands import (
    add_device,
    add_sim_options,
    check_pvr,
    png_path,
    positive_float,
    positive_int,
    ring_slots,
    sim_lab_options,
    warn_optics,
    whole_number,
    xyz_triple,
)
from lfpiv.errors import UsageError


def register(sub: argparse._SubParsersAction) -> None:
    m = sub.add_parser("monitor", help="arm the rig, record, and watch the newest pair reconstructed live",
                       description="Arm the rig (real or simulated) exactly as 'lfpiv acquire' does, record every "
                       "pair to --out, and show the newest pair live: the raw light-field images, projections "
                       "and a slice of the reconstructed volume, the in-plane vectors of the slice over their "
                       "vorticity, and a status line. The live path never slows the recorder: it skips to the "
                       "newest pair and says how many it skipped. Needs the gui extra: pip install 'lfpiv[gui]'.")
    m.add_argument("--rig", required=True, metavar="RIG", help="rig file (TOML)")
    m.add_argument("--pairs", type=positive_int, default=1000,
                   help="double-frame pairs to record per arming (default: 1000)")
    m.add_argument("--out", default=None, metavar="RUN",
                   help="run store to record to (a .zarr directory); without it the pairs are only shown "
                   "(the 'record' box turns recording on for the next arming)")
    m.add_argument("--overwrite", action="store_true", help="replace an existing run store at --out")
    m.add_argument("--screenshot", type=png_path, default=None, metavar="PNG",
                   help="save the window as PNG after --after pairs were shown, then end when the recording "
                   "does (works without a display)")
    m.add_argument("--after", type=positive_int, default=3, metavar="N",
                   help="pairs shown before the screenshot (default: 3)")
    m.add_argument("--method", choices=("drt-mart", "mlos-mart"), default="drt-mart",
                   help="reconstruction: drt-mart (dense ray-traced weights) or mlos-mart (the same elimination, "
                   "line-of-sight weights; faster on a GPU) (default: drt-mart)")
    m.add_argument("--iterations", type=lambda t: whole_number(t, 0), default=5,
                   help="MART iterations per frame (default: 5; changeable in the window)")
    m.add_argument("--relaxation", type=positive_float, default=1.0,
                   help="MART relaxation, at most 2 (default: 1; changeable in the window)")
    m.add_argument("--pvr", type=xyz_triple, default=None, metavar="X,Y,Z",
                   help="pixel-voxel ratio per axis of the live volume (default: the rig's volume.pvr); a "
                   "coarser one, e.g. twice the rig's, watches the flow on 8x fewer voxels, several times faster. "
                   "The recording keeps the raw frames whatever it is")
    m.add_argument("--slice", choices=("x", "y", "z"), default="z", help="axis normal to the slice (default: z)")
    m.add_argument("--passes", type=int, choices=(1, 2), default=2, help="correlation passes (default: 2)")
    m.add_argument("--ring", type=ring_slots, default=32, metavar="PAIRS",
                   help="ring-buffer depth in pairs (default: 32)")
    add_device(m)
    add_sim_options(m)
    m.add_argument("--quiet", action="store_true", help="no progress messages")
    m.set_defaults(func=run)


def _check_display(screenshot: bool) -> None:
    if os.environ.get("QT_QPA_PLATFORM") or not sys.platform.startswith("linux"):
        return
    if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        return
    if screenshot:
        os.environ["QT_QPA_PLATFORM"] = "offscreen"  # nothing to show on: draw offscreen for the PNG
        return
    raise UsageError("no display to show the monitor on (DISPLAY is not set); run it on a desktop, or give "
                     "--screenshot out.png to draw offscreen")


def run(args: argparse.Namespace) -> int:  # noqa: C901 - one linear sequence of set-up steps
    from acquisition.pulse_generator import signals_call
    from lfpiv.acquire import check_plan
    from lfpiv.rigfile import load_rig
    from realtime.monitor import GuiUnavailable, require_qt

    rig = load_rig(args.rig)
    warn_optics(rig)
    check_plan(rig, args.pairs)
    if args.screenshot is not None:
        folder = Path(args.screenshot).parent
        if folder.exists() and not (folder.is_dir() and os.access(folder, os.W_OK)):
            raise UsageError(f"cannot write the screenshot into {folder}; give a writable --screenshot path")
    _check_display(args.screenshot is not None)
    try:
        pg, QtCore, _, _ = require_qt()
    except GuiUnavailable as exc:
        raise UsageError(str(exc)) from None
    from lfcore.correlate import CorrelationConfig, CorrelationError
    from lfcore.device import resolve_device
    from lfcore.runstore import RunStore
    from lfcore.volume import VolumeGrid
    from lfpiv.live import LiveRecorder
    from realtime.monitor import MonitorWindow
    from realtime.pipeline import LivePipeline, LiveSettings, default_windows, monitoring_recon

    check_pvr(args.pvr)
    if args.out is not None:
        RunStore.check_new(args.out, args.overwrite)
    try:
        settings = LiveSettings(iterations=args.iterations, relaxation=args.relaxation, slice_axis=args.slice)
    except ValueError as exc:
        raise UsageError(f"--iterations/--relaxation: {exc}") from None
    device = resolve_device(args.device)

    def say(text: str) -> None:
        if not args.quiet:
            print(f"lfpiv monitor: {text}", file=sys.stderr)

    with ExitStack() as stack:
        sim_options = sim_lab_options(rig, args)
        if sim_options is not None:
            from sim.lab import SimLab  # the application is the one layer that wires the simulated lab

            say(f"simulated lab: rendering {args.sim_pool} pair(s) of '{args.sim_flow}' per camera ...")
            sim_options = {"lab": stack.enter_context(SimLab(rig, **sim_options))}
        grid = VolumeGrid.from_rig(rig, args.pvr)
        try:
            corr = CorrelationConfig(windows=default_windows(grid.shape, args.passes), overlap=0.5,
                                     deform_iterations=0)
        except CorrelationError as exc:
            raise UsageError(str(exc)) from None
        pipe = LivePipeline(rig, settings=settings, recon=monitoring_recon(method=args.method), correlation=corr,
                            pvr=args.pvr, device=device)
        say(f"building the reconstruction ({'x'.join(map(str, pipe.grid.shape[::-1]))} voxels) and correlation "
            f"on {device} ...")
        pipe.build()
        stack.callback(pipe.stop)
        rec = LiveRecorder(rig, pipe, pairs=args.pairs, out=args.out, overwrite=args.overwrite,
                           sim_options=sim_options, ring_slots=args.ring)

        def end_recording() -> None:
            rec.disarm()
            rec.wait(120.0)

        stack.callback(end_recording)  # the laser is disarmed whatever happens
        app = pg.mkQApp("lfpiv monitor")
        win = MonitorWindow(pipe, rec, title=f"lfpiv monitor: {args.rig}")
        win.show()
        pipe.start()
        rec.arm()
        shot: dict[str, object] = {"path": None, "error": None}
        interrupted: list[str] = []

        def interrupt(*_: object) -> None:
            # Only noted here: tick() closes the window from the event loop. A signal handler
            # runs between any two bytecodes of the main thread, possibly inside a paint
            # event, where destroying the widgets being painted is unsafe.
            interrupted.append("signal")

        previous_int = signal.signal(signal.SIGINT, interrupt)
        stack.callback(signal.signal, signal.SIGINT, previous_int)
        # a kill or a closed terminal: the laser off at once, then the window closes as on Ctrl-C
        stack.enter_context(signals_call(interrupt))

        def tick() -> None:
            if interrupted:
                win.close()
                app.quit()
                return
            # Offscreen mode: the screenshot after --after pairs were shown (or once the recording
            # ended and the live path has caught up), then quit when the recording has ended.
            if args.screenshot is None:
                return
            st = pipe.stats()
            caught_up = (not rec.armed and st.state in ("waiting", "stopped")
                         and st.last_pair >= rec.status()["committed_pairs"] - 1)
            if shot["path"] is None and (win.displayed >= args.after or (caught_up and not win.drawing_pending)):
                win.refresh_status()
                try:
                    shot["path"] = win.screenshot(args.screenshot)
                except OSError as exc:  # the monitor stops: the run it recorded is kept
                    shot["path"], shot["error"] = args.screenshot, exc
                    rec.disarm()
                if win.displayed < args.after:
                    say(f"the recording ended after {win.displayed} pair(s) were shown, fewer than --after "
                        f"{args.after}")
            if shot["path"] is not None and not rec.armed:
                app.quit()

        timer = QtCore.QTimer()
        timer.timeout.connect(tick)
        timer.start(50)
        app.exec()
        timer.stop()
        if win.isVisible():
            win.close()
        t0 = time.monotonic()
        end_recording()
        pipe.stop()
        numbers = win.status_numbers()
        say(f"window closed; recording and live path stopped {time.monotonic() - t0:.1f} s later")

    for r in rec.recordings:
        where = str(r.path) if r.path is not None else "not recorded (no --out)"
        print(f"recording: {where}: {r.committed_pairs} pair(s) x {len(rig.camera)} camera(s), {r.frames_recorded} "
              f"frames recorded, {r.frames_dropped} dropped, {r.overruns} overruns, state {r.state}")
    lat = numbers["latency_s"]
    print(f"live: {int(numbers['processed'])} pair(s) processed, {int(numbers['skipped'])} skipped, "
          f"{int(numbers['discarded'])} discarded, {int(numbers['displayed'])} shown; last trigger-to-display "
          f"latency {f'{lat:.2f} s' if math.isfinite(lat) else 'n/a'}; {args.method}, {args.iterations} iteration(s) "
          f"on {device}, {'x'.join(map(str, pipe.grid.shape[::-1]))} voxels at PVR "
          f"{','.join(f'{v:g}' for v in args.pvr or rig.volume.pvr)}")
    st = pipe.stats()
    if st.error:
        print(f"lfpiv monitor: warning: the live path reported: {st.error}", file=sys.stderr)
    if shot["path"] is not None and shot["error"] is None:
        print(f"screenshot: {shot['path']}")
    failed = [r for r in rec.recordings if r.state == "failed"]
    if failed:
        from acquisition.protocols import DeviceError

        raise DeviceError(failed[-1].message)
    if shot["error"] is not None:
        raise UsageError(f"{shot['error']}; give a writable --screenshot path")
    if interrupted:
        raise KeyboardInterrupt
    return 0
