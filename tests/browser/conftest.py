"""The browser tier's fixtures: headless chromium once per test module, and pages of the app on it
(tests/support/browser.py's Page), closed after each test."""

from __future__ import annotations

import pytest

from tests.conftest import missing
from tests.support.browser import CHROMIUM, CHROMIUM_ARGS, Page, sync_api
from tests.support.paths import REPO


@pytest.fixture(scope="module")
def chromium():
    """Headless chromium, once per test module."""
    if not CHROMIUM.exists():
        missing(f"no chromium at {CHROMIUM}: apt-get install chromium (scripts/setup.sh)")
    if not (REPO / "client_web" / "node_modules" / "three").is_dir():
        pytest.fail("client_web/node_modules is missing: `npm ci` in client_web (scripts/setup.sh)")
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        yield browser
        browser.close()


@pytest.fixture
def open_page(chromium, demo_ready):
    """open_page(server, path="/", init=None, **context) -> Page; closed after the test.
    init(context) runs before the page loads (e.g. tests/support/webxr_device.install)."""
    pages = []

    def open_(server, path: str = "/", init=None, **context) -> Page:
        page = Page(chromium, server, path, init, **context)
        pages.append(page)
        return page

    yield open_
    for page in pages:
        page.close()
