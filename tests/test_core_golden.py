"""No behaviour change: the core answers every recorded op stream exactly as the core
it was recorded with (tests/golden/make_golden.py), on CPython and in the MicroPython VM.

The traces hold every mode, MODE_FAST with and without a skin model, tests/strategies.py's
scenarios, random op streams with the firmware's calls between updates, closed loops on a
float skin, the benchmarks' sequences and bench/controllers.py's scenarios. A record is
status, i_ua, t_us, mq_last, rp_ohm, me, mq_target, rp0, fast_jumps, model_jumps, mode
and calibrated after every op (tests/golden/replay.py)."""

import gzip
import json
import subprocess
import sys

import pytest

from conftest import ROOT

GOLDEN = ROOT / "tests" / "golden"
sys.path[:0] = [str(GOLDEN), str(ROOT / "bench"), str(ROOT / "firmware")]
import make_golden  # noqa: E402
import replay  # noqa: E402

DATA = json.loads(gzip.decompress((GOLDEN / "core_traces.json.gz").read_bytes()))


def first_difference(case, got):
    want = case.get("out")
    if want is None:
        return f"{case['name']}: sha differs (rerun the old core on its ops to see where)"
    for k, (a, b) in enumerate(zip(want, got)):
        if a != b:
            return f"{case['name']}: op {k} ({case['ops'].split()[k]}): want {a}, got {b}"
    return f"{case['name']}: {len(want)} records wanted, {len(got)} given"


def mismatches(cases, answers):
    bad = [first_difference(c, got) for c, got in zip(cases, answers) if make_golden.sha(got) != c["sha"]]
    return bad


def pieces(line, n=400):
    """A long op stream as lines of n ops, each but the last ending in " +" (replay.py)."""
    ops = line.split()
    return " +\n".join(" ".join(ops[k:k + n]) for k in range(0, len(ops), n))


def cpython_answer(line):
    out = []
    replay.run(line, out)
    return out


def micropython_answers(micropython, mpy_dir, lines):
    """Every line through tests/golden/replay.py in one MicroPython process: records per line."""
    import os

    env = dict(os.environ, MICROPYPATH=str(mpy_dir))
    text = "\n".join(pieces(line) for line in lines) + "\n\n"
    r = subprocess.run([micropython, str(GOLDEN / "replay.py")], input=text,
                       capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    out = r.stdout.split("\n")
    assert out[0].startswith("READY") and out[0].endswith(".mpy"), out[0]  # the compiled core, not a .py
    answers, cur = [], []
    for rec in out[1:]:
        if rec == ".":
            answers.append(cur)
            cur = []
        elif rec:
            cur.append(rec)
    assert len(answers) == len(lines)
    return answers


def test_the_corpus_is_what_it_claims():
    """Every section is there, with every mode, the skin model and the firmware's calls."""
    names = {c["name"].split("/")[0] for c in DATA["cases"]}
    assert names == {"hyp", "ops", "skin", "hand"}
    ops = " ".join(c["ops"] for c in DATA["cases"])
    for mode in range(6):
        assert f"M,{mode} " in ops
    for k in ("S,", "D,", "X,", "V,", " L,", " C,"):
        assert k in ops
    d = [o.count(",") for o in ops.split() if o.startswith("D,")]
    assert d.count(2) > 100 and d.count(3) > 100  # delivered() with the status as it is, and with one told
    assert len(DATA["cases"]) > 4000 and len(DATA["bench"]) >= 140


def test_the_generator_still_makes_the_stored_streams():
    """The seeded sections regenerate exactly (the skin section's Rp comes from closed loops
    through the core, so this replays those loops too). The hypothesis section is stored
    as drawn: it does not depend on the hypothesis version."""
    stored = {}
    for c in DATA["cases"]:
        sec, k = c["name"].split("/")
        stored.setdefault(sec, []).append(c["ops"])
    assert make_golden.ops_cases() == stored["ops"]
    assert make_golden.skin_cases() == stored["skin"]
    assert make_golden.hand_cases() == stored["hand"]


def test_cpython_replays_the_golden_traces():
    cases = DATA["cases"]
    bad = mismatches(cases, [cpython_answer(c["ops"]) for c in cases])
    assert not bad, f"{len(bad)} of {len(cases)} traces differ; first: " + "\n".join(bad[:5])


def test_micropython_replays_the_golden_traces(micropython, core_mpy_dir):
    cases = DATA["cases"]
    bad = mismatches(cases, micropython_answers(micropython, core_mpy_dir, [c["ops"] for c in cases]))
    assert not bad, f"{len(bad)} of {len(cases)} traces differ; first: " + "\n".join(bad[:5])


def test_the_bench_scenarios_replay_the_golden_traces(micropython, core_mpy_dir):
    """bench/controllers.py's scenarios run closed loop on CPython give the recorded traces;
    their op streams replayed in MicroPython give the same records."""
    runs = make_golden.record_bench()
    assert set(runs) == set(DATA["bench"])
    bad = [k for k, (ops, recs) in runs.items() if make_golden.sha(recs) != DATA["bench"][k]]
    assert not bad, f"{len(bad)} bench runs differ: {bad[:5]}"
    keys = sorted(runs)
    mp = micropython_answers(micropython, core_mpy_dir, [runs[k][0] for k in keys])
    bad = [k for k, got in zip(keys, mp) if got != runs[k][1]]
    assert not bad, f"{len(bad)} bench runs differ in MicroPython: {bad[:5]}"


@pytest.mark.parametrize("where", ["cpython", "micropython"])
def test_a_changed_answer_is_caught(where, micropython, core_mpy_dir):
    """The check is live: a trace whose recorded sha is of another answer fails."""
    case = dict(next(c for c in DATA["cases"] if c["name"] == "hand/0"))
    if where == "cpython":
        got = cpython_answer(case["ops"])
    else:
        got = micropython_answers(micropython, core_mpy_dir, [case["ops"]])[0]
    assert not mismatches([case], [got])
    got[500] = got[500].replace(",", ",1", 1)  # one digit more in one i_ua
    assert mismatches([case], [got])
