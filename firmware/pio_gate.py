# PIO program that gates one monophasic pulse per word pushed into its TX FIFO.
# At 1 MHz (1 us per cycle) the gate is high for exactly (word + 2) cycles:
# `set pins, 1` (1), the `jmp x--` loop (word + 1), then `set pins, 0`. The CPU
# pushes t_us - GATE_OVERHEAD_US once per frame; between pulses the program
# waits on `pull` with the gate low.
import rp2

GATE_OVERHEAD_US = 2


@rp2.asm_pio(set_init=rp2.PIO.OUT_LOW)
def gate():
    wrap_target()  # noqa: F821 (names injected by rp2.asm_pio)
    pull(block)  # noqa: F821
    mov(x, osr)  # noqa: F821
    set(pins, 1)  # noqa: F821
    label("high")  # noqa: F821
    jmp(x_dec, "high")  # noqa: F821
    set(pins, 0)  # noqa: F821
    wrap()  # noqa: F821
