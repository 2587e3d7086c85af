# Board configuration of the rp2 stimulator board: pins, scales and HARD LIMITS.
# Documented in docs/hardware.md. Hard limits are read once at boot; no host
# command can raise them (commands may only set soft limits inside them).
try:
    from micropython import const
except ImportError:

    def const(x):
        return x


BOARD_NAME = "pico-stmisola"

# ---- hard limits (safety) ----
HARD_I_MAX_UA = const(10000)  # 10 mA: never commanded above this
HARD_T_MAX_US = const(8000)  # longest pulse (a peeling electrode needs several ms)
HARD_Q_MAX_PC = const(10000000)  # 10 uC per phase
COMPLIANCE_MV = const(100000)  # stimulator compliance voltage (100 V)
ELECTRODE_OFF_PERMILLE = const(950)  # Vp >= 95 % of compliance: electrode off

# ---- defaults ----
N_CHANNELS = const(2)  # 1..4 (the Pico has 3 free ADC inputs; a 4th needs GPIO29 or a mux)
RATE_HZ = const(50)  # 10..100
I_MIN_UA = const(500)  # sensation floor (paper, Discussion)
T_MIN_US = const(100)  # sensation floor (paper, Discussion)

# ---- pins, one entry per channel ----
GATE_PINS = (2, 3, 4, 5)  # PIO-driven gate (trigger) input of each stimulator
AMP_PWM_PINS = (6, 7, 8, 9)  # filtered PWM -> amplitude input of each stimulator
ADC_INPUTS = (0, 1, 2, 3)  # ADC input (GPIO 26+n) on each voltage monitor

# ---- scales ----
AMP_PWM_FREQ_HZ = const(200000)
AMP_UA_AT_FULL = const(10000)  # 100 % PWM duty = this current (stimulator range setting)
ADC_SAMPLE_US = const(10)  # free-running ADC at 100 ksps during the pulse
VMON_UV_PER_COUNT = const(27000)  # electrode uV per 12-bit ADC count (monitor gain and divider)
PIO_FREQ_HZ = const(1000000)  # 1 us per PIO cycle
WATCHDOG_MS = const(500)
