"""examples/use_attention_in_your_model.py: --help, and all five ways run (random weights, no files)."""
from __future__ import annotations

import pytest


def test_help_and_run(load_script, capsys):
    mod = load_script("examples/use_attention_in_your_model.py")
    with pytest.raises(SystemExit) as info:
        mod.main(["--help"])
    assert info.value.code == 0
    assert "an RGB image file to describe" in capsys.readouterr().out
    mod.main(["--random-weights"])
    out = capsys.readouterr().out
    assert "1. descriptor (1, 1600)" in out  # the regional code of stage7: 5 regions x 320 channels
    assert "2. pieces (1, 1600) equal to 1.: True" in out
    assert "G by hand equal: True" in out
    assert "4. trainable parameters: ['1.weight', '1.bias']" in out
    assert "5. gradient on the layer after the tap: True" in out


def test_unreadable_image_is_a_clear_exit(load_script, tmp_path):
    mod = load_script("examples/use_attention_in_your_model.py")
    with pytest.raises(SystemExit, match="cannot read the image"):
        mod.main([str(tmp_path / "missing.jpg")])
