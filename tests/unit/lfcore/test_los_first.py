"""DRT-MART's first iterations on line-of-sight weights (ReconSettings.los_iterations): DRT weights then
built only for the voxels still bright, to the quality of DRT weights from the start."""

from __future__ import annotations

import pytest

from lfcore import metrics
from lfcore.plan import projector_for
from lfcore.reconstruct import FrameReconstructor, ReconSettings
from lfcore.rig import Rig
from tests.helpers import lightfield_scene


def _crop(rig: Rig, size_mm=(0.5, 0.4, 1.2)) -> Rig:
    return rig.model_copy(update={"volume": rig.volume.model_copy(update={"size_mm": size_mm})})


@pytest.fixture(scope="module")
def scene(tiny_rig):
    return lightfield_scene(_crop(tiny_rig))


def test_the_settings_are_checked():
    with pytest.raises(ValueError, match="fewer than the iterations"):
        ReconSettings(iterations=20, los_iterations=20)
    with pytest.raises(ValueError, match="drt-mart's simultaneous form"):
        ReconSettings(method="mlos-mart", los_iterations=5)
    with pytest.raises(ValueError, match="0 or more"):
        ReconSettings(los_iterations=-1)


def test_line_of_sight_first_reaches_the_drt_quality_on_a_fraction_of_the_voxels(scene):
    rig, grid, pts, img = scene
    truth = metrics.truth_volume(grid, pts)
    proj = projector_for(rig.camera[:1], grid, device="cpu")
    plain = FrameReconstructor(proj, ReconSettings(iterations=50, projector="stored")).reconstruct([img])
    los = FrameReconstructor(proj, ReconSettings(iterations=50, projector="stored", los_iterations=20)
                             ).reconstruct([img])
    q_plain, q_los = metrics.q_recon(plain.volume, truth), metrics.q_recon(los.volume, truth)
    assert q_los >= q_plain - 0.01, (q_los, q_plain)
    assert los.operator == "line-of-sight weights, then traced weights" and los.iterations == 50
    assert los.active_voxels == plain.active_voxels
    # the DRT weights were built for the voxels the line-of-sight iterations left bright: fewer rows
    assert los.nnz < 0.8 * plain.nnz, (los.nnz, plain.nnz)
