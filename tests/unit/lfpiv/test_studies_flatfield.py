"""The studies correct frames of a rig with a camera response as reconstruct --flat-field does."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np

from lfcore.flatfield import sensor_response
from lfcore.rig import Rig
from lfpiv.studies.pipeline import simulated_flats

TINY = Path(__file__).resolve().parents[3] / "examples" / "tiny.toml"


def test_simulated_flats_measure_the_rendered_response():
    rig = Rig.from_dict(tomllib.loads(TINY.read_text()))
    render = rig.render.model_copy(update={"lens_falloff": 0.4, "micro_vignetting": 0.3, "dust_spots": 2,
                                           "dark_fpn_counts": 4.0})
    (flat,) = simulated_flats(rig.camera, render)
    truth = sensor_response(rig.camera[0], render)
    keep = ~flat.mask
    ratio = flat.gain[keep] / truth.gain[keep]
    # the white image's shot and read noise (about 1% on 20000 counts) is what is left
    assert np.std(ratio / np.median(ratio)) < 0.02
    # the dark frame is the dark offset within its read and shot noise
    assert abs(float(np.mean(flat.dark - truth.dark))) < 1.0
