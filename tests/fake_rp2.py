"""A stand-in for MicroPython's `rp2` module that turns an @rp2.asm_pio program
into pioasm text, so the very program the board runs can be assembled with
adafruit_pioasm and run in rp2040-pio-emulator."""

import sys
import types


class _Name(str):
    pass


def _arg(v):
    return v if isinstance(v, str) else str(v)


def asm_pio(**config):
    def deco(f):
        lines = []

        def emit(op):
            def ins(*args):
                lines.append("    " + op + (" " + ", ".join(_arg(a) for a in args) if args else ""))
            return ins

        names = {
            "wrap_target": lambda: lines.append(".wrap_target"),
            "wrap": lambda: lines.append(".wrap"),
            "label": lambda n: lines.append(f"{n}:"),
            "pull": emit("pull"), "push": emit("push"), "mov": emit("mov"), "set": emit("set"),
            "jmp": emit("jmp"), "nop": emit("nop"), "out": emit("out"), "in_": emit("in"),
            "block": _Name("block"), "noblock": _Name("noblock"), "x": _Name("x"), "y": _Name("y"),
            "osr": _Name("osr"), "isr": _Name("isr"), "pins": _Name("pins"), "x_dec": _Name("x--"),
            "y_dec": _Name("y--"), "not_x": _Name("!x"), "null": _Name("null"),
        }
        g = f.__globals__
        saved = {k: g[k] for k in names if k in g}
        g.update(names)
        try:
            f()
        finally:
            for k in names:
                g.pop(k, None)
            g.update(saved)
        f.pioasm = ".program " + f.__name__ + "\n" + "\n".join(lines) + "\n"
        f.config = config
        return f

    return deco


class PIO:
    OUT_LOW = 0
    OUT_HIGH = 1
    SHIFT_LEFT = 0
    SHIFT_RIGHT = 1


def install():
    mod = types.ModuleType("rp2")
    mod.asm_pio = asm_pio
    mod.PIO = PIO
    sys.modules["rp2"] = mod
    return mod
