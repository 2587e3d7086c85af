# The worked example of the paper notes, run through the shared core in
# MicroPython: I0 = 1 mA, T0 = 1000 us, Rp0 = 20 kohm, (x*, y*) = (-1.67 kohm,
# 0.186 uC). For each Rp: the next pulse (I, T) and the mQ that pulse has at
# that Rp (target 37.563 pC/ohm).
import sys

import sensation_core as sc


def main():
    c = sc.Controller(500, 10000, 100, 2000, 10000000)
    c.calibrate(1000, 1000, 20000, -1670, 186000)
    print("steadytouch %s, core on %s %s" % (sc.VERSION, sys.implementation.name, ".".join(str(v) for v in sys.implementation.version[:3])))
    print("calibration: I0 1000 uA, T0 1000 us, Rp0 20000 ohm, x* -1670 ohm, y* 186000 pC")
    print("mE = %d uA^2*ms, target mQ = %d fC/ohm" % (c.me_ua2ms, c.mq_target_fc_per_ohm))
    print("")
    print("  Rp ohm |   I uA |  T us | mQ fC/ohm | status")
    print("---------+--------+-------+-----------+-------")
    for rp in (20000, 10000, 5000, 30000, 60000, 120000, 250000):
        st = c.update(rp)
        i, t = c.i_ua, c.t_us
        if i:
            c.update(rp)  # the same skin again: mQ of the pulse just chosen
            mq = "%9d" % c.mq_last_fc_per_ohm
        else:
            mq = "        -"
        print("%8d | %6d | %5d | %s | %s" % (rp, i, t, mq, status_words(st)))


def status_words(st):
    names = (
        (sc.ST_I_MIN, "I at min"), (sc.ST_I_MAX, "I at max"), (sc.ST_T_MIN, "T at min"),
        (sc.ST_T_MAX, "T at max"), (sc.ST_Q_MAX, "charge limit"), (sc.ST_RP_LOW, "FAULT Rp low"),
        (sc.ST_RP_HIGH, "FAULT Rp high (electrode off)"), (sc.ST_Q_NONPOS, "FAULT Q<=0"),
        (sc.ST_UNCALIBRATED, "FAULT uncalibrated"),
    )
    words = [w for b, w in names if st & b]
    return ", ".join(words) if words else "ok"


main()
