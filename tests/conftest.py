"""Shared fixtures: the example rigs and every compute device Warp finds."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from lfcore.device import available_devices
from lfcore.rig import Rig
from lfpiv.cli import main
from lfpiv.rigfile import load_rig

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
DEVICES = available_devices()


def wait_for(condition, timeout_s: float = 5.0) -> bool:
    """Poll ``condition()`` until it is true (True) or ``timeout_s`` passed (False)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.002)
    return True


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    # Every test that takes `device` runs once on each device Warp finds (CPU in CI).
    if "device" in metafunc.fixturenames:
        metafunc.parametrize("device", DEVICES)


@pytest.fixture(scope="session")
def tiny_rig() -> Rig:
    return load_rig(EXAMPLES / "tiny.toml")


def tiny_variant(rig: Rig, **camera_changes) -> Rig:
    """The tiny rig with some camera keys changed (validated again)."""
    d = rig.to_dict()
    d["camera"][0].update(camera_changes)
    return Rig.from_dict(d)


def run_cli(capsys: pytest.CaptureFixture[str], *argv: object) -> tuple[int, str, str]:
    """Run the ``lfpiv`` command in this process: its exit code, stdout and stderr."""
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err
