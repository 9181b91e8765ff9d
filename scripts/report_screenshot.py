"""Screenshots of a built report in a real browser (Playwright driving Chromium), to check what a reader
sees first.

    python scripts/report_screenshot.py reports/gpu/index.html --out /tmp/shots
    python scripts/report_screenshot.py reports/latest/index.html --width 1366 --height 768 --full-page

Writes ``first_screen_<W>x<H>.png`` (the first screen, what opens without scrolling) and, with
``--full-page``, ``full_page_<W>.png``; prints one JSON line of what the page holds at that size: the
navigation's links and how many of them lie outside the window or are hidden (a navigation that is cut
off), the verdict cards and how many of them start on the first screen, the page's size in bytes, and
whether the page asked for anything outside its folder.

Needs the ``report-check`` extra (``pip install playwright``) and a Chromium: Playwright's own
(``playwright install chromium``) or a system one (Debian: ``apt-get install chromium``), found at
``--chromium`` (default: $CLOUDPBF_CHROMIUM, else /usr/bin/chromium, else Playwright's).
``tests/test_report_browser.py`` runs it and is skipped where either is missing.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

SYSTEM_CHROMIUM = ("/usr/bin/chromium", "/usr/bin/chromium-browser")


def find_chromium(given: str | None = None) -> str | None:
    """The Chromium executable to drive: `given`, $CLOUDPBF_CHROMIUM, a system one, else None (Playwright's)."""
    for candidate in (given, os.environ.get("CLOUDPBF_CHROMIUM"), *SYSTEM_CHROMIUM, shutil.which("chromium")):
        if candidate and Path(candidate).is_file():
            return candidate
    return None


def inspect(page_path: Path, out: Path, width: int = 1366, height: int = 768, full_page: bool = False,
            chromium: str | None = None) -> dict:
    """Open `page_path` at width x height, write the screenshots into `out`, return what the page holds."""
    from playwright.sync_api import sync_playwright
    page_path = Path(page_path).resolve()
    out.mkdir(parents=True, exist_ok=True)
    outside = []
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=find_chromium(chromium),
                                     args=["--no-sandbox", "--disable-gpu"])
        try:
            page = browser.new_page(viewport={"width": width, "height": height})
            folder = page_path.parent.as_uri()
            page.on("request", lambda r: outside.append(r.url)
                    if not (r.url.startswith(folder) or r.url.startswith("data:")) else None)
            page.goto(page_path.as_uri(), wait_until="load")
            first = out / f"first_screen_{width}x{height}.png"
            page.screenshot(path=str(first))
            facts = page.evaluate("""([w, h]) => {
                const links = [...document.querySelectorAll('nav a')];
                const box = e => e.getBoundingClientRect();
                const cut = links.filter(a => { const b = box(a);
                    return b.right > w || b.left < 0 || b.width === 0 || b.bottom > h; });
                const cards = [...document.querySelectorAll('.card')];
                return {nav_links: links.length, nav_cut_off: cut.map(a => a.textContent),
                        nav_height: document.querySelector('nav') ? box(document.querySelector('nav')).height : 0,
                        cards: cards.map(c => c.id),
                        cards_on_first_screen: cards.filter(c => box(c).top < h).length,
                        horizontal_scroll: document.documentElement.scrollWidth > w};
            }""", [width, height])
            shots = [str(first)]
            if full_page:
                whole = out / f"full_page_{width}.png"
                page.screenshot(path=str(whole), full_page=True)
                shots.append(str(whole))
        finally:
            browser.close()
    return {**facts, "screenshots": shots, "page_bytes": page_path.stat().st_size, "outside_requests": outside}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("page", type=Path, help="the report's index.html")
    parser.add_argument("--out", type=Path, default=Path("report-screenshots"), help="folder for the screenshots")
    parser.add_argument("--width", type=int, default=1366)
    parser.add_argument("--height", type=int, default=768)
    parser.add_argument("--full-page", action="store_true", help="also the whole page at this width")
    parser.add_argument("--chromium", help="the Chromium executable (default: see the module's docstring)")
    args = parser.parse_args(argv)
    if not args.page.is_file():
        print(f"no report at {args.page} (build one: cloudpbf report --out DIR)", file=sys.stderr)
        return 2
    try:
        facts = inspect(args.page, args.out, args.width, args.height, args.full_page, args.chromium)
    except ImportError:
        print("playwright is not installed: pip install playwright (the report-check extra)", file=sys.stderr)
        return 2
    print(json.dumps(facts))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
