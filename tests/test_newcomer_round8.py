"""Robustness round eight, a newcomer's hour (issue 81, items 12 to 18): costs that tell the truth
(each method's peak its own or marked shared; the machine's load beside a run's cost, flagged in
`table` and `report`), README figures from committed files only, one Quickstart, the "No GPU?"
line's need said beside it, `reproduce` running what can run offline, paper rows on other pairs
said so, `compare`'s interval printed so that it cannot read as a contradiction, and
`datasets --root`."""

from __future__ import annotations

from helpers import invoke


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
