"""The live pipeline on the matrix-free projector: the templates are built with the pipeline, every
pair is reconstructed on them, and the volume is the batch path's and close to the stored weights'."""

from __future__ import annotations

import time

import numpy as np
import pytest

from acquisition.ring import PairRing
from realtime.pipeline import LivePipeline, LiveSettings, monitoring_recon
from tests.helpers import RING_SHAPE as SHAPE


@pytest.fixture(scope="module")
def frames(tiny_rig):
    """Frames A and B of the tiny rig (0.5 PPM, 10 um apart along x) and their particles."""
    from lfcore.particles import particle_count, seed_particles
    from lfcore.render import LightFieldRenderer

    pts = seed_particles(tiny_rig.volume, particle_count(tiny_rig, ppm=0.5), np.random.default_rng(6))
    cfg = tiny_rig.render.model_copy(update={"rays_per_particle": 20_000})
    renderer = LightFieldRenderer(tiny_rig.camera[0], cfg, wavelength_nm=tiny_rig.laser.wavelength_nm, device="cpu")
    shots = np.stack([renderer.frame(pts + np.array([0.01 * f, 0.0, 0.0]), 50_000.0, seed=f) for f in (0, 1)])
    return shots, pts


def _ring(shots: np.ndarray) -> PairRing:
    ring = PairRing({"cam0": SHAPE}, slots=2)
    for f in range(2):
        assert ring.put("cam0", 0, f, shots[f], f, time.time_ns())
    ring.publish(0)
    return ring


def test_live_matrix_free_is_the_batch_volume_and_close_to_the_stored_weights(tiny_rig, frames, device) -> None:
    """Measured on the development VM's CPU (tiny rig, 3 iterations): the live matrix-free volume
    equals the batch matrix-free one exactly; against the stored weights' volume Q = 0.999995, the
    largest voxel difference 1.1% of the peak, and Q against the truth 0.534 (0.535 stored)."""
    from lfcore.metrics import q_recon, truth_volume
    from lfcore.projector import LightFieldProjector
    from lfcore.reconstruct import reconstruct

    shots, pts = frames
    results = []
    pipe = LivePipeline(tiny_rig, _ring(shots), settings=LiveSettings(iterations=3, slice_axis="z", slice_index=14),
                        recon=monitoring_recon(method="drt-mart", projector="matrix-free"), device=device)
    assert pipe.recon.projector == "matrix-free"
    pipe.build()
    assert pipe._recon.frames._templates is not None  # built with the pipeline, not by the first pair
    pipe.subscribe(results.append)
    with pipe:
        assert pipe.wait_processed(1, 120.0)
    st = pipe.stats()
    assert st.error is None and st.projector == "matrix-free"
    r = results[0]
    assert r.projector == "matrix-free" and 0.0 < r.active_fraction < 0.5

    proj = LightFieldProjector(tiny_rig.camera, pipe.grid, sub_apertures=pipe.recon.sub_apertures, device=device)
    mf = reconstruct(proj, [shots[0]], monitoring_recon(3, 1.0, "drt-mart", projector="matrix-free"))
    stored = reconstruct(proj, [shots[0]], monitoring_recon(3, 1.0, "drt-mart", projector="stored"))
    assert mf.projector == "matrix-free" and stored.projector == "stored"
    scale = float(mf.volume.max())
    assert scale > 0
    for ax, a in enumerate("zyx"):  # the live path is the batch path's loop
        assert np.allclose(r.mip[a], mf.volume.max(axis=ax), rtol=1e-3, atol=1e-4 * scale)
    assert np.allclose(r.slice_image, mf.volume[14], rtol=1e-3, atol=1e-4 * scale)
    a, b = stored.volume, mf.volume
    assert q_recon(b, a) > 0.9999
    assert np.abs(a - b).max() <= 0.05 * float(a.max())
    e0 = truth_volume(pipe.grid, pts)
    assert abs(q_recon(b, e0) - q_recon(a, e0)) < 0.01


def test_live_auto_runs_the_stored_weights_where_they_fit(tiny_rig, frames) -> None:
    shots, _ = frames
    results = []
    pipe = LivePipeline(tiny_rig, _ring(shots), settings=LiveSettings(iterations=1), device="cpu")
    assert pipe.recon.projector == "auto"
    pipe.subscribe(results.append)
    with pipe:
        assert pipe.wait_processed(1, 60.0)
    assert results[0].projector == "stored" and pipe.stats().projector == "stored"


def test_live_matrix_free_needs_drt_mart() -> None:
    with pytest.raises(ValueError, match="use it with drt-mart"):
        monitoring_recon(method="mlos-mart", projector="matrix-free")
