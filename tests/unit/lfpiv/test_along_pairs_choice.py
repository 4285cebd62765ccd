"""``lfpiv.pair_runner.along_pairs_choice``: whether ``lfpiv particles`` and ``lfpiv track`` follow a
run's particles along its pairs (the default ``auto``, ``--along-pairs``, ``--pair-by-pair``)."""

from __future__ import annotations

import pytest

from lfpiv.errors import UsageError
from lfpiv.pair_runner import WORKERS_GIVEN, AlongChoice, along_option_error, along_pairs_choice


def test_auto_follows_a_time_resolved_run_through_consecutive_pairs():
    choice = along_pairs_choice("auto", time_resolved=True, pairs=[0, 1, 2])
    assert choice.on and "time-resolved" in choice.why and "pairs 0 to 2" in choice.why
    assert choice.line().startswith("along the pairs: ")


@pytest.mark.parametrize(("given", "words"), [
    ({"time_resolved": False}, "not a time-resolved run"),
    ({"workers": True}, "--workers"),
    ({"previous": True}, "--predictor previous"),
    ({"pairs": [0, 2, 3]}, "not consecutive"),
    ({"pairs": [4]}, "fewer than the 3"),
    ({"pairs": [0, 1], "min_frames": 5}, "fewer than the 5"),
])
def test_auto_goes_pair_by_pair_where_it_cannot_follow_and_says_why(given, words):
    args = {"time_resolved": True, "pairs": [0, 1, 2], **given}
    choice = along_pairs_choice("auto", **args)
    assert not choice.on and words in choice.why, choice
    assert choice.line().startswith("pair by pair: ")


def test_on_and_off_are_as_asked():
    # --along-pairs is on whatever the run (the jobs refuse what cannot run, with one line)
    assert along_pairs_choice("on", time_resolved=False, pairs=[0], workers=True).on
    off = along_pairs_choice("off", time_resolved=True, pairs=[0, 1, 2])
    assert not off.on and "--pair-by-pair" in off.why


def test_the_same_inputs_give_the_same_choice():
    """--skip-done finds what ran: the choice depends on its inputs only."""
    a = along_pairs_choice("auto", time_resolved=True, pairs=range(5), min_frames=4)
    assert a == along_pairs_choice("auto", time_resolved=True, pairs=list(range(5)), min_frames=4)


def test_an_unknown_mode_and_options_that_cannot_apply_are_refused_in_one_line():
    with pytest.raises(UsageError, match="auto, on, off"):
        along_pairs_choice("yes", time_resolved=True, pairs=[0, 1])
    text = along_option_error(["--relink", "--pool-pairs"], AlongChoice(False, WORKERS_GIVEN))
    assert "--relink, --pool-pairs" in text and "--workers" in text and "\n" not in text
