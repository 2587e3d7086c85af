"""Rule 7's tau gain, measured by the host on the calibration sweeps (host/skin.py: tau_gain) and sent with the
model: the realistic simulated board's decay read as the frame reads it (bench/controllers.py's Meter), with the
monitor's read of tau distorted as a filter or a lead would."""

import contextlib
import importlib.util
import math
import sys

import numpy as np
import pytest

import sensation_core as sc

from conftest import ROOT

if "bench_controllers" in sys.modules:
    bench = sys.modules["bench_controllers"]
else:
    spec = importlib.util.spec_from_file_location("bench_controllers", ROOT / "bench" / "controllers.py")
    bench = importlib.util.module_from_spec(spec)
    sys.modules["bench_controllers"] = bench  # dataclasses look their module up
    spec.loader.exec_module(bench)
skin = bench.skin


def sweeps(k=1.0, add_us=0.0, seed=7, n=30, electrode=0, keep=1.0, noise_oct=0.0):
    """n wide sweeps on one study electrode; the tau read x k + add_us; keep: the share of pulses whose tau
    is read at all. Returns the averaged fit, the (i_ua, t_us, ltau_q16) of every sweep pulse and the sweeps
    (each a list of (i_ua, t_us, rp_ohm))."""
    rng = np.random.default_rng(seed)
    for _ in range(electrode + 1):
        mk = bench.random_electrode(rng)
    e = mk()
    e.h = 1.0
    m = bench.Meter(e, "real", 1000 + electrode, bench.selftest_correction("real"))
    m.pulse(1000, 1000)
    sw, taus = [], []
    pick = np.random.default_rng(1)
    for _ in range(n):
        row = []
        for i, t in skin.sweep_wide(1000, 1000):
            row.append((i, t, m.pulse(i, t)[1]))
            lt = m.ltau_q16
            if lt and pick.random() < keep:
                tau = 2 ** (lt / 65536 + noise_oct * pick.normal()) * k + add_us
                lt = max(1, round(math.log2(tau) * 65536)) if tau > 1 else 0
            else:
                lt = 0
            taus.append((i, t, lt))
        sw.append(row)
    return skin.fit_sweeps(sw, 1000, 1000, bench.LIMITS[3]), taus, sw


@pytest.mark.parametrize("electrode", [0, 1, 2])
def test_a_true_tau_is_trusted_with_a_gain_near_one(electrode):
    f, taus, _ = sweeps(electrode=electrode)
    g = skin.tau_gain(f.model, taus)
    assert f.trusted and g.trusted, g.why
    assert abs(g.gain_oct) < 0.06 and g.q16 == round(g.gain_oct * 65536) and g.reads > 300


@pytest.mark.parametrize("k", [0.75, 1.3])
def test_a_monitor_that_scales_tau_is_measured(k):
    """A scale within +-1/2 octave is measured to ~4 % and sent (the controller takes it out of every tau)."""
    f, taus, _ = sweeps(k=k)
    g = skin.tau_gain(f.model, taus)
    assert g.trusted, g.why
    assert abs(g.gain_oct - math.log2(k)) < 0.06 and 0.97 <= g.slope <= 1.04


@pytest.mark.parametrize("k, add_us, why", [
    (1.6, 0, "the monitor reads tau x 1.6"),  # past 1/2 octave: a monitor to fix, not to correct
    (0.6, 0, "the monitor reads tau x 0.6"),
    (1.0, 50, "slope"),  # a lead's offset: log tau read flattens against log tau model
])
def test_a_tau_read_wrong_is_not_used(k, add_us, why):
    f, taus, _ = sweeps(k=k, add_us=add_us)
    g = skin.tau_gain(f.model, taus)
    assert not g.trusted and g.q16 == sc.SKIN_TAU_OFF and why in g.why, g


def test_a_noisy_or_narrow_tau_is_not_used():
    """Reads that spread over more than TAU_SPREAD_MAX (0.3 octave of noise), or sweeps that span too little of
    tau to tell a slope (only the 1 ms pulses): refused, named."""
    f, taus, _ = sweeps(noise_oct=0.3)
    g = skin.tau_gain(f.model, taus)
    assert not g.trusted and "tau's reads spread over" in g.why, g
    f, taus, _ = sweeps()
    g = skin.tau_gain(f.model, [x for x in taus if x[1] in (700, 1000)])
    assert not g.trusted and "the sweeps span" in g.why, g


def test_too_few_taus_read_is_not_used():
    f, taus, _ = sweeps(keep=0.4)
    g = skin.tau_gain(f.model, taus)
    assert not g.trusted and g.q16 == sc.SKIN_TAU_OFF and "tau was read on" in g.why


def test_skin_sends_the_gain_measured_on_the_sweeps_ltau_column(tmp_path, monkeypatch, capsys):
    """`steadytouch skin` on repeated sweeps with the ltau_q16 column `record` writes: the gain goes to the
    device with the model (its Calibration report says it back); a tau read x 1.6 is named and not sent; a bad
    ltau_q16 is one line naming the row."""
    from steadytouch import cli
    from steadytouch.device import Device
    from steadytouch.transport import open_transport

    def write(name, k):
        _, taus, sw = sweeps(k=k, n=12)
        rows = [(s, i, t, rp, taus[s * len(row) + j][2]) for s, row in enumerate(sw) for j, (i, t, rp) in enumerate(row)]
        p = tmp_path / name
        p.write_text("sweep,i_ua,t_us,rp_ohm,ltau_q16\n" + "".join(",".join(map(str, r)) + "\n" for r in rows))
        return p

    url = "sim://steady"
    with open_transport(url) as t:
        monkeypatch.setattr(cli, "open_transport", lambda u: contextlib.nullcontext(t))
        for k, sent in ((1.2, True), (1.6, False)):
            p = write(f"sweeps-{k}.csv", k)
            assert cli.main(["skin", str(p), "--send", "--channel", "0", "--device", url]) == 0
            out = capsys.readouterr().out
            c = Device(t).calibration(0)
            if sent:
                assert "the monitor reads it x 1.2" in out and "anchor on it (rule 7)" in out, out
                assert abs(c.skin_tau_q16 - math.log2(1.2) * 65536) < 0.06 * 65536, c
            else:
                assert "tau not used (rule 7): the monitor reads tau x 1.6" in out, out
                assert c.skin_tau_q16 == sc.SKIN_TAU_OFF and c.skin_cp_pf > 0, c
    bad = tmp_path / "bad.csv"
    lines = p.read_text().splitlines()
    lines[3] = lines[3].rsplit(",", 1)[0] + ",x1"
    bad.write_text("\n".join(lines) + "\n")
    assert cli.main(["skin", str(bad)]) == 2
    assert "bad.csv row 4: column ltau_q16 is not a whole number: 'x1'" in capsys.readouterr().err



def test_skin_sends_no_gain_to_a_firmware_that_does_not_read_tau(tmp_path, monkeypatch, capsys):
    """A device before firmware 0.5.0 ignores SET_SKIN's gain bytes: the command says so and sends the model
    without it (review of session 26: it printed "jumps anchor on it")."""
    import dataclasses

    from steadytouch import cli
    from steadytouch.device import Device
    from steadytouch.transport import open_transport

    _, taus, sw = sweeps(n=12)
    p = tmp_path / "sweeps.csv"
    p.write_text("sweep,i_ua,t_us,rp_ohm,ltau_q16\n" + "".join(
        f"{s},{i},{t},{rp},{taus[s * len(row) + j][2]}\n" for s, row in enumerate(sw) for j, (i, t, rp) in enumerate(row)))
    url = "sim://steady"
    info = Device.info
    monkeypatch.setattr(Device, "info", lambda self: dataclasses.replace(info(self), firmware="0.4.1"))
    with open_transport(url) as t:
        monkeypatch.setattr(cli, "open_transport", lambda u: contextlib.nullcontext(t))
        assert cli.main(["skin", str(p), "--send", "--channel", "0", "--device", url]) == 0
        assert Device(t).calibration(0).skin_tau_q16 == sc.SKIN_TAU_OFF
    out = capsys.readouterr().out
    assert "firmware 0.4.1 does not read tau (rule 7: firmware 0.5.0 on" in out and "skin: ok" in out, out
