"""``--help`` of every command, example and benchmark script works and reads well.

Each is run as ``python SCRIPT --help`` would run it (``tests/docs_commands.py``, one fresh interpreter for
all): exit code 0, a usage line, every argument with a help string, and a description or epilog written in
lines and paragraphs of its own (a list, an indented example) only under a formatter that keeps them
(``argparse.RawDescriptionHelpFormatter``), so that no lines run together. The usage examples that the help
texts give (``python -m benchmarks.x --flag``) name options their script has.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest
from docs_commands import COMMANDS, ask
from helpers import synopsis_flags

ROOT = Path(__file__).resolve().parents[2]


def scripts() -> list[str]:
    """The runnable scripts of examples/ and benchmarks/ (a module without a ``__main__`` guard is a helper)."""
    found = []
    for folder in ("examples", "benchmarks"):
        for path in sorted((ROOT / folder).glob("*.py")):
            if re.search(r"^if __name__ == .__main__.:", path.read_text(encoding="utf-8"), flags=re.MULTILINE):
                found.append(f"{folder}/{path.name}")
    return found


@pytest.fixture(scope="module")
def helps() -> dict:
    names = list(COMMANDS) + scripts()
    return dict(zip(names, ask([{"job": "help", "command": n} for n in names])))


def test_every_script_is_covered():
    names = scripts()
    assert {"examples/optimize_g2o.py", "examples/tum_slam.py", "examples/use_attention_in_your_model.py",
            "examples/ablation.py", "benchmarks/slam_pipeline.py"} <= set(names)
    assert "benchmarks/index_data.py" not in names  # a helper module, no command


@pytest.mark.parametrize("name", list(COMMANDS) + scripts())
def test_help(name, helps):
    h = helps[name]
    assert not h.get("exception"), h.get("error")
    assert h["exit_code"] == 0, f"{name} --help: exit code {h['exit_code']}"
    assert h["help"].startswith("usage: "), h["help"][:200]
    assert not h["no_help"], f"{name}: arguments without a help string: {h['no_help']}"
    assert h["raw_where_needed"], (f"{name}: its description or epilog has lines of its own (a list, an example) "
                                   "that argparse's default formatter runs together; use "
                                   "formatter_class=argparse.RawDescriptionHelpFormatter")


def test_commands_in_the_help_texts_exist(helps):
    """The usage examples of every help text (``python -m benchmarks.x --flag ...``) name options that exist."""
    found = [(c, f, name) for name, h in helps.items() for c, f in synopsis_flags(h.get("help", ""))]
    wrong = [f"{where}'s help: {c} has no option {f}" if c in helps else f"{where}'s help: no command {c}"
             for c, f, where in found if f not in (helps.get(c, {}).get("options") or [])]
    assert len(found) > 20 and not wrong, "\n".join(wrong)
