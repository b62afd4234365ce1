"""Look at the documentation as a reader does: build the site, serve it on 127.0.0.1 and
take headless-Chromium screenshots of a few pages (not part of CI).

    python tools/docs_screenshots.py [OUT_DIR] [--width 1280] [--height 2400] [--no-build]

Needs Chromium (`apt-get install chromium`; `--chromium PATH` or `$CHROMIUM` to choose
another binary). Scripts run (MathJax typesets) within `--virtual-time-budget`; the PNGs go
to OUT_DIR (default `site-screenshots/`, ignored by git). Open them and check that the math
is typeset and nothing is cut off.
"""

from __future__ import annotations

import argparse
import functools
import http.server
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# (name of the PNG, path in the site): home, a theory page, a notebook page, an API page.
PAGES = [
    ("home", ""),
    ("theory-equations", "theory/equations/"),
    ("theory-closed-forms", "theory/closed-forms/"),
    ("theory-conventions", "theory/conventions/"),
    ("theory-checks", "theory/checks/"),
    ("notebook-heavy-top", "notebooks/05_heavy_top/"),
    ("api-simulate", "api/simulate/"),
]


def find_chromium(explicit: str | None) -> str:
    for name in (explicit, os.environ.get("CHROMIUM"), "chromium", "chromium-browser"):
        if name and shutil.which(name):
            return shutil.which(name)
    sys.exit("Chromium not found: apt-get install chromium (or pass --chromium PATH)")


def build(site: Path) -> None:
    mkdocs = Path(sys.executable).with_name("mkdocs")
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    cmd = [str(mkdocs), "build", "--strict", "--quiet", "--site-dir", str(site)]
    subprocess.run(cmd, cwd=ROOT, env=env, check=True)


def serve(site: Path) -> http.server.ThreadingHTTPServer:
    handler = functools.partial(QuietHandler, directory=str(site))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


class QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


def screenshot(chromium: str, url: str, png: Path, width: int, height: int) -> None:
    with tempfile.TemporaryDirectory() as profile:
        cmd = [
            chromium,
            "--headless",
            "--no-sandbox",  # as root in a container
            "--disable-gpu",
            "--hide-scrollbars",
            "--run-all-compositor-stages-before-draw",  # draw what the scripts changed
            f"--user-data-dir={profile}",
            f"--window-size={width},{height}",
            "--virtual-time-budget=15000",  # let MathJax load and typeset
            f"--screenshot={png}",
            url,
        ]
        subprocess.run(cmd, check=True, capture_output=True, timeout=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", nargs="?", default=str(ROOT / "site-screenshots"))
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=2400)
    parser.add_argument("--no-build", action="store_true", help="use the site in ./site")
    parser.add_argument("--chromium", default=None)
    args = parser.parse_args()
    chromium = find_chromium(args.chromium)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    site = ROOT / "site"
    if not args.no_build:
        build(site)
    server = serve(site)
    base = f"http://127.0.0.1:{server.server_address[1]}/"
    try:
        for name, path in PAGES:
            png = out / f"{name}.png"
            screenshot(chromium, base + path, png, args.width, args.height)
            print(png)
    finally:
        server.shutdown()


if __name__ == "__main__":
    main()
