"""Help of every algorithm, made from its Param list: the dialog's help panel and a shipped HTML page.

``shortHelpString`` (the panel beside a Processing dialog) is :func:`short_help`; the dialog's Help
button opens ``resources/help/ID.html`` (``helpUrl``), written by :func:`write_pages`::

    python -m sylva.algorithms.helppages      # rewrites resources/help/*.html

``tests/test_params.py`` checks that the shipped pages are those the current definitions give.
"""
from __future__ import annotations

import html
from pathlib import Path

from . import spec as S

HELP_DIR = Path(__file__).resolve().parents[1] / "resources" / "help"

_KIND_WORDS = {S.FILE: "file", S.NUMBER: "number", S.INTEGER: "whole number", S.BOOLEAN: "yes / no",
               S.ENUM: "choice", S.CRS: "CRS", S.STRING: "text", S.RASTER: "raster layer", S.VECTOR: "vector layer",
               S.RASTER_OUT: "raster (GeoTIFF)", S.VECTOR_OUT: "vector layer", S.FILE_OUT: "file",
               S.FOLDER_OUT: "folder", S.NUMBER_RESULT: "number", S.STRING_RESULT: "text"}


def _e(text) -> str:
    return html.escape(str(text), quote=False)


def _facts(p: S.Param) -> str:
    bits = []
    if p.kind == S.ENUM:
        bits.append("options: " + "; ".join(f"<code>{_e(o)}</code> {_e(lab)}" if lab != o else f"<code>{_e(o)}</code>"
                                            for o, lab in zip(p.options, p.option_labels)))
    if p.kind in (S.NUMBER, S.INTEGER):
        bits.append(f"range {_e(p.range_text())}")
    if p.default is not None and not p.is_output:
        bits.append(f"default <code>{_e(p.default)}</code>")
    if p.optional:
        bits.append("optional")
    if p.advanced:
        bits.append("advanced")
    return "; ".join(bits)


def short_help(alg: S.Algorithm) -> str:
    """HTML for the help panel of the Processing dialog."""
    out = [f"<p>{_e(alg.summary)}</p>", "<dl>"]
    for p in alg.params:
        facts = _facts(p)
        out.append(f"<dt><b>{_e(p.description)}</b> <code>{_e(p.name)}</code></dt>"
                   f"<dd>{_e(p.help)}{' <i>(' + facts + ')</i>' if facts else ''}</dd>")
    for r in alg.results:
        out.append(f"<dt><b>{_e(r.description)}</b> <code>{_e(r.name)}</code> (result)</dt><dd>{_e(r.help)}</dd>")
    out.append("</dl>")
    return "\n".join(out)


def page(alg: S.Algorithm) -> str:
    """A whole HTML page: summary, a table of inputs, outputs and results, and the command lines."""
    def rows(params):
        body = []
        for p in params:
            body.append(f"<tr><td><b>{_e(p.description)}</b><br><code>{_e(p.name)}</code></td>"
                        f"<td>{_e(_KIND_WORDS.get(p.kind, p.kind))}</td><td>{_e(p.help)}"
                        f"{'<br><i>' + _facts(p) + '</i>' if _facts(p) else ''}</td></tr>")
        return "\n".join(body)

    head = "<tr><th>parameter</th><th>type</th><th>meaning</th></tr>"
    example = " ".join(f"--{p.name}=…" for p in alg.inputs if not p.optional and p.default is None)
    parts = [
        "<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
        f"<title>Sylva: {_e(alg.name)}</title>",
        "<style>body{font-family:sans-serif;max-width:60em;margin:1em auto;line-height:1.4}"
        "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:.3em;vertical-align:top}"
        "th{background:#eee;text-align:left}code{background:#f4f4f4}</style></head><body>",
        f"<h1>{_e(alg.name)} <small><code>sylva:{_e(alg.id)}</code></small></h1>",
        f"<p>{_e(alg.summary)}</p>",
        "<h2>Inputs</h2>", f"<table>{head}\n{rows(alg.inputs)}</table>",
        "<h2>Outputs</h2>", f"<table>{head}\n{rows(alg.outputs + alg.results)}</table>",
        "<h2>From a terminal</h2>",
        f"<pre>qgis_process run sylva:{_e(alg.id)} {_e(example)}\nsylva {_e(alg.id)} {_e(example)}</pre>",
        "<p>Choices take the option's id (in <code>code</code> above) or its index; lengths are metres. "
        "A value outside a parameter's range, NaN or infinity is refused with a message naming the parameter.</p>",
        "</body></html>", "",
    ]
    return "\n".join(parts)


def write_pages(folder: Path = HELP_DIR) -> list:
    """Write ``ID.html`` for every algorithm into ``folder``; returns the paths."""
    from . import all_algorithms

    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for alg in all_algorithms().values():
        path = folder / f"{alg.id}.html"
        path.write_text(page(alg), encoding="utf-8")
        paths.append(path)
    return paths


if __name__ == "__main__":
    for written in write_pages():
        print(written)
