"""Regenerate the pictures of the cookbook: run each page's python blocks in order, as one script,
with docs/images/ as working directory, so that each committed PNG is exactly what its page's code
draws. Usage, from the repository root: ``python docs/render_images.py [page-stem ...]``.

The blocks are found as tests/test_readme.py finds them (it runs the same scripts in a temporary
directory); needs matplotlib, and SciPy for the LQR page (``pip install ".[docs]"``).
"""

import os
import pathlib
import re
import subprocess
import sys
import tempfile

ROOT = pathlib.Path(__file__).resolve().parents[1]
_FENCE = re.compile(r"^(\s*)```(\S*)\s*$")


def page_script(page):
    """The page's ```python blocks, each at its own line numbers (other lines blank)."""
    lines, language, indent = [], None, ""
    for number, line in enumerate(page.read_text(encoding="utf-8").splitlines(), start=1):
        fence = _FENCE.match(line)
        if language is None:
            if fence:
                indent, language = fence.group(1), fence.group(2)
        elif fence and not fence.group(2):
            language = None
        elif language == "python":
            lines += [""] * (number - 1 - len(lines))
            lines.append(line[len(indent) :] if line.startswith(indent) else line)
    return "\n".join(lines) + "\n"


def main(stems):
    images = ROOT / "docs" / "images"
    images.mkdir(exist_ok=True)
    # This checkout's jaxlag first, whatever is installed; no windows.
    path = os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")])
    env = {**os.environ, "PYTHONPATH": path, "MPLBACKEND": "Agg"}
    for page in sorted((ROOT / "docs" / "cookbook").glob("*.md")):
        source = page_script(page)
        if (stems and page.stem not in stems) or not source.strip():
            continue
        with tempfile.NamedTemporaryFile("w", suffix=".py", delete=False, encoding="utf-8") as script:
            script.write(source)
        print(f"--- {page.relative_to(ROOT)}", flush=True)
        try:
            subprocess.run([sys.executable, script.name], cwd=images, check=True, env=env)
        finally:
            os.unlink(script.name)


if __name__ == "__main__":
    main(sys.argv[1:])
