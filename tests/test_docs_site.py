"""The documentation site builds with ``mkdocs build --strict``: a broken link, a missing page in
the navigation, an API name that no longer resolves or a docstring mkdocstrings cannot render
fails here (the pages' code is executed by test_readme.py).

The built pages are then read as a reader sees them (one build: the checks share it): no page
points to a private module, every formula is MathML (nothing is left as TeX and no script is
loaded from the network to typeset it), and the ready models are cards with pictures large
enough to read.
"""

import os
import pathlib
import re
import subprocess
import sys
from html.parser import HTMLParser

ROOT = pathlib.Path(__file__).resolve().parents[1]

# The changelog is history: it names the modules that changes moved.
HISTORY = {"changelog/index.html"}
PRIVATE_NAMES = sorted(p.stem for p in (ROOT / "src" / "jaxlag").iterdir() if p.name.startswith("_"))
PRIVATE = re.compile(
    r"jaxlag(?:\.\w+)*\._[a-z]|jaxlag/_[a-z]|(?<![\w.])(?:" + "|".join(map(re.escape, PRIVATE_NAMES)) + r")\b"
)
# TeX a reader would see as such: \( \) \[ \] delimiters, $$, or $...$ holding a command.
TEX = re.compile(r"\\[()\[\]]|\$\$|\$[^$\n]*\\[A-Za-z]+[^$\n]*\$")


class _Page(HTMLParser):
    """The text of a page (and the attributes a reader sees: titles, alternative texts, links),
    with and without its code."""

    def __init__(self) -> None:
        super().__init__()
        self.text: list[str] = []
        self.prose: list[str] = []
        self.scripts: list[str] = []
        self.stylesheets: list[str] = []
        self._hidden = 0
        self._code = 0

    def handle_starttag(self, tag, attrs):
        attributes = dict(attrs)
        if tag == "script" and attributes.get("src"):
            self.scripts.append(attributes["src"] or "")
        if tag == "link" and attributes.get("rel") == "stylesheet":
            self.stylesheets.append(attributes.get("href") or "")
        if tag in ("script", "style"):
            self._hidden += 1
        elif tag in ("code", "pre"):
            self._code += 1
        for name in ("title", "alt", "href", "src"):
            if attributes.get(name):
                self.text.append(f" [{name}={attributes[name]}] ")

    def handle_endtag(self, tag):
        if tag in ("script", "style"):
            self._hidden -= 1
        elif tag in ("code", "pre"):
            self._code -= 1

    def handle_data(self, data):
        if not self._hidden:
            self.text.append(data)
            if not self._code:
                self.prose.append(data)


def _read(site: pathlib.Path) -> dict[str, _Page]:
    pages = {}
    for path in sorted(site.rglob("*.html")):
        page = _Page()
        page.feed(path.read_text(encoding="utf-8"))
        pages[path.relative_to(site).as_posix()] = page
    return pages


def _excerpts(pattern: re.Pattern[str], text: str) -> list[str]:
    return [text[max(m.start() - 60, 0) : m.end() + 30].replace("\n", " ") for m in pattern.finditer(text)]


def _check_no_private_modules(pages: dict[str, _Page]) -> None:
    found = {
        name: _excerpts(PRIVATE, "".join(page.text)) for name, page in pages.items() if name not in HISTORY
    }
    found = {name: hits for name, hits in found.items() if hits}
    assert not found, f"pages that point to private modules: {found}"


def _check_maths(site: pathlib.Path, pages: dict[str, _Page]) -> None:
    tex = {name: _excerpts(TEX, "".join(page.prose)) for name, page in pages.items() if name not in HISTORY}
    tex = {name: hits for name, hits in tex.items() if hits}
    assert not tex, f"TeX left in the rendered text: {tex}"
    remote = {name: page.scripts for name, page in pages.items() if any("//" in s for s in page.scripts)}
    assert not remote, f"scripts loaded from the network: {remote}"
    remote = {
        name: page.stylesheets for name, page in pages.items() if any("//" in s for s in page.stylesheets)
    }
    assert not remote, f"stylesheets (fonts) loaded from the network: {remote}"
    for path in site.rglob("*.html"):
        html = path.read_text(encoding="utf-8")
        assert "mathjax" not in html.lower(), path
        assert not re.search(r'class="arithmatex">(?![(\[]?<math)', html), path
    concepts = (site / "concepts" / "index.html").read_text(encoding="utf-8")
    assert concepts.count('<math xmlns="http://www.w3.org/1998/Math/MathML" display="block">') >= 3
    assert concepts.count('display="inline"') >= 20


def _check_ready_models(site: pathlib.Path) -> None:
    """docs/api/systems.md shows each model as a card (not a table column that breaks its name)
    with a picture drawn large enough to read (docs/render_images.py) and still small on disk."""
    import jaxlag.systems

    helpers = {"bicycle_eigenvalues", "bicycle_upright_state", "default_args"}
    models = set(jaxlag.systems.__all__) - helpers
    html = (site / "api" / "systems" / "index.html").read_text(encoding="utf-8")
    grid = html.split('<div class="grid cards models">', 1)[1].split("</div>", 1)[0]
    cards = grid.split("<li>")[1:]
    shown = {re.search(r'src="[^"]*systems-(\w+)\.png"', card)[1] for card in cards}
    assert shown == models and len(cards) == len(models), sorted(shown ^ models)
    for card in cards:
        name = re.search(r'src="[^"]*systems-(\w+)\.png"', card)[1]
        assert f"<code>{name}</code>" in card.split("<img", 1)[0], name  # the name, then the picture
    for name in models:
        png = (ROOT / "docs" / "images" / f"systems-{name}.png").read_bytes()
        width = int.from_bytes(png[16:20], "big")  # the IHDR chunk
        assert width >= 400 and len(png) < 40_000, (name, width, len(png))


def test_mkdocs_build_strict(tmp_path):
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "mkdocs",
            "build",
            "--strict",
            "-f",
            str(ROOT / "mkdocs.yml"),
            "-d",
            str(tmp_path),
        ],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    log = out.stdout + out.stderr
    assert out.returncode == 0, log[-5000:]
    assert "WARNING" not in log, log[-5000:]
    assert (tmp_path / "api" / "systems" / "index.html").exists()
    pages = _read(tmp_path)
    _check_no_private_modules(pages)
    _check_maths(tmp_path, pages)
    _check_ready_models(tmp_path)


def test_formula_that_cannot_be_converted_fails_the_build():
    sys.path.insert(0, str(ROOT / "docs" / "hooks"))
    try:
        import mathml  # docs/hooks/mathml.py
    finally:
        sys.path.pop(0)
    from mkdocs.exceptions import PluginError

    good = mathml.convert_page(r'<p>a <span class="arithmatex">\(\dot q^2\)</span>.</p>', "page.md")
    assert "<math" in good and "\\" not in good
    for tex in (r"x^", r"\unknowncommand x", r"\begin{nosuchenv} x \end{nosuchenv}"):
        html = f'<div class="arithmatex">\\[{tex}\\]</div>'
        try:
            mathml.convert_page(html, "page.md")
        except PluginError as error:
            assert "page.md" in str(error)
        else:
            raise AssertionError(f"{tex!r} was not refused")
