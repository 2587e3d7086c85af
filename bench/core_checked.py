"""The core with every arithmetic result range-checked, all its modules included.

load_core() loads shared/fixmath.py, skin_model.py, fast_step.py and
sensation_core.py through steadytouch.rangecheck (each BinOp/UnaryOp/AugAssign
result raises at |x| >= 2**30), with one tracker. While each module loads, the
checked modules before it stand in sys.modules, so its `from fixmath import ...`
binds the checked functions; sys.modules is restored afterwards. The tracker's
largest value starts at 0 after loading. Used by
bench/core_accuracy.py and tests/test_core_range.py.
"""

import sys
from pathlib import Path

from steadytouch.rangecheck import Tracker, load_instrumented

SHARED = Path(__file__).resolve().parent.parent / "shared"
CORE_MODULES = ("fixmath", "fast_step", "skin_tau", "skin_model", "sensation_core")  # each imports only those before it


def load_core():
    """({module name: checked module}, tracker)."""
    track = Tracker()
    saved = {name: sys.modules.get(name) for name in CORE_MODULES}
    mods = {}
    try:
        for name in CORE_MODULES:
            mods[name], _ = load_instrumented(SHARED / f"{name}.py", name, track)
            sys.modules[name] = mods[name]
    finally:
        for name, m in saved.items():
            if m is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = m
    track.max_abs = 0  # count what the calls compute, not the modules' constants (NOROOT = -(2**30 - 1))
    track.where = ""
    return mods, track
