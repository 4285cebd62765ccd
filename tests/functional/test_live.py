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
