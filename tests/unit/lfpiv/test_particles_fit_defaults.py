"""``lfpiv particles --noise-model auto`` and ``--residual-mask auto`` (the defaults): chosen from the
cameras used, ``shot`` and 3 where a light-field camera is among them, ``flat`` and 0 for pinhole
cameras alone; given values kept as they are, and what ``particles/`` records is the chosen value."""

from __future__ import annotations

import argparse

import pytest

from lfcore.ipr import IprSettings
from lfpiv.commands.particles import register
from lfpiv.errors import UsageError
from lfpiv.jobs.particles import LIGHT_FIELD_FIT, PINHOLE_FIT, fit_defaults, same_settings, used_cameras
from lfpiv.rigfile import load_rig
from tests.conftest import EXAMPLES


@pytest.fixture(scope="module")
def rigs():
    return {name: load_rig(EXAMPLES / f"{name}.toml") for name in ("tiny", "tomo_4_cameras", "mixed_cameras")}


def test_light_field_cameras_get_shot_and_a_mask_of_3(rigs) -> None:
    assert LIGHT_FIELD_FIT == {"noise_model": "shot", "residual_mask": 3.0}
    assert fit_defaults(used_cameras(rigs["tiny"], None)) == {"noise_model": "shot", "residual_mask": 3.0}
    # one light-field camera among pinhole ones: the mixed rig's measured gain (recall 0.852 -> 0.890)
    assert fit_defaults(used_cameras(rigs["mixed_cameras"], None)) == LIGHT_FIELD_FIT


def test_pinhole_cameras_alone_keep_the_flat_fit_and_no_mask(rigs) -> None:
    """Four pinhole cameras lost with shot + 3 (recall 0.904 -> 0.871): their default is unchanged."""
    assert PINHOLE_FIT == {"noise_model": "flat", "residual_mask": 0.0}
    cams = used_cameras(rigs["tomo_4_cameras"], None)
    assert len(cams) == 4
    fit = fit_defaults(cams)
    assert fit == PINHOLE_FIT
    # what the command recorded for these cameras before auto existed: the lfcore defaults
    before = IprSettings()
    assert (before.noise_model, before.residual_mask) == (fit["noise_model"], fit["residual_mask"])


def test_the_cameras_used_decide_not_the_rigs(rigs) -> None:
    mixed = rigs["mixed_cameras"]
    lf = [c.name for c in mixed.camera if getattr(c, "kind", "lightfield") != "pinhole"]
    pin = [c.name for c in mixed.camera if getattr(c, "kind", "lightfield") == "pinhole"]
    assert lf and pin
    assert [c.name for c in used_cameras(mixed, pin)] == pin
    assert fit_defaults(used_cameras(mixed, pin)) == PINHOLE_FIT  # --cameras: the pinhole ones alone
    assert fit_defaults(used_cameras(mixed, lf)) == LIGHT_FIELD_FIT
    assert fit_defaults(used_cameras(mixed, [])) == LIGHT_FIELD_FIT  # none named: all of them


def test_a_camera_the_rig_does_not_have_is_named(rigs) -> None:
    """--cameras with a name the rig lacks: the same one-line refusal as the pairs' (not 'none is given')."""
    with pytest.raises(UsageError, match=r"--cameras: no camera 'nonexist' in this run \(it has "):
        used_cameras(rigs["tiny"], ["nonexist"])


def test_given_values_are_kept_exactly(rigs) -> None:
    lf, pin = used_cameras(rigs["tiny"], None), used_cameras(rigs["tomo_4_cameras"], None)
    assert fit_defaults(lf, noise_model="flat", residual_mask=0.0) == PINHOLE_FIT
    assert fit_defaults(pin, noise_model="shot", residual_mask=3) == LIGHT_FIELD_FIT
    # one auto, one given
    assert fit_defaults(lf, noise_model="flat") == {"noise_model": "flat", "residual_mask": 3.0}
    assert fit_defaults(pin, residual_mask=2.5) == {"noise_model": "flat", "residual_mask": 2.5}
    # nothing auto: no cameras needed
    assert fit_defaults([], noise_model="shot", residual_mask=1.0) == {"noise_model": "shot", "residual_mask": 1.0}


def test_bad_values_are_refused(rigs) -> None:
    lf = used_cameras(rigs["tiny"], None)
    with pytest.raises(UsageError, match="--noise-model is one of auto, shot, flat, got 'poisson'"):
        fit_defaults(lf, noise_model="poisson")
    with pytest.raises(UsageError, match="--residual-mask is auto or a number"):
        fit_defaults(lf, residual_mask="three")
    with pytest.raises(UsageError, match="none is given"):
        fit_defaults([])


def _parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    return parser.parse_args(["particles", "run.zarr", *argv])


def test_the_commands_options_default_to_auto_and_take_their_old_values() -> None:
    args = _parse()
    assert args.noise_model == "auto" and args.residual_mask == "auto"
    args = _parse("--noise-model", "shot", "--residual-mask", "3")
    assert args.noise_model == "shot" and args.residual_mask == 3.0
    args = _parse("--noise-model", "flat", "--residual-mask", "0")
    assert args.noise_model == "flat" and args.residual_mask == 0.0
    assert _parse("--residual-mask", "auto").residual_mask == "auto"
    with pytest.raises(SystemExit):
        _parse("--residual-mask", "-1")


def test_skip_done_sees_the_chosen_values(rigs) -> None:
    """A group written before noise_model and residual_mask existed (flat, no mask) is kept by
    ``--skip-done`` on pinhole cameras alone, and made again on a light-field camera, whose default
    now makes other particles; one written with auto's values matches them."""
    def meta(**fit) -> dict:
        return {**IprSettings(**fit).as_dict(), "method": "drt-mart", "cameras": ["cam0"]}

    old = {k: v for k, v in meta().items() if k not in ("noise_model", "noise_floor", "residual_mask")}
    assert same_settings(old, meta(**fit_defaults(used_cameras(rigs["tomo_4_cameras"], None))))
    lf_fit = fit_defaults(used_cameras(rigs["tiny"], None))
    assert not same_settings(old, meta(**lf_fit))
    assert same_settings(meta(**lf_fit), meta(noise_model="shot", residual_mask=3.0))
