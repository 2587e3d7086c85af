# Runs under MicroPython and CPython alike: reads one case per line from stdin,
# prints the core's outputs for it. Used to prove CPython == MicroPython.
# Case: imin imax tmin tmax qmax i0 t0 rp0 x y mode rs beta cp rp...   ("" ends;
# rs beta cp: the skin model, 0 0 0 for none; an rp may be rp/lt: ltau_q16 = lt told before that update;
# a last word "T<g>": the model set with rule 7's tau gain g (log2 Q.16), so the taus told reach the tau jump)
import sys

import sensation_core as sc


def run(line):
    w = line.split()
    tau = sc.SKIN_TAU_OFF
    if w[-1].startswith("T"):
        tau = int(w[-1][1:])
        w = w[:-1]
    v = [int(x) for x in w[:14]]
    try:
        c = sc.Controller(v[0], v[1], v[2], v[3], v[4])
        c.calibrate(v[5], v[6], v[7], v[8], v[9])
        c.set_mode(v[10])
        c.set_skin(v[11], v[12], v[13], tau)
        if tau != sc.SKIN_TAU_OFF:
            c.skin.tau_checked = 1  # (rule 7's check at calibration taken as passed: the taus told reach the jump)
    except ValueError as e:
        return "E " + str(e).split("=")[0]
    out = [c.me_ua2ms, c.mq_target_fc_per_ohm, c.i_ua, c.t_us]
    for x in w[14:]:
        rp, _, lt = x.partition("/")
        if lt:
            c.ltau_q16 = int(lt)
        out.append(c.update(int(rp)))
        out.append(c.i_ua)
        out.append(c.t_us)
        out.append(c.mq_last_fc_per_ohm)
    out.append(c.model_jumps)
    out.append(c.skin.tau_jumps)
    out.append(c.skin.tau_ok)
    out.append(c.skin.tau_gain_q16)
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
