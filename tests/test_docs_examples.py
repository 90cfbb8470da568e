"""The ```python examples of docs/api.md run as written, in order, in an empty folder."""
from __future__ import annotations

import re

import pytest
from conftest import ROOT

API_PAGE = ROOT / "docs/api.md"


def python_blocks(markdown: str) -> list[str]:
    """The bodies of the ```python fenced blocks of ``markdown``, in order."""
    return re.findall(r"^```python\n(.*?)^```", markdown, flags=re.DOTALL | re.MULTILINE)


def test_python_blocks_are_found_exactly():
    page = "text\n```python\na = 1\n```\n```text\nnot python\n```\n```python\nb = 2\nc = 3\n```\n"
    assert python_blocks(page) == ["a = 1\n", "b = 2\nc = 3\n"]
    assert python_blocks("no code") == []


def test_api_page_examples_run(tmp_path, monkeypatch, shared):
    blocks = python_blocks(API_PAGE.read_text())
    assert len(blocks) >= 5, "docs/api.md lost its examples"
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "docs_api_example"}
    for number, block in enumerate(blocks, 1):
        try:
            exec(compile(block, f"docs/api.md example {number}", "exec"), namespace)  # noqa: S102 - the docs' own code
        except Exception as exc:  # noqa: BLE001 - name the example that failed, with its code
            pytest.fail(f"docs/api.md example {number} failed: {exc!r}\n{block}")
    assert (tmp_path / "out/sfm/model").is_dir()
