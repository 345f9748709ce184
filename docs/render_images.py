"""Regenerate the pictures of the cookbook: run each page's python blocks in order, as one script,
with docs/images/ as working directory, so that each committed PNG is exactly what its page's code
draws. Usage, from the repository root: ``python docs/render_images.py [page-stem ...]``."""

import os
import pathlib
import subprocess
import sys
import tempfile

os.environ.setdefault("MPLBACKEND", "Agg")
ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from test_readme import SCRIPTS, page_script  # noqa: E402


def main(stems):
    images = ROOT / "docs" / "images"
    images.mkdir(exist_ok=True)
    for page in SCRIPTS:
        if stems and page.stem not in stems:
            continue
        _, source = page_script(page)
        with tempfile.NamedTemporaryFile("w", suffix=".py", delete=False) as script:
            script.write(source)
        print(f"--- {page.relative_to(ROOT)}", flush=True)
        # This checkout's jaxlag first, whatever is installed.
        path = os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")])
        env = {**os.environ, "PYTHONPATH": path}
        subprocess.run([sys.executable, script.name], cwd=images, check=True, env=env)
        os.unlink(script.name)


if __name__ == "__main__":
    main(sys.argv[1:])
