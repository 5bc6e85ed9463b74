"""Line counts of Python files: total, docstring and code lines (comments and blank lines are the rest).

    python scripts/count_lines.py $(find quadswarm_mj -name '*.py')
"""

from __future__ import annotations

import ast
import io
import sys
import tokenize
from pathlib import Path

_SKIP = (tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT, tokenize.ENDMARKER)


def counts(path: str) -> tuple[int, int, int]:
    """(total, docstring, code) lines of one file; a docstring line never counts as code."""
    src = Path(path).read_text(encoding="utf-8")
    doc: set[int] = set()
    for node in ast.walk(ast.parse(src)):
        if isinstance(node, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(
                    first.value.value, str):
                doc.update(range(first.lineno, first.end_lineno + 1))
    code: set[int] = set()
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type not in _SKIP:
            code.update(line for line in range(tok.start[0], tok.end[0] + 1) if line not in doc)
    return src.count("\n"), len(doc), len(code)


def main(paths: list[str]) -> None:
    total = [sum(c) for c in zip(*(counts(p) for p in paths))] if paths else [0, 0, 0]
    print(f"total {total[0]} docstring {total[1]} code {total[2]}")


if __name__ == "__main__":
    main(sys.argv[1:])
