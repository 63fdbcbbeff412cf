"""The report's document: a list of blocks (headings, paragraphs, lists, tables, figures) rendered to Markdown or
to self-contained HTML (figures embedded as base64 PNG)."""

from __future__ import annotations

import base64
import html
import re

import numpy as np
import pandas as pd

STYLE = ("body{font-family:sans-serif;max-width:1100px;margin:2em auto;line-height:1.4}"
         "table{border-collapse:collapse;margin:.5em 0;font-size:90%}"
         "td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}th{background:#eee}"
         "img{max-width:100%}figcaption{font-size:90%;color:#444}")


def fmt(x, spec: str = ".4g") -> str:
    """A table cell: a number formatted with ``spec``, "" for None, NaN and inf, anything else as ``str``."""
    if x is None or (isinstance(x, (float, np.floating)) and not np.isfinite(x)):
        return ""
    if isinstance(x, (float, np.floating, int, np.integer)):
        return format(x, spec)
    return str(x)


class Doc:
    """A list of blocks rendered to Markdown (:meth:`markdown`) or to self-contained HTML (:meth:`html`)."""

    def __init__(self):
        self.blocks: list[tuple] = []

    def h(self, level: int, text: str):
        self.blocks.append(("h", level, text))

    def p(self, text: str):
        self.blocks.append(("p", text))

    def ul(self, items: list[str]):
        if items:
            self.blocks.append(("ul", list(items)))

    def table(self, df: pd.DataFrame):
        self.blocks.append(("table", pd.DataFrame([[fmt(v) for v in r] for r in df.itertuples(index=False)],
                                                  columns=[str(c) for c in df.columns], dtype=object)))

    def img(self, name: str, caption: str):
        self.blocks.append(("img", name, caption))

    def markdown(self) -> str:
        return "\n\n".join(_markdown_block(b) for b in self.blocks) + "\n"

    def html(self, images: dict[str, bytes], title: str) -> str:
        """The document with the figures of ``images`` (name -> PNG bytes) embedded; others left out."""
        out = [_html_block(b, images) for b in self.blocks if b[0] != "img" or b[1] in images]
        e = html.escape
        return (f'<!doctype html>\n<html><head><meta charset="utf-8"><title>{e(title)}</title>'
                f"<style>{STYLE}</style></head><body>\n" + "\n".join(out) + "\n</body></html>\n")


def _markdown_block(b: tuple) -> str:
    if b[0] == "h":
        return "#" * b[1] + " " + b[2]
    if b[0] == "p":
        return b[1]
    if b[0] == "ul":
        return "\n".join(f"- {i}" for i in b[1])
    if b[0] == "table":
        df = b[1]
        esc = lambda s: str(s).replace("|", "\\|")  # noqa: E731
        rows = ["| " + " | ".join(esc(c) for c in df.columns) + " |", "|" + "---|" * len(df.columns)]
        rows += ["| " + " | ".join(esc(v) for v in r) + " |" for r in df.itertuples(index=False)]
        return "\n".join(rows)
    return f"![{b[2]}](figures/{b[1]})"


def _html_block(b: tuple, images: dict[str, bytes]) -> str:
    e = html.escape
    if b[0] == "h":
        return f"<h{b[1]}>{e(b[2])}</h{b[1]}>"
    if b[0] == "p":
        return "<p>" + re.sub(r"\*\*(.+?)\*\*", r"<strong>\1</strong>", e(b[1])) + "</p>"
    if b[0] == "ul":
        return "<ul>" + "".join(f"<li>{e(i)}</li>" for i in b[1]) + "</ul>"
    if b[0] == "table":
        df = b[1]
        head = "".join(f"<th>{e(str(c))}</th>" for c in df.columns)
        body = "".join("<tr>" + "".join(f"<td>{e(v)}</td>" for v in r) + "</tr>" for r in df.itertuples(index=False))
        return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"
    data = base64.b64encode(images[b[1]]).decode()
    return (f'<figure><img alt="{e(b[2])}" src="data:image/png;base64,{data}">'
            f"<figcaption>{e(b[2])}</figcaption></figure>")
