"""Check the built documentation in a headless browser: every page's figures readable at page
width, no table wider than the text column, no code block whose lines wrap, and the home
page's headline table.

    mkdocs build --strict --site-dir site && python tools/check_site.py site

Needs Chromium (Debian: ``apt-get install chromium``). Each page of the site is copied with a
small script that, once the page has loaded, writes what the browser laid out into the page:
the body text's font size, and per figure its file, natural width and displayed width.
``chromium --headless --dump-dom`` prints the page; this script reads those figures and the
PNGs' metadata (`mbrl_delan.figure_style`: the smallest type size in points and the figure's
width in inches) and computes each figure's smallest type as displayed:

    min_px = min_font_pt / 72 * displayed_width_px / width_in

which must be at least the body text's px. A figure without that metadata (not drawn by the
project's figure code) fails too. Exit 0 when all holds, 1 otherwise, with one line per
problem.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from urllib.parse import unquote, urlparse

from PIL import Image

log = logging.getLogger("check_site")

FONT_KEY = "mbrl_delan:min_font_pt"  # as mbrl_delan.figure_style writes them
WIDTH_KEY = "mbrl_delan:width_in"
WINDOW = "1280,900"  # a laptop's browser window
MEASURE = """
<script>
window.addEventListener("load", () => {
  const body = document.querySelector(".md-typeset p") || document.body;
  const images = [...document.querySelectorAll(".md-typeset img")].map((img) => ({
    src: img.currentSrc || img.src, natural: img.naturalWidth, shown: img.clientWidth}));
  const column = document.querySelector(".md-content__inner") || document.body;
  const tables = [...document.querySelectorAll(".md-typeset table")].map((t) => ({
    head: t.innerText.split("\\n")[0], width: t.scrollWidth, column: column.clientWidth}));
  const blocks = [...document.querySelectorAll(".md-typeset pre > code")].map((code) => {
    const style = getComputedStyle(code);
    const height = code.clientHeight - parseFloat(style.paddingTop)
      - parseFloat(style.paddingBottom);
    return {first: code.innerText.split("\\n")[0],
      lines: code.innerText.replace(/\\n$/, "").split("\\n").length,
      shown: Math.round(height / parseFloat(style.lineHeight))};
  });
  const out = document.createElement("pre");
  out.id = "site-check";
  out.textContent = JSON.stringify({
    body_px: parseFloat(getComputedStyle(body).fontSize), images, tables, blocks});
  document.body.appendChild(out);
});
</script>
"""


def measure(page: Path, chromium: str) -> dict:
    """What the browser laid out on `page` (a copy carrying `MEASURE`)."""
    cmd = [
        chromium, "--headless", "--no-sandbox", "--disable-gpu", "--allow-file-access-from-files",
        f"--window-size={WINDOW}", "--virtual-time-budget=10000", "--dump-dom", page.as_uri(),
    ]  # fmt: skip
    dom = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=True).stdout
    start = dom.index('<pre id="site-check">') + len('<pre id="site-check">')
    text = dom[start : dom.index("</pre>", start)]
    return json.loads(text.replace("&quot;", '"').replace("&amp;", "&"))


def figure_problems(page: str, seen: dict) -> list[str]:
    problems = []
    for image in seen["images"]:
        path = Path(unquote(urlparse(image["src"]).path))
        if path.suffix.lower() != ".png":
            continue
        info = Image.open(path).info
        if FONT_KEY not in info or WIDTH_KEY not in info:
            problems.append(
                f"{page}: {path.name} has no type-size metadata (not drawn by the code)"
            )
            continue
        px = float(info[FONT_KEY]) / 72 * image["shown"] / float(info[WIDTH_KEY])
        if px < seen["body_px"]:
            problems.append(
                f"{page}: {path.name}: smallest type {px:.1f} px as shown "
                f"({image['shown']} of {image['natural']} px) < body text {seen['body_px']} px"
            )
        else:
            body = seen["body_px"]
            log.info("%s: %s smallest type %.1f px (body %.1f px)", page, path.name, px, body)
    return problems


def layout_problems(page: str, seen: dict) -> list[str]:
    """Tables wider than the text column (they scroll sideways), code blocks whose lines
    wrap (a diagram's columns would be scrambled)."""
    problems = [
        f"{page}: table '{t['head'][:40]}' is {t['width']} px wide, the column {t['column']} px"
        for t in seen["tables"]
        if t["width"] > t["column"] + 1
    ]
    problems += [
        f"{page}: code block '{b['first'][:40]}' wraps ({b['lines']} lines shown as {b['shown']})"
        for b in seen["blocks"]
        if b["shown"] > b["lines"]
    ]
    return problems


def check(site: Path, chromium: str) -> list[str]:
    """Every page of the built `site`; -> the problems found."""
    problems = []
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "site"
        shutil.copytree(site, copy)
        for page in sorted(copy.rglob("index.html")):
            name = str(page.parent.relative_to(copy)) or "home"
            html = page.read_text(encoding="utf-8")
            page.write_text(html.replace("</body>", MEASURE + "</body>"), encoding="utf-8")
            seen = measure(page, chromium)
            problems += figure_problems(name, seen) + layout_problems(name, seen)
            if name == "home" and not any(
                "fraction of oracle" in t["head"] for t in seen["tables"]
            ):
                problems.append("home: no headline table (a table with 'fraction of oracle')")
    return problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("site", type=Path, help="the folder `mkdocs build` wrote")
    parser.add_argument("--chromium", default=shutil.which("chromium") or "chromium")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if not (args.site / "index.html").is_file():
        site = args.site
        log.error("%s: no index.html; build it first: mkdocs build --site-dir %s", site, site)
        return 2
    problems = check(args.site, args.chromium)
    for problem in problems:
        log.error("%s", problem)
    log.info("%d problems", len(problems))
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
