"""Every ```python block of README.md and of the pages under docs/ runs, on its own, in a fresh
namespace, with no preamble; a cookbook page (docs/cookbook/) runs as one script: its blocks in
order, in one namespace, in a fresh working directory (the figures they save land there).

So the README cannot drift from the code: a renamed function, a changed signature or a snippet that
relies on names defined in another block fails here. Each block is one test whose id is the heading
above it and the block's index in the file. Blocks that are not meant to run (signatures, shell
commands, equations) are fenced as ```text, ```bash or plain ```.

A block must switch on float64 itself (``jax.config.update("jax_enable_x64", True)``), as a user
copying it into a fresh interpreter would: the test switches x64 off before running each block (and
restores it afterwards) so that a block relying on the test suite's ``conftest.py`` is caught.
"""

import os
import pathlib
import re
import subprocess
import sys

os.environ.setdefault("MPLBACKEND", "Agg")  # before anything imports pyplot: no windows, no display

import jax
import pytest

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"
_FENCE = re.compile(r"^(\s*)```(\S*)\s*$")


def python_blocks(text):
    """``(heading, index, first_line, source)`` for each ```python block, in order of appearance.

    ``heading`` is the nearest Markdown heading above the block, ``index`` counts the python blocks
    of the whole file from 0 and ``first_line`` is the 1-based line of the block's first code line.
    """
    blocks, heading, language, start, body, indent = [], "top", None, 0, [], ""
    for number, line in enumerate(text.splitlines(), start=1):
        fence = _FENCE.match(line)
        if language is None:
            if fence:
                indent, language, start, body = fence.group(1), fence.group(2), number + 1, []
            elif line.startswith("#"):
                heading = line.lstrip("#").strip()
        elif fence and not fence.group(2):
            if language == "python":
                blocks.append((heading, len(blocks), start, "\n".join(body) + "\n"))
            language = None
        else:  # a fence indented inside a list item: its lines carry the same indentation
            body.append(line[len(indent) :] if line.startswith(indent) else line)
    assert language is None, f"README.md: unclosed code fence opened at line {start - 1}"
    return blocks


def _test_id(heading, index):
    slug = re.sub(r"[^0-9A-Za-z]+", "-", heading).strip("-").lower()
    return f"{index:02d}-{slug}"


BLOCKS = python_blocks(README.read_text(encoding="utf-8"))
DOCS = sorted((README.parent / "docs").rglob("*.md"))
COOKBOOK = README.parent / "docs" / "cookbook"
SCRIPTS = [page for page in DOCS if page.parent == COOKBOOK and python_blocks(page.read_text("utf-8"))]
DOC_BLOCKS = [
    (page, *block) for page in DOCS if page not in SCRIPTS for block in python_blocks(page.read_text("utf-8"))
]


def page_script(page):
    """``(first_line, source)`` of a cookbook page: its python blocks in order, each at its own line
    numbers (the lines between blocks are blank), so that tracebacks point into the page."""
    blocks = python_blocks(page.read_text("utf-8"))
    lines = []
    for _, _, first_line, source in blocks:
        lines += [""] * (first_line - 1 - len(lines)) + source.splitlines()
    return blocks[0][2], "\n".join(lines[blocks[0][2] - 1 :]) + "\n"


def test_the_readme_has_python_blocks():
    text = README.read_text(encoding="utf-8")
    opened = sum(1 for line in text.splitlines() if line.strip() == "```python")
    assert len(BLOCKS) == opened >= 1, [b[0] for b in BLOCKS]


@pytest.fixture
def x64_off():
    """Run with x64 off so that the block has to enable it; restore the suite's setting afterwards."""
    previous = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", False)
    try:
        yield
    finally:
        jax.config.update("jax_enable_x64", previous)


@pytest.mark.parametrize(
    "heading, index, first_line, source", BLOCKS, ids=[_test_id(b[0], b[1]) for b in BLOCKS]
)
def test_readme_block_runs(heading, index, first_line, source, x64_off, tmp_path):
    _run_block(README, heading, index, first_line, source, tmp_path)


@pytest.mark.parametrize(
    "page, heading, index, first_line, source",
    DOC_BLOCKS,
    ids=[f"{b[0].stem}-{_test_id(b[1], b[2])}" for b in DOC_BLOCKS],
)
def test_docs_block_runs(page, heading, index, first_line, source, x64_off, tmp_path):
    _run_block(page, heading, index, first_line, source, tmp_path)


@pytest.mark.parametrize("page", SCRIPTS, ids=[page.stem for page in SCRIPTS])
def test_cookbook_page_runs(page, x64_off, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # plt.savefig("name.png") writes here
    first_line, source = page_script(page)
    _run_block(page, page.stem, 0, first_line, source, tmp_path)
    saved = source.count("plt.savefig(")
    assert len(list(tmp_path.glob("*.png"))) >= saved >= 1, f"{page.name}: saves no figure"


def test_docs_pages_exist():
    assert {p.stem for p in DOCS} >= {"compile-time", "changelog", "index", "concepts"}
    assert len(SCRIPTS) >= 10, [page.stem for page in SCRIPTS]


def _run_block(path, heading, index, first_line, source, tmp_path):
    if "jax." in source:
        assert 'jax.config.update("jax_enable_x64", True)' in source, (
            f"{path.name} line {first_line} ({heading!r}): the block uses JAX but does not enable x64 itself"
        )
    if "enable_compilation_cache" in source or "os.environ[" in source:
        # It changes JAX's configuration for the whole process, or sets an environment variable
        # read at import: run it in its own process, with a cache directory of its own.
        env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path)}
        out = subprocess.run(
            [sys.executable, "-c", source], env=env, capture_output=True, text=True, timeout=600, cwd=tmp_path
        )
        assert out.returncode == 0, f"{path.name} line {first_line}:\n{out.stderr[-3000:]}"
        return
    # Line numbers in a traceback point into the page.
    code = compile("\n" * (first_line - 1) + source, str(path), "exec")
    namespace = {"__name__": f"readme_block_{index}"}
    try:
        # A user's script runs with JAX's default ("standard") dtype promotion, not the suite's
        # strict one: the pages show code as users write it (0.1 * jnp.arange(5)).
        with jax.numpy_dtype_promotion("standard"):
            exec(code, namespace)
    finally:
        if "matplotlib.pyplot" in sys.modules:
            import matplotlib.pyplot as plt

            plt.close("all")
