"""mkdocs hooks (mkdocs.yml: ``hooks:``): the documentation pages that are made from the code at build time.

* ``reference/cli.md``: every ``drivebench`` subcommand's ``--help``, from the argparse parser itself
  (``orchestrator.cli.build_parser``), so the reference cannot drift from the CLI;
* ``reference/messages.md``: one table per message, from the JSON Schemas in ``docs/protocol/`` (which
  ``drivebench brains schema`` writes from the types the processes decode with; a test keeps them current);
* ``index.md``: README.md, its links made relative to docs/ (the README is the front door on GitHub and on the site);
* ``architecture/folders.md`` and ``code-style.md``: ARCHITECTURE.md and CODE_STYLE.md from the repository root, so
  each stays one file that reads on GitHub and on the site.

``docs/environment.md`` and the process table in ``docs/architecture.md`` are generated too, but committed (their
tests say when they are stale), because they read well on GitHub as they are.
"""

from __future__ import annotations

import argparse
import json
import os
import re
from pathlib import Path

from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parent.parent
HELP_WIDTH_COLUMNS = "110"  # argparse wraps to $COLUMNS: one width for every build, wide enough for the flags


def on_files(files: Files, config) -> Files:
    pages = {
        "index.md": readme_page(),
        "reference/cli.md": cli_reference(),
        "reference/messages.md": messages_reference(ROOT / "docs" / "protocol"),
        "architecture/folders.md": root_page("ARCHITECTURE.md"),
        "code-style.md": root_page("CODE_STYLE.md"),
    }
    for src_uri, content in pages.items():
        files.append(File.generated(config, src_uri, content=content))
    return files


def cli_reference() -> str:
    os.environ["COLUMNS"] = HELP_WIDTH_COLUMNS
    from orchestrator.cli import build_parser

    parser = build_parser()
    parts = [
        "# Command-line reference\n",
        "Every `drivebench` command and option, as `--help` prints it (this page is generated from the parser at "
        "each docs build: `scripts/docs_hooks.py`). Exit codes: 0 done, 1 the command could not do its job, "
        "2 a usage mistake (one line names it), 3 some episodes of a matrix failed, 130 interrupted.\n",
    ]
    for name, sub in _commands(parser, "drivebench"):
        parts.append(f"## {name}\n\n```text\n{sub.format_help().rstrip()}\n```\n")
    return "\n".join(parts)


def _commands(parser: argparse.ArgumentParser, name: str) -> list[tuple[str, argparse.ArgumentParser]]:
    found = [(name, parser)]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub_name, sub in action.choices.items():
                found += _commands(sub, f"{name} {sub_name}")
    return found


def messages_reference(folder: Path) -> str:
    parts = [
        "# Message schemas\n",
        "Every message on the bus is a MessagePack map; these tables are made at each docs build from the JSON "
        "Schemas in `docs/protocol/` (download them below; `drivebench brains schema` writes them). How a brain "
        "uses them: [the brain protocol](../brain-protocol.md).\n",
    ]
    for path in sorted(folder.glob("*.schema.json")):
        schema = json.loads(path.read_text())
        parts.append(_schema_section(path.name, schema))
    return "\n".join(parts)


def _schema_section(file_name: str, schema: dict) -> str:
    title = file_name.removesuffix(".schema.json")
    definitions = schema.get("$defs", {title: schema})
    lines = [f"## {title}\n", f"Schema: [{file_name}](../protocol/{file_name})\n"]
    for name in sorted(definitions, key=lambda key: key != title):  # the message first, then its parts
        lines.append(_definition(name, definitions[name], heading=name != title))
    return "\n".join(lines)


def _definition(name: str, body: dict, *, heading: bool) -> str:
    lines = [f"### {name}\n"] if heading else []
    if body.get("description"):
        lines.append("```text\n" + body["description"].strip() + "\n```\n")
    if "enum" in body:
        lines.append("One of " + ", ".join(f"`{value}`" for value in body["enum"]) + ".\n")
    required = set(body.get("required", []))
    rows = ["| field | type | required |", "|---|---|---|"]
    for field, spec in body.get("properties", {}).items():
        rows.append(f"| `{field}` | {_type_of(spec)} | {'yes' if field in required else ''} |")
    return "\n".join(lines) + ("\n" + "\n".join(rows) + "\n" if len(rows) > 2 else "")


def _type_of(spec: dict) -> str:
    if "$ref" in spec:
        return "`" + spec["$ref"].rsplit("/", 1)[-1] + "`"
    if "anyOf" in spec:
        return " or ".join(_type_of(option) for option in spec["anyOf"])
    if "enum" in spec:
        return " \\| ".join(f"`{value}`" for value in spec["enum"])
    kind = spec.get("type", "any")
    if kind == "array" and "items" in spec:
        return f"array of {_type_of(spec['items'])}"
    return f"`{kind}`"


def root_page(name: str) -> str:
    """A root Markdown file as a page: links to the other root pages point at their pages on the site."""
    text = (ROOT / name).read_text()
    targets = {"ARCHITECTURE.md": "architecture/folders.md", "CODE_STYLE.md": "code-style.md"}
    here = targets[name]
    for source, page in targets.items():
        relative = os.path.relpath(page, os.path.dirname(here) or ".")
        text = re.sub(rf"\]\({re.escape(source)}\)", f"]({relative})", text)
    return text


def readme_page() -> str:
    """README.md as the site's home page: ``docs/x`` links become ``x``, root pages their pages on the site."""
    text = (ROOT / "README.md").read_text()
    text = text.replace("](docs/", "](")
    text = text.replace("](ARCHITECTURE.md)", "](architecture/folders.md)")
    text = text.replace("](CODE_STYLE.md)", "](code-style.md)")
    return text.replace("<!-- runnable -->\n", "")
