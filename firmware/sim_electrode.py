# The simulated electrode-skin interface and its disturbance scenarios.
# Pure Python (floats): runs in the MicroPython VM as the simulated board's
# "hardware". Model, defaults and their sources: docs/simulation.md.
import math


class Electrode:
    """One electrode pair: Rs + (Rp_skin || Cp) under a constant-current pulse.

    Units: I mA, T us, R kohm, C nF (tau in us = kohm * nF), area cm^2.
    """

    def __init__(self, area_cm2=5.6, rs_kohm=0.5, rho_ref=180.0, j_ref=0.2, beta=0.55,
                 c_nf_cm2=2.5, alpha=1.0):
        self.area0 = area_cm2
        self.rs = rs_kohm
        self.rho_ref = rho_ref
        self.j_ref = j_ref
        self.beta = beta
        self.c = c_nf_cm2
        self.alpha = alpha
        self.contact = 1.0  # fraction of the area in contact (1 - peeled fraction)
        self.h = 1.0  # hydration factor: 1 dry, lower when wet
        self.rho = 0.0  # skin resistivity (kohm cm^2); 0 = no pulse yet
        self.rp_skin = 0.0
        self.tau = 0.0

    def step_hydration(self, h_target, tau_s, dt_s):
        if tau_s <= 0:
            self.h = h_target
        else:
            self.h += (h_target - self.h) * (1.0 - math.exp(-dt_s / tau_s))

    def pulse(self, i_ua):
        """Set rp_skin (kohm) and tau (us) for a pulse of i_ua; False if off."""
        a = self.area0 * self.contact
        if a <= 1e-6 or i_ua <= 0:
            return False
        j = i_ua / 1000.0 / a
        rho_eq = self.h * self.rho_ref * (j / self.j_ref) ** (-self.beta)
        if self.rho <= 0.0:
            self.rho = rho_eq
        else:
            self.rho += self.alpha * (rho_eq - self.rho)
        self.rp_skin = self.rho / a
        self.tau = self.rp_skin * self.c * a
        return True

    def rp_kohm(self, i_ua, t_us):
        """Rp = Vp/I at the end of a pulse (advances the memory like a pulse)."""
        if not self.pulse(i_ua):
            return float("inf")
        return self.rs + self.rp_skin * (1.0 - math.exp(-t_us / self.tau))


class Resistor:
    """A dummy load in place of an electrode pair (`steadytouch selftest --load-ohm`):
    the same interface as Electrode, a pure resistance whatever the scenario does."""

    def __init__(self, r_ohm):
        self.rs = r_ohm / 1000.0  # kohm
        self.rp_skin = 0.0
        self.tau = 1.0
        self.contact = 1.0
        self.h = 1.0

    def step_hydration(self, h_target, tau_s, dt_s):
        pass

    def pulse(self, i_ua):
        return i_ua > 0

    def rp_kohm(self, i_ua, t_us):
        return self.rs if i_ua > 0 else float("inf")


class Scenario:
    """Contact and hydration over time, from keyframes.

    keys: list of (t_s, contact, h_target, tau_s). Contact is interpolated
    linearly between keyframes; hydration relaxes towards h_target with time
    constant tau_s (0: follows at once; with `interp_h` it is interpolated too).
    """

    def __init__(self, name, keys, duration_s, interp_h=False):
        if not keys or keys[0][0] != 0:
            raise ValueError("scenario %s: the first keyframe must be at time 0" % name)
        self.name = name
        self.keys = keys
        self.duration_s = duration_s
        self.interp_h = interp_h
        self._k = 0

    def at(self, t_s):
        """(contact, h_target, tau_s) at time t_s (calls must not go back in time)."""
        keys = self.keys
        k = self._k
        while k + 1 < len(keys) and keys[k + 1][0] <= t_s:
            k += 1
        self._k = k
        a = keys[k]
        if k + 1 < len(keys):
            b = keys[k + 1]
            f = (t_s - a[0]) / (b[0] - a[0])
            contact = a[1] + (b[1] - a[1]) * f
            h = a[2] + (b[2] - a[2]) * f if self.interp_h else a[2]
            return contact, h, a[3]
        return a[1], a[2], a[3]


def _peel():
    k = [(0.0, 1.0, 1.0, 0.0)]
    t = 5.0
    for contact in (0.75, 0.5, 0.25):
        k.append((t, k[-1][1], 1.0, 0.0))
        k.append((t + 0.5, contact, 1.0, 0.0))  # peeled within half a second
        t += 5.5  # then a 5 s pause
    k.append((t, 0.25, 1.0, 0.0))
    k.append((t + 0.5, 1.0, 1.0, 0.0))  # pressed back on
    return Scenario("peel", k, t + 6.0)


BUILTIN = {
    "steady": lambda: Scenario("steady", [(0.0, 1.0, 1.0, 0.0)], 10.0),
    "peel": _peel,
    "gel": lambda: Scenario("gel", [(0.0, 1.0, 1.0, 0.0), (5.0, 1.0, 0.3, 1.0), (20.0, 1.0, 0.7, 2.0)], 35.0),
    "gel-step": lambda: Scenario("gel-step", [(0.0, 1.0, 1.0, 0.0), (2.0, 1.0, 0.3, 0.0)], 6.0),
    "exercise": lambda: Scenario(
        "exercise", [(0.0, 1.0, 1.0, 0.0), (30.0, 1.0, 0.4, 120.0), (330.0, 1.0, 1.0, 480.0)], 930.0
    ),
    "off": lambda: Scenario("off", [(0.0, 1.0, 1.0, 0.0), (5.0, 1.0, 1.0, 0.0), (5.02, 0.0, 1.0, 0.0)], 8.0),
}
NAMES = ("steady", "peel", "gel", "gel-step", "exercise", "off")


def load_csv(path):
    """A scenario from a CSV file with the header `time_s,contact,hydration`.

    Rows in increasing time from 0; contact 0..1 (0 = electrode off), hydration
    0.05..2 (1 = dry skin). Both are interpolated linearly. ValueError names
    the line on any bad row.
    """
    keys = []
    with open(path) as f:
        header = f.readline().strip().replace(" ", "")
        if header != "time_s,contact,hydration":
            raise ValueError("%s line 1: header must be time_s,contact,hydration" % path)
        n = 1
        for line in f:
            n += 1
            line = line.strip()
            if not line or line[0] == "#":
                continue
            parts = line.split(",")
            if len(parts) != 3:
                raise ValueError("%s line %d: expected 3 columns, got %d" % (path, n, len(parts)))
            try:
                t, c, h = float(parts[0]), float(parts[1]), float(parts[2])
            except ValueError:
                raise ValueError("%s line %d: not a number" % (path, n))
            if keys and t <= keys[-1][0]:
                raise ValueError("%s line %d: time must increase" % (path, n))
            if not keys and t != 0:
                raise ValueError("%s line %d: the first row must be at time 0" % (path, n))
            if not 0.0 <= c <= 1.0:
                raise ValueError("%s line %d: contact %g out of range [0, 1]" % (path, n, c))
            if not 0.05 <= h <= 2.0:
                raise ValueError("%s line %d: hydration %g out of range [0.05, 2]" % (path, n, h))
            keys.append((t, c, h, 0.0))
    if not keys:
        raise ValueError("%s: no rows" % path)
    name = path.split("/")[-1]
    return Scenario(name, keys, max(keys[-1][0], 1.0), interp_h=True)


def scenario(name_or_path):
    if name_or_path in BUILTIN:
        return BUILTIN[name_or_path]()
    if name_or_path.endswith(".csv"):
        return load_csv(name_or_path)
    raise ValueError("unknown scenario %r: use one of %s or a .csv file" % (name_or_path, ", ".join(NAMES)))
