"""MkDocs hook: the pages' TeX becomes MathML when the site is built.

``pymdownx.arithmatex`` (generic mode) finds ``$...$`` and ``$$...$$`` in the Markdown, docstrings
included, and leaves ``<span class="arithmatex">\\(...\\)</span>`` and
``<div class="arithmatex">\\[...\\]</div>``. This hook replaces each formula by the MathML that
``latex2mathml`` writes for it, which browsers render natively: the site needs no script and no
network for its maths. A formula that cannot be converted fails the build, with the page and the
formula, instead of showing raw TeX.
"""

import html
import re
import xml.etree.ElementTree as ET

from latex2mathml.commands import MATRICES
from latex2mathml.converter import convert
from mkdocs.exceptions import PluginError

# An inline formula takes the punctuation around it along (a line never starts with its comma).
_FORMULA = re.compile(
    r'(?P<before>[(\[]?)<(?P<tag>span|div) class="arithmatex">\s*'
    r"(?:\\\((?P<inline>.*?)\\\)|\\\[(?P<display>.*?)\\\])"
    r"\s*</(?P=tag)>(?P<after>[.,:;!?)\]]*)",
    re.DOTALL,
)
_ENVIRONMENT = re.compile(r"\\begin\{([^}]*)\}")
_MATHML = "http://www.w3.org/1998/Math/MathML"
ET.register_namespace("", _MATHML)
# latex2mathml writes \dot q, \ddot q as an overscript; marked as an accent it sits on the letter.
_FUNCTIONS = {"sin", "cos", "tan", "cot", "exp", "log", "ln", "max", "min", "sinh", "cosh", "tanh", "det"}
_CLOSING = (")", "]", "}", "|", "\u2016")
_ACCENTS = {"\u02d9", "\u00a8", "\u20db", "^", "~", "\u02c6", "\u02dc"}


def _to_mathml(tex: str, display: bool, where: str) -> str:
    for name in _ENVIRONMENT.findall(tex):
        if "\\" + name not in MATRICES:
            raise PluginError(f"{where}: the environment {name!r} has no MathML conversion: {tex!r}")
    try:
        mathml = convert(tex, display="block" if display else "inline")
    except Exception as error:  # latex2mathml's own exceptions carry no message
        raise PluginError(f"{where}: cannot convert {tex!r} to MathML ({type(error).__name__})") from error
    tree = ET.fromstring(mathml)
    leftover = [text for text in tree.itertext() if "\\" in text]
    leftover += [element.text for element in tree.iter(f"{{{_MATHML}}}mi") if element.text == "&"]
    if leftover:
        raise PluginError(f"{where}: TeX left unconverted ({leftover}) in {tex!r}")
    mo = f"{{{_MATHML}}}mo"
    for over in tree.iter(f"{{{_MATHML}}}mover"):
        if over[-1].tag == mo and over[-1].text in _ACCENTS:
            over.set("accent", "true")
    for row in tree.iter():
        previous = None
        for child in row:
            if child.tag == mo and child.text == "/":  # a quotient, not an operator: as TeX spaces it
                child.set("lspace", "0")
                child.set("rspace", "0")
            # A sign after an operator or at the start (= −mgl) is unary, not binary.
            if child.tag == mo and child.text in ("\u2212", "+") and child.get("form") is None:
                if previous is None or (previous.tag == mo and previous.text not in _CLOSING):
                    child.set("form", "prefix")
            previous = child
        # \cos\theta: TeX puts a thin space after a function's name.
        for index in reversed(range(len(row) - 1)):
            name, after = row[index], row[index + 1]
            if name.tag == f"{{{_MATHML}}}mi" and (name.text or "") in _FUNCTIONS and after.tag != mo:
                row.insert(index + 1, ET.Element(f"{{{_MATHML}}}mspace", {"width": "0.1667em"}))
    return ET.tostring(tree, encoding="unicode")


def convert_page(content: str, where: str) -> str:
    """``content`` (a page's HTML) with every arithmatex formula replaced by MathML."""

    def replace(match: re.Match[str]) -> str:
        display = match["display"] is not None
        tex = html.unescape(match["display"] if display else match["inline"]).strip()
        mathml = _to_mathml(tex, display, where)
        if display:
            return f'{match["before"]}<div class="arithmatex">{mathml}</div>{match["after"]}'
        return f'<span class="arithmatex">{match["before"]}{mathml}{match["after"]}</span>'

    content = _FORMULA.sub(replace, content)
    if re.search(r'class="arithmatex">(?![(\[]?<math)', content):
        raise PluginError(f"{where}: a formula was left as TeX")
    return content


def on_page_content(content: str, page, **kwargs) -> str:
    """MkDocs' event: a page's HTML, before the theme wraps it."""
    return convert_page(content, page.file.src_uri)
