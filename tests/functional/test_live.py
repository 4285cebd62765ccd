"""The live pipeline beside a recording on the simulated lab: results for the newest pairs arrive,
and the recording is untouched (every triggered frame recorded or dropped, no overrun)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lfcore.runstore import RunStore
from lfpiv.jobs.acquire import record
from lfpiv.rigfile import load_rig
from realtime.pipeline import LivePipeline, LiveSettings
from tests.helpers import fast_rig_text, sim_lab


@pytest.mark.parametrize("cameras", [1, 2])
def test_live_pipeline_beside_a_recording(tmp_path: Path, cameras: int) -> None:
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(fast_rig_text(rate_hz=20.0, cameras=cameras))
    rig = load_rig(rig_file)
    pairs = 30
    results = []
    pipe = LivePipeline(rig, settings=LiveSettings(iterations=3), device="cpu")
    pipe.subscribe(results.append)
    pipe.build()
    with pipe, sim_lab(rig) as lab:
        res = record(rig, tmp_path / "run.zarr", pairs, sim_options={"lab": lab},
                     on_session=lambda s: pipe.attach(s.ring))
        triggered = lab.pulse_generator.ticks_fired
        # the ring keeps its last pair after the recording: the pipeline gets to it
        assert pipe.wait_processed(1, 60.0)
    st = pipe.stats()
    assert st.state == "stopped" and st.error is None
    # the recording: complete, every triggered frame recorded or dropped, nothing overrun
    assert res.state == "complete" and triggered == pairs
    assert res.stats.frames_recorded + res.stats.frames_dropped == triggered * 2 * cameras
    assert res.stats.overruns == 0
    store = RunStore.open(tmp_path / "run.zarr")
    assert store.committed_pairs == pairs
    # the live path: every pair up to the newest it took was processed, skipped or discarded
    assert st.processed == len(results) >= 1
    assert st.processed + st.skipped + st.discarded == st.last_pair + 1 <= store.committed_pairs
    pairs_seen = [r.pair for r in results]
    assert pairs_seen == sorted(set(pairs_seen))
    for r in results:  # each result shows its own pair's frames, as recorded
        for cam in store.cameras:
            assert np.array_equal(r.raw[cam], store.frames(cam)[r.pair, 0])
        assert r.mip["z"].max() > 0  # particles were reconstructed
        assert np.isfinite(r.latency_s) and r.latency_s > 0


def test_live_particle_route_tracks_the_simulated_flow(tmp_path: Path) -> None:
    """The particle route beside a recording: its field is close to the vortex ring the simulated
    lab showed, and the recording is as complete as on the voxel route."""
    from lfcore import metrics
    from lfcore.flows import flow_from_params
    from sim.lab import SimLab
    from sim.world import SimWorld

    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(fast_rig_text(rate_hz=20.0, cameras=2))
    rig = load_rig(rig_file)
    world = SimWorld(rig, ppm=0.5)  # the vortex ring
    results = []
    pipe = LivePipeline(rig, settings=LiveSettings(), device="cpu", route="particles")
    pipe.subscribe(results.append)
    pipe.build()
    with pipe, SimLab(rig, world=world, pool_pairs=1, rays_per_particle=1000, reply_latency_s=0.0005) as lab:
        # one pair: the pipeline stops once it is processed (a particle pair takes tens of seconds on a loaded CPU,
        # longer than the 30 s stop() waits for the pair in hand)
        res = record(rig, tmp_path / "run.zarr", 1, sim_options={"lab": lab}, on_session=lambda s: pipe.attach(s.ring))
        triggered = lab.pulse_generator.ticks_fired
        assert pipe.wait_processed(1, 300.0)
    st = pipe.stats()
    assert st.state == "stopped" and st.error is None and st.route == "particles"
    assert res.state == "complete" and res.stats.overruns == 0
    assert res.stats.frames_recorded + res.stats.frames_dropped == triggered * 2 * 2
    r = results[0]
    assert r.route == "particles" and r.projector == ""
    # about 150 particles a frame were seeded: most found, most of A's tracked into B
    n_true = world.n_particles
    assert r.particles is not None and min(r.particles) >= 0.7 * n_true and max(r.particles) <= 1.3 * n_true
    assert r.tracks is not None and r.tracks >= 0.4 * n_true
    assert st.particles == r.particles and st.tracks == r.tracks
    assert {"particles", "track", "volume", "derive", "total"} <= set(r.timings)
    assert r.mip["z"].max() > 0  # frame A's particles drawn into the live grid
    # the field against the flow at the bins' centres at mid-pair: within 30% of the peak speed
    # (measured 24%; the voxel route on this rig: 33%), in at least 15% of the bins (measured 21%)
    x, y, z = r.grid_mm
    truth = metrics.grid_velocity(flow_from_params(world.flow_params), x, y, z,
                                  world.t0_s(0) + 0.5 * rig.timing.dt_us * 1e-6)
    filled = np.isfinite(r.velocity[..., 0])
    assert filled.mean() >= 0.15
    assert metrics.velocity_errors(r.velocity, truth).of_peak < 0.3
    assert r.outlier_fraction == pytest.approx(1.0 - filled.mean())
