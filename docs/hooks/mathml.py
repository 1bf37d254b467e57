"""MkDocs hook: formulas rendered to MathML at build time, so the site needs no script and no
network to show them (browsers render MathML natively).

`pymdownx.arithmatex` (generic mode) leaves `\\(...\\)` and `\\[...\\]` in
`<span class="arithmatex">` / `<div class="arithmatex">`; each is replaced by the MathML of
latex2mathml. A formula it cannot convert fails the build, naming the page and the formula.
"""

import html
import re

from latex2mathml.converter import convert

_MATH = re.compile(
    r'<(span|div) class="arithmatex">\s*(\\\(|\\\[)(.*?)(\\\)|\\\])\s*</\1>', re.DOTALL)


def on_page_content(content, page, **kwargs):
    def render(m):
        tag, opening, tex = m.group(1), m.group(2), html.unescape(m.group(3))
        display = "block" if opening == "\\[" else "inline"
        try:
            mathml = convert(tex, display=display)
        except Exception as err:
            raise ValueError(f"{page.file.src_path}: cannot render {tex!r}: {err}") from err
        return f'<{tag} class="arithmatex">{mathml}</{tag}>'

    return _MATH.sub(render, content)
