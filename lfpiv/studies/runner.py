"""The one runner of every study: its cases (here or on Dask workers, resumable), then its table,
figure and report.

A study (:class:`Study`) plans *cases*, small independent computations (a method at one
relaxation, a density, a separation angle, ...) that each return a JSON-compatible result. The
runner does the cases that are not done yet, writes each result as it finishes to
``DIR/NAME/cases/KEY.json`` (so a study interrupted or killed resumes with ``--skip-done``),
and from all of them writes:

- ``DIR/NAME/table.csv``: one row per measured point, with its units in the column names;
- ``DIR/NAME/figure.png``: the chapter's figure(s), laid out as the chapter lays them out;
- ``DIR/NAME/report.md``: the chapter's claims, ours beside them, reproduced or not and by
  how much, and how this scale differs from the chapter's protocol.

Cases are given out to workers one per task through :func:`lfpiv.batch.map_pairs` (the
coordinator alone writes results, as for a run's pairs). A case's time is measured where it
runs, so a ratio of two methods' times is always timed within one case, on one worker.
"""

from __future__ import annotations

import csv
import datetime
import hashlib
import json
import math
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from lfcore.files import replace_file
from lfpiv import __version__
from lfpiv.errors import UsageError

__all__ = ["SCALES", "Case", "Finding", "Setup", "Study", "StudyOutcome", "load_results", "render_index",
           "render_report", "run_study"]

#: ``tiny``: seconds, a check that a study runs (its figures mean little); ``quick``: minutes on
#: a 2-core CPU (smaller optics, fewer pairs and iterations); ``chapter``: the chapter's optics and
#: protocol, for a GPU workstation or a cluster.
SCALES = ("tiny", "quick", "chapter")

#: Format of the case files; a file of another format is done again.
CASE_FORMAT = 1


@dataclass(frozen=True)
class Setup:
    """What a study runs on: the scale, the user's rig (or the scale's default) and the device.

    Attributes
    ----------
    scale
        One of :data:`SCALES`.
    rig
        The user's rig (``--rig``) as :meth:`lfcore.rig.Rig.to_dict` gives it, or None for the
        scale's default rigs (:mod:`lfpiv.studies.rigs`).
    rig_name
        Where the rig came from, for the report (a file name, or "default").
    device
        Warp device of the computations (None: a GPU if there is one).
    """

    scale: str = "quick"
    rig: dict[str, Any] | None = None
    rig_name: str = "default"
    device: str | None = None

    def __post_init__(self) -> None:
        if self.scale not in SCALES:
            raise UsageError(f"--scale must be one of {', '.join(SCALES)}, got '{self.scale}'")

    def fingerprint(self) -> str:
        """What makes two runs' cases interchangeable: the scale and the rig (not the device)."""
        text = json.dumps({"scale": self.scale, "rig": self.rig}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


@dataclass(frozen=True)
class Case:
    """One independent computation of a study.

    Attributes
    ----------
    key
        Its name, unique in the study and usable as a file name (letters, digits, ``-_.``).
    params
        JSON-compatible parameters, all that :meth:`Study.run_case` needs besides the setup.
    """

    key: str
    params: dict[str, Any]


@dataclass(frozen=True)
class Finding:
    """One of the chapter's claims beside ours.

    Attributes
    ----------
    figure
        The chapter's figure or table, e.g. ``"Fig. 4.8"``.
    claim
        What the chapter says it shows.
    ours
        What this run measured.
    verdict
        ``"reproduced"``, ``"partly"``, ``"not reproduced"`` or ``"not measured"``.
    by
        By how much (the margin, or the shortfall), in words and numbers.
    """

    figure: str
    claim: str
    ours: str
    verdict: str
    by: str = ""

    VERDICTS: ClassVar[tuple[str, ...]] = ("reproduced", "partly", "not reproduced", "not measured")

    def __post_init__(self) -> None:
        if self.verdict not in self.VERDICTS:
            raise ValueError(f"verdict must be one of {self.VERDICTS}, got {self.verdict!r}")


class Study:
    """A study of the chapter: its cases, and what it makes of their results.

    Subclasses set :attr:`name`, :attr:`title`, :attr:`figures` and implement :meth:`plan`,
    :meth:`run_case`, :meth:`rows`, :meth:`figure` and :meth:`findings`; :meth:`protocol`
    says, in a few lines, what this scale does and how it differs from the chapter's.
    """

    name: ClassVar[str] = ""
    title: ClassVar[str] = ""
    figures: ClassVar[str] = ""

    def plan(self, setup: Setup) -> list[Case]:
        """The study's cases at ``setup``'s scale."""
        raise NotImplementedError

    def run_case(self, setup: Setup, params: dict[str, Any], device: str | None) -> dict[str, Any]:
        """Compute one case on ``device``; a JSON-compatible result."""
        raise NotImplementedError

    def rows(self, setup: Setup, results: Mapping[str, dict[str, Any]]) -> list[dict[str, Any]]:
        """The table: one dict per row, the same keys in every row."""
        raise NotImplementedError

    def figure(self, setup: Setup, results: Mapping[str, dict[str, Any]], path: Path) -> None:
        """Draw the figure into ``path`` (PNG)."""
        raise NotImplementedError

    def findings(self, setup: Setup, results: Mapping[str, dict[str, Any]]) -> list[Finding]:
        """The chapter's claims beside ours."""
        raise NotImplementedError

    def protocol(self, setup: Setup) -> list[str]:
        """Lines describing the rig and the protocol at this scale (for the report)."""
        return []


@dataclass
class StudyOutcome:
    """What one study's run wrote and found."""

    name: str
    folder: Path
    table: Path
    figure: Path
    report: Path
    findings: list[Finding]
    cases: int
    done_now: int
    seconds: float
    case_seconds: float = 0.0
    devices: list[str] = field(default_factory=list)


def _atomic_write(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` whole or not at all (:func:`lfcore.files.replace_file`): a reader
    (or a killed run) never sees half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    replace_file(path, text)


def _jsonable(value: Any) -> Any:
    """Plain JSON: NumPy scalars and arrays as numbers and lists, NaN and infinities as None."""
    import numpy as np

    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _case_file(folder: Path, case: Case) -> Path:
    return folder / "cases" / f"{case.key}.json"


def load_results(study: Study, setup: Setup, folder: Path, cases: Iterable[Case]) -> dict[str, dict[str, Any]]:
    """The results in ``folder`` of those ``cases`` that were done with the same parameters, scale
    and rig (a file of other settings, or damaged, counts as not done)."""
    out = {}
    for case in cases:
        path = _case_file(folder, case)
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if (data.get("format") == CASE_FORMAT and data.get("study") == study.name
                and data.get("setup") == setup.fingerprint() and data.get("params") == _jsonable(case.params)):
            out[case.key] = data
    return out


@dataclass(frozen=True)
class _CaseJob:
    """What a worker needs to run cases of a study (picklable)."""

    study: str
    setup: Setup
    cases: tuple[Case, ...]


def _run_one(study: Study, setup: Setup, case: Case, device: str | None) -> dict[str, Any]:
    from lfcore.device import resolve_device

    dev = resolve_device(device)
    t = time.perf_counter()
    result = study.run_case(setup, case.params, dev)
    return {"result": _jsonable(result), "seconds": time.perf_counter() - t, "device": dev}


def _case_task(job: _CaseJob, index: int) -> dict[str, Any]:
    """Worker task: case ``index`` of the job, on the worker's device."""
    from lfpiv.batch import this_worker_device
    from lfpiv.studies import study_named

    return _run_one(study_named(job.study), job.setup, job.cases[index], this_worker_device(job.setup.device))


def _has_results(folder: Path) -> bool:
    return (folder / "cases").is_dir() and any((folder / "cases").glob("*.json"))


def run_study(study: Study, setup: Setup, out: str | Path, *, skip_done: bool = False, overwrite: bool = False,
              client: Any = None, progress: Callable[[str], None] | None = None) -> StudyOutcome:
    """Run one study into ``out/NAME/``: its cases, then its table, figure and report.

    Parameters
    ----------
    study
        The study.
    setup
        Scale, rig and device.
    out
        The output folder; the study writes into its sub-folder ``NAME``.
    skip_done
        Keep the cases already done with the same parameters, scale and rig (resume).
    overwrite
        Do every case again, replacing the results there.
    client
        A Dask client (:func:`lfpiv.batch.dask_client`) to spread the cases over, or None.
    progress
        Called with a line after each case.

    Raises
    ------
    UsageError
        ``out/NAME`` holds results of an earlier run and neither ``skip_done`` nor
        ``overwrite`` says what to do with them; ``out`` is a file.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} is a file; give a folder for the study's results")
    folder = out / study.name
    cases = study.plan(setup)
    keys = [c.key for c in cases]
    if len(set(keys)) != len(keys):
        raise ValueError(f"study {study.name}: case keys are not unique")
    if _has_results(folder) and not (skip_done or overwrite):
        raise UsageError(f"{folder} holds the results of an earlier run; give --skip-done to keep them and do the "
                         "rest, or --overwrite to do every case again")
    start = time.perf_counter()
    done = load_results(study, setup, folder, cases) if skip_done else {}
    todo = [i for i, c in enumerate(cases) if c.key not in done]

    def finished(i: int, record: dict[str, Any]) -> None:
        case = cases[i]
        data = {"format": CASE_FORMAT, "study": study.name, "key": case.key, "params": _jsonable(case.params),
                "setup": setup.fingerprint(), "scale": setup.scale, "rig": setup.rig_name,
                "lfpiv": __version__, "finished": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
                **record}
        _atomic_write(_case_file(folder, case), json.dumps(data, indent=1) + "\n")
        done[case.key] = data
        if progress is not None:
            progress(f"{study.name}: case {case.key} done in {record['seconds']:.1f} s "
                     f"({len(done)} of {len(cases)})")

    if client is None:
        for i in todo:
            finished(i, _run_one(study, setup, cases[i], setup.device))
    elif todo:
        from lfpiv.batch import map_pairs

        job = _CaseJob(study=study.name, setup=setup, cases=tuple(cases))
        map_pairs(client, _case_task, job, todo, on_done=finished, desc=f"study {study.name}", progress=False)

    results = {k: done[k]["result"] for k in keys}
    table = folder / "table.csv"
    figure = folder / "figure.png"
    report = folder / "report.md"
    rows = study.rows(setup, results)
    _write_csv(table, rows)
    study.figure(setup, results, figure)
    findings = study.findings(setup, results)
    case_seconds = sum(float(done[k]["seconds"]) for k in keys)
    devices = sorted({str(done[k]["device"]) for k in keys})
    _atomic_write(report, render_report(study, setup, findings, case_seconds=case_seconds, devices=devices,
                                        n_cases=len(cases), rows=rows))
    return StudyOutcome(name=study.name, folder=folder, table=table, figure=figure, report=report, findings=findings,
                        cases=len(cases), done_now=len(todo), seconds=time.perf_counter() - start,
                        case_seconds=case_seconds, devices=devices)


def _write_csv(path: Path, rows: Sequence[dict[str, Any]]) -> None:
    import io

    buf = io.StringIO()
    names: list[str] = []
    for r in rows:
        names += [k for k in r if k not in names]
    w = csv.DictWriter(buf, fieldnames=names, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: _cell(v) for k, v in r.items()})
    _atomic_write(path, buf.getvalue())


def _cell(v: Any) -> Any:
    if isinstance(v, float):
        return "" if not math.isfinite(v) else f"{v:.6g}"
    return "" if v is None else v


#: Rows of the table shown in the report (the CSV has them all).
REPORT_ROWS = 40


def render_report(study: Study, setup: Setup, findings: Sequence[Finding], *, case_seconds: float,
                  devices: Sequence[str], n_cases: int, rows: Sequence[dict[str, Any]]) -> str:
    """The study's report (markdown): claims beside ours, the figure, the protocol, the table."""
    lines = [f"# `lfpiv study {study.name}`: {study.title}", "",
             f"The chapter's {study.figures}, at `--scale {setup.scale}` on the {setup.rig_name} rig; "
             f"{n_cases} cases, {case_seconds:.0f} s of computation on {', '.join(devices) or 'no device'} "
             f"(lfpiv {__version__}).", "",
             "| Chapter | The chapter's claim | Ours | Verdict |", "| --- | --- | --- | --- |"]
    for f in findings:
        verdict = f.verdict + (f": {f.by}" if f.by else "")
        lines.append(f"| {f.figure} | {_md(f.claim)} | {_md(f.ours)} | **{_md(verdict)}** |")
    lines += ["", "![figure](figure.png)", "", "## Protocol", ""]
    lines += [f"- {p}" for p in study.protocol(setup)]
    if setup.scale != "chapter":
        lines.append(f"- Run `lfpiv study {study.name} --scale chapter` for the chapter's optics and protocol (a GPU "
                     "workstation or a cluster: `--workers N` or `--scheduler ADDRESS`).")
    if rows:
        lines += ["", "## Table", "", f"`table.csv` ({len(rows)} rows)"
                  + (f"; the first {REPORT_ROWS}:" if len(rows) > REPORT_ROWS else ":"), ""]
        names: list[str] = []
        for r in rows:
            names += [k for k in r if k not in names]
        lines.append("| " + " | ".join(names) + " |")
        lines.append("|" + " --- |" * len(names))
        for r in rows[:REPORT_ROWS]:
            lines.append("| " + " | ".join(_md(str(_cell(r.get(k)))) for k in names) + " |")
    return "\n".join(lines) + "\n"


def _md(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def render_index(outcomes: Sequence[StudyOutcome], setup: Setup) -> str:
    """The index of a run of several studies (markdown): every finding, with links to the reports."""
    total = sum(o.case_seconds for o in outcomes)
    lines = [f"# The chapter's studies at `--scale {setup.scale}` ({setup.rig_name} rig)", "",
             f"{len(outcomes)} studies, {sum(o.cases for o in outcomes)} cases, {total / 60:.0f} min of computation "
             f"(lfpiv {__version__}).", "", "| Study | Chapter | The chapter's claim | Ours | Verdict |",
             "| --- | --- | --- | --- | --- |"]
    for o in outcomes:
        for f in o.findings:
            verdict = f.verdict + (f": {f.by}" if f.by else "")
            lines.append(f"| [{o.name}]({o.name}/report.md) | {f.figure} | {_md(f.claim)} | {_md(f.ours)} | "
                         f"**{_md(verdict)}** |")
    return "\n".join(lines) + "\n"
