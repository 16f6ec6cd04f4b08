"""MkDocs hook: the formulas as MathML, written at build time, so that a browser shows them
without a script or a network connection.

``pymdownx.arithmatex`` (generic mode) leaves ``$...$`` as ``<span class="arithmatex">\\(...\\)
</span>`` and ``$$...$$`` as ``<div class="arithmatex">\\[...\\]</div>``; this hook replaces each
with the ``<math>`` element ``latex2mathml`` makes of it.
"""

from __future__ import annotations

import html
import re

from latex2mathml.converter import convert

FORMULA = re.compile(
    r'<(?P<tag>span|div) class="arithmatex">\s*\\[(\[](?P<tex>.*?)\\[)\]]\s*</(?P=tag)>', re.S
)


def on_page_content(text: str, **kwargs) -> str:
    def mathml(match: re.Match) -> str:
        display = "block" if match["tag"] == "div" else "inline"
        return convert(html.unescape(match["tex"]).strip(), display=display)

    return FORMULA.sub(mathml, text)
