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
ADC_INPUTS = (0, 1, 2, 3)  # ADC input (GPIO 26+n) on each voltage monitor

# ---- amplitude DAC: MCP4822 (dual 12-bit, SPI) -> op-amp stage -> stimulator amplitude input ----
# channel k = output A (k even) / B (k odd) of the chip on DAC_CS_PINS[k // 2]; docs/hardware.md
DAC_SPI_ID = const(0)
DAC_SCK_PIN = const(18)  # SPI0 SCK
DAC_MOSI_PIN = const(19)  # SPI0 TX
DAC_MISO_PIN = const(16)  # SPI0 RX: unused (the MCP4822 has no output), left unconnected
DAC_CS_PINS = (17, 20)  # one chip-select per MCP4822 (2 channels each), idle high
DAC_SPI_HZ = const(10000000)  # the MCP4822 takes up to 20 MHz
# ---- scales ----
AMP_UA_AT_FULL = const(10000)  # current at DAC code 4096 (2.048 V x the buffer's gain): LSB = 2.44 uA
ADC_SAMPLE_US = const(2)  # free-running ADC at its full 500 ksps across the pulse (96 ADC clocks a conversion)
ADC_WINDOW = const(128)  # samples kept of each capture: its last 256 us, the falling edge among them (a DMA ring)
ADC_POST_US = const(100)  # the capture runs this long past the fall: the monitor's decay (tau: stim._measure)
VMON_UV_PER_COUNT = const(27000)  # electrode uV per 12-bit ADC count (monitor gain and divider)
PIO_FREQ_HZ = const(1000000)  # 1 us per PIO cycle
WATCHDOG_MS = const(500)
