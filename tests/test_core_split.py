"""The core's modules agree with each other and keep sensation_core's public API.

fast_step.py and skin_model.py keep private copies of a few of the core's constants
(a const() is folded only inside its own module on MicroPython); here they are
checked against sensation_core's, and every public name firmware/, host/, bench/ and
tests/ import from sensation_core is still there."""

import ast

import fast_step
import fixmath
import sensation_core as sc
import skin_model

from conftest import ROOT, SHARED

COPIES = {
    fast_step: {"_ST_OK": sc.ST_OK, "_ST_T_MAX": sc.ST_T_MAX, "_RP_MIN_OHM": sc.RP_MIN_OHM,
                "_RP_MAX_OHM": sc.RP_MAX_OHM, "_SAT30": 2**30 - 1, "_MQ_CAP": 2**29 - 1},
    skin_model: {"_RP_MAX_OHM": sc.RP_MAX_OHM, "_SAT30": 2**30 - 1, "_MQ_CAP": 2**29 - 1},
    fixmath: {"_SAT30": 2**30 - 1},
}


def test_the_private_copies_agree_with_the_core():
    for mod, names in COPIES.items():
        for name, want in names.items():
            assert getattr(mod, name) == want, (mod.__name__, name)
    assert sc._MQ_CAP == 2**29 - 1


def test_every_public_name_used_outside_is_importable_from_sensation_core():
    """Every `sc.NAME` (and `from sensation_core import NAME`) in firmware/, host/, bench/,
    tests/ resolves on sensation_core."""
    used = set()
    for folder in ("firmware", "host", "bench", "tests"):
        for src in (ROOT / folder).rglob("*.py"):
            tree = ast.parse(src.read_text())
            aliases = set()
            for node in ast.walk(tree):
                if isinstance(node, ast.Import):
                    aliases |= {a.asname or a.name for a in node.names if a.name == "sensation_core"}
                elif isinstance(node, ast.ImportFrom) and node.module == "sensation_core":
                    used |= {a.name for a in node.names}
            for node in ast.walk(tree):
                if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases:
                    if not node.attr.startswith("_"):
                        used.add(node.attr)
    assert len(used) > 30
    missing = sorted(n for n in used if not hasattr(sc, n))
    assert not missing, missing


def test_the_api_of_before_the_split_is_all_there():
    names = """VERSION I_LIMIT_UA T_LIMIT_US Q_LIMIT_PC RP_MIN_OHM RP_MAX_OHM X_STAR_MIN_OHM VP_LIMIT_MV
    RP_INVALID RP_OVER ST_OK ST_I_MIN ST_I_MAX ST_T_MIN ST_T_MAX ST_Q_MAX ST_RP_LOW ST_RP_HIGH ST_Q_NONPOS
    ST_UNCALIBRATED ST_BOUND_MASK ST_FAULT_MASK MODE_OPEN_LOOP MODE_CONSTANT_CHARGE MODE_CONSTANT_ENERGY
    MODE_PULSE_WIDTH_LINEAR MODE_AKHTAR MODE_FAST MODES FAST_ELASTICITY_Q12 FAST_MODEL_RAISE_LOG2
    SKIN_RS_MAX_OHM SKIN_BETA_MIN_Q16 SKIN_BETA_MAX_Q16 SKIN_CP_MIN_PF SKIN_CP_MAX_PF rp_from_vp Controller""".split()
    assert not [n for n in names if not hasattr(sc, n)]
    c = sc.Controller(100, 10000, 50, 2000, 10_000_000)
    for m in ("set_limits", "calibrate", "set_mode", "set_skin", "delivered", "stop", "update", "_from_q"):
        assert callable(getattr(c, m)), m
    for a in ("mode", "rp_ohm", "me_ua2ms", "mq_target_fc_per_ohm", "mq_last_fc_per_ohm", "i0_ua", "t0_us",
              "rp0_ohm", "x_star_ohm", "y_star_pc", "i_min_ua", "i_max_ua", "t_min_us", "t_max_us", "q_max_pc",
              "calibrated", "i_ua", "t_us", "status", "fast_jumps", "model_jumps", "skin_rs_ohm", "skin_beta_q16",
              "skin_cp_pf"):
        assert isinstance(getattr(c, a), int), a


def test_the_core_reads_on_a_few_screens():
    """issue 14: the paper's law in a file of at most ~450 lines, MODE_FAST beside it."""
    assert len((SHARED / "sensation_core.py").read_text().splitlines()) <= 450
    src = (SHARED / "sensation_core.py").read_text()
    for moved in ("_rp_model", "_root", "_LOG_TAB", "_EXP_TAB", "_drift", "_model_pulse"):
        assert moved not in src, moved
