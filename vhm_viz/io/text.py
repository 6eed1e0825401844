"""Text outputs: UTF-8 files written atomically, and compact JSON."""

from __future__ import annotations

import json
import re
import sys

from vhm_viz.atomic import atomic_path

__all__ = ["write_text", "json_text", "parse_json", "JSONTextError"]


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


class JSONTextError(ValueError):
    """Text that is not JSON a reader can take; the message says what is wrong, no file."""


def parse_json(text: str):
    """Parse JSON text; anything Python's parser refuses is one :class:`JSONTextError`.

    Besides malformed text, the parser refuses arrays nested past the interpreter's
    recursion limit (``RecursionError``) and integers of more digits than the
    interpreter converts (a bare ``ValueError`` advising ``sys.set_int_max_str_digits``);
    both are worded here for the file. A leading UTF-8 byte-order mark (Windows editors
    write one) is skipped.
    """
    try:
        return json.loads(text.removeprefix("\ufeff"))
    except json.JSONDecodeError as exc:
        raise JSONTextError(f"not valid JSON: {exc}") from None
    except RecursionError:
        raise JSONTextError("not valid JSON: nested too deeply") from None
    except ValueError:  # the interpreter's limit on an integer's digits
        limit = sys.get_int_max_str_digits()
        raise JSONTextError(f"not valid JSON: an integer of more than {limit} digits") from None
