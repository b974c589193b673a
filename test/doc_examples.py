"""Code examples of the repository's doc pages, read by the tests that run them.

A page's example is a fenced ``python`` block whose first line names the file it is
(``# toy_method.py``): the test runs that text, so the page cannot drift from the code.
"""

from __future__ import annotations

import re
from pathlib import Path

DOC = Path(__file__).resolve().parents[1] / "doc"


def example(page: str, name: str) -> str:
    """The block of ``doc/<page>`` that starts ``# <name>`` (without that line)."""
    text = (DOC / page).read_text(encoding="utf-8")
    blocks = [b for b in re.findall(r"^```python\n(.*?)^```", text, re.DOTALL | re.MULTILINE)
              if b.startswith(f"# {name}\n")]
    assert len(blocks) == 1, f"doc/{page} has {len(blocks)} python blocks starting '# {name}'"
    return blocks[0].split("\n", 1)[1]
