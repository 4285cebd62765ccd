"""The live pipeline on a hand-filled ring: settings, skipping, discarding, and stopping from every state."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from acquisition.ring import PairRing
from lfcore.volume import VolumeGrid
from realtime.pipeline import LivePipeline, LiveSettings, default_windows
from tests.helpers import RING_SHAPE as SHAPE
from tests.helpers import filled_ring as _ring
from tests.helpers import ring_frames as _frames


def _wait(cond, timeout_s: float = 20.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.01)
    return cond()


def test_default_windows() -> None:
    assert default_windows((29, 68, 82)) == ((32, 32, 16), (16, 16, 8))
    assert default_windows((29, 68, 82), passes=1) == ((32, 32, 16),)
    assert default_windows((131, 1000, 1000)) == ((64, 64, 64), (32, 32, 32))
    assert default_windows((5, 6, 7)) == ((4, 4, 4), (4, 4, 4))
    with pytest.raises(ValueError, match="1 or 2 passes"):
        default_windows((29, 68, 82), passes=3)


def test_settings_are_validated_and_change_at_run_time(tiny_rig) -> None:
    with pytest.raises(ValueError, match="diverge"):
        LiveSettings(relaxation=3.0)
    with pytest.raises(ValueError, match="slice_axis"):
        LiveSettings(slice_axis="w")
    pipe = LivePipeline(tiny_rig, device="cpu")
    with pytest.raises(ValueError, match="iterations"):
        pipe.update(iterations=-1)
    assert pipe.update(iterations=2, slice_axis="y", slice_index=3) == LiveSettings(iterations=2, slice_axis="y",
                                                                                    slice_index=3)
    with pytest.raises(ValueError, match="camera 'cam0' is not in the ring"):
        pipe.attach(PairRing({"other": SHAPE}, slots=2))


def test_takes_the_newest_pair_counts_the_skipped_and_publishes(tiny_rig) -> None:
    ring = _ring(5)
    results = []
    pipe = LivePipeline(tiny_rig, ring, settings=LiveSettings(iterations=2, slice_axis="y", slice_index=1000),
                        device="cpu")
    pipe.subscribe(results.append)
    with pipe:
        assert pipe.wait_processed(1, 60.0)
        # a newer pair arrives: it is taken next, with nothing skipped in between
        fr = _frames(5)
        for f in range(2):
            ring.put("cam0", 5, f, fr[f], 10 + f, time.time_ns())
        ring.publish(5)
        assert pipe.wait_processed(2, 60.0)
    st = pipe.stats()
    assert st.state == "stopped" and st.error is None
    assert [r.pair for r in results] == [4, 5]
    assert st.processed == 2 and st.skipped == 4 and st.discarded == 0 and st.last_pair == 5
    assert st.processed + st.skipped + st.discarded == st.last_pair + 1
    r = results[0]
    assert np.array_equal(r.raw["cam0"], _frames(4)[0])  # the pair's own frame A, copied
    nz, ny, nx = pipe.grid.shape
    assert r.mip["z"].shape == (ny, nx) and r.mip["y"].shape == (nz, nx) and r.mip["x"].shape == (nz, ny)
    assert r.slice_axis == "y" and r.slice_index == ny - 1 and r.slice_image.shape == (nz, nx)  # clipped
    vs = r.vectors
    assert vs.axis == "y" and vs.uv.shape == (len(vs.v_mm), len(vs.h_mm), 2)
    assert vs.normal_vorticity.shape == vs.uv.shape[:2]
    assert r.velocity.shape == r.vorticity.shape and r.velocity.shape[-1] == 3
    assert r.settings.iterations == 2 and r.skipped == 4 and r.sequence == 0 and results[1].sequence == 1
    assert set(r.timings) == {"copy", "preprocess", "eliminate", "weights", "iterate", "volume", "correlate", "derive",
                             "total"}
    assert 0.0 <= r.latency_s < 60.0
    assert r.extent_mm["x"][0] < 0.0 < r.extent_mm["x"][1]


class _Overwritten:
    """A ring whose slot is always reused during the copy."""

    def __init__(self, ring: PairRing) -> None:
        self.ring = ring
        self.cameras = ring.cameras

    def latest(self):
        return self.ring.latest()

    def still_valid(self, view) -> bool:
        return False


def test_a_pair_overwritten_during_the_copy_is_discarded(tiny_rig) -> None:
    results = []
    pipe = LivePipeline(tiny_rig, _Overwritten(_ring(3)), device="cpu")
    pipe.subscribe(results.append)
    with pipe:
        assert _wait(lambda: pipe.stats().discarded == 1)
    st = pipe.stats()
    assert results == [] and st.processed == 0 and st.skipped == 2 and st.last_pair == 2


def test_stop_from_every_state(tiny_rig) -> None:
    # never started
    idle = LivePipeline(tiny_rig, device="cpu")
    assert idle.stats().state == "idle"
    assert idle.stop() and idle.stats().state == "stopped"
    assert idle.stop()  # twice is fine
    # waiting: no source at all
    waiting = LivePipeline(tiny_rig, device="cpu")
    waiting.start()
    assert _wait(lambda: waiting.stats().state == "waiting")
    assert waiting.stop(10.0) and waiting.stats().state == "stopped"
    with pytest.raises(RuntimeError, match="already started"):
        waiting.start()
    # paused with pairs waiting: nothing is taken
    paused = LivePipeline(tiny_rig, _ring(2), device="cpu")
    paused.pause()
    paused.start()
    assert _wait(lambda: paused.stats().state == "paused")
    assert paused.stop(10.0) and paused.stats().processed == 0
    # processing: a subscriber that blocks holds the thread inside a pair
    inside, release = threading.Event(), threading.Event()
    busy = LivePipeline(tiny_rig, _ring(2), device="cpu")
    busy.subscribe(lambda r: (inside.set(), release.wait(30.0)))
    busy.start()
    assert inside.wait(60.0) and busy.stats().state == "processing"
    stopper = threading.Thread(target=busy.stop)
    stopper.start()
    release.set()
    stopper.join(30.0)
    assert not stopper.is_alive() and busy.stats().state == "stopped" and busy.stats().processed == 1
    # building: stop right after start
    building = LivePipeline(tiny_rig, _ring(1), device="cpu")
    building.start()
    assert building.stop(60.0) and building.stats().state == "stopped"


def test_staging_hands_over_the_newest_pair_intact(tiny_rig) -> None:
    """Pairs keep arriving while one is processed: the feeder replaces the ready pair with newer
    ones and the pipeline prefetches; every result still carries its own pair's frames, pairs
    only go forward, and every published pair is processed, skipped or discarded."""
    ring = _ring(1, slots=4)
    results, gate = [], threading.Event()
    pipe = LivePipeline(tiny_rig, ring, settings=LiveSettings(iterations=1), device="cpu")
    pipe.subscribe(lambda r: (results.append(r), gate.wait(0.3)))
    pipe.build()
    with pipe:
        assert pipe.wait_processed(1, 60.0)
        for p in range(1, 12):
            ring.release(p - 1)  # what the recorder does once a pair is written
            fr = _frames(p)
            for f in range(2):
                assert ring.put("cam0", p, f, fr[f], 2 * p + f, time.time_ns())
            ring.publish(p)
            time.sleep(0.15)
        assert _wait(lambda: pipe.stats().last_pair == 11)
        gate.set()
        assert _wait(lambda: results and results[-1].pair == 11)
    st = pipe.stats()
    assert st.error is None and st.state == "stopped"
    pairs = [r.pair for r in results]
    assert pairs == sorted(set(pairs)) and pairs[0] == 0 and pairs[-1] == 11 and 3 <= len(pairs) < 12
    for r in results:
        assert np.array_equal(r.raw["cam0"], _frames(r.pair)[0])
    assert st.processed == len(results) and st.skipped > 0
    assert st.processed + st.skipped + st.discarded == st.last_pair + 1


@pytest.mark.parametrize(("method", "pvr"), [("drt-mart", None), ("mlos-mart", None), ("mlos-mart", (4, 4, 20))])
def test_live_volume_equals_the_batch_reconstruction(tiny_rig, method, pvr) -> None:
    """Device preprocessing, device volumes and device smoothing give the batch path's volume,
    with either method's weights (kept in the live path's weight cache), at the rig's PVR or a
    coarser monitoring one."""
    from lfcore.particles import particle_count, seed_particles
    from lfcore.projector import LightFieldProjector
    from lfcore.reconstruct import reconstruct
    from lfcore.render import LightFieldRenderer
    from realtime.pipeline import monitoring_recon

    pts = seed_particles(tiny_rig.volume, particle_count(tiny_rig, ppm=0.5), np.random.default_rng(6))
    cfg = tiny_rig.render.model_copy(update={"rays_per_particle": 20_000})
    renderer = LightFieldRenderer(tiny_rig.camera[0], cfg, wavelength_nm=tiny_rig.laser.wavelength_nm, device="cpu")
    frames = np.stack([renderer.frame(pts + np.array([0.01 * f, 0.0, 0.0]), 50_000.0, seed=f) for f in (0, 1)])
    ring = PairRing({"cam0": SHAPE}, slots=2)
    for f in range(2):
        assert ring.put("cam0", 0, f, frames[f], f, time.time_ns())
    ring.publish(0)
    results = []
    pipe = LivePipeline(tiny_rig, ring, settings=LiveSettings(iterations=3, slice_axis="z", slice_index=14),
                        recon=monitoring_recon(method=method), pvr=pvr, device="cpu")
    assert pipe.grid == VolumeGrid.from_rig(tiny_rig, pvr=pvr)
    assert pipe.grid.shape == ((29, 68, 82) if pvr is None else (15, 34, 41))
    pipe.subscribe(results.append)
    with pipe:
        assert pipe.wait_processed(1, 60.0)
    proj = LightFieldProjector(tiny_rig.camera, pipe.grid, sub_apertures=pipe.recon.sub_apertures, device="cpu")
    ref = reconstruct(proj, [frames[0]], monitoring_recon(3, 1.0, method)).volume
    r = results[0]
    assert ref.max() > 0 and 0.0 < r.active_fraction < 0.5
    scale = float(ref.max())
    for ax, a in enumerate("zyx"):
        assert np.allclose(r.mip[a], ref.max(axis=ax), rtol=1e-3, atol=1e-4 * scale)
    assert np.allclose(r.slice_image, ref[14], rtol=1e-3, atol=1e-4 * scale)


def test_live_mlos_smart_on_pinhole_cameras_equals_the_batch_reconstruction() -> None:
    """Four pinhole (Tomo-PIV) cameras live: the projector of their kind, MLOS-SMART by default,
    and the batch path's volume; a light-field method on them is one line naming the camera."""
    from lfcore.particles import seed_particles
    from lfcore.pinhole_projector import PinholeProjector
    from lfcore.reconstruct import reconstruct
    from lfcore.render import PinholeRenderer
    from lfcore.rig import NotLightFieldError
    from lfpiv.rigfile import load_rig
    from realtime.pipeline import monitoring_recon
    from tests.conftest import EXAMPLES

    rig = load_rig(EXAMPLES / "tomo_4_cameras.toml")
    rig = rig.model_copy(update={"volume": rig.volume.model_copy(update={"size_mm": (3.0, 3.0, 2.0)})})
    pts = seed_particles(rig.volume, 60, np.random.default_rng(3))  # sparse enough for MLOS to eliminate
    frames = {c.name: np.stack([PinholeRenderer(c, rig.render, device="cpu").frame(pts + [0.02 * f, 0.0, 0.0], 10000.0,
                                                                                    seed=f) for f in (0, 1)])
              for c in rig.camera}
    ring = PairRing({n: f.shape[1:] for n, f in frames.items()}, slots=2)
    for n, f in frames.items():
        for k in range(2):
            assert ring.put(n, 0, k, f[k], k, time.time_ns())
    ring.publish(0)
    results = []
    pipe = LivePipeline(rig, ring, settings=LiveSettings(iterations=3), device="cpu")
    pipe.build()
    assert pipe.recon.method == "mlos-smart" and isinstance(pipe._recon.projector, PinholeProjector)
    pipe.subscribe(results.append)
    with pipe:
        assert pipe.wait_processed(1, 60.0)
    proj = PinholeProjector(rig.camera, pipe.grid, device="cpu")
    ref = reconstruct(proj, [frames[c.name][0] for c in rig.camera], monitoring_recon(3, 1.0, "mlos-smart")).volume
    r = results[0]
    assert ref.max() > 0 and 0.0 < r.active_fraction < 0.5
    for ax, a in enumerate("zyx"):
        assert np.allclose(r.mip[a], ref.max(axis=ax), rtol=1e-3, atol=1e-4 * float(ref.max()))
    with pytest.raises(NotLightFieldError, match="camera 'cam0' is a pinhole camera"):
        LivePipeline(rig, ring, recon=monitoring_recon(method="drt-mart"), device="cpu")


def test_the_live_path_runs_only_eliminating_methods(tiny_rig) -> None:
    from lfcore.reconstruct import ReconSettings
    from realtime.pipeline import monitoring_recon

    with pytest.raises(ValueError, match="runs drt-mart, mlos-mart or mlos-smart, not 'mart'"):
        monitoring_recon(method="mart")
    with pytest.raises(ValueError, match="not 'mart'"):
        LivePipeline(tiny_rig, recon=ReconSettings(method="mart"), device="cpu")


def _two_shifted_pairs(tiny_rig, *, seed: int) -> list[list[np.ndarray]]:
    """Two pairs of fresh particles (0.5 PPM, seeds ``seed`` and ``seed + 1``) on the tiny rig's camera, each
    frame B moved (2, 1, 0) voxels from its A, rendered with 20,000 rays a particle: [pair][frame] images."""
    from lfcore.particles import particle_count, seed_particles
    from lfcore.render import LightFieldRenderer

    cfg = tiny_rig.render.model_copy(update={"rays_per_particle": 20_000})
    renderer = LightFieldRenderer(tiny_rig.camera[0], cfg, wavelength_nm=tiny_rig.laser.wavelength_nm, device="cpu")
    shift = np.array([0.022, 0.011, 0.0])  # mm: (2, 1, 0) voxels
    frames = []
    for p in range(2):
        pts = seed_particles(tiny_rig.volume, particle_count(tiny_rig, ppm=0.5), np.random.default_rng(seed + p))
        frames.append([renderer.frame(pts + f * shift, 50_000.0, seed=2 * p + f) for f in range(2)])
    return frames


def test_live_warm_start_starts_frame_b_from_a_after_the_first_pair(tiny_rig) -> None:
    """With warm starts, the first pair's B starts uniform; a later pair's B from its A carried along
    the first pair's field, with a fifth of the iterations, still close to the uniform start's volume."""
    from realtime.pipeline import monitoring_recon

    frames = _two_shifted_pairs(tiny_rig, seed=10)
    results = {}
    for warm in (False, True):
        ring = PairRing({"cam0": SHAPE}, slots=4)
        for p in range(2):
            for f in range(2):
                assert ring.put("cam0", p, f, frames[p][f], f, time.time_ns())
        ring.publish(0)
        got = []
        pipe = LivePipeline(tiny_rig, ring, settings=LiveSettings(iterations=10),
                            recon=monitoring_recon(warm_start=warm), device="cpu")
        pipe.subscribe(got.append)
        with pipe:
            assert pipe.wait_processed(1, 60.0)
            ring.publish(1)
            assert pipe.wait_processed(2, 60.0), pipe.stats()
        results[warm] = got
    assert [r.warm for r in results[True]] == [False, True]
    assert not any(r.warm for r in results[False])
    # the second pair's field: the warm-started B moves the same way as the uniform one
    cold, warm = (np.nanmedian(results[w][1].velocity.reshape(-1, 3), axis=0) for w in (False, True))
    assert np.sign(warm[0]) == np.sign(cold[0]) != 0
    np.testing.assert_allclose(warm[:2], cold[:2], rtol=0.35)


def test_prefilled_weights_trace_no_pair_and_change_nothing(tiny_rig) -> None:
    """The fast plan's build traces the line-of-sight weights of every voxel an all-lit frame keeps (a
    superset of any frame's survivors): two pairs of fresh particles then trace nothing, and give the
    same volumes and vectors to the bit as the pipeline that traces each pair's new voxels."""
    from realtime.pipeline import monitoring_recon

    frames = _two_shifted_pairs(tiny_rig, seed=20)
    results, cached = {}, {}
    for prefill in (None, False):  # None: the default, prefilled for line-of-sight weights
        ring = PairRing({"cam0": SHAPE}, slots=4)
        for p in range(2):
            for f in range(2):
                assert ring.put("cam0", p, f, frames[p][f], f, time.time_ns())
        got = []
        pipe = LivePipeline(tiny_rig, ring, settings=LiveSettings(iterations=5),
                            recon=monitoring_recon(method="mlos-mart", warm_start=True), device="cpu", prefill=prefill)
        pipe.build()
        rc = pipe._recon
        built = rc.cache.n_cached
        assert (built == rc.prefilled > 0) if prefill is None else (built == rc.prefilled == 0)
        pipe.subscribe(got.append)
        ring.publish(0)
        with pipe:
            assert pipe.wait_processed(1, 60.0)
            ring.publish(1)
            assert pipe.wait_processed(2, 60.0), pipe.stats()
        cached[prefill] = (built, rc.cache.n_cached)
        results[prefill] = got
    built, after = cached[None]
    assert after == built  # no pair traced a voxel
    assert cached[False][1] > 0 and cached[False][1] <= built  # the traced pipeline's voxels are among them
    for a, b in zip(results[None], results[False], strict=True):
        assert a.pair == b.pair and a.warm == b.warm
        for axis in "zyx":
            assert np.array_equal(a.mip[axis], b.mip[axis])
        assert np.array_equal(a.velocity, b.velocity, equal_nan=True)


def test_drt_weights_are_not_prefilled_by_default(tiny_rig) -> None:
    """DRT-MART's traced weights take about ten times as long as line-of-sight ones: the build leaves
    them to the pairs unless asked."""
    from realtime.pipeline import monitoring_recon

    pipe = LivePipeline(tiny_rig, recon=monitoring_recon(method="drt-mart"), device="cpu")
    pipe.build()
    assert pipe._recon.prefilled == 0 and pipe._recon.cache.n_cached == 0


def test_the_prefill_stays_within_its_limits(tiny_rig, monkeypatch) -> None:
    """No prefill where an all-lit frame keeps more voxels than PREFILL_MAX_VOXELS; a budget too small
    for all of them stops it after its first part (the pairs trace what they need, as without it)."""
    import realtime.processing as processing
    from lfcore import weight_cache
    from realtime.pipeline import monitoring_recon

    recon = monitoring_recon(method="mlos-mart", warm_start=True)
    monkeypatch.setattr(processing, "PREFILL_MAX_VOXELS", 10)
    pipe = LivePipeline(tiny_rig, recon=recon, device="cpu")
    pipe.build()
    assert pipe._recon.prefilled == 0 == pipe._recon.cache.n_cached
    rc = pipe._recon
    every = rc.frames.eliminate(rc.wp.ones(rc.projector.n_pixels, dtype=rc.wp.uint8, device="cpu")).numpy()
    monkeypatch.setattr(weight_cache, "PREFILL_VOXELS", 1000)
    small = weight_cache.WeightCache(rc.projector, method="los", budget_bytes=8 * 250 * 3000, checks=0)
    assert every.size > 3000 and small.prefill(voxels=every, whole=True) == 1000
    assert small.prefill(voxels=every) < every.size  # without whole: until the pool is full
