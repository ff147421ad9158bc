"""Pages opened in a real browser: headless Chromium (/usr/bin/chromium) driven by Playwright.

A page is opened from disk (file://) with every request that is not file: aborted (the pages
must work offline); its console errors and the requests it tried are collected. Where Chromium
or the playwright package is missing, the tests that need a browser are skipped, saying why.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--no-first-run"]


@pytest.fixture(scope="module")
def browser():
    """One headless Chromium per test module."""
    if not os.path.exists(CHROMIUM):
        pytest.skip(f"{CHROMIUM} is missing: the browser tests need Debian's chromium "
                    "(apt-get install chromium)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("the playwright package is missing: pip install '.[test]'")
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        yield browser
        browser.close()


def open_page(browser, path: Path, drawn="#viewer-plot canvas", width: int = 1200):
    """(page, console errors, requests tried) of the page at ``path``, once ``drawn`` (a CSS
    selector) is there."""
    page = browser.new_page(viewport={"width": width, "height": 900})
    errors, requests = [], []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))

    def route(r):
        if r.request.url.startswith("file:"):
            r.continue_()
        else:
            requests.append(r.request.url)
            r.abort()

    page.route("**/*", route)
    page.goto(path.as_uri())
    page.wait_for_selector(drawn, timeout=30000)
    page.wait_for_timeout(500)
    return page, errors, requests
