# Replays op streams through sensation_core and prints what it tells the outside world
# after every op. Runs under MicroPython and CPython alike (tests/test_core_golden.py).
#
# One case per stdin line, ops separated by spaces ("" ends); a line ending in " +" goes
# on in the next one (the VM reads long cases in pieces: one huge line fills its heap):
#   L,i_min,i_max,t_min,t_max,q_max   Controller(...) (first L) or set_limits(...)
#   C,i0,t0,rp0,x,y                   calibrate(...)
#   M,mode   S,rs,beta,cp             set_mode, set_skin
#   D,i,t[,status]  X,status          delivered (no status: the status as it is, as before
#                                     firmware 0.4.0 told it), stop
#   V,vp,i                            rp_from_vp (its result is the record)
#   RP                                update(RP)  (a bare integer)
# Record after each op: status,i_ua,t_us,mq_last,rp_ohm,me,mq_target,rp0,fast_jumps,
# model_jumps,mode,calibrated; "E <message>" for a ValueError; "-" before any Controller.
# Output per case: one record per line, then a line ".".
import sys

import sensation_core as sc


def snap(c):
    return "%d,%d,%d,%d,%d,%d,%d,%d,%d,%d,%d,%d" % (
        c.status, c.i_ua, c.t_us, c.mq_last_fc_per_ohm, c.rp_ohm, c.me_ua2ms, c.mq_target_fc_per_ohm,
        c.rp0_ohm, c.fast_jumps, c.model_jumps, c.mode, 1 if c.calibrated else 0)


def run(line, out, c=None):
    """Append one record per op of `line` to `out` (a list, or a Printer); returns the
    Controller (None if none was built), which `c` continues."""
    for op in line.split():
        if op == "+":
            break
        if op[0] in "LCMSDXV":
            a = [int(w) for w in op[2:].split(",")]
            k = op[0]
        else:
            a = None
            k = "U"
        try:
            if k == "V":
                out.append(str(sc.rp_from_vp(a[0], a[1])))
                continue
            if k == "L" and c is None:
                c = sc.Controller(a[0], a[1], a[2], a[3], a[4])
            elif c is None:
                out.append("-")
                continue
            elif k == "L":
                c.set_limits(a[0], a[1], a[2], a[3], a[4])
            elif k == "C":
                c.calibrate(a[0], a[1], a[2], a[3], a[4])
            elif k == "M":
                c.set_mode(a[0])
            elif k == "S":
                c.set_skin(a[0], a[1], a[2])
            elif k == "D":
                c.delivered(a[0], a[1], a[2] if len(a) > 2 else c.status)
            elif k == "X":
                c.stop(a[0])
            else:
                c.update(int(op))
        except ValueError as e:
            out.append("E " + str(e))
            continue
        out.append(snap(c))
    return c


class Printer:
    """run()'s `out` that prints each record at once (a 10 000-op case would not fit the heap)."""

    def append(self, record):
        print(record)


def main():
    print("READY " + getattr(sc, "__file__", "?"))
    out = Printer()
    c = None
    while True:
        line = sys.stdin.readline()
        if not line or not line.strip():
            break
        c = run(line, out, c)
        if not line.rstrip().endswith(" +"):
            print(".")
            c = None


if __name__ == "__main__":
    main()
