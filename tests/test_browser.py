"""The matrix report and the documentation site's home page, opened in headless Chromium (Debian's package; .ci/run
installs it where it is missing): no console error, no broken image, nothing wider than the window. The same
checks as ``python scripts/browser_check.py --screenshots docs/screenshots``, which refreshes the screenshots."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest
from needs import missing, require

ROOT = Path(__file__).resolve().parent.parent

pytestmark = [pytest.mark.slow, pytest.mark.integration]


def browser_check():
    spec = importlib.util.spec_from_file_location("browser_check", ROOT / "scripts" / "browser_check.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["browser_check"] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def checker():
    module = browser_check()
    browser = module.chromium()
    if browser is None:
        missing("no chromium on PATH (Debian: apt-get install chromium)")
    return module, browser


def test_the_matrix_report_loads_cleanly_in_chromium(checker, tmp_path):
    module, browser = checker
    page = module.build_report(tmp_path / "matrix")
    with module.served(page.parent) as base:
        check = module.check_page(browser, page, base + page.name)
    assert check.problems() == [], check
    assert check.images >= 5 and check.scroll_width_px <= module.WINDOW_PX[0]


def test_the_docs_home_page_loads_cleanly_in_chromium(checker, tmp_path):
    require("mkdocs")
    module, browser = checker
    site = module.build_site(tmp_path / "site")
    with module.served(site) as base:
        check = module.check_page(browser, site / "index.html", base + "index.html")
    assert check.problems() == [], check


def test_the_check_finds_a_broken_image_an_error_and_a_page_too_wide(checker, tmp_path):
    module, browser = checker
    page = tmp_path / "bad.html"
    page.write_text(
        "<!DOCTYPE html><html><head><title>bad</title></head><body>"
        '<img src="missing.png"><div style="width: 3000px">wide</div>'
        "<script>undefinedFunction();</script></body></html>"
    )
    with module.served(tmp_path) as base:
        problems = module.check_page(browser, page, base + "bad.html").problems()
    assert any(p.startswith("broken image: missing.png") for p in problems), problems
    assert any("undefinedFunction" in p for p in problems), problems
    assert any("3000 px wide" in p or "px wide in a" in p for p in problems), problems
