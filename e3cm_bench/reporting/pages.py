"""The report's HTML pages: the index (table, plots, runs, the sortable and filterable pair
table) and one page per drawn pair; styles and scripts are written into each page, so that the
site opens from the file system with no server and no network.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from e3cm_bench.ground.files import write_atomically
from e3cm_bench.reporting.drawings import file_slug
from e3cm_bench.reporting.escape import html_text
from e3cm_bench.reporting.runs import Run
from e3cm_bench.reporting.tables import display_cells


STYLE = """
body{font:14px/1.45 system-ui,sans-serif;margin:1.5em auto;max-width:1400px;padding:0 1em;color:#222}
h1{font-size:1.5em}h2{font-size:1.2em;margin-top:1.6em}table{border-collapse:collapse;margin:.5em 0}
th,td{border:1px solid #ccc;padding:2px 6px;text-align:right;white-space:nowrap}th{background:#f3f3f3;cursor:pointer}
td.t,th.t{text-align:left}td.fail{background:#fbdada}tr.paper td{color:#777}img{max-width:100%}
.controls{margin:.5em 0}.drawing{margin:1em 0}.muted{color:#777}
.plots img{display:block;max-width:100%;height:auto;margin:.8em 0}
.wide{overflow-x:auto;max-width:100%}#summary td{white-space:normal;min-width:4.5em}
"""


def _number(value, column: str = "") -> str:
    from e3cm_bench.drawing.formats import format_number

    if value is None or (isinstance(value, float) and np.isnan(value)):
        return "-"
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "no"
    if isinstance(value, (int, float, np.number)):
        if column.startswith("n_") and float(value).is_integer():
            return str(int(value))
        return format_number(float(value), column)
    return html_text(str(value))


def _page(title: str, body: str, script: str = "") -> str:
    return (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{html_text(title)}</title>"
            f"<style>{STYLE}</style></head><body>\n{body}\n" + (f"<script>{script}</script>\n" if script else "")
            + "</body></html>\n")


# Short headers where the summary's name is long (the full name in the header's tooltip): the
# table must fit a 1400 px window (tests/reporting/test_report_site.py).
HEADERS = {"seconds_per_pair": "s/pair", "peak_memory_mb": "peak MiB", "shared_peak_memory_mb": "shared peak MiB"}


def _header(column: str, text: bool) -> str:
    return (f"<th class=\"{'t' if text else ''}\" title=\"{html_text(column)}\">"
            f"{html_text(HEADERS.get(column, column))}</th>")


def index_page(runs: list[Run], table: pd.DataFrame, plots: list[str], run_links: list[dict],
                pairs: pd.DataFrame, chosen: set[str], notes: list[str], comparison=None) -> str:
    """The report's index.html: the runs' table, plots, runs and pairs; the benchmark is the
    runs' (site.py refuses runs of several)."""
    benchmark = runs[0].benchmark.name
    # The table as the Markdown shows it: each number with its interval, differences flagged.
    text_columns = ("method", "source", "vs_paper", "protocol")
    shown, body, _ = display_cells(table)
    head = "".join(_header(c, c in text_columns) for c in shown)
    rows = []
    for source, cells_text in zip(table["source"], body):
        cells = "".join(f"<td class=\"t\">{html_text('' if text == '-' else text)}</td>" if c in text_columns
                        else f"<td>{html_text(text)}</td>" for c, text in zip(shown, cells_text))
        rows.append(f"<tr class=\"{html_text(str(source))}\">{cells}</tr>")
    intervals_note = ("[lo, hi]: the bootstrap interval over the pairs (95% unless the run recorded another), "
                      "where the run has one; \"outside CI\": the paper's number lies outside it (a run on the paper's "
                      "pairs); \"other pairs\": the run's pairs are not the paper's, so the difference is no "
                      "regression and no improvement (the note above says which pairs each side holds).")
    run_items = []
    for k, (run, links) in enumerate(zip(runs, run_links), start=1):
        items = " · ".join(f"<a href=\"{html_text(path)}\">{html_text(name)}</a>" for name, path in links.items())
        run_items.append(f"<li><b>{html_text(run.label)}</b> ({html_text(str(run.dir))}): {items}</li>")
    data = {
        "methods": [r.label for r in runs],
        "columns": list(runs[0].benchmark.report_columns),
        "failure": list(runs[0].benchmark.failure) if runs[0].benchmark.failure else None,
        "pairs": [
            {"pair": name, "page": f"pairs/{file_slug(name)}.html" if name in chosen else None,
             "cells": [{c: _json_value(row.get(f"{k}:{c}")) for c in [*runs[0].benchmark.report_columns, "fail"]}
                       for k in range(len(runs))]}
            for name, row in pairs.iterrows()
        ],
    }
    payload = script_json(data)
    selects = "".join(f"<option value=\"{k}\">{html_text(label)}</option>" for k, label in enumerate(data["methods"]))
    failure = (f"a pair fails where {html_text(data['failure'][0])} &gt; {data['failure'][1]:g} (or none)"
               if data["failure"] else "")
    body = f"""
<h1>e3cm-bench report: {html_text(benchmark)}</h1>
<p class="muted">Every number comes from the runs' own summary.csv and per_pair.csv; nothing is recomputed.</p>
{''.join(f'<p class="muted">note: {html_text(n)}</p>' for n in notes)}
<h2>Table</h2>
<div class="wide"><table id="summary"><thead><tr>{head}</tr></thead><tbody>{''.join(rows)}</tbody></table></div>
<p class="muted">{html_text(intervals_note)}</p>
{_comparison_section(comparison)}
<h2>Plots</h2>
<div class="plots">{''.join(f'<img src="{html_text(p)}" alt="{html_text(p)}">' for p in plots)}</div>
<h2>Runs</h2>
<ul>{''.join(run_items)}</ul>
<h2>Pairs</h2>
<div class="controls">
 show pairs where <select id="fails"><option value="">any method</option>{selects}</select> fails
 and <select id="passes"><option value="">any method</option>{selects}</select> does not;
 name contains <input id="q" size="16"> · <span id="count"></span> · {failure}; click a column to sort;
 linked pairs have drawings.
</div>
<div class="wide"><table id="pairs"><thead></thead><tbody></tbody></table></div>
<script type="application/json" id="pair-data">{payload}</script>
"""
    return _page(f"e3cm-bench report: {benchmark}", body, SCRIPT)


def _comparison_section(comparison) -> str:
    """The two runs compared pair by pair: the table `e3cm-bench compare` prints."""
    if comparison is None:
        return ""
    header, body = comparison.display()
    text = (0, 1, 2, 8)  # metric, statistic, better, verdict: left-aligned
    head = "".join(f"<th class=\"{'t' if k in text else ''}\">{html_text(h)}</th>" for k, h in enumerate(header))
    rows = "".join("<tr>" + "".join(f"<td class=\"{'t' if k in text else ''}\">{html_text(cell)}</td>"
                                    for k, cell in enumerate(row)) + "</tr>" for row in body)
    return (f"<h2>Paired comparison</h2>\n<p>{html_text(comparison.heading())}</p>\n"
            f"<table id=\"comparison\"><thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table>\n"
            f"<p class=\"muted\">{html_text(comparison.explanation())} (e3cm-bench compare)</p>")


def script_json(data) -> str:
    """`data` as JSON for a <script type="application/json"> block: with <, > and & written as
    \\u escapes the block holds no '<' at all, so no name ('</script>', '<!--<script>') can end
    it or put the HTML parser into a script state that swallows the rest of the page;
    JSON.parse reads the escapes back as the characters."""
    text = json.dumps(data, allow_nan=False)
    return text.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")


def _json_value(value):
    if value is None or (isinstance(value, float) and np.isnan(value)):
        return None
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    value = float(value)
    return value if np.isfinite(value) else ("inf" if value > 0 else "-inf")


# The pair table: built from the embedded JSON; the filter lives in location.hash
# (#fails=K&passes=J&q=TEXT) so that a filtered view is a link one can send.
SCRIPT = r"""
const data = JSON.parse(document.getElementById('pair-data').textContent);
const cols = data.columns, table = document.getElementById('pairs');
let sortKey = null, sortDir = 1;
function esc(t) {
  return String(t).replace(/[&<>"]/g, ch => ({'&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;'}[ch]));
}
function cell(v, c) { if (v === null || v === undefined) return '-'; if (typeof v === 'string') return v;
  if (c === 'n_matches') return String(v); return Math.abs(v) >= 100 ? v.toFixed(1) : v.toFixed(3); }
function num(v) { return v === null ? -Infinity : v === 'inf' ? Infinity : v === '-inf' ? -Infinity : v; }
function state() { const p = new URLSearchParams(location.hash.slice(1));
  return {fails: p.get('fails') || '', passes: p.get('passes') || '', q: p.get('q') || ''}; }
function setState() { const p = new URLSearchParams();
  for (const id of ['fails', 'passes', 'q']) { const v = document.getElementById(id).value; if (v) p.set(id, v); }
  history.replaceState(null, '', '#' + p.toString()); render(); }
function render() {
  const s = state();
  for (const id of ['fails', 'passes', 'q']) document.getElementById(id).value = s[id];
  let head = `<tr><th class="t" rowspan="2" data-k="pair">pair</th>`, sub = '<tr>';
  data.methods.forEach((m, k) => { head += `<th class="t" colspan="${cols.length}">${esc(m)}</th>`;
    cols.forEach(c => { sub += `<th data-k="${k}:${c}">${esc(c)}</th>`; }); });
  table.tHead.innerHTML = head + '</tr>' + sub + '</tr>';
  let rows = data.pairs.filter(p => (!s.q || p.pair.includes(s.q))
    && (s.fails === '' || p.cells[+s.fails].fail === true)
    && (s.passes === '' || p.cells[+s.passes].fail === false));
  if (sortKey) rows = rows.slice().sort((a, b) => {
    if (sortKey === 'pair') return sortDir * a.pair.localeCompare(b.pair);
    const [k, c] = sortKey.split(':'); return sortDir * (num(a.cells[k][c]) - num(b.cells[k][c])); });
  table.tBodies[0].innerHTML = rows.map(p => {
    const name = p.page ? `<a href="${esc(p.page)}">${esc(p.pair)}</a>` : esc(p.pair);
    let r = `<tr><td class="t">${name}</td>`;
    p.cells.forEach(x => cols.forEach(c => { r += `<td class="${x.fail ? 'fail' : ''}">${cell(x[c], c)}</td>`; }));
    return r + '</tr>'; }).join('');
  document.getElementById('count').textContent = `${rows.length} of ${data.pairs.length} pairs`;
  table.tHead.querySelectorAll('th[data-k]').forEach(th => th.onclick = () => {
    sortDir = sortKey === th.dataset.k ? -sortDir : 1; sortKey = th.dataset.k; render(); });
}
for (const id of ['fails', 'passes']) document.getElementById(id).onchange = setState;
document.getElementById('q').oninput = setState;
window.addEventListener('hashchange', render);
render();
"""


def write_pair_page(out: Path, name: str, runs: list[Run], pairs: pd.DataFrame,
                    drawings: dict[str, dict[int, str]]) -> None:
    columns = runs[0].benchmark.report_columns
    blocks = []
    for k, run in enumerate(runs):
        numbers = ", ".join(f"{c} {_number(pairs.loc[name].get(f'{k}:{c}'), c)}" for c in columns)
        failed = bool(pairs.loc[name].get(f"{k}:fail"))
        image = drawings.get(name, {}).get(k)
        picture = f"<img src=\"../{html_text(image)}\" alt=\"{html_text(run.label)}\">" if image else \
            "<p class=\"muted\">no drawing (no cached matches or no ground truth here)</p>"
        blocks.append(f"<div class=\"drawing\"><h2>{html_text(run.label)}{' (fails)' if failed else ''}</h2>"
                      f"<p>{numbers}</p>{picture}</div>")
    body = (f"<p><a href=\"../index.html\">back to the report</a></p><h1>{html_text(name)}</h1>"
            "<p class=\"muted\">Green: right by the ground truth; red: wrong (at most 400 lines drawn).</p>"
            + "".join(blocks))
    page = _page(name, body)
    write_atomically(out / "pairs" / f"{file_slug(name)}.html", lambda tmp: tmp.write_text(page))
