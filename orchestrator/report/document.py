"""The report's document model and its two renderings: :class:`Table`, :class:`Plot` and :class:`Section` blocks,
written out as Markdown (:func:`render_markdown`) or as one self-contained HTML page (:func:`render_html`).

Separate from :mod:`orchestrator.report.matrix` because it knows nothing of results or matrices: the report and
``drivebench paper`` (:mod:`orchestrator.report.paper`) both build these blocks, and only this module turns them into
text.
"""

from __future__ import annotations

import base64
import html
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

FAIL_MARK = "✗"  # a cell that starts with it is a failure (HTML: class "fail")


# -- document model: the same blocks render to Markdown and to HTML ---------------------------------------------------


@dataclass
class Table:
    columns: list[str]
    rows: list[list[str]]
    numeric: list[bool] | None = None  # right-aligned columns
    caption: str = ""


@dataclass
class Plot:
    path: Path
    caption: str


@dataclass
class Section:
    title: str
    blocks: list[Table | Plot | str] = field(default_factory=list)  # str: a paragraph (may hold `code`)


# -- rendering --------------------------------------------------------------------------------------------------------


def _md_cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def render_markdown(sections: Sequence[Section], output: Path) -> str:
    lines: list[str] = []
    for level, section in enumerate(sections):
        lines += [f"{'#' if level == 0 else '##'} {section.title}", ""]
        for block in section.blocks:
            if isinstance(block, Table):
                if block.caption:
                    lines += [f"*{block.caption}*", ""]
                align = block.numeric or [False] * len(block.columns)
                lines.append("| " + " | ".join(_md_cell(c) for c in block.columns) + " |")
                lines.append("|" + "|".join("---:" if a else ":---" for a in align) + "|")
                lines += ["| " + " | ".join(_md_cell(c) for c in row) + " |" for row in block.rows]
                lines.append("")
            elif isinstance(block, Plot):
                relative = block.path.relative_to(output).as_posix()
                lines += [f"![{block.path.stem}]({relative})", "", f"*{block.caption}*", ""]
            else:
                lines += [block, ""]
    return "\n".join(lines)


_CSS = """
body { font-family: -apple-system, "Segoe UI", Roboto, "Helvetica Neue", Arial, sans-serif; color: #222;
       margin: 24px auto; padding: 0 28px; line-height: 1.45; font-size: 14px; }
nav.toc { font-size: 13px; columns: 3 220px; margin: 8px 0 18px; }
nav.toc a { color: #234; text-decoration: none; display: block; }
nav.toc a:hover { text-decoration: underline; }
.scroll { overflow-x: auto; max-width: 100%; }
th.sortable { cursor: pointer; user-select: none; }
th.sortable::after { content: " \\2195"; color: #99a; font-weight: 400; }
h1 { font-size: 22px; border-bottom: 2px solid #345; padding-bottom: 6px; }
h2 { font-size: 17px; margin-top: 32px; color: #234; border-bottom: 1px solid #ccd; padding-bottom: 3px; }
table { border-collapse: collapse; margin: 10px 0 6px; font-size: 13px; }
th, td { border: 1px solid #d4d8de; padding: 4px 9px; vertical-align: top; }
th { background: #eef1f5; text-align: left; font-weight: 600; }
tr:nth-child(even) td { background: #f8f9fb; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
td.fail { color: #b3261e; font-weight: 600; }
caption { caption-side: top; text-align: left; font-style: italic; color: #555; padding-bottom: 3px; }
table.facts th { display: none; }
table.facts td:first-child { font-weight: 600; background: #eef1f5; }
p.note { color: #555; font-size: 12.5px; max-width: 1000px; }
code { background: #f1f3f5; padding: 0 3px; border-radius: 3px; font-size: 12px; }
figure { margin: 14px 22px 22px 0; display: inline-table; vertical-align: top; max-width: 100%; }
figure figcaption { display: table-caption; caption-side: bottom; }
figure img { max-width: 100%; height: auto; border: 1px solid #e1e4e8; }
figcaption { color: #555; font-size: 12.5px; max-width: 1000px; }
"""


def _inline(text: str) -> str:
    """Escape, then turn `code` spans into <code>."""
    return re.sub(r"`([^`]*)`", r"<code>\1</code>", html.escape(text))


# Click a column's header to sort the table by it (numbers as numbers, then text; again: the other way). Inline,
# so the page stays one self-contained file.
_SORT_JS = """
document.querySelectorAll("table.sortable").forEach(function (table) {
  table.querySelectorAll("th").forEach(function (th, column) {
    th.classList.add("sortable");
    th.addEventListener("click", function () {
      var body = table.tBodies[0], rows = Array.prototype.slice.call(body.rows);
      var up = th.getAttribute("data-order") !== "up";
      th.setAttribute("data-order", up ? "up" : "down");
      var key = function (row) {
        var text = row.cells[column] ? row.cells[column].textContent.trim() : "";
        var number = parseFloat(text.replace(/[^0-9eE.+-].*$/, ""));
        return isNaN(number) ? [1, text] : [0, number];
      };
      rows.sort(function (a, b) {
        var x = key(a), y = key(b), order = x[0] - y[0] || (x[1] < y[1] ? -1 : x[1] > y[1] ? 1 : 0);
        return up ? order : -order;
      });
      rows.forEach(function (row) { body.appendChild(row); });
    });
  });
});
"""


def _anchor(index: int, title: str) -> str:
    return f"s{index}-" + re.sub(r"[^a-z0-9]+", "-", title.lower()).strip("-")


def _toc(sections: Sequence[Section]) -> str:
    links = "".join(
        f'<a href="#{_anchor(i, section.title)}">{html.escape(section.title)}</a>'
        for i, section in enumerate(sections)
        if i > 0
    )
    return f'<nav class="toc">{links}</nav>'


def render_html(sections: Sequence[Section], title: str) -> str:
    out = [
        "<!DOCTYPE html>",
        '<html lang="en">',
        "<head>",
        '<meta charset="utf-8">',
        f"<title>{html.escape(title)}</title>",
        f"<style>{_CSS}</style>",
        "</head>",
        "<body>",
    ]
    for level, section in enumerate(sections):
        tag = "h1" if level == 0 else "h2"
        out.append(f'<{tag} id="{_anchor(level, section.title)}">{html.escape(section.title)}</{tag}>')
        if level == 0 and len(sections) > 2:
            out.append(_toc(sections))
        for block in section.blocks:
            if isinstance(block, Table):
                facts = all(not c for c in block.columns)
                out.append(
                    '<div class="scroll"><table class="facts">'
                    if facts
                    else '<div class="scroll"><table class="sortable">'
                )
                if block.caption:
                    out.append(f"<caption>{html.escape(block.caption)}</caption>")
                if not facts:
                    out.append(
                        "<thead><tr>" + "".join(f"<th>{html.escape(c)}</th>" for c in block.columns) + "</tr></thead>"
                    )
                out.append("<tbody>")
                numeric = block.numeric or [False] * len(block.columns)
                for row in block.rows:
                    cells = []
                    for value, is_number in zip(row, numeric):
                        classes = (["num"] if is_number else []) + (["fail"] if value.startswith(FAIL_MARK) else [])
                        attribute = f' class="{" ".join(classes)}"' if classes else ""
                        cells.append(f"<td{attribute}>{_inline(value)}</td>")
                    out.append("<tr>" + "".join(cells) + "</tr>")
                out.append("</tbody></table></div>")
            elif isinstance(block, Plot):
                encoded = base64.b64encode(block.path.read_bytes()).decode("ascii")
                out.append(
                    f'<figure><img alt="{html.escape(block.path.name)}" '
                    f'src="data:image/png;base64,{encoded}">'
                    f"<figcaption>{_inline(block.caption)}</figcaption></figure>"
                )
            else:
                out.append(f'<p class="note">{_inline(block)}</p>')
    out += [f"<script>{_SORT_JS}</script>", "</body>", "</html>"]
    return "\n".join(out)
