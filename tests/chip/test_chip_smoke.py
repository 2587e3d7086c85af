def test_boots_and_imports(chip):
    out = chip.exec("import sys, board_rp2, stim, sensation_core\nprint(sys.implementation._machine)")
    assert "RP2040" in out
