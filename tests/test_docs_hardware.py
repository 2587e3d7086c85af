"""docs/hardware.md's front-end schematic follows the code: the committed figure
names board_config's pins and the DAC's LSB, and docs/schematic.py draws exactly
the committed file (when the docs extra, schemdraw, is installed)."""

import importlib.util
import subprocess
import sys

import pytest

from conftest import FIRMWARE, ROOT

SVG = ROOT / "docs" / "img" / "front-end.svg"


def cfg():
    spec = importlib.util.spec_from_file_location("board_config_docs", FIRMWARE / "board_config.py")
    m = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(m)
    return m


def test_the_committed_schematic_names_the_configured_pins():
    c = cfg()
    text = SVG.read_text()
    for label in (f"GP{c.DAC_CS_PINS[0]} (CS0)", f"GP{c.DAC_SCK_PIN} (SPI0 SCK)", f"GP{c.DAC_MOSI_PIN} (SPI0 TX)",
                  f"GP{c.GATE_PINS[0]} (GATE0)", f"GP{26 + c.ADC_INPUTS[0]} (ADC{c.ADC_INPUTS[0]})",
                  f"{c.AMP_UA_AT_FULL / 4096:.4g} µA"):
        assert label in text, f"docs/img/front-end.svg lacks {label!r}: run docs/schematic.py"
    assert "hardware.md" in (ROOT / "docs" / "schematic.py").read_text()
    assert "img/front-end.svg" in (ROOT / "docs" / "hardware.md").read_text()


def test_the_script_draws_the_committed_figure(tmp_path):
    if importlib.util.find_spec("schemdraw") is None:
        pytest.skip("schemdraw (the docs extra) is not installed: pip install -c constraints.txt -e '.[docs]'")
    out = tmp_path / "front-end.svg"
    p = subprocess.run([sys.executable, str(ROOT / "docs" / "schematic.py"), "--out", str(out)], capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert out.read_bytes() == SVG.read_bytes(), "docs/img/front-end.svg is stale: run docs/schematic.py"
