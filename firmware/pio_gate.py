# PIO program that gates one monophasic pulse per word pushed into its TX FIFO,
# with a bound built into the program: whatever word reaches it, the gate is
# never high longer than T_MAX_US (= board_config.HARD_T_MAX_US).
#
# The state machine runs at FREQ_HZ = 2 MHz: each microsecond of the pulse is
# two instructions, one counting the commanded width down (x) and one counting
# the bound down (y). The gate is high for exactly min(word, BOUND) + 2 us:
#   set pins 1, nop                  2 cycles  (1 us)
#   n x (jmp x--, jmp y--)          2n cycles (n us), n = min(word, BOUND)
#   jmp x-- falls / jmp y-- falls    2 cycles  (1 us), then set pins 0.
# So the CPU pushes t_us - GATE_OVERHEAD_US and a word of 0xFFFFFFFF (e.g. a
# negative number truncated by StateMachine.put) gives T_MAX_US, not 2**32 us.
# BOUND is rebuilt in the ISR before every pulse from 5-bit `set` immediates
# (SM restarts clear the ISR), with the gate still low. Between pulses the
# program waits on `pull` with the gate low.
#
# No instruction uses a delay: rp2040js (the emulated chip in tests/chip) does
# not time PIO delays, and none are needed.
import rp2

import board_config as cfg

GATE_OVERHEAD_US = 2
FREQ_HZ = 2000000  # 2 cycles per us
T_MAX_US = cfg.HARD_T_MAX_US
BOUND = T_MAX_US - GATE_OVERHEAD_US  # largest count; 15 bits at most (3 x 5-bit set)
if not 0 < BOUND < 1 << 15:
    raise ValueError("pio_gate: HARD_T_MAX_US out of the gate program's range")


@rp2.asm_pio(set_init=rp2.PIO.OUT_LOW, in_shiftdir=rp2.PIO.SHIFT_LEFT)
def gate(hi=(BOUND >> 10) & 31, mid=(BOUND >> 5) & 31, lo=BOUND & 31):
    # rp2.asm_pio replaces this function's globals while it runs: the bound
    # comes in through default arguments, evaluated when the module loads.
    wrap_target()  # noqa: F821 (names injected by rp2.asm_pio)
    pull(block)  # noqa: F821
    mov(x, osr)  # noqa: F821
    mov(isr, null)  # noqa: F821
    set(y, hi)  # noqa: F821
    in_(y, 5)  # noqa: F821
    set(y, mid)  # noqa: F821
    in_(y, 5)  # noqa: F821
    set(y, lo)  # noqa: F821
    in_(y, 5)  # noqa: F821
    mov(y, isr)  # noqa: F821  (y = BOUND)
    set(pins, 1)  # noqa: F821
    nop()  # noqa: F821
    label("count")  # noqa: F821
    jmp(x_dec, "bound")  # noqa: F821
    jmp("off")  # noqa: F821
    label("bound")  # noqa: F821
    jmp(y_dec, "count")  # noqa: F821
    label("off")  # noqa: F821
    set(pins, 0)  # noqa: F821
    wrap()  # noqa: F821
