"""The report as a document: one list of blocks (headings, paragraphs, bullet lists, tables,
figures, quotes, code) written both as Markdown (``README.md``) and as a self-contained HTML
page (``index.html``, figures embedded), and the text helpers its cells and sentences use."""

from __future__ import annotations

import base64
import html
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

#: The images a report embeds, by suffix (figures and ``--image`` renders).
IMAGE_TYPES = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg",
               ".gif": "image/gif"}
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


class ReportError(ValueError):
    """A results file or an option the report cannot use (the message names it)."""


# ============================================================================================
# Text
# ============================================================================================


def num(x, digits: int = 3) -> str:
    """A table cell: ``digits`` significant digits in plain notation between 1e-3 and 1e6,
    scientific outside; integers whole; None as a dash; strings ("nan", "inf") as they are."""
    if x is None:
        return "–"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, str):
        return x
    if isinstance(x, int):
        return str(x)
    x = float(x)
    if not math.isfinite(x):
        return str(x)
    if x == 0:
        return "0"
    e = math.floor(math.log10(abs(x)))
    if -3 <= e < 6:
        return f"{x:.{max(0, digits - 1 - e)}f}"
    return f"{x:.{digits - 1}e}"


def seconds_text(x) -> str:
    """A duration in seconds as ``1.3e+03 s``; ``? s`` where it is not a number."""
    return f"{x:.3g} s" if isinstance(x, int | float) and not isinstance(x, bool) else "? s"


def plural(n: int, word: str) -> str:
    """``n`` with thousands separators and ``word``, plural unless ``n`` is 1."""
    return f"{n:,} {word}{'' if n == 1 else 's'}"


def join_words(items) -> str:
    """``a``, ``a and b``, ``a, b and c``."""
    items = list(items)
    if len(items) <= 1:
        return "".join(items)
    return ", ".join(items[:-1]) + " and " + items[-1]


# ============================================================================================
# The document: one list of blocks, written as Markdown and as HTML
# ============================================================================================


@dataclass
class Block:
    kind: str  # heading, para, bullets, table, figure, code, quote
    text: str = ""
    level: int = 2
    items: list = field(default_factory=list)
    header: list = field(default_factory=list)
    rows: list = field(default_factory=list)
    file: Path | None = None  # figure: the PNG on disk
    rel: str = ""  # figure: its path relative to the report's folder
    anchor: str = ""


class Doc:
    """Headings, paragraphs (inline `code` and **bold**), bullet lists, tables, figures."""

    def __init__(self):
        self.blocks: list[Block] = []
        self._anchors: set[str] = set()

    def heading(self, level: int, text: str) -> None:
        base = re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-") or "section"
        anchor, i = base, 1
        while anchor in self._anchors:
            i += 1
            anchor = f"{base}-{i}"
        self._anchors.add(anchor)
        self.blocks.append(Block("heading", text, level=level, anchor=anchor))

    def para(self, text: str) -> None:
        self.blocks.append(Block("para", text))

    def quote(self, text: str) -> None:
        self.blocks.append(Block("quote", text))

    def bullets(self, items) -> None:
        items = [i for i in items if i]
        if items:
            self.blocks.append(Block("bullets", items=items))

    def table(self, header, rows, caption: str = "") -> None:
        if rows:
            self.blocks.append(Block("table", caption, header=list(header),
                                     rows=[[str(c) for c in r] for r in rows]))

    def figure(self, file: Path, rel: str, caption: str) -> None:
        self.blocks.append(Block("figure", caption, file=file, rel=rel))

    def code(self, text: str) -> None:
        self.blocks.append(Block("code", text))

    # --- Markdown ---

    def markdown(self) -> str:
        out = []
        for b in self.blocks:
            if b.kind == "heading":
                out.append(f"{'#' * b.level} {b.text}")
            elif b.kind == "para":
                out.append(b.text)
            elif b.kind == "quote":
                out.append("> " + b.text.replace("\n", "\n> "))
            elif b.kind == "bullets":
                out.append("\n".join(f"- {item}" for item in b.items))
            elif b.kind == "table":
                lines = ["| " + " | ".join(_md_cell(c) for c in b.header) + " |",
                         "| " + " | ".join("---" for _ in b.header) + " |"]
                lines += ["| " + " | ".join(_md_cell(c) for c in r) + " |" for r in b.rows]
                if b.text:
                    lines += ["", f"*{b.text}*"]
                out.append("\n".join(lines))
            elif b.kind == "figure":
                alt = re.sub(r"[`*\[\]]", "", b.text.split(". ")[0])[:100]
                out.append(f"![{alt}]({b.rel})\n\n*{b.text}*")
            elif b.kind == "code":
                out.append(f"```\n{b.text}\n```")
        return "\n\n".join(out) + "\n"

    # --- HTML ---

    def html(self, title: str) -> str:
        body = []
        for b in self.blocks:
            if b.kind == "heading":
                body.append(f'<h{b.level} id="{b.anchor}">{_inline(b.text)}</h{b.level}>')
            elif b.kind == "para":
                body.append(f"<p>{_inline(b.text)}</p>")
            elif b.kind == "quote":
                body.append(f"<blockquote>{_inline(b.text)}</blockquote>")
            elif b.kind == "bullets":
                body.append("<ul>" + "".join(f"<li>{_inline(i)}</li>" for i in b.items)
                            + "</ul>")
            elif b.kind == "table":
                head = "".join(f"<th>{_inline(c)}</th>" for c in b.header)
                rows = "".join("<tr>" + "".join(f"<td>{_inline(c)}</td>" for c in r) + "</tr>"
                               for r in b.rows)
                cap = f"<caption>{_inline(b.text)}</caption>" if b.text else ""
                body.append(f"<table>{cap}<thead><tr>{head}</tr></thead>"
                            f"<tbody>{rows}</tbody></table>")
            elif b.kind == "figure":
                mime = IMAGE_TYPES.get(b.file.suffix.lower(), "image/png")
                data = base64.b64encode(b.file.read_bytes()).decode("ascii")
                alt = html.escape(re.sub(r"[`*]", "", b.text)[:100], quote=True)
                body.append(f'<figure><img alt="{alt}" src="data:{mime};base64,{data}">'
                            f"<figcaption>{_inline(b.text)}</figcaption></figure>")
            elif b.kind == "code":
                body.append(f"<pre><code>{html.escape(b.text)}</code></pre>")
        return (
            "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            f"<title>{html.escape(title)}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n"
            + "\n".join(body) + "\n</body>\n</html>\n")


_CSS = (
    "body{font-family:system-ui,-apple-system,'Segoe UI',sans-serif;max-width:70em;"
    "margin:2em auto;padding:0 1em;line-height:1.45;color:#222}"
    "table{border-collapse:collapse;margin:1em 0;font-size:.9em}"
    "th,td{border:1px solid #ccc;padding:.25em .6em;text-align:left;vertical-align:top}"
    "th{background:#f3f3f3}caption{caption-side:bottom;font-style:italic;padding:.3em}"
    "code{background:#f3f3f3;padding:0 .2em;border-radius:3px;font-size:.92em}"
    "pre{background:#f3f3f3;padding:.6em;overflow-x:auto}"
    "figure{margin:1.5em 0}img{max-width:100%}figcaption{font-style:italic;font-size:.9em}"
    "blockquote{border-left:4px solid #ccc;margin:1em 0;padding:.1em 1em;color:#444}")


def _md_cell(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _inline(text: str) -> str:
    """HTML of a line with `code` spans and **bold**; everything else escaped."""
    parts = str(text).split("`")
    out = []
    for i, part in enumerate(parts):
        if i % 2 and i < len(parts) - 1:
            out.append(f"<code>{html.escape(part)}</code>")
        else:
            esc = html.escape(part if i % 2 == 0 else "`" + part)
            esc = re.sub(r"\*\*(.+?)\*\*", r"<strong>\1</strong>", esc)
            out.append(re.sub(r"(?<![*\w])\*(?![\s*])(.+?)(?<![\s*])\*(?![*\w])",
                              r"<em>\1</em>", esc))
    return "".join(out)
