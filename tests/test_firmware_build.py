"""Firmware files compile for the RP2040, the HID descriptor parses with the
sizes we declare, and the VM entry point rejects bad arguments clearly."""

import os
import subprocess

import pytest

import hid_protocol as hp

from conftest import FIRMWARE, SHARED, compile_mpy, tool

FIRMWARE_FILES = sorted(FIRMWARE.glob("*.py"))


@pytest.mark.parametrize("src", FIRMWARE_FILES + sorted(SHARED.glob("*.py")), ids=lambda p: p.name)
def test_compiles_for_rp2040(mpy_cross, tmp_path, src):
    out = compile_mpy(mpy_cross, src, tmp_path, "-march=armv6m")
    assert out.read_bytes()[:2] == b"M\x06"


def test_the_firmware_tree_is_complete():
    names = {p.name for p in FIRMWARE_FILES}
    assert {"main.py", "stim.py", "board_config.py", "board_rp2.py", "board_sim.py", "pio_gate.py",
            "usb_hid64.py", "sim_electrode.py"} <= names


def test_report_descriptor_parses_with_declared_sizes():
    from hidtools.hid import ReportDescriptor

    rd = ReportDescriptor.from_bytes(list(hp.REPORT_DESCRIPTOR))
    assert len(hp.REPORT_DESCRIPTOR) == 25 and hp.REPORT_DESCRIPTOR[-1] == 0xC0  # End Collection
    ins = rd.input_reports
    outs = rd.output_reports
    assert len(ins) == 1 and len(outs) == 1
    (rin,), (rout,) = ins.values(), outs.values()
    assert rin.size == hp.REPORT_LEN and rout.size == hp.REPORT_LEN  # bytes, no report ID


def run_main(*args, stdin=""):
    env = dict(os.environ, MICROPYPATH=os.pathsep.join([str(SHARED), str(FIRMWARE)]))
    p = subprocess.run([tool("micropython"), str(FIRMWARE / "main.py"), *args], input=stdin.encode(),
                       capture_output=True, env=env, timeout=60)
    p.stderr = p.stderr.decode()
    return p


@pytest.mark.parametrize(
    "args, words",
    [
        (["--channels", "5"], "--channels=5 out of range [1, 4]"),
        (["--rate", "abc"], "--rate: 'abc' is not a whole number"),
        (["--scenario", "nosuch"], "unknown scenario 'nosuch'"),
        (["--auto", "1000,1000"], "--auto takes I0_UA,T0_US,XSTAR_OHM,YSTAR_PC"),
        (["--auto", "50000,1000,-1670,186000"], "--auto: I0 50000 uA out of range: the device accepts 500.."),
        (["--bogus"], "unknown option --bogus"),
        (["--scenario", "/nonexistent/file.csv"], "steadytouch firmware:"),
    ],
)
def test_main_rejects_bad_arguments_in_one_line(args, words):
    p = run_main(*args)
    assert p.returncode == 2
    assert words in p.stderr and "Traceback" not in p.stderr
    assert len(p.stderr.strip().splitlines()) <= 2
    if "--auto" not in args:
        assert p.stdout == b""


def test_main_runs_a_scenario_and_streams_reports():
    from steadytouch.protocol import Ack, Telemetry, decode, split_stdio_stream

    p = subprocess.run(
        [tool("micropython"), str(FIRMWARE / "main.py"), "--scenario", "steady", "--frames", "20",
         "--auto", "1000,1000,-1670,186000"],
        capture_output=True, env=dict(os.environ, MICROPYPATH=f"{SHARED}:{FIRMWARE}"), timeout=60,
    )
    assert p.returncode == 0, p.stderr
    reps = [decode(r) for r in split_stdio_stream(p.stdout)]
    assert [type(r) for r in reps[:3]] == [Ack, Ack, Ack] and all(r.ok for r in reps[:3])
    tel = [r for r in reps if isinstance(r, Telemetry)]
    assert len(tel) == 40 and {t.channel for t in tel} == {0, 1}
    assert all(t.i_ua > 0 and t.stop == hp.STOP_NONE for t in tel)
