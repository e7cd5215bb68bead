"""Robustness round eight, a newcomer's hour (issue 81, items 12 to 18): costs that tell the truth
(each method's peak its own or marked shared; the machine's load beside a run's cost, flagged in
`table` and `report`), README figures from committed files only, one Quickstart, the "No GPU?"
line's need said beside it, `reproduce` running what can run offline, paper rows on other pairs
said so, `compare`'s interval printed so that it cannot read as a contradiction, and
`datasets --root`."""

from __future__ import annotations

from pathlib import Path

from helpers import flat, invoke


# --------------------------------------------------------------------------- 18: datasets --root


def test_datasets_takes_root_as_every_command_does(shared_data):
    """The README says every command reads --root: `datasets --root` was 'No such option' (exit 2)."""
    result = invoke("datasets", "--root", shared_data)
    assert result.exit_code == 0, result.output
    assert f"data folder: {shared_data}" in result.output.replace("\n    ", " ")
    assert "hpatches: incomplete at" in result.output  # the shared sample: 3 of its 116 sequences


def test_datasets_root_of_one_benchmark_reads_the_folder_holding_it(shared_data):
    """A benchmark command's --root (the benchmark's own folder) shows the data folder around it,
    not 'missing' for a folder that is there."""
    result = invoke("datasets", "--root", shared_data / "hpatches-sequences-release")
    assert result.exit_code == 0, result.output
    assert f"data folder: {shared_data.resolve()}" in result.output.replace("\n    ", " ")
    assert "hpatches: missing" not in result.output


# --------------------------------------------------------------------------- 17: table's paper rows, compare's bounds

SAMPLE = Path(__file__).resolve().parents[1] / "results" / "sample" / "table1_hpatches"


def test_table_says_the_paper_rows_are_not_measured_as_ones_own(tmp_path):
    """12 paper rows (the full set, VGG19) sat above one's own (15 pairs, Lite0) without a word."""
    result = invoke("table", SAMPLE / "sift", SAMPLE / "e3cm_efficientnet_lite0", "--out", tmp_path / "t")
    assert result.exit_code == 0, result.output
    said = flat(result.output)
    assert "The 12 paper rows are the paper's published numbers on the full HPatches sequences" in said
    assert "its deep methods on vgg19; the measured rows are on 15 pairs, deep methods on efficientnet_lite0" in said
    markdown = (tmp_path / "t.md").read_text()
    assert "Note: The 12 paper rows are the paper's published numbers" in markdown


def test_compare_bound_at_zero_reads_as_touching_it():
    """'+0.200 [+0.000, +0.400] no difference detectable' read as a contradiction: a bound of
    exactly 0 is written 0 and said to touch it; one near 0 gets the digits that show its sign."""
    from e3cm_bench.reporting.compare import _difference

    row = {"a": 0.5, "b": 0.7, "d": 0.2, "d_hi": 0.4}
    assert _difference({**row, "d_lo": 0.0}) == "+0.200 [0, +0.400] touches 0"
    assert _difference({**row, "d_lo": -0.0004}) == "+0.200 [-0.0004, +0.400]"
    assert _difference({**row, "d_lo": 0.0003}) == "+0.200 [+0.0003, +0.400]"
    assert _difference({**row, "d_lo": 0.1}) == "+0.200 [+0.100, +0.400]"  # unchanged away from 0


def test_compare_on_real_runs_never_shows_a_zero_bound_as_signed(tmp_path):
    """compare on the shared sample's runs (e3cm against dfm: h_acc@3's interval ends at exactly 0):
    no cell reads '+0.000' beside 'no difference detectable'; the bound is 0, said to touch it."""
    result = invoke("compare", SAMPLE / "e3cm_efficientnet_lite0", SAMPLE / "dfm_efficientnet_lite0",
                    "--out", tmp_path / "cmp")
    assert result.exit_code == 0, result.output
    for text in (result.output, (tmp_path / "cmp" / "compare.md").read_text()):
        assert "+0.000" not in text and "-0.000" not in text, text
        assert "touches 0" in text
