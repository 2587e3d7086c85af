# Runs under MicroPython and CPython alike: reads one case per line from stdin,
# prints the core's outputs for it. Used to prove CPython == MicroPython.
# Case: imin imax tmin tmax qmax i0 t0 rp0 x y mode rs beta cp rp...   ("" ends;
# rs beta cp: the skin model, 0 0 0 for none)
import sys

import sensation_core as sc


def run(line):
    v = [int(w) for w in line.split()]
    try:
        c = sc.Controller(v[0], v[1], v[2], v[3], v[4])
        c.calibrate(v[5], v[6], v[7], v[8], v[9])
        c.set_mode(v[10])
        c.set_skin(v[11], v[12], v[13])
    except ValueError as e:
        return "E " + str(e).split("=")[0]
    out = [c.me_ua2ms, c.mq_target_fc_per_ohm, c.i_ua, c.t_us]
    for rp in v[14:]:
        out.append(c.update(rp))
        out.append(c.i_ua)
        out.append(c.t_us)
        out.append(c.mq_last_fc_per_ohm)
    out.append(c.model_jumps)
    return " ".join([str(x) for x in out])


def main():
    f = getattr(sc, "__file__", "?")
    print("READY " + f)
    while True:
        line = sys.stdin.readline()
        if not line or not line.strip():
            break
        print(run(line))


if __name__ == "__main__":
    main()
