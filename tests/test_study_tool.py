"""bench/study.py (issue 13's study over seeds) and bench/controllers.py's --scope correction."""

import importlib.util
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
spec = importlib.util.spec_from_file_location("bench_study", ROOT / "bench" / "study.py")
study = importlib.util.module_from_spec(spec)
spec.loader.exec_module(study)
bench = sys.modules.get("bench_controllers") or study._bench()


def test_the_scope_correction_stores_the_dac_gain_and_the_monitor_s_own_gain():
    """Without --scope the self-test fits the whole path's gain (DAC x monitor: it cannot tell them
    apart); with it each channel's DAC gain is known and stored, and the fit finds the monitor's own."""
    plain = bench.selftest_correction("real")
    scoped = bench.selftest_correction("real", scope=True)
    for ch in range(2):
        dac, mon = bench.board_sim.DAC_GAIN[ch], bench.board_sim.MON_GAIN[ch]
        assert len(plain[ch]) == 2
        assert abs(plain[ch][0] / 1e6 - dac * mon) < 0.002, (plain[ch], dac * mon)
        assert scoped[ch][2] == round(dac * 1e6)
        assert abs(scoped[ch][0] / 1e6 - mon) < 0.002, (scoped[ch], mon)
    m = bench.Meter(bench.board_sim.sim_electrode.Resistor(10000), "real", correction=scoped)
    di, rp, i_true, _ = m.pulse(4500, 1000)
    assert abs(di - i_true) <= 3, (di, i_true)  # the board reports the current it drives, to a code
    assert abs(rp - 10000) <= 100, rp


def test_a_small_study_writes_one_record_a_step_and_mode(tmp_path, capsys):
    out = tmp_path / "steps.jsonl"
    study.main(["--seeds", "7", "--electrodes", "2", "--sweeps", "3", "--jobs", "1", "--out", str(out)])
    text = capsys.readouterr().out
    recs = [json.loads(ln) for ln in out.read_text().splitlines()]
    assert recs and {r["mode"] for r in recs} == set(study.MODES)
    assert {r["electrode"] for r in recs} <= {0, 1}
    n = sum(1 for r in recs if r["mode"] == study.MODES[0])
    assert f"model: {n} steps; reach " in text, text
    assert all(r["reach"] is None or 0 <= r["reach"] < 100 for r in recs)
    study.main(["--seeds", "7", "--electrodes", "2", "--sweeps", "3", "--jobs", "1", "--compare", str(out)])
    assert "0 steps differ" in capsys.readouterr().out  # the same draws give the same steps


@pytest.mark.parametrize("args, says", [
    (["--seeds", "7-x"], "--seeds: '7-x' is not a seed"),
    (["--seeds", "9-3"], "--seeds: '9-3'"),
    (["--seeds", "-3"], "--seeds"),
    (["--electrodes", "0"], "--electrodes 0: accepted 1 to 1000"),
    (["--sweeps", "1"], "--sweeps 1: accepted 2 to 200"),
    (["--jobs", "0"], "--jobs 0: accepted 1 or more"),
    (["--compare", "/nonexistent/x.jsonl"], "--compare /nonexistent/x.jsonl: cannot read it"),
])
def test_bad_arguments_are_named_with_their_range(args, says):
    with pytest.raises(SystemExit) as e:
        study.main(args)
    assert says in str(e.value), e.value


def _attacks():
    have = sys.modules.get("bench_attacks")
    if have is None:
        sp = importlib.util.spec_from_file_location("bench_attacks", ROOT / "bench" / "attacks.py")
        have = importlib.util.module_from_spec(sp)
        sp.loader.exec_module(have)
        sys.modules["bench_attacks"] = have
    return have


def test_the_attack_families_have_their_cases_and_a_run_writes_one_record_a_case(tmp_path, capsys):
    attacks = _attacks()
    counts = {f: len(list(attacks.cases(f, bench))) for f in attacks.FAMILIES}
    assert counts == {"badread": 44, "smallpeel": 24, "second": 30, "ramp": 8}
    for name, ev, n, bad, a, b in attacks.cases("badread", bench):  # each read lands inside its window, after its step
        assert all(a <= p < b <= n for p in bad), name
    out = tmp_path / "ramp.jsonl"
    attacks.main(["ramp", "--seeds", "31", "--electrodes", "1", "--out", str(out)])
    recs = [json.loads(ln) for ln in out.read_text().splitlines()]
    assert [r["case"].split("/", 2)[2] for r in recs] == [c[0] for c in attacks.cases("ramp", bench)]
    assert all(r["max"] is not None and r["min"] <= r["max"] for r in recs)
    attacks.main(["ramp", "--seeds", "31", "--electrodes", "1", "--compare", str(out)])  # the same draws: no case moved
    text = capsys.readouterr().out
    assert "ramp: 8 cases" in text and "on the same cases: 8 cases" in text and "highest" in text
    assert "->" not in text


@pytest.mark.parametrize("args,says", [(["ramp", "--electrodes", "0"], "--electrodes 0: accepted 1 to 1000"),
                                       (["second", "--exact", "0.5"], "--exact 0.5: accepted 0 to 0.1"),
                                       (["ramp", "--seeds", "x"], "--seeds")])
def test_attacks_refuses_bad_arguments_by_name(args, says):
    with pytest.raises(SystemExit) as e:
        _attacks().main(args)
    assert says in str(e.value)
