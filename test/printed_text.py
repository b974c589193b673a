"""What a printed line's parentheses must be: closed, none nested to a '))'.

A clause in parentheses inside another (``noise as stated (..., gyro x1 +- 0.004 (its
samples))``) reads as a stutter; the lines say such a clause with a comma or a colon.
Read by ``test_lint.py`` (the report printers' lines) and the ``cli`` fixture (every line a
command the tests run prints).
"""

from __future__ import annotations


def parentheses_problem(line: str) -> str | None:
    """What is wrong with ``line``'s parentheses (``None``: nothing)."""
    if "))" in line:
        return "'))': a parenthesis closed at another's end"
    depth = 0
    for ch in line:
        depth += (ch == "(") - (ch == ")")
        if depth < 0:
            return "a ')' that closes nothing"
    return f"{depth} '(' never closed" if depth else None


def parentheses_problems(lines) -> list[str]:
    """``"problem: line"`` for every line of ``lines`` (text lines) with a problem."""
    out = []
    for text in lines:
        for line in str(text).splitlines():
            why = parentheses_problem(line)
            if why:
                out.append(f"{why}: {line}")
    return out
