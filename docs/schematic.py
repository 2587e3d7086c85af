"""Draw the analog front end of one stimulator channel (docs/hardware.md) from the
code: pin numbers, the DAC's full scale and the channel's chip select come from
firmware/board_config.py, the DAC's word from firmware/dac_mcp4822.py.

    .venv/bin/python -m pip install -c constraints.txt -e '.[docs]'   # schemdraw (docs only)
    .venv/bin/python docs/schematic.py                                # -> docs/img/front-end.svg

Only the docs need schemdraw; nothing in the product imports this script."""

from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "img" / "front-end.svg"

# the front end's parts (docs/hardware.md, bill of materials): values a builder uses
FULL_SCALE_V = 10.0  # the stimulator's input voltage for AMP_UA_AT_FULL (10 mA at 1 mA/V)
RG_OHM = 10_000  # gain stage: G = 1 + RF / RG
RF_OHM = 37_400  # + a 2 kohm trimmer in series: G trimmed to 4.883 (2.048 V -> 10.00 V)
RTRIM_OHM = 2_000
GAIN = FULL_SCALE_V / 2.048  # 2.048 V (the DAC's code 4096) -> the stimulator's input at AMP_UA_AT_FULL
assert RF_OHM < (GAIN - 1) * RG_OHM < RF_OHM + RTRIM_OHM  # the trimmer reaches it
RPD_OHM = 100_000  # DAC output pull-down: 0 V when the DAC is unpowered or shut down
RS_OHM = 100  # series resistor into the stimulator's input
MON_V_PER_V = 0.1  # the stimulator's voltage monitor: 1 V per 10 V at the electrodes
MON_BOT_OHM = 10_000  # monitor divider bottom; the top follows from VMON_UV_PER_COUNT (mon_top_ohm)
ADC_UV_PER_COUNT = 3.3e6 / 4096  # the RP2040's ADC: 3.3 V reference, 12 bits


def e96(r: float) -> int:
    """The nearest E96 (1 %) resistor value."""
    import math

    dec = 10 ** math.floor(math.log10(r))
    vals = [round(10 ** (k / 96), 2) for k in range(97)]
    return int(round(min(vals, key=lambda v: abs(v * dec - r)) * dec))


def mon_top_ohm(cfg) -> int:
    """Divider top so one ADC count is VMON_UV_PER_COUNT at the electrodes."""
    ratio = cfg.VMON_UV_PER_COUNT / ADC_UV_PER_COUNT * MON_V_PER_V  # monitor volts per ADC volt
    return e96(MON_BOT_OHM * (ratio - 1))


def module(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "firmware" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def kohm(r: int) -> str:
    return f"{r / 1000:g} kΩ" if r >= 1000 else f"{r} Ω"


def draw(out: Path, ch: int = 0) -> None:
    import schemdraw
    import schemdraw.elements as elm

    cfg = module("board_config")
    dac = module("dac_mcp4822")
    gate = cfg.GATE_PINS[ch]
    cs = cfg.DAC_CS_PINS[ch // 2]
    out_ab = "A" if ch % 2 == 0 else "B"
    adc = cfg.ADC_INPUTS[ch]
    lsb_ua = cfg.AMP_UA_AT_FULL / dac.CODES

    schemdraw.use("matplotlib" if out.suffix == ".png" else "svg")
    with schemdraw.Drawing(file=str(out), show=False) as d:
        d.config(fontsize=10, unit=2)
        # Pico: right-side pins bottom to top, 1 unit apart; the DAC's three lines line up with U1
        pico = elm.Ic(pins=[
            elm.IcPin(name=f"GP{26 + adc} (ADC{adc})", side="R", anchorname="adc"),
            elm.IcPin(name=f"GP{gate} (GATE{ch})", side="R", anchorname="gate"),
            elm.IcPin(name=f"GP{cfg.DAC_MOSI_PIN} (SPI0 TX)", side="R", anchorname="mosi"),
            elm.IcPin(name=f"GP{cfg.DAC_SCK_PIN} (SPI0 SCK)", side="R", anchorname="sck"),
            elm.IcPin(name=f"GP{cs} (CS{ch // 2})", side="R", anchorname="cs"),
            elm.IcPin(name="GND", side="L", anchorname="gnd"),
            elm.IcPin(name="3V3(OUT)", side="L", anchorname="v33"),
        ], pinspacing=1.0, edgepadH=0.8, edgepadW=0.8).right().at((0, 0)).anchor("adc")
        pico.label("Raspberry Pi Pico (RP2040)", "top", fontsize=9)
        d += pico
        d += elm.Line().at(pico.gnd).left(0.4)
        d += elm.Ground()
        d += elm.Line().at(pico.v33).left(0.4)
        d += elm.Vdd().label("3V3", fontsize=8)

        # U1 MCP4822: left pins bottom to top LDAC, SDI, SCK, CS
        u1 = elm.Ic(pins=[
            elm.IcPin(name="LDAC", pin="5", side="L", anchorname="ldac", invert=True),
            elm.IcPin(name="SDI", pin="4", side="L", anchorname="sdi"),
            elm.IcPin(name="SCK", pin="3", side="L", anchorname="sck"),
            elm.IcPin(name="CS", pin="2", side="L", anchorname="cs", invert=True),
            elm.IcPin(name="VOUTB", pin="6", side="R", anchorname="vb"),
            elm.IcPin(name="VOUTA", pin="8", side="R", anchorname="va"),
            elm.IcPin(name="VDD", pin="1", side="T", anchorname="vdd"),
            elm.IcPin(name="VSS", pin="7", side="B", anchorname="vss"),
        ], pinspacing=1.0, edgepadH=0.6, edgepadW=1.8).right().at((pico.mosi[0] + 3.5, pico.mosi[1])).anchor("sdi")
        d += u1
        d += elm.Label().at((u1.vss[0], u1.vss[1] - 1.3)).label(f"U1 MCP4822 (12 bit, 2.048 V ref)\nchannel {ch}: output {out_ab}",
                                                                fontsize=8)
        d += elm.Line().at(pico.cs).to(u1.cs)
        d += elm.Line().at(pico.sck).to(u1.sck)
        d += elm.Line().at(pico.mosi).to(u1.sdi)
        d += elm.Line().at(u1.ldac).left(0.5)
        d += elm.Ground()
        d += elm.Ground().at(u1.vss)
        d += elm.Line().at(u1.vdd).up(0.5)
        d += elm.Vdd().label("3V3 (100 nF + 10 µF to GND at pin 1)", fontsize=8)

        # VOUT -> pull-down -> non-inverting gain stage (flipped: + on top, - below)
        vout = u1.va if out_ab == "A" else u1.vb
        d += elm.Line().at(vout).right(1.2)
        node = d.here
        d += elm.Dot()
        d += elm.Resistor().down(2.0).label(f"R1\n{kohm(RPD_OHM)}", loc="top", fontsize=8)
        d += elm.Ground()
        d += elm.Line().at(node).right(0.8)
        op = elm.Opamp(leads=True).right().flip().anchor("in2")
        d += op
        d += elm.Label().at((op.out[0] - 1.6, op.out[1] + 1.2)).label(f"U2a OPA2192, ±12 V\nG = {GAIN:.3f} (trimmed)", fontsize=8)
        d += elm.Line().at(op.in1).down(1.0)
        fb = d.here
        d += elm.Dot()
        d += elm.Resistor().right(op.out[0] - fb[0]).label(f"R3 {kohm(RF_OHM)} 0.1 %\n+ RV1 {kohm(RTRIM_OHM)} trim",
                                                          loc="bottom", fontsize=8)
        d += elm.Line().toy(op.out[1])
        d += elm.Resistor().at(fb).down(1.8).label(f"R2\n{kohm(RG_OHM)}\n0.1 %", loc="top", fontsize=8)
        d += elm.Ground()

        # level -> series R -> analog switch (the gate) -> stimulator input
        d += elm.Line().at(op.out).right(0.3)
        d += elm.Resistor().right(1.6).label(f"R4 {kohm(RS_OHM)}", loc="top", fontsize=8)
        lvl = d.here
        u3 = elm.Ic(pins=[
            elm.IcPin(name="S2", side="L", anchorname="s2"),
            elm.IcPin(name="S1", side="L", anchorname="s1"),
            elm.IcPin(name="D", side="R", anchorname="d"),
            elm.IcPin(name="IN", side="B", anchorname="inp"),
        ], pinspacing=1.0, edgepadH=0.5, edgepadW=0.8).right().at(lvl).anchor("s1")
        d += u3
        d += elm.Label().at((u3.s1[0] + 1.2, u3.s1[1] + 1.2)).label("U3 ADG1419\nIN high: D = S1", fontsize=8)
        d += elm.Line().at(u3.s2).left(0.4)
        d += elm.Ground()
        # the gate: under everything, up into IN
        y_gate = -3.5
        d += elm.Line().at(pico.gate).right(0.8)
        d += elm.Line().toy(y_gate)
        d += elm.Line().tox(u3.inp[0])
        d += elm.Line().toy(u3.inp[1])
        d += elm.Dot().at((u3.inp[0], y_gate + 1.0))
        d += elm.Line().right(0.6)
        d += elm.Resistor().down(1.0).label(f"R7\n{kohm(RPD_OHM)}", loc="bottom", fontsize=8)
        d += elm.Ground()  # the switch stays open while the Pico is unpowered, resetting or booting
        d += elm.Label().at((pico.gate[0] + 4.5, y_gate + 0.35)).label(
            f"gate: high for exactly T µs (PIO); U3 passes the level only then", fontsize=8)

        stim = elm.Ic(pins=[
            elm.IcPin(name="GND (input side)", side="L", anchorname="gnd"),
            elm.IcPin(name="V MON", side="L", anchorname="mon"),
            elm.IcPin(name="AMP IN", side="L", anchorname="amp"),
            elm.IcPin(name="OUT −", side="R", anchorname="om"),
            elm.IcPin(name="OUT +", side="R", anchorname="op"),
        ], pinspacing=1.2, edgepadH=0.8, edgepadW=2.5).right().at((u3.d[0] + 2.0, u3.d[1])).anchor("amp")
        d += stim
        d += elm.Label().at((stim.mon[0] + 2.2, stim.gnd[1] - 1.6)).label(
            "isolated constant-current stimulator\n(BIOPAC STMISOLA, Digitimer DS5, ...)", fontsize=8)
        d += elm.Line().at(u3.d).to(stim.amp)
        d += elm.Line().at(stim.gnd).left(0.4)
        d += elm.Ground()
        xb = stim.op[0] + 0.4  # the stimulator's isolation barrier: the electrodes are on its far side only
        d += elm.Line().at((xb, stim.op[1] + 1.5)).toy(stim.gnd[1] - 1.0).linestyle("--").color("red")
        d += elm.Label().at((xb, stim.op[1] + 1.8)).label("isolation barrier\n(in the stimulator)", fontsize=8, color="red")
        d += elm.Line().at(stim.op).right(1.0)
        d += elm.Label().label("to electrode +", loc="right", fontsize=8, halign="left")
        d += elm.Line().at(stim.om).right(1.0)
        d += elm.Label().label("to electrode −", loc="right", fontsize=8, halign="left")

        # voltage monitor -> divider -> clamp -> ADC
        y_adc = -5.2
        d += elm.Line().at(stim.mon).left(1.3)
        d += elm.Line().toy(y_adc + 2.6)
        d += elm.Resistor().toy(y_adc).label(f"R5 {kohm(mon_top_ohm(cfg))}", loc="bottom", fontsize=8)
        adc_node = d.here
        d += elm.Dot()
        d += elm.Resistor().down(1.6).label(f"R6 {kohm(MON_BOT_OHM)}", loc="bottom", fontsize=8)
        d += elm.Ground()
        d += elm.Line().at(adc_node).right(0.8)
        d += elm.Schottky().up(1.4).label("D1 BAT54\nclamp", loc="bottom", fontsize=8)
        d += elm.Vdd().label("3V3", fontsize=8)
        d += elm.Line().at(pico.adc).right(0.4)
        d += elm.Line().toy(y_adc)
        d += elm.Line().tox(adc_node[0])
        d += elm.Label().at((pico.adc[0] + 4.0, y_adc - 0.4)).label(
            f"monitor -> ADC: Rp = Vp / I_delivered, I_delivered = DAC code x {lsb_ua:.4g} µA", fontsize=8)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=OUT)
    p.add_argument("--channel", type=int, default=0)
    a = p.parse_args(argv)
    try:
        import schemdraw  # noqa: F401
    except ImportError:
        print("docs/schematic.py needs schemdraw: .venv/bin/python -m pip install -c constraints.txt -e '.[docs]'",
              file=sys.stderr)
        return 2
    a.out.parent.mkdir(parents=True, exist_ok=True)
    draw(a.out, a.channel)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
