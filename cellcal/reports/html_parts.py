"""The report pages' HTML pieces: escaped text, numbers in mm, tables, figures."""

from __future__ import annotations

import html
import math
from collections.abc import Sequence


def esc(v: object) -> str:
    return html.escape(str(v))


def mm_text(v: float | None, digits: int = 4) -> str:
    return "—" if v is None or not math.isfinite(v) else f"{v:.{digits}f}"


def table(
    head: Sequence[str], rows: Sequence[Sequence[object]], left: int = 1, ident: str = ""
) -> str:
    def cell(tag: str, k: int, v: object) -> str:
        cls = ' class="l"' if k < left else ""
        return f"<{tag}{cls}>{esc(v)}</{tag}>"

    h = "".join(cell("th", k, v) for k, v in enumerate(head))
    body = "".join(
        "<tr>" + "".join(cell("td", k, v) for k, v in enumerate(r)) + "</tr>" for r in rows
    )
    head_row = f"<tr>{h}</tr>" if any(head) else ""
    tag = f'<table id="{esc(ident)}">' if ident else "<table>"
    return f"{tag}{head_row}{body}</table>"


def figure_html(svg: str, caption: str, ident: str) -> str:
    return f'<figure id="{esc(ident)}">{svg}<figcaption>{esc(caption)}</figcaption></figure>'
