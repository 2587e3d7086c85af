"""The guided calibration session end to end: the simulated participant on the
simulated device (the real firmware in the VM, in real time)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from steadytouch.device import Device
from steadytouch.session import Session, SimResponder, Stopped
from steadytouch.transport import open_transport

from conftest import ROOT

EXE = str(Path(sys.executable).parent / "steadytouch")


def test_session_presses_keys_and_stays_within_limits():
    with open_transport("sim://steady?channels=1") as t:
        d = Device(t)
        # a low soft ceiling the strong level will hit; the charge up to the hard limit the device reports
        d.limits(500, 2000, 100, 8000, d.info().hard_q_max_pc)
        r = SimResponder(seed=3, a=0.62)  # not on I^2 T = const: the person must adjust
        s = Session(d, r, present_s=0.12, log=lambda *a: None)
        res = s.run({"weak": 1500, "strong": 2700})
        cal = d.calibration(0)
        assert not (cal.flags & 2)  # disarmed at the end
    assert r.keys > 30 and res.presentations > 22 + 4  # it took key presses, not just the first guesses
    weak = [row for row in res.rows if row["condition"] == "weak"]
    assert [row["t_us"] for row in weak] == list(range(200, 701, 50))
    assert all(500 <= row["i_ua"] <= 2000 for row in res.rows)  # never beyond the soft limits
    # the matched currents follow the person's own strength-duration law within its JND
    for row in weak[1:]:
        target = 1500 * (row["t_us"] / 200) ** -0.62
        assert abs(row["i_ua"] / target - 1) < 0.05


def test_stop_key_disarms_at_once():
    class Quitter(SimResponder):
        def key(self, **kw):
            self.keys += 1
            return "q" if self.keys >= 3 else super().key(**kw)

    with open_transport("sim://steady?channels=1") as t:
        d = Device(t)
        s = Session(d, Quitter(seed=1, a=0.6), present_s=0.1, log=lambda *a: None)
        with pytest.raises(Stopped):
            s.run({"weak": 1500})
        assert not (d.calibration(0).flags & 2)


def test_cli_session_produces_a_calibration_the_device_accepts(tmp_path):
    p = subprocess.run([EXE, "calibrate", "--interactive", "--participant", "sim", "--device", "sim://steady?channels=1",
                        "--present-s", "0.12", "--send", "--out", str(tmp_path), "--t0-us", "500"],
                       capture_output=True, text=True, timeout=180, cwd=ROOT)
    assert p.returncode == 0, p.stderr
    cal = json.loads((tmp_path / "calibration.json").read_text())
    assert -20000 <= cal["x_star_ohm"] <= 0 and cal["y_star_pc"] >= 0
    assert "calibrate: ok" in p.stdout
    rows = (tmp_path / "session.csv").read_text().splitlines()
    assert rows[0] == "participant,condition,t_us,i_ua,rp_ohm" and len(rows) == 1 + 22
