"""Open every page of the built documentation in a real browser and check it (``make docs-check``).

    python docs/check_site.py [docs/_build/html]

Each page is loaded in headless Chromium (the system's, ``/usr/bin/chromium``, driven by
Playwright: no browser is downloaded) and photographed whole into ``docs/_build/screenshots``.
A page fails on a console error or an uncaught exception, a resource that does not load, an
image that does not render, or an internal link to a page or an anchor that does not exist.
Every problem is one line; the exit status is the number of pages with problems (0: all good).
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path
from urllib.parse import unquote, urlsplit

CHROMIUM = ("/usr/bin/chromium", "/usr/bin/chromium-browser")
# MathJax typesets after the load event: wait for it, so the screenshot shows the formulas
TYPESET = "() => window.MathJax?.startup?.promise ?? null"
# what a page reports of itself once loaded: images that did not render, local links, its ids
SURVEY = """() => ({
  broken: Array.from(document.images).filter(i => !i.complete || i.naturalWidth === 0).map(i => i.src),
  links: Array.from(document.querySelectorAll('a[href]')).map(a => a.href).filter(h => h.startsWith('file:')),
  ids: Array.from(document.querySelectorAll('[id]')).map(e => e.id),
})"""


def browser_path() -> str:
    """The system's Chromium, or a one-line exit naming how to install it."""
    for candidate in (*CHROMIUM, shutil.which("chromium") or ""):
        if candidate and Path(candidate).is_file():
            return candidate
    raise SystemExit("docs-check: no Chromium found (Debian: apt-get install chromium)")


def pages_of(site: Path) -> list[Path]:
    """The site's pages: its HTML files but the theme's template fragments among the assets."""
    return sorted(p for p in site.rglob("*.html") if "_static" not in p.relative_to(site).parts)


def check(site: Path, shots: Path) -> dict[str, list[str]]:
    """Problems by page (relative path), every page visited once."""
    from playwright.sync_api import sync_playwright

    pages = pages_of(site)
    problems: dict[str, list[str]] = {}
    ids: dict[Path, set[str]] = {}
    links: list[tuple[str, str]] = []
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=browser_path(), args=["--no-sandbox"])
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        seen: list[str] = []
        page.on("console", lambda m: seen.append(f"console {m.type}: {m.text}") if m.type == "error" else None)
        page.on("pageerror", lambda e: seen.append(f"uncaught: {e}"))
        page.on("requestfailed", lambda r: seen.append(f"not loaded: {r.url} ({r.failure})"))
        for path in pages:
            name = path.relative_to(site).as_posix()
            seen.clear()
            page.goto(path.resolve().as_uri(), wait_until="load")
            page.evaluate(TYPESET)
            survey = page.evaluate(SURVEY)
            shot = shots / name.replace(".html", ".png")
            shot.parent.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(shot), full_page=True)
            found = seen + [f"image not rendered: {src}" for src in survey["broken"]]
            if found:
                problems[name] = found
            ids[path.resolve()] = set(survey["ids"])
            links += [(name, href) for href in survey["links"]]
        browser.close()
    for name, href in links:
        parts = urlsplit(href)
        target = Path(unquote(parts.path))
        if not target.exists():
            problems.setdefault(name, []).append(f"link to a missing file: {href}")
        elif parts.fragment and target.suffix == ".html" and unquote(parts.fragment) not in ids.get(target, set()):
            problems.setdefault(name, []).append(f"link to a missing anchor: {href}")
    return problems


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("site", nargs="?", default="docs/_build/html", help="the built site")
    args = parser.parse_args()
    site = Path(args.site)
    if not (site / "index.html").is_file():
        raise SystemExit(f"docs-check: no built site at '{site}' (make docs first)")
    shots = site.parent / "screenshots"
    problems = check(site, shots)
    for name, found in problems.items():
        for problem in found:
            print(f"{name}: {problem}")
    count = len(pages_of(site))
    print(f"docs-check: {count} pages, {len(problems)} with problems; screenshots in {shots}")
    return min(len(problems), 100)


if __name__ == "__main__":
    sys.exit(main())
