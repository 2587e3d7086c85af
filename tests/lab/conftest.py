"""Fixtures of the lab tests (LSL, the live view). Every test that opens an LSL
outlet or inlet takes `lsl`: it points LSLAPICFG at the project's loopback
configuration (host/lsl/loopback.cfg) before pylsl is first imported, for this
process and the steadytouch processes the tests start, so nothing leaves 127.0.0.1."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
LOOPBACK = ROOT / "host" / "lsl" / "loopback.cfg"
STEADYTOUCH = Path(sys.executable).parent / "steadytouch"


@pytest.fixture(scope="session")
def lsl():
    """pylsl, imported with LSLAPICFG = the loopback configuration (set for the session)."""
    assert LOOPBACK.is_file(), LOOPBACK
    if "pylsl" in sys.modules and os.environ.get("LSLAPICFG") != str(LOOPBACK):
        pytest.fail("pylsl was imported before the loopback configuration was set: its LSL is not confined")
    old = os.environ.get("LSLAPICFG")
    os.environ["LSLAPICFG"] = str(LOOPBACK)
    try:
        import pylsl
    except (ImportError, RuntimeError) as e:
        pytest.skip(f"pylsl not installed ({e}): `make setup` installs it (the `lab` extra)")
    cfg = LOOPBACK.read_text()
    for line in ("IPv6 = disable", "ResolveScope = machine", "MachineAddresses = {127.0.0.1}", "KnownPeers = {127.0.0.1}"):
        assert line in cfg, line
    yield pylsl
    if old is None:
        os.environ.pop("LSLAPICFG", None)
    else:
        os.environ["LSLAPICFG"] = old


def steadytouch(*args, **kw) -> subprocess.Popen:
    """The CLI as a user runs it, in the background, with this environment (LSLAPICFG included)."""
    assert os.environ.get("LSLAPICFG") == str(LOOPBACK), "an LSL test without the loopback configuration"
    return subprocess.Popen([str(STEADYTOUCH), *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ), **kw)


def pull_all(pylsl, source_id: str, proc: subprocess.Popen, max_s: float = 60.0, resolve_s: float = 20.0):
    """Resolve the telemetry and marker streams of one source (within resolve_s: the outlets
    open once the device answered, which on emu:// is after the emulated Pico booted), pull
    until the process ends (and a moment after); (telemetry info XML, samples, timestamps,
    markers [(text, ts)])."""
    tel = pylsl.resolve_byprop("source_id", f"{source_id}-telemetry", 1, resolve_s)
    mk = pylsl.resolve_byprop("source_id", f"{source_id}-markers", 1, resolve_s)
    assert tel and mk, f"streams of {source_id} not found in {resolve_s} s (the process: {proc.poll()})"
    ti, mi = pylsl.StreamInlet(tel[0]), pylsl.StreamInlet(mk[0])
    ti.open_stream(10)
    mi.open_stream(10)
    xml = ti.info(10).as_xml()
    samples, stamps, markers = [], [], []
    end = time.monotonic() + max_s
    done_at = None
    while time.monotonic() < end:
        x, t = ti.pull_chunk(timeout=0.1)
        samples += x
        stamps += t
        x, t = mi.pull_chunk(timeout=0.0)
        markers += [(m[0], s) for m, s in zip(x, t)]
        if proc.poll() is not None:
            done_at = done_at or time.monotonic()
            if time.monotonic() - done_at > 0.5 and not x:
                break
    return xml, samples, stamps, markers
