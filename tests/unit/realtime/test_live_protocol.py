"""The live monitor's named plans (``lfpiv monitor --protocol``): what each resolves to, the user's
options over them, the status line's name of the plan, and the fast plan's field from a known shift."""

from __future__ import annotations

import time

import numpy as np
import pytest

from acquisition.ring import PairRing
from realtime.pipeline import LivePipeline, LiveSettings, monitoring_recon
from realtime.settings import DEFAULT_LIVE_PROTOCOL, LIVE_PROTOCOLS, describe_plan, live_protocol
from tests.helpers import RING_SHAPE as SHAPE


def test_each_plan_resolves_to_its_method_and_start() -> None:
    assert DEFAULT_LIVE_PROTOCOL == "fast" and set(LIVE_PROTOCOLS) == {"fast", "drt"}
    assert live_protocol("fast", cameras_method="drt-mart") == ("mlos-mart", True)
    assert live_protocol("drt", cameras_method="drt-mart") == ("drt-mart", False)
    # pinhole cameras keep their own method in every plan
    assert live_protocol("fast", cameras_method="mlos-smart") == ("mlos-smart", True)
    assert live_protocol("drt", cameras_method="mlos-smart") == ("mlos-smart", False)


def test_the_users_options_change_the_plan() -> None:
    assert live_protocol("fast", cameras_method="drt-mart", method="drt-mart") == ("drt-mart", True)
    assert live_protocol("drt", cameras_method="drt-mart", method="mlos-mart") == ("mlos-mart", False)
    assert live_protocol("fast", cameras_method="drt-mart", warm_start=False) == ("mlos-mart", False)
    assert live_protocol("drt", cameras_method="drt-mart", warm_start=True) == ("drt-mart", True)
    # a projector other than auto applies DRT-MART's operator: `monitor --projector matrix-free` as before
    for projector in ("stored", "matrix-free"):
        assert live_protocol("fast", cameras_method="drt-mart", projector=projector) == ("drt-mart", True)
    assert live_protocol("fast", cameras_method="mlos-smart", projector="matrix-free") == ("mlos-smart", True)
    with pytest.raises(ValueError, match="one of fast, drt, not 'slow'"):
        live_protocol("slow", cameras_method="drt-mart")


def test_the_pipeline_names_its_plan(tiny_rig) -> None:
    recon = monitoring_recon(method="mlos-mart", warm_start=True)
    assert describe_plan("fast", recon) == "fast (mlos-mart, frame B warm)"
    assert describe_plan(None, monitoring_recon()) == "custom (drt-mart, uniform starts)"
    pipe = LivePipeline(tiny_rig, recon=recon, device="cpu", protocol="fast")
    assert pipe.plan == "fast (mlos-mart, frame B warm)" == pipe.stats().plan
    assert LivePipeline(tiny_rig, route="particles", device="cpu").stats().plan == ""


def test_a_lit_hysteresis_the_live_path_cannot_apply_is_refused(tiny_rig) -> None:
    """The live lit mask is made on the device (ImagePreprocessor), without ReconSettings.lit_hysteresis: settings
    with it (the batch plan for several light-field cameras) are refused rather than run without it."""
    from dataclasses import replace

    with pytest.raises(ValueError, match="lit_hysteresis 0.5: the live path's lit mask"):
        LivePipeline(tiny_rig, recon=replace(monitoring_recon(), lit_hysteresis=0.5), device="cpu")
    assert LivePipeline(tiny_rig, recon=monitoring_recon(), device="cpu").recon.lit_hysteresis is None


@pytest.mark.parametrize("protocol", ["drt", "fast"])
def test_each_plan_measures_a_known_shift_live(tiny_rig, protocol: str) -> None:
    """Two pairs of a uniform shift of (2, 1, 0) voxels through the live pipeline of each plan: the
    second pair's B starts warm in the fast plan only, and both plans measure the shift (median over
    the vectors) within 0.15 voxel laterally."""
    from lfcore.particles import particle_count, seed_particles
    from lfcore.render import LightFieldRenderer

    method, warm = live_protocol(protocol, cameras_method="drt-mart")
    cfg = tiny_rig.render.model_copy(update={"rays_per_particle": 20_000})
    renderer = LightFieldRenderer(tiny_rig.camera[0], cfg, wavelength_nm=tiny_rig.laser.wavelength_nm, device="cpu")
    shift = np.array([0.022, 0.011, 0.0])  # mm: (2, 1, 0) voxels of the tiny rig (11 um laterally)
    ring = PairRing({"cam0": SHAPE}, slots=4)
    for p in range(2):
        pts = seed_particles(tiny_rig.volume, particle_count(tiny_rig, ppm=0.5), np.random.default_rng(10 + p))
        for f in range(2):
            assert ring.put("cam0", p, f, renderer.frame(pts + f * shift, 50_000.0, seed=2 * p + f), f, time.time_ns())
    got = []
    pipe = LivePipeline(tiny_rig, ring, settings=LiveSettings(iterations=10),
                        recon=monitoring_recon(method=method, warm_start=warm), device="cpu", protocol=protocol)
    pipe.subscribe(got.append)
    ring.publish(0)
    with pipe:
        assert pipe.wait_processed(1, 120.0), pipe.stats()
        ring.publish(1)
        assert pipe.wait_processed(2, 120.0), pipe.stats()
    assert [r.warm for r in got] == [False, warm]
    voxel = np.asarray(pipe.grid.voxel_mm)
    for r in got:
        d = np.nanmedian(r.velocity.reshape(-1, 3), axis=0) * pipe.dt_s * 1e3 / voxel  # voxels (x, y, z)
        np.testing.assert_allclose(d[:2], [2.0, 1.0], atol=0.15)
