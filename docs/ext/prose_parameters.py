"""Griffe extension: nhjax's parameter entries are prose, not types.

nhjax writes a numpy-style ``Parameters`` section as ``name : what it is``, with the
text after the colon a sentence (``saveat : int (that many equally spaced times,
default 101) or 1-D array of times.``), not a type. Griffe's numpy parser reads that
text as the type (and a ", default ..." in it as the default). This extension puts the
line back, verbatim, at the head of the description and leaves the type column to
the signature's annotation.
"""

from __future__ import annotations

import re

import griffe


class ProseParameters(griffe.Extension):
    def on_function_instance(self, *, func: griffe.Function, **kwargs) -> None:
        if func.docstring is None or "----------" not in func.docstring.value:
            return
        lines = func.docstring.value.splitlines()
        for section in func.docstring.parsed:
            if section.kind is not griffe.DocstringSectionKind.parameters:
                continue
            for param in section.value:
                head = _first_line(lines, param.name)
                if head is None:
                    continue
                param.description = f"{head}\n{param.description}".strip()
                signature = func.parameters[param.name] if param.name in func.parameters else None
                param.annotation = signature.annotation if signature is not None else None
                param.value = signature.default if signature is not None else None


def _first_line(lines: list[str], name: str) -> str | None:
    """The text after ``name :`` on the entry's first line (entries may name several
    parameters: ``rtol, atol : ...``)."""
    pattern = re.compile(rf"^(?:\w+, )*{re.escape(name)}(?:, \w+)* : (.*)$")
    for line in lines:
        match = pattern.match(line)
        if match:
            return match.group(1)
    return None
