"""`e3cm-bench report` on the demo's runs: a self-contained static site whose
numbers are the runs' own, every link and image present, and, in a real browser (headless
Chromium from the Debian packages), a rendered page and a working filter."""

from __future__ import annotations

import html.parser
import json
import re
import shutil
import subprocess
from pathlib import Path
from urllib.parse import unquote, urlparse

import numpy as np
import pandas as pd
import pytest

from helpers import invoke, one_line_error


# Every test here reads the report of a demo run: 62 s alone on a loaded 2-core machine (docs/development.md, Testing).
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("demo") / "demo"
    result = invoke("demo", "--quick", "--methods", "sift,e3cm-release", "--out", out)
    assert result.exit_code == 0
    return out


@pytest.fixture(scope="module")
def site(demo, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("report") / "site"
    result = invoke("report", demo / "hpatches" / "sift", demo / "hpatches" / "e3cm-release", "--out", out, "--no-compare")
    assert result.exit_code == 0
    return out


class Links(html.parser.HTMLParser):
    """Every href and src of a page, and the text of its tables' cells."""

    def __init__(self):
        super().__init__()
        self.targets, self.cells, self._cell = [], [], None

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        for key in ("href", "src"):
            if attrs.get(key):
                self.targets.append(attrs[key])
        if tag == "td":
            self._cell = ""

    def handle_data(self, data):
        if self._cell is not None:
            self._cell += data

    def handle_endtag(self, tag):
        if tag == "td" and self._cell is not None:
            self.cells.append(self._cell.strip())
            self._cell = None


def parse(page: Path) -> Links:
    parser = Links()
    parser.feed(page.read_text())
    parser.close()
    return parser


def test_every_page_parses_and_every_link_and_image_exists(site):
    pages = [site / "index.html", *sorted((site / "pairs").glob("*.html"))]
    assert len(pages) > 1
    for page in pages:
        text = page.read_text()
        assert "http://" not in text and "https://" not in text  # nothing from a network
        for target in parse(page).targets:
            path = unquote(urlparse(target).path)
            assert (page.parent / path).resolve().is_file(), (page, target)
    assert list((site / "img").glob("*.jpg")) and list((site / "runs").glob("*/config.yaml"))


def test_the_numbers_are_the_runs_own(site, demo):
    index = site / "index.html"
    cells = parse(index).cells
    for label in ("sift", "e3cm-release"):
        summary = pd.read_csv(demo / "hpatches" / label / "summary.csv").iloc[0]
        row = cells[cells.index(label):cells.index(label) + 8]
        # each number with its bootstrap interval from the run's own summary.csv
        assert row[2:5] == [f"{summary[m]:.2f} [{summary[m + '_lo']:.2f}, {summary[m + '_hi']:.2f}]"
                            for m in ("h_acc@1", "h_acc@3", "h_acc@5")], row
    data = json.loads(re.search(r'<script type="application/json" id="pair-data">(.*?)</script>', index.read_text(), re.S).group(1))
    assert data["methods"] == ["sift", "e3cm-release"]
    for k, label in enumerate(data["methods"]):
        per_pair = pd.read_csv(demo / "hpatches" / label / "per_pair.csv").set_index("pair")
        assert [p["pair"] for p in data["pairs"]] == list(per_pair.index) or k > 0
        for entry in data["pairs"]:
            row = per_pair.loc[entry["pair"]]
            cell = entry["cells"][k]
            assert cell["n_matches"] == int(row["n_matches"])
            for column in ("mma@3", "h_error"):
                value = row[column]
                assert (cell[column] == "inf") if np.isinf(value) else cell[column] == pytest.approx(value, abs=0)
            assert cell["fail"] == (not value <= 3.0)


def test_two_runs_get_the_paired_comparison(site, demo):
    """Given exactly two runs of one benchmark, the page holds the table `e3cm-bench compare` prints."""
    from e3cm_bench.reporting.compare import compare_runs
    from e3cm_bench.reporting.tables import load_run

    text = (site / "index.html").read_text()
    assert "<h2>Paired comparison</h2>" in text and 'id="comparison"' in text
    parser = Links()
    parser.feed(text.split('id="comparison"')[1].split("</table>")[0])
    expected = compare_runs(load_run(demo / "hpatches" / "sift"), load_run(demo / "hpatches" / "e3cm-release"))
    _, body = expected.display()
    assert [row[0] for row in body] == ["mma@3", "h_error", "h_acc@1", "h_acc@3", "h_acc@5"]
    assert parser.cells == [cell for row in body for cell in row]
    assert all(row[-1] in ("A better", "B better") or row[-1].startswith("no difference detectable") for row in body)


def test_runs_of_different_benchmarks_are_refused(demo, tmp_path):
    line = one_line_error(invoke("report", demo / "hpatches" / "sift", demo / "scenes" / "sift", "--out", tmp_path / "r"))
    assert "runs of different benchmarks" in line and "hpatches:" in line and "yfcc:" in line


def chromium() -> str:
    found = shutil.which("chromium") or shutil.which("chromium-browser")
    if found is None:
        pytest.skip("Chromium is not installed (Debian: apt-get install chromium; .ci/run installs it)")
    return found


def browse(*args, timeout: int = 120) -> subprocess.CompletedProcess:
    command = [chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", *map(str, args)]
    return subprocess.run(command, capture_output=True, text=True, timeout=timeout)


def test_the_pages_render_in_a_real_browser(site, tmp_path):
    import cv2

    for page, name in ((site / "index.html", "index"), (next((site / "pairs").glob("*.html")), "pair")):
        shot = tmp_path / f"{name}.png"
        browse(f"--screenshot={shot}", "--window-size=1400,1400", page.as_uri())
        image = cv2.imread(str(shot))
        assert image is not None and image.shape[:2] == (1400, 1400), name
        assert image.std() > 20 and (image < 100).mean() > 0.005, name  # not blank: text, tables, drawings
    dom = browse("--virtual-time-budget=3000", "--dump-dom", (site / "index.html").as_uri()).stdout
    assert dom.count('<td class="t">') >= 2  # the pair table was built by the page's script


def test_the_filter_works_in_the_browser(site):
    """'pairs where e3cm-release fails and sift does not' (and the reverse), set through the URL as a user's link would,
    shows exactly the pairs the runs' CSVs say."""
    data = json.loads(re.search(r'id="pair-data">(.*?)</script>', (site / "index.html").read_text(), re.S).group(1))
    total = 0
    for fails, passes in ((0, 1), (1, 0)):
        expected = [p["pair"] for p in data["pairs"] if p["cells"][fails]["fail"] and not p["cells"][passes]["fail"]]
        dom = browse("--virtual-time-budget=3000", "--dump-dom", f"{(site / 'index.html').as_uri()}#fails={fails}&passes={passes}").stdout
        body = dom[dom.index('id="pairs"'):]
        body = body[:body.index("</table>")]
        shown = re.findall(r'<tr><td class="t">(?:<a href="[^"]*">)?([^<]*)', body)
        assert shown == expected, (fails, passes, shown, expected)
        assert f"{len(expected)} of {len(data['pairs'])} pairs" in dom
        total += len(expected)
    assert total > 0  # the demo's pairs separate the two methods somewhere
    # the name filter, the same way
    first = data["pairs"][0]["pair"]
    dom = browse("--virtual-time-budget=3000", "--dump-dom", f"{(site / 'index.html').as_uri()}#q={first}").stdout
    assert f"{sum(first in p['pair'] for p in data['pairs'])} of {len(data['pairs'])} pairs" in dom


@pytest.fixture(scope="module")
def site_with_paper(demo, tmp_path_factory) -> Path:
    """The same runs reported against the paper's Table 1: its rows and the difference columns."""
    out = tmp_path_factory.mktemp("report") / "site"
    result = invoke("report", demo / "hpatches" / "sift", demo / "hpatches" / "e3cm-release", "--out", out)
    assert result.exit_code == 0
    return out


@pytest.mark.parametrize("which", ["site", "site_with_paper"])
def test_the_layout_fits_a_1400_px_window_and_plots_are_readable(which, request):
    """The plots are shown about as large as they were drawn (not two to a row at
    about 600 px), the summary table fits the page at 1400 px, and the page never scrolls
    sideways. Measured in Chromium on a copy of the page with a script that writes the layout."""
    site = request.getfixturevalue(which)
    probe = site / "layout-probe.html"
    measure = """<script>window.addEventListener('load', () => {
      const width = el => el.getBoundingClientRect().width;
      const table = document.getElementById('summary');
      document.body.setAttribute('data-layout', JSON.stringify({
        page: document.documentElement.scrollWidth, window: window.innerWidth,
        table: width(table), box: width(table.parentElement), area: width(document.querySelector('.plots')),
        plots: [...document.querySelectorAll('.plots img')].map(i => [width(i), i.naturalWidth])}));
    });</script></body>"""
    probe.write_text((site / "index.html").read_text().replace("</body>", measure))
    dom = browse("--virtual-time-budget=5000", "--window-size=1400,1000", "--dump-dom", probe.as_uri()).stdout
    layout = json.loads(html.unescape(re.search(r'data-layout="([^"]*)"', dom).group(1)))
    assert layout["page"] <= layout["window"], layout  # nothing overflows the window
    assert layout["table"] <= layout["box"] + 1, layout  # the table fits: no scrolling inside its box either
    assert len(layout["plots"]) >= 2  # the headline h_acc and the MMA curves
    for shown, natural in layout["plots"]:
        assert natural > 0 and shown >= min(natural, layout["area"]) - 1, layout  # full size, or the page's width
        assert shown >= 900, layout
