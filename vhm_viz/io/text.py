"""Text outputs: UTF-8 files written atomically, and compact JSON."""

from __future__ import annotations

import json
import re

from vhm_viz.atomic import atomic_path

__all__ = ["write_text", "json_text"]


def write_text(path, text: str) -> None:
    """Write UTF-8 text atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def json_text(obj) -> str:
    """JSON text with one point (a list of numbers) per line, floats at full precision.

    ``json.dumps(indent=...)`` writes one number per line, which makes a scene of a
    500-face cage 5,000 lines long; here innermost lists stay on one line.
    """
    text = json.dumps(obj, indent=1)
    # join the lines of every innermost list of numbers: "[\n  1.0,\n  2.0\n ]" -> "[1.0, 2.0]"
    number_list = re.compile(r"\[\s*(-?[0-9][^\[\]{}\"]*?)\s*\]")
    joined = number_list.sub(lambda m: "[" + ", ".join(re.split(r",\s*", m.group(1))) + "]", text)
    return joined + "\n"
