"""A small HTML builder that escapes everything it is given.

Every text and attribute value passes through :func:`html.escape` (quotes included); image and
link targets are relative paths written by f2l, percent-encoded (:func:`href`). Nothing here
emits a ``<script>``, an event-handler attribute or a remote URL, and every page carries a
Content-Security-Policy that forbids scripts and remote loads, so a file name or EXIF field
holding HTML shows as text.
"""

from __future__ import annotations

import html
from urllib.parse import quote

__all__ = ["Html", "el", "text", "href", "page", "CSP"]

CSP = "default-src 'none'; img-src 'self' file: data:; style-src 'unsafe-inline'; base-uri 'none'; form-action 'none'"
_ALLOWED_ATTRS = {"class", "id", "src", "href", "alt", "title", "loading", "width", "height", "colspan", "rowspan",
                  "lang", "charset", "name", "content", "http-equiv", "decoding"}


class Html(str):
    """Markup built by this module (already escaped); plain ``str`` children are escaped."""


def text(value) -> Html:
    return Html(html.escape("" if value is None else str(value), quote=True))


def href(relative_path: str) -> str:
    """A relative URL for a file f2l wrote: each path segment percent-encoded."""
    return "/".join(quote(part, safe="") for part in str(relative_path).split("/"))


def el(tag: str, *children, **attrs) -> Html:
    """``<tag attrs>children</tag>``; ``class_`` for class; void tags (img, meta) take no children."""
    parts = [f"<{tag}"]
    for key, value in attrs.items():
        name = key.rstrip("_").replace("_", "-")
        if name not in _ALLOWED_ATTRS:
            raise ValueError(f"attribute {name!r} is not allowed")
        if value is None or value is False:
            continue
        parts.append(f' {name}="{html.escape(str(value), quote=True)}"')
    parts.append(">")
    if tag in ("img", "meta", "br"):
        return Html("".join(parts))
    body = "".join(c if isinstance(c, Html) else text(c) for c in children if c is not None)
    return Html("".join(parts) + body + f"</{tag}>")


STYLE = """
body{font:14px/1.4 system-ui,sans-serif;margin:1.5em;color:#222;max-width:1400px}
h1{font-size:1.5em}h2{font-size:1.2em;margin-top:1.6em;border-bottom:1px solid #ccc}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}
th{background:#f3f3f3}td.l,th.l{text-align:left}.warn{color:#8a4b00}.bad{color:#a00}.ok{color:#070}
.face{display:flex;flex-wrap:wrap;gap:8px;align-items:flex-start;border-top:1px solid #ddd;padding:6px 0}
figure{margin:0;text-align:center;font-size:12px}img{display:block;image-rendering:auto}
nav a{margin-right:.6em}.small{font-size:12px;color:#555}
"""


def page(title: str, *body, nav: Html | None = None) -> str:
    head = el("head", el("meta", charset="utf-8"), el("meta", http_equiv="Content-Security-Policy", content=CSP),
              el("meta", name="referrer", content="no-referrer"), el("title", title), Html(f"<style>{STYLE}</style>"))
    return "<!DOCTYPE html>\n" + el("html", head, el("body", el("h1", title), nav, *body, nav), lang="en") + "\n"
