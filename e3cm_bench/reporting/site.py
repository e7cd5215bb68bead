"""`e3cm-bench report`: run folders of one benchmark -> a static site one can open from the
file system or send to a colleague (no server, no network: styles and scripts are written
into each page).

It reads the runs' own files and recomputes no metric: the table comes from summary.csv
(paper layout, report.paper_table), the pair table from per_pair.csv, the plots from the
two, each run's config.yaml is copied beside it. Match drawings are made from the cached
matches (matches.h5) and coloured by ground truth as `--viz` colours them; they are bounded
in number (the worst pairs and an even sample) and in size, so a 4000-pair run stays small.

    OUT/index.html            table, plots, runs, the pair table (sortable; filter such as
                              "pairs where A fails and B does not", kept in the URL's #hash)
    OUT/pairs/<pair>.html     one drawing per method, side by side, with the pair's numbers
    OUT/runs/<k>/             config.yaml, summary.csv, per_pair.csv, the run's plot
    OUT/img/                  comparison plots and the drawings (JPEG)
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import html
import json
import os
import re
import shutil
import signal
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from rich.console import Console

from ..files import create_new, writable_folder, write_atomically
from .tables import Run, display_cells, load_run, paper_reference, paper_set_notes, paper_table, without_comparison

N_WORST = 8          # pairs drawn because most methods fail there
N_SAMPLE = 8         # pairs drawn as an even sample of the rest
DRAWING_WIDTH = 1280  # px: a drawing (both images side by side) is shrunk to this width
DRAWING_QUALITY = 80  # JPEG


@dataclass
class Report:
    index: Path
    pairs: list[str]      # the pairs with a page of drawings
    drawings: int
    notes: list[str]


def write_report(run_dirs: list[Path], out: Path, console: Console | None = None, reference: Path | None = None,
                 compare: bool = True) -> Report:
    """The site for `run_dirs` (one benchmark) under `out`; returns where it is and what it holds.
    compare=False leaves out the paper's rows and the differences (data that is not the paper's)."""
    console = console or Console()
    if not run_dirs:
        raise ValueError("report: give at least one run folder")
    runs = [load_run(d) for d in run_dirs]
    kinds = sorted({r.benchmark.name for r in runs})
    if len(kinds) > 1:
        listing = "; ".join(f"{k}: {', '.join(str(r.dir) for r in runs if r.benchmark.name == k)}" for k in kinds)
        raise ValueError(f"report: runs of different benchmarks ({listing}); one report per benchmark")
    labels = [r.label for r in runs]
    if len(set(labels)) != len(labels):
        raise ValueError(f"report: two runs share a label ({', '.join(sorted({l for l in labels if labels.count(l) > 1}))}); "
                         "give each its own --label")
    for run in runs:
        if run.per_pair.empty:
            raise ValueError(f"{run.folder.per_pair_path}: missing or empty; the report reads each run's pairs from it")
    benchmark = runs[0].benchmark
    target = _report_target(Path(out))
    # Built in a new folder beside the target and swapped in whole at the end: a failure or a
    # signal on the way leaves the previous report as it was (and the half-built one removed).
    writable_folder(target.parent)
    built = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".report-tmp", dir=target.parent))
    try:
        with _terminate_as_exception():
            report, line = _build(runs, benchmark, built, Path(out) / "index.html", reference, compare)
            _swap_in(built, target)
    finally:
        shutil.rmtree(built, ignore_errors=True)  # the half-built report, or the previous one swapped out
    console.print(line, markup=False)
    for note in report.notes:
        console.print(f"[yellow]note[/]: {note}", highlight=False)
    return report


def _build(runs: list[Run], benchmark, out: Path, index: Path, reference: Path | None,
           compare: bool) -> tuple[Report, str]:
    """The site written into the new folder `out` (index: where its index.html will be), and the
    line that says what it holds."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(out, 0o777 & ~umask)  # mkdtemp makes it 0700; a report folder is as any other
    with create_new(out / MARKER) as f:  # first: a folder holding it is a report, to be replaced whole
        f.write(b"written by e3cm-bench report; the next report into this folder replaces it whole\n")
    for sub in ("runs", "pairs", "img"):
        (out / sub).mkdir()
    if reference is None and benchmark.paper_table and compare:
        candidate = paper_reference(benchmark)
        reference = candidate if candidate is not None and candidate.is_file() else None
    table = paper_table(runs, benchmark, reference)
    if not compare:
        table = without_comparison(table, vs_paper=True)
    notes: list[str] = paper_set_notes(table)  # a run on other pairs than the paper's: said first
    comparison = _comparison(runs, notes)
    plots = [p.relative_to(out).as_posix() for p in
             benchmark.plot_comparison({r.label: (r.summary, r.per_pair) for r in runs}, out / "img" / "comparison")]
    run_links = [_copy_run(run, out / "runs" / f"{k:02d}") for k, run in enumerate(runs, start=1)]
    pairs = _pair_rows(runs)
    chosen = _choose_pairs(pairs, runs)
    drawings = _draw(runs, chosen, out, notes)
    for name in chosen:
        _write_pair_page(out, name, runs, pairs, drawings)
    page = _index_page(benchmark.name, runs, table, plots, run_links, pairs, set(chosen), notes, comparison)
    write_atomically(out / "index.html", lambda tmp: tmp.write_text(page))
    n_drawings = sum(len(v) for v in drawings.values())
    line = f"report: {index} ({len(runs)} runs, {len(pairs)} pairs, {len(chosen)} pair pages, {n_drawings} drawings)"
    return Report(index, chosen, n_drawings, notes), line


# --------------------------------------------------------------------------- the folder

MARKER = ".e3cm-bench-report"  # in every report folder: what a later report may replace
REPORT_ENTRIES = {MARKER, "index.html", "runs", "pairs", "img"}


def _report_target(out: Path) -> Path:
    """`out` as an absolute path, or a one-line ValueError where a report may not replace it: a
    link, a file, or a folder holding anything a report did not write (run folders, a user's
    photos). An empty or missing folder is free; one with MARKER and report entries only is a
    previous report."""
    out = Path(os.path.abspath(out))
    if out.is_symlink():
        raise ValueError(f"{out}: is a symbolic link (to {os.readlink(out)}); give the report's folder itself as --out")
    if not out.exists():
        return out
    if not out.is_dir():
        raise ValueError(f"{out}: is a file, not a folder; choose another --out")
    entries = sorted(os.listdir(out))
    if not entries:
        return out
    marker = out / MARKER
    if not marker.is_file() or marker.is_symlink():
        shown = ", ".join(entries[:3]) + (", ..." if len(entries) > 3 else "")
        raise ValueError(f"{out}: not empty and not a report folder (it holds {shown}); a report replaces only a "
                         "folder it wrote itself: choose a new or empty --out")
    foreign = [e for e in entries if e not in REPORT_ENTRIES]
    if foreign:
        raise ValueError(f"{out}: a report folder that also holds {', '.join(foreign[:3])}, which a report did not "
                         "write; move it away or choose another --out")
    return out


def _swap_in(built: Path, target: Path) -> None:
    """`built` becomes `target`; the previous report, if any, is left at `built` (to be removed).
    SIGINT and SIGTERM wait until it is done, so that no signal leaves the target half moved."""
    blocked = {signal.SIGINT, signal.SIGTERM}
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, blocked)
    try:
        _report_target(target)  # again: files may have been put there while the report was built
        if not os.path.lexists(target):
            os.rename(built, target)
        elif not os.listdir(target):
            # A folder the user made (a shell may stand in it): keep it, move the report in, marker first.
            for name in [MARKER, *sorted(set(os.listdir(built)) - {MARKER})]:
                os.rename(built / name, target / name)
        elif not _exchange(built, target):
            aside = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".report-old", dir=target.parent))
            os.rename(target, aside / "previous")
            os.rename(built, target)
            os.rename(aside, built)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def _exchange(a: Path, b: Path) -> bool:
    """Swap two folders in one step (Linux renameat2 RENAME_EXCHANGE); False where that is not
    available, and the caller renames twice."""
    try:
        renameat2 = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    at_fdcwd, rename_exchange = -100, 2
    if renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    error = ctypes.get_errno()
    if error in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False
    raise OSError(error, os.strerror(error), str(b))


class _Terminated(SystemExit):
    """SIGTERM while a report is built: unwinds, so that the half-built folder is removed."""


@contextlib.contextmanager
def _terminate_as_exception():
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def terminate(signum, frame):
        raise _Terminated(128 + signum)

    previous = signal.signal(signal.SIGTERM, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


# --------------------------------------------------------------------------- data


def _comparison(runs: list[Run], notes: list[str]):
    """The paired comparison of exactly two runs (compare_runs), or None; why not, in the notes."""
    from .compare import compare_runs

    if len(runs) != 2:
        return None
    try:
        return compare_runs(runs[0], runs[1])
    except ValueError as error:
        notes.append(f"no paired comparison: {error}")
        return None


def _copy_run(run: Run, folder: Path) -> dict:
    folder.mkdir(parents=True)
    files = {}
    own = run.folder
    # the run's record and tables, and its plot (each benchmark draws one of these two)
    for name in (own.CONFIG, own.SUMMARY, own.PER_PAIR, "mma.png", "pose_error_cdf.png"):
        if (run.dir / name).is_file():
            shutil.copy(run.dir / name, folder / name)
            files[name] = (folder / name).relative_to(folder.parents[1]).as_posix()
    return files


def _pair_rows(runs: list[Run]) -> pd.DataFrame:
    """One row per pair (in the first run's order), per method the report columns and `fail`."""
    benchmark = runs[0].benchmark
    frames = []
    for k, run in enumerate(runs):
        columns = [c for c in benchmark.report_columns if c in run.per_pair.columns]
        part = run.per_pair[["pair", *columns]].set_index("pair").add_prefix(f"{k}:")
        if benchmark.failure is not None and benchmark.failure[0] in run.per_pair.columns:
            value = run.per_pair.set_index("pair")[benchmark.failure[0]].astype(float)
            part[f"{k}:fail"] = ~(value <= benchmark.failure[1])  # NaN and inf fail
        frames.append(part)
    order = list(runs[0].per_pair["pair"])
    table = pd.concat(frames, axis=1, join="outer")
    order += [p for p in table.index if p not in set(order)]
    return table.loc[order]


def _choose_pairs(pairs: pd.DataFrame, runs: list[Run]) -> list[str]:
    """The N_WORST pairs most methods fail (ties: fewer matches first), then an even sample."""
    fails = pairs[[c for c in pairs.columns if c.endswith(":fail")]].fillna(True).sum(axis=1)
    matches = pairs[[c for c in pairs.columns if c.endswith(":n_matches")]].fillna(0).sum(axis=1)
    ranked = pd.DataFrame({"fails": fails, "matches": matches, "order": range(len(pairs))}, index=pairs.index)
    worst = list(ranked.sort_values(["fails", "matches", "order"], ascending=[False, True, True]).index[:N_WORST])
    rest = [p for p in pairs.index if p not in set(worst)]
    sample = [rest[int(i)] for i in np.linspace(0, len(rest) - 1, min(N_SAMPLE, len(rest)))] if rest else []
    return list(dict.fromkeys(worst + sample))


def _draw(runs: list[Run], chosen: list[str], out: Path, notes: list[str]) -> dict[str, dict[int, str]]:
    """pair -> {run index: drawing path}; matches from each run's cache, colours from the ground
    truth of the run's own dataset (recorded in its config.yaml) when it can be loaded."""
    import cv2

    from ..benchmarks import EvalSettings
    from ..evaluate import drawn
    from ..images import load_image
    from ..viz import draw_matches, save_image

    drawings: dict[str, dict[int, str]] = {name: {} for name in chosen}
    for k, run in enumerate(runs):
        cache = run.folder.cache()
        cached = set(cache.names())
        pairs = _dataset_pairs(run, notes)
        ev = EvalSettings.from_record(run.config.get("evaluation"))
        for name in chosen:
            if name not in cached or name not in pairs:
                continue
            pair, matches = pairs[name], drawn(cache.read(name))  # the matches its row scored
            try:
                image0, image1 = load_image(pair.image0), load_image(pair.image1)
            except ValueError as error:
                notes.append(f"{run.label}: {error}; no drawing")
                continue
            correct = run.benchmark.correct_mask(pair, matches, ev) if len(matches) else None
            canvas = draw_matches(image0, image1, matches.keypoints0, matches.keypoints1, correct=correct, max_lines=400)
            scale = min(1.0, DRAWING_WIDTH / canvas.shape[1])
            if scale < 1:
                canvas = cv2.resize(canvas, (round(canvas.shape[1] * scale), round(canvas.shape[0] * scale)),
                                    interpolation=cv2.INTER_AREA)
            path = out / "img" / f"{_slug(name)}--{k:02d}.jpg"
            save_image(path, canvas, [cv2.IMWRITE_JPEG_QUALITY, DRAWING_QUALITY])
            drawings[name][k] = path.relative_to(out).as_posix()
    return drawings


def _dataset_pairs(run: Run, notes: list[str]) -> dict:
    """The run's pairs with their ground truth, from the dataset its config.yaml names."""
    dataset = run.config.get("dataset") or {}
    options = {k: dataset[k] for k in run.benchmark.option_names if dataset.get(k) is not None}
    try:
        loaded = run.benchmark.load_dataset(dataset.get("root", ""), skip_bad=True, **options)
    except (ValueError, OSError, TypeError) as error:
        notes.append(f"{run.label}: its dataset cannot be read here ({str(error).splitlines()[0]}); no drawings")
        return {}
    return {pair.name: pair for pair in loaded}


def _slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name)


# --------------------------------------------------------------------------- pages

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
    from .formats import format_number

    if value is None or (isinstance(value, float) and np.isnan(value)):
        return "-"
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "no"
    if isinstance(value, (int, float, np.number)):
        if column.startswith("n_") and float(value).is_integer():
            return str(int(value))
        return format_number(float(value), column)
    return html.escape(str(value))


def _page(title: str, body: str, script: str = "") -> str:
    return (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{html.escape(title)}</title>"
            f"<style>{STYLE}</style></head><body>\n{body}\n" + (f"<script>{script}</script>\n" if script else "")
            + "</body></html>\n")


def _index_page(benchmark: str, runs: list[Run], table: pd.DataFrame, plots: list[str], run_links: list[dict],
                pairs: pd.DataFrame, chosen: set[str], notes: list[str], comparison=None) -> str:
    # The table as the Markdown shows it: each number with its interval, differences flagged.
    text_columns = ("method", "source", "vs_paper", "protocol")
    shown, body, _ = display_cells(table)
    head = "".join(f"<th class=\"{'t' if c in text_columns else ''}\">{html.escape(c)}</th>" for c in shown)
    rows = []
    for source, cells_text in zip(table["source"], body):
        cells = "".join(f"<td class=\"t\">{html.escape('' if text == '-' else text)}</td>" if c in text_columns
                        else f"<td>{html.escape(text)}</td>" for c, text in zip(shown, cells_text))
        rows.append(f"<tr class=\"{html.escape(str(source))}\">{cells}</tr>")
    intervals_note = ("[lo, hi]: the bootstrap interval over the pairs (95% unless the run recorded another), "
                      "where the run has one; \"outside CI\": the paper's number lies outside it (a run on the paper's "
                      "pairs); \"other pairs\": the run's pairs are not the paper's, so the difference is no regression "
                      "and no improvement (the note above says which pairs each side holds).")
    run_items = []
    for k, (run, links) in enumerate(zip(runs, run_links), start=1):
        items = " · ".join(f"<a href=\"{html.escape(path)}\">{html.escape(name)}</a>" for name, path in links.items())
        run_items.append(f"<li><b>{html.escape(run.label)}</b> ({html.escape(str(run.dir))}): {items}</li>")
    data = {
        "methods": [r.label for r in runs],
        "columns": list(runs[0].benchmark.report_columns),
        "failure": list(runs[0].benchmark.failure) if runs[0].benchmark.failure else None,
        "pairs": [
            {"pair": name, "page": f"pairs/{_slug(name)}.html" if name in chosen else None,
             "cells": [{c: _json_value(row.get(f"{k}:{c}")) for c in [*runs[0].benchmark.report_columns, "fail"]}
                       for k in range(len(runs))]}
            for name, row in pairs.iterrows()
        ],
    }
    payload = script_json(data)
    selects = "".join(f"<option value=\"{k}\">{html.escape(label)}</option>" for k, label in enumerate(data["methods"]))
    failure = (f"a pair fails where {html.escape(data['failure'][0])} &gt; {data['failure'][1]:g} (or none)"
               if data["failure"] else "")
    body = f"""
<h1>e3cm-bench report: {html.escape(benchmark)}</h1>
<p class="muted">Every number comes from the runs' own summary.csv and per_pair.csv; nothing is recomputed.</p>
{''.join(f'<p class="muted">note: {html.escape(n)}</p>' for n in notes)}
<h2>Table</h2>
<div class="wide"><table id="summary"><thead><tr>{head}</tr></thead><tbody>{''.join(rows)}</tbody></table></div>
<p class="muted">{html.escape(intervals_note)}</p>
{_comparison_section(comparison)}
<h2>Plots</h2>
<div class="plots">{''.join(f'<img src="{html.escape(p)}" alt="{html.escape(p)}">' for p in plots)}</div>
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
    head = "".join(f"<th class=\"{'t' if k in text else ''}\">{html.escape(h)}</th>" for k, h in enumerate(header))
    rows = "".join("<tr>" + "".join(f"<td class=\"{'t' if k in text else ''}\">{html.escape(cell)}</td>"
                                    for k, cell in enumerate(row)) + "</tr>" for row in body)
    return (f"<h2>Paired comparison</h2>\n<p>{html.escape(comparison.heading())}</p>\n"
            f"<table id=\"comparison\"><thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table>\n"
            f"<p class=\"muted\">{html.escape(comparison.explanation())} (e3cm-bench compare)</p>")


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
function esc(t) { return String(t).replace(/[&<>"]/g, ch => ({'&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;'}[ch])); }
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
  if (sortKey) rows = rows.slice().sort((a, b) => { if (sortKey === 'pair') return sortDir * a.pair.localeCompare(b.pair);
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


def _write_pair_page(out: Path, name: str, runs: list[Run], pairs: pd.DataFrame, drawings: dict[str, dict[int, str]]) -> None:
    columns = runs[0].benchmark.report_columns
    blocks = []
    for k, run in enumerate(runs):
        numbers = ", ".join(f"{c} {_number(pairs.loc[name].get(f'{k}:{c}'), c)}" for c in columns)
        failed = bool(pairs.loc[name].get(f"{k}:fail"))
        image = drawings.get(name, {}).get(k)
        picture = f"<img src=\"../{html.escape(image)}\" alt=\"{html.escape(run.label)}\">" if image else \
            "<p class=\"muted\">no drawing (no cached matches or no ground truth here)</p>"
        blocks.append(f"<div class=\"drawing\"><h2>{html.escape(run.label)}{' (fails)' if failed else ''}</h2>"
                      f"<p>{numbers}</p>{picture}</div>")
    body = (f"<p><a href=\"../index.html\">back to the report</a></p><h1>{html.escape(name)}</h1>"
            "<p class=\"muted\">Green: right by the ground truth; red: wrong (at most 400 lines drawn).</p>" + "".join(blocks))
    page = _page(name, body)
    write_atomically(out / "pairs" / f"{_slug(name)}.html", lambda tmp: tmp.write_text(page))
