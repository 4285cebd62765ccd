"""The emulated pulse generator speaks the QC 9520 / BNC 575 SCPI set as the manuals give it:
one test per row of the command table, sent as raw lines through the pseudo-terminal."""

from __future__ import annotations

import time

import pytest
import serial

from sim.serial_emulators import QC_COMMANDS, PulseGeneratorEmulator
from tests.conftest import wait_for


class Raw:
    def __init__(self, port: str) -> None:
        self.ser = serial.Serial(port, 115200, timeout=5.0)  # a busy CPU may delay the emulator thread

    def __call__(self, line: str) -> str:
        self.ser.reset_input_buffer()
        self.ser.write(line.encode() + b"\r\n")
        return self.ser.read_until(b"\n").decode().strip()


@pytest.fixture
def emu():
    with PulseGeneratorEmulator(latency_s=0) as e:
        yield e


@pytest.fixture
def q(emu):
    r = Raw(emu.port)
    yield r
    r.ser.close()


def _ticks(emu, q, setup: list[str], n: int) -> list[dict[int, float]]:
    """Outputs of the first ``n`` T0 ticks after ``setup`` (T0 at 2 ms)."""
    seen: list[dict[int, float]] = []
    emu.add_listener(lambda tick, t0, outputs: seen.append(outputs))
    for cmd in [":PULSE0:PER 0.002", ":PULSE1:STATE ON", *setup, ":PULSE0:STATE ON"]:
        assert q(cmd) == "ok", cmd
    assert wait_for(lambda: len(seen) >= n or not emu.running, 5.0)
    q(":PULSE0:STATE OFF")
    return seen[:n]


def row_idn(emu, q):
    assert q("*IDN?") == "QC,9528,EMU0001,3.0.0-emulator"
    assert q("*IDN") == "?6"


def row_rst(emu, q):
    q(":PULSE1:WIDT 0.002")
    assert q("*RST") == "ok" and q(":PULSE1:WIDT?") == "0.00001000000"
    assert q("*RST?") == "?7"


def row_sav(emu, q):
    q(":PULSE2:DEL 0.000123")
    assert q("*SAV 3") == "ok" and q("*SAV 13") == "?5"


def row_rcl(emu, q):
    q(":PULSE2:DEL 0.000123")
    q("*SAV 3")
    q("*RCL 0")
    assert q(":PULSE2:DEL?") == "0.00000000000"
    assert q("*RCL 3") == "ok" and q(":PULSE2:DEL?") == "0.00012300000"
    q(":PULSE0:STATE ON")
    assert q("*RCL 3") == "?8"  # not while T0 runs
    q(":PULSE0:STATE OFF")


def row_cat(emu, q):
    assert q(":INST:CAT?") == "T0,CHA,CHB,CHC,CHD,CHE,CHF,CHG,CHH"
    assert q(":INST:CAT") == "?6"


def row_full(emu, q):
    assert q(":INST:FULL?").startswith("T0,0,CHA,1,CHB,2")


def row_inst_state(emu, q):
    assert q(":INST:STAT ON") == "ok" and emu.enabled_channels() == tuple(range(1, 9))
    assert q(":INST:STAT OFF") == "ok" and not emu.outputs_enabled()


def row_nsel(emu, q):
    assert q(":INST:NSEL 2") == "ok"
    assert q(":PULSE:WIDT 0.000005") == "ok"  # the implied channel
    assert emu.channel_state(2).width_s == pytest.approx(5e-6)
    assert q(":INST:NSEL 9") == "?5"


def row_sel(emu, q):
    assert q(":INST:SEL CHC") == "ok" and q(":INST:SEL?") == "CHC"
    q(":PULSE:POL INV")
    assert emu.channel_state(3).polarity == "INV"


def row_state(emu, q):
    assert q(":PULSE0:STATE ON") == "ok" and emu.running and q(":PULSE0:STATE?") == "1"
    assert q(":PULSE0:STATE OFF") == "ok" and not emu.running
    assert q(":PULSE0:STATE MAYBE") == "?5"


def row_period(emu, q):
    assert q(":PULSE0:PER 0.001000000004") == "ok"
    assert q(":PULSE0:PER?") == "0.001000000"  # 10 ns resolution
    assert q(":PULSE0:PER 0.00000001") == "?5"  # below 100 ns


def row_mode(emu, q):
    seen = _ticks(emu, q, [":PULSE0:MODE BURS", ":PULSE0:BCO 3"], 5)
    assert len(seen) == 3 and not emu.running
    assert q(":PULSE0:MODE?") == "BURS" and q(":PULSE0:MODE SING") == "ok"
    assert len(_ticks(emu, q, [], 2)) == 1


def row_bco(emu, q):
    assert q(":PULSE0:BCO 1000000") == "ok" and q(":PULSE0:BCO 1000001") == "?5" and q(":PULSE0:BCO 2.5") == "?5"


def row_pco(emu, q):
    seen = _ticks(emu, q, [":PULSE0:MODE DCYC", ":PULSE0:PCO 3", ":PULSE0:OCO 2"], 6)
    assert q(":PULSE0:PCO?") == "3"
    assert emu.ticks_fired >= 6 and all(seen)  # only the "on" periods reach the listeners


def row_oco(emu, q):
    t0 = time.perf_counter()
    _ticks(emu, q, [":PULSE0:MODE DCYC", ":PULSE0:PCO 1", ":PULSE0:OCO 3"], 3)
    assert time.perf_counter() - t0 >= 2 * 4 * 0.002  # one in four periods fires


def row_icl(emu, q):
    assert q(":PULSE0:ICL EXT10") == "ok" and q(":PULSE0:ICL?") == "EXT10" and q(":PULSE0:ICL EXT7") == "?5"


def row_ocl(emu, q):
    assert q(":PULSE0:OCL 50") == "ok" and q(":PULSE0:OCL?") == "50"


def row_trig_mode(emu, q):
    assert q(":PULSE0:TRIG:MOD TRIG") == "ok" and q(":PULSE0:TRIG:MODE?") == "TRIG"
    q(":PULSE1:STATE ON")
    q(":PULSE0:STATE ON")
    time.sleep(0.05)
    assert emu.ticks_fired == 0  # T0 waits for the trigger input
    emu.external_trigger()
    assert wait_for(lambda: emu.ticks_fired == 1, 2.0)
    q(":PULSE0:STATE OFF")


def row_trig_edge(emu, q):
    assert q(":PULSE0:TRIG:EDGE FALL") == "ok" and q(":PULSE0:TRIG:EDGE?") == "FALL"
    assert q(":PULSE0:TRIG:EDGE UP") == "?5"


def row_trig_level(emu, q):
    assert q(":PULSE0:TRIG:LEV 2.345") == "ok" and q(":PULSE0:TRIG:LEV?") == "2.35"
    assert q(":PULSE0:TRIG:LEV 20") == "?5"


def row_gate_mode(emu, q):
    seen = _ticks(emu, q, [":PULSE0:GATE:MOD PULS"], 2)
    assert seen == [{}, {}]  # the gate input is low: every pulse held back
    assert q(":PULSE0:GATE:MODE?") == "PULS"


def row_gate_logic(emu, q):
    assert q(":PULSE0:GATE:LOG LOW") == "ok" and q(":PULSE0:GATE:LOG?") == "LOW"


def row_gate_level(emu, q):
    assert q(":PULSE0:GATE:LEV 1.5") == "ok" and q(":PULSE0:GATE:LEV?") == "1.50"


def row_counter_state(emu, q):
    assert q(":PULSE0:COUN:STAT ON") == "ok"
    _ticks(emu, q, [":PULSE0:MODE BURS", ":PULSE0:BCO 4"], 4)
    assert q(":PULSE0:COUN:COUN?") == "4"


def row_counter_counts(emu, q):
    assert q(":PULSE0:COUN:COUN?") == "0" and q(":PULSE0:COUN:COUN") == "?6"


def row_counter_clear(emu, q):
    assert q(":PULSE0:COUN:CLE") == "ok" and q(":PULSE0:COUN:CLE?") == "?7"


def row_ch_state(emu, q):
    assert q(":PULSE1:STATE ON") == "ok" and emu.enabled_channels() == (1,) and q(":PULSE1:STATE?") == "1"


def row_width(emu, q):
    assert q(":PULSE1:WIDT 0.00000123456789") == "ok"
    assert q(":PULSE1:WIDT?") == "0.00000123450"  # 1234.5 ns: the nearest 250 ps step
    assert q(":PULSE1:WIDT 0.000000001") == "?5"  # below 10 ns


def row_delay(emu, q):
    assert q(":PULSE1:DEL 0.00000000037") == "ok"
    assert q(":PULSE1:DEL?") == "0.00000000025"  # rounded to the 250 ps resolution
    assert q(":PULSE1:DEL -1e-6") == "ok" and q(":PULSE1:DEL 1000") == "?5"


def row_sync(emu, q):
    assert q(":PULSE2:SYNC CHA") == "ok" and q(":PULSE2:SYNC?") == "CHA"
    assert q(":PULSE1:SYNC CHB") == "?9"  # A timed from B timed from A
    assert q(":PULSE1:SYNC CHA") == "?9" and q(":PULSE1:SYNC CHZ") == "?5"
    seen = _ticks(emu, q, [":PULSE1:DEL 0.0001", ":PULSE2:DEL 0.00005", ":PULSE2:STATE ON"], 1)
    assert seen[0][2] == pytest.approx(150e-6)


def row_mux(emu, q):
    seen = _ticks(emu, q, [":PULSE1:DEL 0.0002", ":PULSE2:DEL 0.0001", ":PULSE1:MUX 3"], 1)
    assert seen[0][1] == pytest.approx(100e-6)  # timer B routed to output A fires first
    assert q(":PULSE1:MUX 256") == "?5"


def row_pol(emu, q):
    assert q(":PULSE1:POL COMP") == "ok" and q(":PULSE1:POL?") == "COMP" and q(":PULSE1:POL X") == "?5"


def row_outp_mode(emu, q):
    assert q(":PULSE1:OUTP:MODE ADJ") == "ok" and q(":PULSE1:OUTP:MODE?") == "ADJ"


def row_outp_ampl(emu, q):
    assert q(":PULSE1:OUTP:AMPL 5") == "ok" and q(":PULSE1:OUTP:AMPL?") == "5.00"
    assert q(":PULSE1:OUTP:AMPL 25") == "?5"


def row_cmod(emu, q):
    seen = _ticks(emu, q, [":PULSE1:CMOD DCYC", ":PULSE1:PCO 1", ":PULSE1:OCO 1"], 4)
    assert [1 in s for s in seen] == [True, False, True, False]


def row_ch_bco(emu, q):
    seen = _ticks(emu, q, [":PULSE1:CMOD BURS", ":PULSE1:BCO 2"], 4)
    assert [1 in s for s in seen] == [True, True, False, False]


def row_ch_pco(emu, q):
    seen = _ticks(emu, q, [":PULSE1:CMOD DCYC", ":PULSE1:PCO 2", ":PULSE1:OCO 1"], 6)
    assert [1 in s for s in seen] == [True, True, False, True, True, False]


def row_ch_oco(emu, q):
    seen = _ticks(emu, q, [":PULSE1:CMOD DCYC", ":PULSE1:PCO 1", ":PULSE1:OCO 2"], 6)
    assert [1 in s for s in seen] == [True, False, False, True, False, False]


def row_wco(emu, q):
    seen = _ticks(emu, q, [":PULSE1:WCO 2"], 4)
    assert [1 in s for s in seen] == [False, False, True, True]


def row_cgat(emu, q):
    seen = _ticks(emu, q, [":PULSE1:CGAT HIGH"], 2)
    assert seen == [{}, {}]


def row_disp(emu, q):
    assert q(":DISP:ENAB OFF") == "ok" and q(":DISP:ENAB?") == "0"


def row_echo(emu, q):
    assert q(":SYST:COMM:SER:ECHO ON") == "ok"
    # With echo on every command gives two lines, the echo first; read both, so that a late
    # reply is never left in the buffer for the next command.
    assert q(":PULSE0:STATE?") == ":PULSE0:STATE?"
    assert q.ser.read_until(b"\n").decode().strip() == "0"
    assert q(":SYST:COMM:SER:ECHO OFF") == ":SYST:COMM:SER:ECHO OFF"
    assert q.ser.read_until(b"\n").decode().strip() == "ok"
    assert q(":PULSE0:STATE?") == "0"


def row_klock(emu, q):
    assert q(":SYST:KLOC ON") == "ok" and q(":SYST:KLOC?") == "1"


def row_vers(emu, q):
    assert q(":SYST:VERS?") == "1999.0" and q(":SYST:VERS") == "?6"


def row_sern(emu, q):
    assert q(":SYST:SERN?") == "EMU0001"


def row_errors(emu, q):
    assert [q(c) for c in ("PULSE1:STATE ON", ":", ":PULSE1:FOO 1", ":PULSE1:WIDT", ":PULSE1:WIDT x",
                           ":INST:CAT", "*RST?", "*SAV 1")] == ["?1", "?2", "?3", "?4", "?5", "?6", "?7", "ok"]


#: The command table of the manuals: section, command, check.
TABLE = [
    ("IEEE 488.2 common commands", "*IDN?", row_idn),
    ("IEEE 488.2 common commands", "*RST", row_rst),
    ("IEEE 488.2 common commands", "*SAV 3", row_sav),
    ("IEEE 488.2 common commands", "*RCL 3", row_rcl),
    ("Instrument subsystem", ":INST:CAT?", row_cat),
    ("Instrument subsystem", ":INST:FULL?", row_full),
    ("Instrument subsystem", ":INST:STAT OFF", row_inst_state),
    ("Instrument subsystem", ":INST:NSEL 2", row_nsel),
    ("Instrument subsystem", ":INST:SEL CHB", row_sel),
    ("System (T0) commands", ":PULSE0:STATE ON", row_state),
    ("System (T0) commands", ":PULSE0:PER 0.001", row_period),
    ("System (T0) commands", ":PULSE0:MODE BURS", row_mode),
    ("System (T0) commands", ":PULSE0:BCO 10", row_bco),
    ("System (T0) commands", ":PULSE0:PCO 3", row_pco),
    ("System (T0) commands", ":PULSE0:OCO 2", row_oco),
    ("System (T0) commands", ":PULSE0:ICL EXT10", row_icl),
    ("System (T0) commands", ":PULSE0:OCL T0", row_ocl),
    ("System (T0) commands", ":PULSE0:TRIG:MOD TRIG", row_trig_mode),
    ("System (T0) commands", ":PULSE0:TRIG:EDGE FALL", row_trig_edge),
    ("System (T0) commands", ":PULSE0:TRIG:LEV 2.5", row_trig_level),
    ("System (T0) commands", ":PULSE0:GATE:MOD PULS", row_gate_mode),
    ("System (T0) commands", ":PULSE0:GATE:LOG LOW", row_gate_logic),
    ("System (T0) commands", ":PULSE0:GATE:LEV 2.5", row_gate_level),
    ("System (T0) commands", ":PULSE0:COUN:STAT ON", row_counter_state),
    ("System (T0) commands", ":PULSE0:COUN:COUN?", row_counter_counts),
    ("System (T0) commands", ":PULSE0:COUN:CLE", row_counter_clear),
    ("Channel commands", ":PULSE1:STATE ON", row_ch_state),
    ("Channel commands", ":PULSE1:WIDT 0.00001", row_width),
    ("Channel commands", ":PULSE1:DEL 0.0001", row_delay),
    ("Channel commands", ":PULSE1:SYNC CHB", row_sync),
    ("Channel commands", ":PULSE1:MUX 3", row_mux),
    ("Channel commands", ":PULSE1:POL INV", row_pol),
    ("Channel commands", ":PULSE1:OUTP:MODE ADJ", row_outp_mode),
    ("Channel commands", ":PULSE1:OUTP:AMPL 5.0", row_outp_ampl),
    ("Channel commands", ":PULSE1:CMOD DCYC", row_cmod),
    ("Channel commands", ":PULSE1:BCO 4", row_ch_bco),
    ("Channel commands", ":PULSE1:PCO 2", row_ch_pco),
    ("Channel commands", ":PULSE1:OCO 2", row_ch_oco),
    ("Channel commands", ":PULSE1:WCO 5", row_wco),
    ("Channel commands", ":PULSE1:CGAT HIGH", row_cgat),
    ("Display subsystem", ":DISP:ENAB OFF", row_disp),
    ("System subsystem", ":SYST:COMM:SER:ECHO ON", row_echo),
    ("System subsystem", ":SYST:KLOC ON", row_klock),
    ("System subsystem", ":SYST:VERS?", row_vers),
    ("System subsystem", ":SYST:SERN?", row_sern),
    ("Error codes", ":PULSE1:FOO 1", row_errors),
]


def test_the_table_covers_every_command_the_emulator_lists():
    assert [(s, c) for s, c, _ in TABLE] == [(s, c) for s, c, _ in QC_COMMANDS]


@pytest.mark.parametrize("section, command, check", TABLE, ids=[f"{s}: {c}" for s, c, _ in TABLE])
def test_command_table(emu, q, section, command, check):
    check(emu, q)


@pytest.mark.parametrize("model, reads", [("9528", "0.00000000025"), ("575-8", "0.00000000025"),
                                          ("9518", "0.000000000")])
def test_each_model_rounds_to_its_own_resolution(model, reads):
    with PulseGeneratorEmulator(latency_s=0, model=model) as e:
        r = Raw(e.port)
        try:
            assert r("*IDN?").split(",")[:2] == [e.model.maker, model]
            r(":PULSE1:DEL 0.00000000037")
            assert r(":PULSE1:DEL?") == reads
        finally:
            r.ser.close()
