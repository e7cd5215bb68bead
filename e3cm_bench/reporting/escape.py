"""Text from the user (run labels, method and benchmark names, paths) as it goes into the files
the reports write: one function per format, used by every writer of that format.

A label is the user's: ``sift | ok`` must stay one cell of a Markdown table (a bare ``|`` starts
a new column, so a table's "regression" ends up under another heading or past its end), and
``<b>x</b>`` or ``[a](http://x)`` must read as those characters, not as HTML or a link.
"""

from __future__ import annotations

import html
import re

# CommonMark lets a backslash escape any ASCII punctuation. These are the characters that make
# structure out of text: a cell boundary (|), raw HTML (<: no tag starts without it, so `>` is
# left alone and the notes' arrows `a -> b` read as written), an entity (&), a link or image
# ([, ], so `![x](y)` and `[a](b)` stay text), code (`), emphasis (*), and the backslash itself.
# `_` is left as it is: GitHub's Markdown never reads an underscore inside a word as emphasis,
# and method names (`direct-efficientnet_lite0`) stay readable in the raw file.
MARKDOWN_SPECIAL = re.compile(r"([\\`*\[\]<|&])")


def markdown_text(value) -> str:
    """`value` as literal text in Markdown (a table cell, a heading, a list item): its special
    characters backslash-escaped, line breaks turned into spaces (a row is one line)."""
    return MARKDOWN_SPECIAL.sub(r"\\\1", " ".join(str(value).splitlines()))


def markdown_code(value) -> str:
    """`value` as an inline code span (a path in a heading): fenced by one backtick more than its
    longest run of backticks, so that no backtick in it ends the span; line breaks as spaces."""
    text = " ".join(str(value).splitlines())
    longest = max((len(run) for run in re.findall(r"`+", text)), default=0)
    fence = "`" * (longest + 1)
    pad = " " if text.startswith("`") or text.endswith("`") else ""
    return f"{fence}{pad}{text}{pad}{fence}"


def html_text(value) -> str:
    """`value` as literal text in HTML, in an element or a quoted attribute."""
    return html.escape(str(value), quote=True)
