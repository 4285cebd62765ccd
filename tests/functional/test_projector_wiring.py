"""The projector choice everywhere it serves, end to end: ``lfpiv monitor --projector``, the Dask
workers of ``reconstruct --workers``, and the operator's memory and time per iteration that
``volumes/`` records and ``lfpiv info`` and the progress line show."""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

from lfcore.matrix_free import PROJECTORS  # noqa: E402
from lfcore.runstore import RunStore  # noqa: E402
from lfpiv.cli import main  # noqa: E402
from tests.conftest import EXAMPLES  # noqa: E402
from tests.conftest import run_cli as _run  # noqa: E402
from tests.helpers import fast_rig_text  # noqa: E402

TINY = str(EXAMPLES / "tiny.toml")
RECON = ("--iterations", "2", "--device", "cpu", "--quiet")


@pytest.fixture(scope="module")
def frames_only(tmp_path_factory) -> Path:
    """A 2-pair synthetic run of the tiny rig, not reconstructed."""
    path = tmp_path_factory.mktemp("wiring") / "run.zarr"
    assert main(["synth", "--rig", TINY, "--out", str(path), "--pairs", "2", "--ppm", "0.1", "--flow", "uniform",
                 "--quiet"]) == 0
    return path


@pytest.fixture(scope="module")
def matrix_free_here(frames_only, tmp_path_factory) -> Path:
    """The run reconstructed on the matrix-free templates in this process: the reference."""
    path = tmp_path_factory.mktemp("here") / "run.zarr"
    shutil.copytree(frames_only, path)
    assert main(["reconstruct", str(path), "--projector", "matrix-free", *RECON]) == 0
    return path


def _copy(run: Path, tmp_path: Path) -> Path:
    path = tmp_path / "run.zarr"
    shutil.copytree(run, path)
    return path


def test_monitor_and_reconstruct_share_the_choices_and_help() -> None:
    from lfpiv.cli import _build_parser

    parser = _build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    options = [next(a for a in sub.choices[c]._actions if a.dest == "projector") for c in ("reconstruct", "monitor")]
    for o in options:
        assert tuple(o.choices) == PROJECTORS and o.default == "auto"
    assert options[0].help == options[1].help


def test_monitor_reconstructs_live_on_the_matrix_free_templates(tmp_path, capsys) -> None:
    pytest.importorskip("pyqtgraph")
    rig = tmp_path / "fast1.toml"
    rig.write_text(fast_rig_text(rate_hz=20.0, cameras=1))
    shot = tmp_path / "shot.png"
    rc, out, err = _run(capsys, "monitor", "--rig", rig, "--pairs", "4", "--screenshot", shot, "--after", "1",
                        "--device", "cpu", "--iterations", "2", "--projector", "matrix-free", "--sim-rays", "300",
                        "--sim-pool", "2", "--pvr", "4,4,20", "--quiet")
    assert rc == 0, err
    assert "live path reported" not in err  # no pair failed on the templates
    assert "drt-mart, 2 iteration(s) on cpu, 41x34x15 voxels at PVR 4,4,20, projector matrix-free" in out, out
    assert shot.exists()


def test_monitor_matrix_free_on_pinhole_cameras_gives_reconstructs_one_line_error(tmp_path, capsys) -> None:
    """The same one-line error as ``reconstruct`` gives, before anything is rendered or armed."""
    pytest.importorskip("pyqtgraph")
    text = (EXAMPLES / "tomo_4_cameras.toml").read_text()
    rig = tmp_path / "tomo4.toml"
    rig.write_text(text.replace("size_mm = [10.0, 10.0, 4.0]", "size_mm = [3.0, 3.0, 2.0]"))
    run = tmp_path / "run.zarr"
    assert main(["synth", "--rig", str(rig), "--out", str(run), "--pairs", "1", "--ppp", "0.0005", "--quiet"]) == 0
    capsys.readouterr()
    rc, _, batch = _run(capsys, "reconstruct", run, "--projector", "matrix-free", *RECON)
    assert rc == 2 and batch.count("\n") == 1 and "drt-mart" in batch
    rc, _, live = _run(capsys, "monitor", "--rig", rig, "--pairs", "2", "--projector", "matrix-free", "--device",
                       "cpu", "--sim-pool", "1", "--quiet")
    assert rc == 2 and live == batch


def test_workers_carry_the_projector_and_give_the_volumes_made_here(matrix_free_here, frames_only, tmp_path,
                                                                     capsys) -> None:
    """Measured on the development VM: the largest difference from the volumes made in this
    process was 2.3e-7 of the peak (the same kernels; only the CPU threads' split of a launch
    differs)."""
    path = _copy(frames_only, tmp_path)
    rc, out, err = _run(capsys, "reconstruct", path, "--projector", "matrix-free", *RECON, "--workers", "2")
    assert rc == 0, err
    assert "by 2 local worker(s)" in out and "matrix-free templates" in out
    s, ref = RunStore.open(path), RunStore.open(matrix_free_here)
    assert s.reconstructed_pairs() == [0, 1]
    a, b = s.volumes()[...], ref.volumes()[...]
    assert b.max() > 0
    assert np.abs(a - b).max() <= 1e-4 * b.max()
    attrs = s.group["volumes"].attrs
    assert attrs["settings"]["projector"] == "matrix-free"
    assert attrs["settings"] == ref.group["volumes"].attrs["settings"]
    op = attrs["operator"]
    assert op["projector"] == "matrix-free" and op["frames"] == 4 and op["ms_per_iteration"] > 0
    # the templates' bytes do not depend on the process that built them
    assert op["bytes"] == ref.group["volumes"].attrs["operator"]["bytes"] > 2**20


@pytest.mark.parametrize("projector", PROJECTORS)
def test_info_shows_the_operator_memory_and_time_per_iteration(frames_only, matrix_free_here, tmp_path, capsys,
                                                               projector) -> None:
    if projector == "matrix-free":
        path = matrix_free_here
    else:
        path = _copy(frames_only, tmp_path)
        assert main(["reconstruct", str(path), "--projector", projector, *RECON]) == 0
    op = RunStore.open(path).group["volumes"].attrs["operator"]
    # auto: these few thousand active voxels cost less to trace than the templates to build
    ran = "matrix-free" if projector == "matrix-free" else "stored"
    assert op["projector"] == ran and op["frames"] == 4 and op["bytes"] > 0 and op["ms_per_iteration"] > 0
    capsys.readouterr()
    rc, out, err = _run(capsys, "info", path)
    assert rc == 0, err
    shown = f"projector {projector}{' (stored)' if projector == 'auto' else ''}, operator " \
            f"{op['bytes'] / 2**20:.1f} MiB, {op['ms_per_iteration']:.1f} ms per iteration"
    assert shown in out, out


def test_auto_takes_the_templates_images_where_they_pay(frames_only, matrix_free_here, tmp_path, capsys,
                                                        monkeypatch) -> None:
    """With the templates made cheap to build (as they are against the Mc crop's 400,000 active
    voxels), ``--projector auto`` takes their images for every frame, and ``info`` says so."""
    import lfcore.plan as recon

    monkeypatch.setattr(recon, "TEMPLATE_TRACES", 0.0)
    path = _copy(frames_only, tmp_path)
    rc, out, err = _run(capsys, "reconstruct", path, *RECON)
    assert rc == 0, err
    assert "matrix-free templates and their images" in out
    s, ref = RunStore.open(path), RunStore.open(matrix_free_here)
    assert s.group["volumes"].attrs["operator"]["projector"] == "matrix-free"
    a, b = s.volumes()[...], ref.volumes()[...]
    assert np.abs(a - b).max() <= 1e-4 * b.max()  # the images the matrix-free run stored: the same volumes
    rc, out, err = _run(capsys, "info", path)
    assert rc == 0 and "projector auto (matrix-free), operator" in out, out


def test_info_on_volumes_made_before_the_operator_was_recorded(matrix_free_here, tmp_path, capsys) -> None:
    path = _copy(matrix_free_here, tmp_path)
    s = RunStore.open(path, mode="r+")
    del s.group["volumes"].attrs["operator"]
    rc, out, err = _run(capsys, "info", path)
    assert rc == 0, err
    line = next(ln for ln in out.splitlines() if ln.startswith("volumes "))
    assert line.endswith("voxels, projector matrix-free") and "operator" not in line
    # such volumes are kept and added to as before, their figures recorded from then on
    rc, _, err = _run(capsys, "reconstruct", path, "--projector", "matrix-free", "--pair-range", "1:2", *RECON)
    assert rc == 0, err
    s = RunStore.open(path)
    assert s.reconstructed_pairs() == [0, 1] and s.group["volumes"].attrs["operator"]["frames"] == 2


def test_volumes_added_to_keep_one_record_of_the_operator(frames_only, tmp_path, capsys) -> None:
    path = _copy(frames_only, tmp_path)
    for pairs in ("0:1", "1:2"):
        assert main(["reconstruct", str(path), "--pair-range", pairs, *RECON]) == 0
    s = RunStore.open(path)
    assert s.reconstructed_pairs() == [0, 1]
    op = s.group["volumes"].attrs["operator"]
    assert op["projector"] == "stored" and op["frames"] == 4


def test_the_progress_line_shows_the_operator_memory_and_time_per_iteration(frames_only, tmp_path, capsys) -> None:
    path = _copy(frames_only, tmp_path)
    rc, _, err = _run(capsys, "reconstruct", path, "--projector", "matrix-free", "--iterations", "2", "--device",
                      "cpu", "--pair-range", "0:1")
    assert rc == 0, err
    op = RunStore.open(path).group["volumes"].attrs["operator"]
    assert "projector=matrix-free" in err
    # each frame's: the templates and that frame's images of its voxels (the record keeps the largest)
    mem = [float(m) for m in re.findall(r"mem=(\d+\.\d)MiB", err)]
    assert mem and abs(max(mem) - op["bytes"] / 2**20) <= 0.1 and min(mem) > 0, err
    assert re.search(r"ms_it=\d+\.\d", err), err


def test_reconstruct_v_says_the_plan_and_info_shows_it(frames_only, tmp_path, capsys) -> None:
    """The planner's choice and its reasons: logged by ``-v``, recorded in ``volumes/`` and shown by
    ``lfpiv info`` with the operators that ran."""
    path = _copy(frames_only, tmp_path)
    rc, out, err = _run(capsys, "-v", "reconstruct", path, *RECON)
    assert rc == 0, err
    assert "plan: auto on cpu, weight cache, in memory" in err, err
    assert "--projector auto: per frame, the templates' images where building them costs less" in err
    assert "weight cache: each voxel's rows are traced once" in err
    attrs = RunStore.open(path).group["volumes"].attrs
    assert attrs["plan"]["operator"] == "auto" and attrs["plan"]["cache"] is True and attrs["plan"]["slabs"] == 1
    assert attrs["operator"]["operators"] == ["traced weights"]  # these few voxels cost less to trace
    rc, out, err = _run(capsys, "info", path)
    assert rc == 0, err
    assert re.search(r"^plan\s+auto on cpu, weight cache, in memory; ran traced weights$", out, re.M), out


def test_monitor_refuses_a_box_the_planner_refuses_in_one_line(tmp_path, capsys, monkeypatch) -> None:
    """The live path is planned by the batch path's planner: a box whose buffers do not fit is one
    line naming the fix the monitor has (a coarser --pvr, not the depth slabs it cannot use)."""
    pytest.importorskip("pyqtgraph")
    import lfcore.plan as plan

    monkeypatch.setattr(plan, "available_bytes", lambda device: 1000)
    rig = tmp_path / "fast1.toml"
    rig.write_text(fast_rig_text(rate_hz=20.0, cameras=1))
    rc, out, err = _run(capsys, "monitor", "--rig", rig, "--pairs", "2", "--device", "cpu", "--sim-pool", "1",
                        "--quiet")
    assert rc == 2 and err.count("\n") == 1, err
    assert "more than it has free; use a coarser --pvr" in err and "--slabs" not in err, err
