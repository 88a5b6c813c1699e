"""Pages looked at in a real browser (headless Chromium, Debian's package): console errors, broken images, and a
page wider than the window, plus screenshots.

    python scripts/browser_check.py --screenshots docs/screenshots   # rebuild both pages, check them, screenshot

builds the documentation site (mkdocs --strict) and a matrix report of synthetic results (the report test's
fixture: real scorer, real plots), serves each over HTTP on loopback (file:// would refuse the site's search
worker), checks them and writes ``docs-index.png`` and ``matrix-report.png``. ``tests/test_browser.py`` runs the
same checks.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import http.server
import json
import re
import shutil
import subprocess
import sys
import tempfile
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
WINDOW_PX = (1280, 900)
CHROMIUM_TIMEOUT_S = 90

# Put first in <head>: records uncaught errors and console.error calls from the start, then, once the page has
# loaded, writes what it found into the DOM for --dump-dom to carry out.
PROBE = """<script>
(function () {
  var errors = [];
  window.addEventListener("error", function (event) {
    errors.push(event.message || ("failed to load " + (event.target && (event.target.src || event.target.href))));
  }, true);
  var original = console.error;
  console.error = function () {
    errors.push(Array.prototype.join.call(arguments, " "));
    original.apply(console, arguments);
  };
  window.addEventListener("load", function () {
    setTimeout(function () {
      var broken = Array.prototype.filter.call(document.images, function (img) {
        return !img.complete || img.naturalWidth === 0;
      }).map(function (img) { return img.getAttribute("src").slice(0, 80); });
      var report = {errors: errors, broken_images: broken, images: document.images.length,
                    scroll_width_px: document.documentElement.scrollWidth, window_width_px: window.innerWidth};
      var pre = document.createElement("pre");
      pre.id = "browser-probe";
      pre.textContent = JSON.stringify(report);
      document.body.appendChild(pre);
    }, 500);
  });
})();
</script>"""


@dataclass(frozen=True)
class PageCheck:
    url: str
    errors: list[str]
    broken_images: list[str]
    images: int
    scroll_width_px: int
    window_width_px: int

    def problems(self) -> list[str]:
        found = [f"console error: {error}" for error in self.errors]
        found += [f"broken image: {source}" for source in self.broken_images]
        if self.scroll_width_px > self.window_width_px:
            found.append(f"the page is {self.scroll_width_px} px wide in a {self.window_width_px} px window")
        return found


def chromium() -> str | None:
    return next((path for name in ("chromium", "chromium-browser") if (path := shutil.which(name))), None)


def _flags(browser: str) -> list[str]:
    width, height = WINDOW_PX
    # --no-sandbox: CI runs as root, where Chromium's sandbox refuses to start.
    return [browser, "--headless=new", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
            f"--window-size={width},{height}", "--virtual-time-budget=8000"]  # fmt: skip


def check_page(browser: str, page: Path, url: str) -> PageCheck:
    """Inject the probe into ``page`` (the served file), load ``url`` and read back what the probe found."""
    text = page.read_text()
    page.write_text(re.sub(r"<head[^>]*>", lambda m: m.group(0) + PROBE, text, count=1))
    done = subprocess.run(
        [*_flags(browser), "--dump-dom", url], capture_output=True, text=True, timeout=CHROMIUM_TIMEOUT_S
    )
    found = re.search(r'<pre id="browser-probe">(.*?)</pre>', done.stdout, re.S)
    if found is None:
        raise RuntimeError(f"{url}: the probe did not report (chromium exit {done.returncode}): {done.stderr[-400:]}")
    import html

    return PageCheck(url=url, **json.loads(html.unescape(found.group(1))))


def screenshot(browser: str, url: str, output: Path, *, height_px: int = 1600) -> None:
    output.parent.mkdir(parents=True, exist_ok=True)
    flags = [flag for flag in _flags(browser) if not flag.startswith("--window-size")]
    subprocess.run(
        [*flags, f"--window-size={WINDOW_PX[0]},{height_px}", f"--screenshot={output}", url],
        capture_output=True,
        timeout=CHROMIUM_TIMEOUT_S,
        check=True,
    )


@contextlib.contextmanager
def served(folder: Path) -> Iterator[str]:
    """``folder`` over HTTP on a free loopback port, for as long as the block runs: the base URL."""

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args) -> None:  # the test's output stays the test's
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(folder)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/"
    finally:
        server.shutdown()
        server.server_close()


def build_site(output: Path) -> Path:
    subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(output)],
        cwd=ROOT,
        capture_output=True,
        check=True,
        env={**__import__("os").environ, "NO_MKDOCS_2_WARNING": "1"},
    )
    return output


def build_report(folder: Path) -> Path:
    """A matrix report of the report test's synthetic results (real scorer and plots, no stack)."""
    sys.path.insert(0, str(ROOT / "tests"))
    from test_matrix_report import make_results

    from orchestrator.report.matrix import write_report

    make_results(folder)
    return write_report(folder).html


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--screenshots", type=Path, help="folder for docs-index.png and matrix-report.png")
    args = parser.parse_args()
    browser = chromium()
    if browser is None:
        print("browser_check: no chromium (Debian: apt-get install chromium)", file=sys.stderr)
        return 1
    problems = []
    with tempfile.TemporaryDirectory() as temporary:
        site = build_site(Path(temporary) / "site")
        report = build_report(Path(temporary) / "matrix")
        for folder, page, name in ((site, site / "index.html", "docs-index"), (report.parent, report, "matrix-report")):
            with served(folder) as base:
                url = base + page.relative_to(folder).as_posix()
                if args.screenshots:
                    screenshot(browser, url, args.screenshots / f"{name}.png")
                check = check_page(browser, page, url)
            problems += [f"{name}: {problem}" for problem in check.problems()]
            print(
                f"{name}: {check.images} image(s), {check.scroll_width_px} px wide, {len(check.problems())} problem(s)"
            )
    for problem in problems:
        print(problem, file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
