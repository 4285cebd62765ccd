"""The emulated Zaber chain speaks the ASCII protocol as its manual defines it: one test per row
of the manual's command table, sent as raw lines through the pseudo-terminal."""

from __future__ import annotations

import re
import time

import pytest
import serial

from acquisition.stage import ZABER_PRODUCTS, checksum
from sim.serial_emulators import ZABER_COMMANDS, StageEmulator, ZaberAxis, ZaberDevice
from tests.conftest import wait_for


class Raw:
    """A terminal on the emulator's port: send a line, collect every line that comes back."""

    def __init__(self, port: str) -> None:
        self.ser = serial.Serial(port, 115200, timeout=0.05)

    def send(self, line: str, wait_s: float = 0.15) -> list[str]:
        self.ser.reset_input_buffer()
        self.ser.write(line.encode() + b"\n")
        return self.read(wait_s)

    def read(self, wait_s: float = 0.15) -> list[str]:
        out, end = b"", time.monotonic() + wait_s
        while time.monotonic() < end:
            out += self.ser.read(4096)
        return [x for x in out.decode("ascii", "replace").split("\r\n") if x]

    def close(self) -> None:
        self.ser.close()


@pytest.fixture
def emu():
    with StageEmulator(latency_s=0, speed_mm_s=50.0, position_mm=12.5) as e:
        yield e


@pytest.fixture
def raw(emu):
    r = Raw(emu.port)
    yield r
    r.close()


def _chain() -> StageEmulator:
    stage = ZaberDevice(address=1, deviceid=59901, axes=[ZaberAxis(ZABER_PRODUCTS[59901])])
    ctrl = ZaberDevice(address=2, deviceid=59950, axes=[ZaberAxis(ZABER_PRODUCTS[69901], peripheral_id=69901)
                                                       for _ in range(2)])
    return StageEmulator(chain=[stage, ctrl], latency_s=0, homed=True, position_mm=5.0)


def _data(reply: str) -> str:
    m = re.fullmatch(r"@\d\d \d+(?: \d\d)? \S+ \S+ \S+ (.*)", reply)
    return m.group(1) if m else ""


def _homed(raw: Raw, emu: StageEmulator) -> None:
    raw.send("/1 1 home")
    assert wait_for(lambda: emu.homed and not emu.busy, 3.0)


# --- one check per row: (manual section, what is sent, check) -------------------------------
def row_empty(emu, raw):
    assert raw.send("/1 1") == ["@01 1 OK IDLE WR 0"]


def row_message_id(emu, raw):
    assert raw.send("/1 1 42 get pos") == ["@01 1 42 OK IDLE WR 0"]
    assert raw.send("/1 1 -- get pos") == ["@01 1 OK IDLE WR 0"]  # "--": no id


def row_checksum(emu, raw):
    body = "1 1 get pos"
    assert raw.send(f"/{body}:{checksum(body)}") == ["@01 1 OK IDLE WR 0"]
    assert raw.send(f"/{body}:00") == []  # a corrupted command is dropped
    raw.send("/1 set comm.checksum 1")
    (reply,) = raw.send("/1 1 get pos")
    m = re.fullmatch(r"@(.*):([0-9A-F]{2})", reply)
    assert m and checksum(m.group(1)) == m.group(2)


def row_broadcast(emu, raw):
    with _chain() as chain:
        r = Raw(chain.port)
        try:
            replies = r.send("/get deviceid")
        finally:
            r.close()
    assert replies == ["@01 0 OK IDLE -- 59901", "@02 0 OK IDLE -- 59950"]


def row_packets(emu, raw):
    text = " ".join(f"word{i:02d}" for i in range(30))
    lines = raw.send(f"/1 0 7 tools echo {text}")
    assert len(lines) >= 3 and all(len(x) <= 80 for x in lines)
    assert lines[0].startswith("@01 0 07 OK IDLE") and lines[0].endswith(" \\")
    assert all(x.startswith("#01 0 07 cont ") for x in lines[1:])
    assert not lines[-1].endswith("\\")
    parts = [_data(lines[0])] + [x.split(" cont ", 1)[1] for x in lines[1:]]
    joined = " ".join(p.removesuffix("\\").strip() for p in parts)
    assert joined == text


def row_alerts(emu, raw):
    raw.send("/1 set comm.alert 1")
    _homed(raw, emu)
    assert wait_for(lambda: any(a.startswith("!01 1 IDLE") for a in emu.alerts), 2.0)
    lines = raw.send("/1 1 move abs 20000") + raw.read(1.0)
    assert lines[0].startswith("@01 1 OK BUSY") and "!01 1 IDLE --" in lines


def row_home(emu, raw):
    assert raw.send("/1 1 home")[0].startswith("@01 1 OK BUSY WR 0")
    assert wait_for(lambda: not emu.busy, 3.0)
    assert raw.send("/1 1 get pos") == ["@01 1 OK IDLE -- 0"]
    assert emu.position_mm == pytest.approx(0.0)


def row_move_abs(emu, raw):
    assert raw.send("/1 1 move abs 1000") == ["@01 1 RJ IDLE WR BADDATA"]  # not homed
    _homed(raw, emu)
    assert raw.send("/1 1 move abs 100000")[0].startswith("@01 1 OK BUSY")
    assert wait_for(lambda: not emu.busy, 3.0)
    assert raw.send("/1 1 get pos") == ["@01 1 OK IDLE -- 100000"]
    assert emu.position_mm == pytest.approx(10.0)


def row_move_rel(emu, raw):
    _homed(raw, emu)
    raw.send("/1 1 move rel 30000")
    assert wait_for(lambda: not emu.busy, 3.0)
    raw.send("/1 1 move rel -10000")
    assert wait_for(lambda: not emu.busy, 3.0)
    assert raw.send("/1 1 get pos") == ["@01 1 OK IDLE -- 20000"]
    assert raw.send("/1 1 move rel -30000") == ["@01 1 RJ IDLE -- BADDATA"]  # below limit.min


def row_move_vel(emu, raw):
    _homed(raw, emu)
    assert raw.send("/1 1 move vel 163840")[0].startswith("@01 1 OK BUSY")  # 100000 microsteps/s
    time.sleep(0.2)
    assert emu.busy and emu.position_mm > 0.5
    raw.send("/1 1 stop")
    assert wait_for(lambda: not emu.busy, 3.0)


def row_move_min(emu, raw):
    _homed(raw, emu)
    raw.send("/1 1 move abs 50000")
    assert wait_for(lambda: not emu.busy, 3.0)
    raw.send("/1 1 move min")
    assert wait_for(lambda: not emu.busy, 3.0)
    assert emu.position_mm == pytest.approx(0.0)


def row_move_max(emu, raw):
    _homed(raw, emu)
    raw.send("/1 1 move max")
    assert wait_for(lambda: not emu.busy, 5.0)
    assert raw.send("/1 1 get pos") == ["@01 1 OK IDLE -- 500000"]


def row_stop(emu, raw):
    _homed(raw, emu)
    raw.send("/1 1 set accel 100")  # a slow brake: 100 / 1.6384e-4 microsteps/s^2 = 61 mm/s^2
    raw.send("/1 1 move abs 400000")
    time.sleep(0.5)
    assert raw.send("/1 1 stop")[0].startswith("@01 1 OK BUSY")  # still braking
    assert emu.busy
    assert wait_for(lambda: not emu.busy, 3.0)
    assert "NI" in emu.flags and 0.0 < emu.position_mm < 40.0


def row_estop(emu, raw):
    _homed(raw, emu)
    raw.send("/1 1 move abs 400000")
    time.sleep(0.1)
    assert raw.send("/1 1 estop")[0].startswith("@01 1 OK IDLE NI")


def row_warnings(emu, raw):
    assert raw.send("/1 1 warnings") == ["@01 1 OK IDLE WR 01 WR"]


def row_warnings_clear(emu, raw):
    emu.set_flags("WL", "FD")
    assert raw.send("/1 1 warnings clear") == ["@01 1 OK IDLE FD 03 FD WL WR"]
    assert raw.send("/1 1 warnings") == ["@01 1 OK IDLE FD 02 FD WR"]  # WL latched, FD and WR stand


def row_get(emu, raw):
    (reply,) = raw.send("/1 1 get maxspeed")
    assert int(_data(reply)) == round(50.0 * 1000 / 0.1 * 1.6384)
    with _chain() as chain:
        r = Raw(chain.port)
        try:
            assert r.send("/2 0 get peripheral.id") == ["@02 0 OK IDLE -- 69901 69901"]
            assert r.send("/2 0 get system.axiscount") == ["@02 0 OK IDLE -- 2"]
        finally:
            r.close()


def row_set(emu, raw):
    assert raw.send("/1 1 set maxspeed 100000") == ["@01 1 OK IDLE WR 0"]
    assert raw.send("/1 1 get maxspeed") == ["@01 1 OK IDLE WR 100000"]
    assert raw.send("/1 1 set maxspeed -1") == ["@01 1 RJ IDLE WR BADDATA"]
    assert raw.send("/1 set deviceid 5") == ["@01 0 RJ IDLE WR BADCOMMAND"]
    assert raw.send("/1 1 set limit.max 1000") == ["@01 1 RJ IDLE WR NOACCESS"]


def row_renumber(emu, raw):
    with _chain() as chain:
        r = Raw(chain.port)
        try:
            assert r.send("/2 renumber 7") == ["@07 0 OK IDLE -- 0"]
            assert r.send("/7 0 get deviceid") == ["@07 0 OK IDLE -- 59950"]
            assert r.send("/renumber") == ["@01 0 OK IDLE -- 0", "@02 0 OK IDLE -- 0"]
        finally:
            r.close()


def row_system_reset(emu, raw):
    _homed(raw, emu)
    assert raw.send("/1 system reset") == ["@01 0 OK IDLE -- 0"]
    assert wait_for(lambda: not emu.homed, 1.0)
    assert raw.send("/1 1 warnings") == ["@01 1 OK IDLE WR 01 WR"]


def row_system_restore(emu, raw):
    raw.send("/1 1 set resolution 128")
    assert raw.send("/1 1 get resolution") == ["@01 1 OK IDLE WR 128"]
    raw.send("/1 system restore")
    assert raw.send("/1 1 get resolution") == ["@01 1 OK IDLE WR 64"]


def row_tools_echo(emu, raw):
    assert raw.send("/1 tools echo hello") == ["@01 0 OK IDLE WR hello"]


def row_badcommand(emu, raw):
    assert raw.send("/1 1 frobnicate") == ["@01 1 RJ IDLE WR BADCOMMAND"]


def row_badaxis(emu, raw):
    assert raw.send("/1 5 get pos") == ["@01 5 RJ IDLE -- BADAXIS"]


def row_baddata(emu, raw):
    _homed(raw, emu)
    assert raw.send("/1 1 move abs -5") == ["@01 1 RJ IDLE -- BADDATA"]
    assert raw.send("/1 1 move abs x") == ["@01 1 RJ IDLE -- BADDATA"]


def row_badmessageid(emu, raw):
    assert raw.send("/1 1 123 get pos") == ["@01 1 RJ IDLE WR BADMESSAGEID"]


def row_deviceonly(emu, raw):
    assert raw.send("/1 1 get deviceid") == ["@01 1 RJ IDLE WR DEVICEONLY"]


#: The ASCII protocol manual's command table: section, command, the check.
TABLE = [
    ("Message format: empty command", "/1 1", row_empty),
    ("Message format: message id", "/1 1 42 get pos", row_message_id),
    ("Message format: checksum", "/1 1 get pos:XX", row_checksum),
    ("Message format: broadcast", "/get deviceid", row_broadcast),
    ("Replies: packets", "/1 tools echo <long text>", row_packets),
    ("Alerts", "/1 set comm.alert 1", row_alerts),
    ("Commands: home", "/1 1 home", row_home),
    ("Commands: move abs", "/1 1 move abs 1000", row_move_abs),
    ("Commands: move rel", "/1 1 move rel -500", row_move_rel),
    ("Commands: move vel", "/1 1 move vel 16384", row_move_vel),
    ("Commands: move min", "/1 1 move min", row_move_min),
    ("Commands: move max", "/1 1 move max", row_move_max),
    ("Commands: stop", "/1 1 stop", row_stop),
    ("Commands: estop", "/1 1 estop", row_estop),
    ("Commands: warnings", "/1 1 warnings", row_warnings),
    ("Commands: warnings clear", "/1 1 warnings clear", row_warnings_clear),
    ("Commands: get", "/1 1 get maxspeed", row_get),
    ("Commands: set", "/1 1 set maxspeed 100000", row_set),
    ("Commands: renumber", "/renumber", row_renumber),
    ("Commands: system reset", "/1 system reset", row_system_reset),
    ("Commands: system restore", "/1 system restore", row_system_restore),
    ("Commands: tools echo", "/1 tools echo hello", row_tools_echo),
    ("Rejections: BADCOMMAND", "/1 1 frobnicate", row_badcommand),
    ("Rejections: BADAXIS", "/1 5 get pos", row_badaxis),
    ("Rejections: BADDATA", "/1 1 move abs -5", row_baddata),
    ("Rejections: BADMESSAGEID", "/1 1 123 get pos", row_badmessageid),
    ("Rejections: DEVICEONLY", "/1 1 get deviceid", row_deviceonly),
]


def test_the_table_covers_every_command_the_emulator_lists():
    assert [(s, c) for s, c, _ in TABLE] == [(s, c) for s, c, _ in ZABER_COMMANDS]


@pytest.mark.parametrize("section, command, check", TABLE, ids=[f"{s}: {c}" for s, c, _ in TABLE])
def test_command_table(emu, raw, section, command, check):
    check(emu, raw)
