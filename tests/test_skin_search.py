"""The skin model's searches (shared/skin_model.py `_root`; docs/controller.md, "How a search
ends"), checked on the golden skin streams (tests/golden: closed loops on a float electrode,
MODE_FAST with a skin model that fits or not):
- a search ends on a sign change of g 1/2**16 wide (or where g is 0), whatever its start;
- the duration ceiling's search started where the mE curve meets t_max finds the root the
  search over the whole current range finds;
- the pulse before's words and its anchor taken from the last jump give the answers that
  computing them again gives, and spare searches."""

import gzip
import json
import sys
from array import array

import pytest

import skin_model as sm
from fixmath import log2q

from conftest import ROOT

sys.path.insert(0, str(ROOT / "tests" / "golden"))
import replay  # noqa: E402

DATA = json.loads(gzip.decompress((ROOT / "tests" / "golden" / "core_traces.json.gz").read_bytes()))
SKIN = [c["ops"] for c in DATA["cases"] if c["name"].startswith("skin/")]
SEARCHES = (sm._K_ANCHOR, sm._K_PEEL, sm._K_LAW, sm._K_CEIL, sm._K_TWO)


def g(vv, kind, x, lc0):
    """g(kind, x) evaluated alone, on a copy (an evaluation of _K_TWO writes a word). An anchor
    finds its own range (no evaluation alone): its g is log2 of the model's Rp (_K_RP, the
    same pulse) less log2 of the Rp read."""
    if kind & 0xFF == sm._K_ANCHOR:
        pb = (kind >> 8) & 0xFF
        rp = sm._root(array("i", vv), sm._K_RP + (pb << 8), x, x - 1, lc0)
        return log2q(rp) - vv[pb + sm._P_RLP]
    return sm._root(array("i", vv), kind & 0xFFFFFF, x, x - 1, lc0)


@pytest.fixture
def searches(monkeypatch):
    """Every search _root runs in the streams: (kind, a, b, lc0, the values before, its answer)."""
    seen = []
    real = sm._root

    def spy(vv, kind, a, b, lc0):
        before = array("i", vv)
        x = real(vv, kind, a, b, lc0)
        if b >= a and (kind & 0xFF) in SEARCHES:
            seen.append((kind, a, b, lc0, before, x))
        return x

    monkeypatch.setattr(sm, "_root", spy)
    return seen, real


def run_streams(n):
    for line in SKIN[:n]:
        replay.run(line, [])


def test_a_search_ends_on_a_sign_change_one_step_wide(searches):
    """The ceiling's search starts where the mE curve meets t_max and the contact search no
    longer at 0: the end is still a sign change 1/2**16 wide (the answer to 1/2**16)."""
    seen, real = searches
    run_streams(150)
    checked = 0
    for kind, a, b, lc0, vv, x in seen:
        if x == sm.NOROOT:
            continue
        k = kind & 0xFF
        lc = lc0 if k == sm._K_ANCHOR else 0
        fx = g(vv, kind, x, lc)
        if fx != 0:  # a sign change between x and a neighbour, 1/2**16 away
            lo, hi = g(vv, kind, x - 1, lc), g(vv, kind, x + 1, lc)
            assert (lo > 0) != (fx > 0) or (hi > 0) != (fx > 0), (k, x, lo, fx, hi)
        checked += 1
    assert checked > 2000, checked


def test_the_ceilings_search_from_the_mE_curve_finds_the_whole_ranges_root(searches):
    seen, real = searches
    run_streams(len(SKIN))
    narrow = [s for s in seen if (s[0] & 0xFF) == sm._K_CEIL and s[0] & sm._FA_KNOWN]
    assert len(narrow) > 20, len(narrow)
    found = 0
    for kind, a, b, lc0, vv, x in narrow:
        v = array("i", vv)
        v[sm._V_WORK] = 0  # the whole range, without the jump's budget
        lo = v[sm._V_LIMIN]
        hi = min(v[sm._V_LQMAX] - v[sm._V_LTMAX], v[sm._V_LIMAX])
        full = real(v, sm._K_CEIL, lo, hi, 0)
        if x == sm.NOROOT:  # (jump then searches the whole range itself)
            continue
        found += 1
        assert full != sm.NOROOT and abs(full - x) <= 16, (x, full)  # both 1/2**16 from g's sign change
        assert a <= x <= b
    assert found > 0.9 * len(narrow), (found, len(narrow))


def test_the_pulse_before_taken_from_the_last_jump_changes_no_answer(searches):
    seen, real = searches
    n = 0
    for line in SKIN[:200]:
        seen.clear()
        kept = []
        replay.run(line, kept)
        with_cache = len(seen)
        seen.clear()
        fresh = []
        c = None
        for op in line.split():  # the same ops, the model's memory of the last jump erased before each
            if c is not None:
                c.skin.v[sm._V_NI] = 0
                c.skin.v[sm._V_ACH_OK] = 0
            c = replay.run(op, fresh, c)
        assert fresh == kept
        assert len(seen) >= with_cache
        n += len(seen) - with_cache
    assert n > 100, n  # the anchors spared
