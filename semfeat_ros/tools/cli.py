"""Command-line plumbing shared by the offline tools: usage and input errors as one line."""
from __future__ import annotations

import argparse


class OneLineParser(argparse.ArgumentParser):
    """argparse whose usage errors are one line (``<tool>: error: ...``) with exit status 2;
    sub-command parsers report under the tool's name too."""

    @classmethod
    def for_tool(cls, prog: str, doc: str | None) -> OneLineParser:
        """The parser of tool ``prog``: its description is the first paragraph of ``doc`` (the
        module docstring), shown as written."""
        return cls(prog=prog, description=(doc or '').split('\n\n')[0],
                   formatter_class=argparse.RawDescriptionHelpFormatter)

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f'{self.prog.split()[0]}: error: {message}\n')


def error_line(exc: BaseException) -> str:
    """An exception as one line: its text with whitespace collapsed, else its class name."""
    return ' '.join(str(exc).split()) or type(exc).__name__
