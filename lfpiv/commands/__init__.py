"""One module per ``lfpiv`` subcommand, each with ``register(subparsers)`` that adds its parser
and sets ``func`` to the function that runs it; shared argument types live here.

A command parses its arguments, calls its job (:mod:`lfpiv.jobs`, the module of the same name)
and prints; it never reaches below the application (``lint-imports`` checks that). To add a
command, write its module here and its job, and name it in :data:`COMMANDS`.
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from lfpiv.errors import UsageError

#: Subcommands in the order ``lfpiv --help`` lists them; each is the module of its name (with a
#: trailing underscore where the name is a Python keyword: ``import`` is :mod:`lfpiv.commands.import_`, and
#: underscores for hyphens).
COMMANDS = ("demo", "devices", "check-camera", "acquire", "monitor", "calibrate", "import", "synth", "info", "check",
            "views", "reconstruct", "particles", "track", "correlate", "evaluate", "export",
            "study")


def module_of(command: str) -> str:
    """The module name of a command (:data:`COMMANDS`): hyphens become underscores
    (``check-camera`` is :mod:`lfpiv.commands.check_camera`)."""
    import keyword

    name = command.replace("-", "_")
    return f"{name}_" if keyword.iskeyword(name) else name


def whole_number(text: str, least: int = 0, most: int | None = None) -> int:
    """argparse type: an integer of at least ``least`` (and at most ``most``)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a whole number") from None
    if v < least:
        raise argparse.ArgumentTypeError(f"must be at least {least}, got {v}")
    if most is not None and v > most:
        raise argparse.ArgumentTypeError(f"must be at most {most}, got {v}")
    return v


def pair_range(text: str) -> slice:
    """argparse type of ``--pairs``: '3' -> pair 3; '0:10' -> pairs 0..9; '5:' -> 5 to the end;
    ':5' -> 0..4 (Python slice rules, no negative indices)."""
    m = re.fullmatch(r"\s*(\d*)\s*(:?)\s*(\d*)\s*", text)
    if not m or (not m.group(2) and (not m.group(1) or m.group(3))):  # "2 0" is no range
        raise argparse.ArgumentTypeError(f"'{text}' is not a pair or a range START:STOP, e.g. 0:10")
    start = int(m.group(1)) if m.group(1) else 0
    if not m.group(2):
        return slice(start, start + 1)
    return slice(start, int(m.group(3)) if m.group(3) else None)


#: ``CAM=VALUE``: a camera name as the rig allows one, then the value.
_NAMED = re.compile(r"([A-Za-z][A-Za-z0-9_-]{0,31})=(.+)")


def by_camera(values: list[str], option: str, cameras: list[str], *, bare: str = "only",
              many: bool = False) -> dict[str, Any]:
    """``CAM=VALUE`` options (``--frames cam0=rec/*.tif``) as camera -> value.

    Parameters
    ----------
    values
        The option's values, in order.
    option
        Its name, for the messages.
    cameras
        The rig's camera names.
    bare
        What a VALUE without ``CAM=`` means: ``"only"``, the rig's one camera (an error with
        several); ``"every"``, every camera.
    many
        Collect every value of a camera in a list (``--white cam0=a.tif --white cam0=b.tif``)
        instead of refusing a camera given twice.

    Raises
    ------
    UsageError
        A bare value for a rig of several cameras, or a camera given twice.
    """
    out: dict[str, Any] = {}
    for v in values:
        m = _NAMED.fullmatch(v)
        if m:
            names, value = [m.group(1)], m.group(2)
        elif bare == "every" or len(cameras) == 1:
            names, value = cameras, v
        else:
            raise UsageError(f"{option} {v}: name the camera, e.g. {option} {cameras[0]}={v} (the rig has "
                             f"{len(cameras)} cameras)")
        for n in names:
            if many:
                out.setdefault(n, []).append(value)
            elif n in out:
                raise UsageError(f"{option}: camera '{n}' is given twice; give each camera's files once")
            else:
                out[n] = value
    return out


class _OldSpelling(argparse.Action):
    """An option's old spelling: stores its value where the new one does and notes that it was
    used (:func:`old_spelling_notes`)."""

    def __init__(self, option_strings: list[str], dest: str, *, new: str, **kwargs: Any) -> None:
        self.new = new
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        setattr(namespace, self.dest, values)
        namespace.old_spellings = [*getattr(namespace, "old_spellings", []), (option_string, self.new)]


def add_old_spelling(parser: argparse.ArgumentParser, old: str, new: str, dest: str, **kwargs: Any) -> None:
    """Accept ``old`` (hidden from --help) for the option now called ``new``, storing to ``dest``."""
    parser.add_argument(old, action=_OldSpelling, new=new, dest=dest, help=argparse.SUPPRESS, **kwargs)


def add_pair_range(parser: argparse.ArgumentParser, default: str) -> None:
    """``--pair-range START:STOP`` (``args.pairs``, a slice or None); the old ``--pairs START:STOP``
    still works (``--pairs`` counts pairs in synth, acquire, monitor and demo)."""
    parser.add_argument("--pair-range", dest="pairs", type=pair_range, default=None, metavar="START:STOP",
                        help=f"pairs, e.g. 0:10 or 3 (default: {default})")
    add_old_spelling(parser, "--pairs", "--pair-range", "pairs", type=pair_range)


def named(args: argparse.Namespace, option: str) -> str:
    """How the user spelt ``option`` (for messages): itself, or the old spelling that was used."""
    return next((old for old, new in getattr(args, "old_spellings", []) if new == option), option)


def pairs_option(args: argparse.Namespace) -> str:
    """How the user named the pair range (for messages): ``--pair-range`` or the old ``--pairs``."""
    return named(args, "--pair-range")


def old_spelling_notes(args: argparse.Namespace) -> None:
    """One line on stderr for each old option spelling used (after the command succeeded)."""
    for old, new in dict(getattr(args, "old_spellings", [])).items():
        what = " (--pairs counts pairs in synth, acquire, monitor and demo)" if old == "--pairs" else ""
        print(f"lfpiv: note: {old} is now {new}{what}; the old spelling still works for now", file=sys.stderr)


def positive_int(text: str) -> int:
    return whole_number(text, 1)


#: The most MART iterations a command takes: the chapter's converge within 50; a billion would
#: run for weeks with no word of it.
MAX_ITERATIONS = 10_000


def iterations(text: str) -> int:
    """argparse type of ``--iterations``: a whole number from 1 to :data:`MAX_ITERATIONS`."""
    return whole_number(text, 1, MAX_ITERATIONS)


def ring_slots(text: str) -> int:
    """argparse type of ``--ring``: pairs the ring buffer holds, at least 2 (one being filled
    while the recorder writes another)."""
    return whole_number(text, 2)


def sub_apertures(text: str) -> int:
    """argparse type of ``--sub-apertures``: 1 to :data:`lfcore.reconstruct.MAX_SUB_APERTURES`."""
    from lfpiv.jobs.reconstruct import MAX_SUB_APERTURES

    return whole_number(text, 1, MAX_SUB_APERTURES)


def rays_per_particle(text: str) -> int:
    """argparse type of the rays per particle of a rendering: 1 to
    :data:`lfcore.rig.MAX_RAYS_PER_PARTICLE`."""
    from lfpiv.jobs.synth import MAX_RAYS_PER_PARTICLE

    return whole_number(text, 1, MAX_RAYS_PER_PARTICLE)


def seeding_ppm(text: str) -> float:
    """argparse type of a seeding density, particles per microlens: positive, at most
    :data:`lfcore.particles.MAX_PPM`."""
    from lfpiv.jobs.synth import MAX_PPM

    return _at_most(text, MAX_PPM, "particles per microlens (about 1 is the usual limit of a light-field "
                    "reconstruction)")


def seeding_ppp(text: str) -> float:
    """argparse type of a seeding density, particles per pixel: positive, at most
    :data:`lfcore.particles.MAX_PPP`."""
    from lfpiv.jobs.synth import MAX_PPP

    return _at_most(text, MAX_PPP, "particles per pixel (Tomo-PIV reconstructs up to about 0.1)")


def _at_most(text: str, most: float, unit: str) -> float:
    v = positive_float(text)
    if v > most:
        raise argparse.ArgumentTypeError(f"must be at most {most:g} {unit}, got {text}")
    return v


def camera_names(text: str) -> list[str]:
    """argparse type of ``--cameras``: comma-separated names, each once."""
    names = [c.strip() for c in text.split(",")]
    if "" in names:
        raise argparse.ArgumentTypeError(f"'{text}' has an empty name; give names like cam0,cam1")
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise argparse.ArgumentTypeError(f"'{twice[0]}' is named twice; give each camera once")
    return names


def png_path(text: str) -> str:
    """argparse type of a picture's path: it must end in .png, in a folder that exists (checked
    before any work; no folder is made, anywhere on the disk)."""
    if not text.lower().endswith(".png"):
        raise argparse.ArgumentTypeError(f"'{text}' does not end in .png; pictures are written as PNG")
    folder = Path(text).parent
    if not folder.exists():
        raise argparse.ArgumentTypeError(f"the folder {folder} does not exist; create it first, or give a picture "
                                         "path in a folder that exists")
    return text


def positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a number") from None
    if not (v > 0 and v != float("inf")):
        raise argparse.ArgumentTypeError(f"must be {'finite' if v > 0 else 'a positive number'}, got {text}")
    return v


def non_negative_float(text: str) -> float:
    """argparse type: a finite number of at least 0."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a number") from None
    if not 0 <= v < float("inf"):
        raise argparse.ArgumentTypeError(f"must be {'finite' if v > 0 else '0 or more'}, got {text}")
    return v


def fraction(text: str) -> float:
    """argparse type: a number above 0 and at most 1."""
    v = positive_float(text)
    if v > 1:
        raise argparse.ArgumentTypeError(f"must be a fraction above 0 and at most 1, got {text}")
    return v


def xyz_triple(text: str) -> tuple[float, float, float]:
    """argparse type: three numbers x,y,z (a PVR, a margin; their ranges are checked by the command)."""
    try:
        v = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not three numbers like 2,2,10") from None
    if len(v) != 3:
        raise argparse.ArgumentTypeError(f"'{text}' is not three numbers like 2,2,10")
    return v  # type: ignore[return-value]


def check_pvr(pvr: tuple[float, float, float] | None) -> None:
    """A one-line usage error unless ``pvr`` is None or three positive finite numbers, at most
    1000 (the range of the rig's volume.pvr)."""
    if pvr is not None and not all(0 < v < float("inf") for v in pvr):
        raise UsageError(f"--pvr must be three positive numbers, got {','.join(f'{v:g}' for v in pvr)}")
    if pvr is not None and max(pvr) > 1000:
        raise UsageError(f"--pvr must be at most 1000 per axis (as the rig's volume.pvr), got "
                         f"{','.join(f'{v:g}' for v in pvr)}")


@contextmanager
def progress_bar(total: int, desc: str, unit: str, quiet: bool) -> Iterator[Any]:
    """A progress bar on stderr for a job's ``progress(done, total)`` callback, shown on a terminal
    unless ``quiet`` (a log or a pipe gets no bar lines); its ``write(line)`` prints a line above
    the bar (also when there is no bar)."""
    from tqdm import tqdm

    with tqdm(total=total, desc=desc, unit=unit, disable=quiet or not sys.stderr.isatty(), leave=False) as bar:

        def update(done: int, of: int | None = None) -> None:
            if of is not None:
                bar.total = of
            bar.n = done
            bar.refresh()

        update.write = lambda line: tqdm.write(line, file=sys.stderr)  # type: ignore[attr-defined]
        yield update


def add_device(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", default=None, help="cpu, cuda or cuda:N (default: a GPU if there is one)")


def add_workers(parser: argparse.ArgumentParser, what: str) -> None:
    """``--workers`` / ``--scheduler`` / ``--skip-done``: a run's pairs spread over Dask workers
    (:mod:`lfpiv.batch`)."""
    g = parser.add_mutually_exclusive_group()
    g.add_argument("--workers", type=positive_int, default=None, metavar="N",
                   help=f"{what} pairs in N worker processes on this machine, one pair each at a time (with "
                   "--device cuda, worker i takes GPU i modulo the GPUs; default: in this process)")
    g.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help=f"{what} pairs on the workers of a running Dask cluster, e.g. tcp://head:8786; they "
                   "must see the run store at the same absolute path")
    parser.add_argument("--skip-done", action="store_true",
                        help="leave out the selected pairs already done with the same settings (to resume)")


def add_along_pairs(parser: argparse.ArgumentParser, *, along_help: str, pair_by_pair_help: str) -> None:
    """``--along-pairs`` / ``--pair-by-pair``: how ``particles`` and ``track`` go through a time-resolved
    run (``args.along_pairs`` ``"on"``, ``"off"``, or ``"auto"`` where neither is given:
    :func:`lfpiv.pair_runner.along_pairs_choice`)."""
    g = parser.add_mutually_exclusive_group()
    g.add_argument("--along-pairs", dest="along_pairs", action="store_const", const="on", default="auto",
                   help=along_help)
    g.add_argument("--pair-by-pair", dest="along_pairs", action="store_const", const="off", help=pair_by_pair_help)


def workers_phrase(args: argparse.Namespace) -> str:
    """Where the pairs were done, for a command's summary line (see :func:`add_workers`)."""
    if args.workers:
        return f" by {args.workers} local worker(s)"
    return f" by the workers of {args.scheduler}" if args.scheduler else ""


def examples_dir() -> Path:
    return Path(__file__).resolve().parents[2] / "examples"


def warn_outdated_vectors(store) -> None:
    """A note on stderr when the run's vectors come from volumes that were replaced since."""
    if store.vectors_outdated:
        print(f"lfpiv: note: the vectors of {store.path} were correlated from volumes that have since been "
              f"replaced; run 'lfpiv correlate {store.path}' again for vectors of the current volumes",
              file=sys.stderr)


def warn_optics(rig) -> None:
    """Print the rig's optics warnings, one line each, on stderr."""
    warn(rig.optics_warnings())


def warn(lines: list[str]) -> None:
    """Print warnings, one line each, on stderr."""
    for w in lines:
        print(f"lfpiv: warning: {w}", file=sys.stderr)


def run_flat_fields(rig, calibration: str | None, cameras: list[str] | None = None) -> tuple[dict | None, dict | None]:
    """``--flat-field CALIB``'s flat fields of ``rig``'s light-field cameras (``cameras``: those used, None:
    all) and what they are (:func:`lfpiv.jobs.calibrate.flat_fields`), a camera without a dark image
    warned of on stderr; ``(None, None)`` where no calibration is given."""
    if calibration is None:
        return None, None
    from lfpiv.jobs.calibrate import flat_fields

    flats, info, notes = flat_fields(rig, calibration, cameras)
    warn(notes)
    return flats, info


def add_sim_options(parser: argparse.ArgumentParser) -> None:
    """The ``--sim-*`` options of commands that can run on the simulated lab."""
    parser.add_argument("--sim-flow", default="vortex-ring", metavar="FLOW",
                        help="simulated lab only: the flow the simulated cameras see (default: vortex-ring)")
    density = parser.add_mutually_exclusive_group()
    density.add_argument("--sim-ppm", type=seeding_ppm, default=None, metavar="PPM",
                         help="simulated lab only: seeding in particles per microlens (default: 0.5)")
    density.add_argument("--sim-ppp", type=seeding_ppp, default=None, metavar="PPP",
                         help="simulated lab only: seeding in particles per pixel of the first pinhole camera instead "
                         "(default for a rig of pinhole cameras only: 0.05)")
    parser.add_argument("--sim-rays", type=rays_per_particle, default=None, metavar="N",
                        help="simulated lab only: rays per particle when rendering (default: the rig's)")
    parser.add_argument("--sim-pool", type=positive_int, default=4, metavar="PAIRS",
                        help="simulated lab only: distinct pairs rendered and cycled through (default: 4)")


def sim_lab_options(rig, args: argparse.Namespace) -> dict | None:
    """Keyword arguments of the simulated lab from the ``--sim-*`` options, or None for real
    hardware (:func:`lfpiv.rigging.sim_lab_options`)."""
    from lfpiv.rigging import sim_lab_options as options

    return options(rig, flow=args.sim_flow, ppm=args.sim_ppm, ppp=args.sim_ppp, pool=args.sim_pool,
                   rays=args.sim_rays)
