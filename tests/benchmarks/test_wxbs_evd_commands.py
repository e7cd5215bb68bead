"""WxBS and EVD are benchmarks like the others: resume, --limit, shards, export and
import, reproduce by name, table, check, compare and report on their commands; and their
release zips download from a server (here on 127.0.0.1) with a cut resumed, a wrong md5 and
an unsafe member refused."""

from __future__ import annotations

import dataclasses
import hashlib
import io
import zipfile

import pandas as pd
import pytest

import e3cm_bench.datasets.sources as sources
from e3cm_bench.storage import RunFolder
from helpers import accuracy_summary, flat, invoke, one_line_error
from http_server import Server, answer

SIFT = ("--matcher", "sift", "--protocol", "wxbs")


def ok(*args):
    result = invoke(*args)
    assert result.exit_code == 0, flat(result.output)
    return result


def test_wxbs_resumes_and_limits(wxbs_root, tmp_path):
    out = tmp_path / "wxbs"
    ok("wxbs", "--root", wxbs_root, "--out", out, *SIFT, "--limit", 2)
    assert len(pd.read_csv(RunFolder(out).per_pair_path)) == 2
    again = ok("wxbs", "--root", wxbs_root, "--out", out, *SIFT, "--limit", 3)
    assert "2 already in" in flat(again.output)
    per_pair = pd.read_csv(RunFolder(out).per_pair_path)
    assert len(per_pair) == 3 and {"category", "maa@10"} <= set(per_pair.columns)


def test_evd_shards_merge_to_the_unsharded_run(evd_root, tmp_path):
    whole, sharded = tmp_path / "whole", tmp_path / "sharded"
    ok("evd", "--root", evd_root, "--out", whole, *SIFT, "--limit", 4)
    ok("evd", "--root", evd_root, "--out", sharded, *SIFT, "--limit", 4, "--shard", "1/2")
    ok("evd", "--root", evd_root, "--out", sharded, *SIFT, "--limit", 4, "--shard", "2/2")
    assert RunFolder(sharded).per_pair_path.read_bytes() == RunFolder(whole).per_pair_path.read_bytes()
    pd.testing.assert_frame_equal(accuracy_summary(RunFolder(sharded).summary_path),
                                  accuracy_summary(RunFolder(whole).summary_path), check_exact=True)


@pytest.mark.parametrize("benchmark", ["wxbs", "evd"])
def test_export_then_import_gives_the_same_numbers(wxbs_root, evd_root, tmp_path, benchmark):
    root = wxbs_root if benchmark == "wxbs" else evd_root
    run, files, back = tmp_path / "run", tmp_path / "npz", tmp_path / "back"
    ok(benchmark, "--root", root, "--out", run, *SIFT, "--limit", 3)
    ok("export", run, files, "--to", "npz")
    ok("import", benchmark, "--root", root, "--out", back, "--npz", files, "--limit", 3, "--protocol", "wxbs")
    assert RunFolder(back).per_pair_path.read_bytes() == RunFolder(run).per_pair_path.read_bytes()


def test_reproduce_by_name_table_check_compare_and_report(wxbs_root, tmp_path):
    out = tmp_path / "rep"
    ok("reproduce", "wxbs", "--root", wxbs_root, "--out", out, "--limit", 2, "--methods", "sift,direct",
       "--no-compare")
    table = pd.read_csv(out / "table.csv")
    assert set(table["method"]) == {"sift", "direct"} and "mAA@10px" in table.columns
    assert (out / "report" / "index.html").is_file()
    baseline = tmp_path / "baseline.csv"
    ok("check", out / "sift", out / "direct", "--baseline", baseline, "--update")
    # without a noise ensemble (check --update --ensemble K), a tolerance per metric
    checked = ok("check", out / "sift", out / "direct", "--baseline", baseline, "--tolerance", "mAA@10px=0.01")
    assert "no regression" in flat(checked.output)
    compared = flat(ok("compare", out / "sift", out / "direct").output)
    assert "maa@10" in compared and "recall@1" in compared  # (the console may cut longer names)


def test_reproduce_evd_by_name_holds_every_built_in_method():
    from e3cm_bench.benchmarks import get_benchmark
    from e3cm_bench.pipeline.experiments import experiment_method, load_experiment
    from e3cm_bench.paper import resolve_config

    for name in ("wxbs", "evd"):
        config = load_experiment(resolve_config(name))
        labels = [experiment_method(m, config, get_benchmark(name), available=False).label for m in config["methods"]]
        assert labels == ["sift", "dfm", "e3cm-release", "e3cm", "e3cm-ransac", "e3cm-plus", "direct"]
        assert config["protocol"] == "wxbs" and config["backbone"] == "efficientnet_lite0"


# ----------------------------------------------------------------------------- download

# The smallest valid PNG (1 x 1 grey).
PNG = bytes.fromhex(
    "89504e470d0a1a0a0000000d4948445200000001000000010800000000"
    "3a7e9b550000000a49444154789c63600000000200015d1f3d2b0000000049454e44ae426082"
)


def release_zip(name: str, unsafe: bool = False) -> bytes:
    """A zip laid out as the release is (WxBS_v1.1.zip: category folders at the top; EVD.zip:
    one EVD/ folder), one pair, with noise so that a cut is a real cut."""
    noise = hashlib.sha256(name.encode()).digest() * 2000
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_STORED) as zf:
        if name == "wxbs":
            zf.writestr("README.txt", noise)
            for image in ("01.png", "02.png"):
                zf.writestr(f"WGBS/kremlin/{image}", PNG)
            zf.writestr("WGBS/kremlin/corrs.txt", "0.5 0.5 0.5 0.5\n1 1 1 1\n")  # on the 1 x 1 px images
        else:
            zf.writestr("EVD/readme.txt", noise)
            zf.writestr("EVD/1/fox.png", PNG)
            zf.writestr("EVD/2/fox.png", PNG)
            zf.writestr("EVD/h/fox.txt", "1 0 0\n0 1 0\n0 0 1\n")
        if unsafe:
            zf.writestr("../outside.txt", "written outside the data folder")
    return buffer.getvalue()


def serve(body: bytes, cut_first: bool = False):
    def route(handler, range_header, asked):
        if cut_first and asked == 1:
            answer(handler, 200, body[: len(body) // 2], length=len(body))
        elif range_header:
            start = int(range_header.split("=")[1].split("-")[0])
            answer(handler, 206, body[start:], {"Content-Range": f"bytes {start}-{len(body) - 1}/{len(body)}"})
        else:
            answer(handler, 200, body)
    return route


def point_source(monkeypatch, name: str, url: str, body: bytes, md5: str | None = None) -> None:
    """The real source entry, fetched from `url`, with the md5 of `body` (or `md5`) and one pair."""
    source = sources.SOURCES[name]
    part = dataclasses.replace(source.parts[0], url=url, md5=md5 or hashlib.md5(body).hexdigest(), size=len(body))
    monkeypatch.setitem(sources.SOURCES, name, dataclasses.replace(source, parts=(part,), expected={"pairs": 1}))


@pytest.mark.parametrize("name", ["wxbs", "evd"])
def test_a_cut_download_resumes_and_unpacks_into_the_loaders_layout(monkeypatch, tmp_path, name):
    body = release_zip(name)
    file = sources.SOURCES[name].parts[0].file
    with Server({f"/{file}": serve(body, cut_first=True)}) as server:
        point_source(monkeypatch, name, f"{server.url}/{file}", body)
        data = tmp_path / "data"
        first = invoke("download", name, "--to", data)
        if first.exit_code != 0:  # the cut ended the first command in one line, the part kept
            one_line_error(first)
            ok("download", name, "--to", data)
        # the second request resumed where the cut left off: a Range from the half
        assert server.requests[0][1] is None and server.requests[1][1] == f"bytes={len(body) // 2}-"
    folder = data / sources.SOURCES[name].folder
    from e3cm_bench.benchmarks import get_benchmark

    assert len(get_benchmark(name).load_dataset(folder)) == 1


@pytest.mark.parametrize("name", ["wxbs", "evd"])
def test_a_wrong_md5_and_an_unsafe_member_are_refused_in_one_line(monkeypatch, tmp_path, name):
    body = release_zip(name)
    file = sources.SOURCES[name].parts[0].file
    with Server({f"/{file}": serve(body)}) as server:
        point_source(monkeypatch, name, f"{server.url}/{file}", body, md5="0" * 32)
        line = one_line_error(invoke("download", name, "--to", tmp_path / "data"))
        assert "md5" in line
    assert not (tmp_path / "data" / sources.SOURCES[name].folder).exists()
    unsafe = release_zip(name, unsafe=True)
    with Server({f"/{file}": serve(unsafe)}) as server:
        point_source(monkeypatch, name, f"{server.url}/{file}", unsafe)
        line = one_line_error(invoke("download", name, "--to", tmp_path / "data2"))
        assert "outside" in line or "unsafe" in line
    assert not (tmp_path / "outside.txt").exists() and not (tmp_path / "data2" / "outside.txt").exists()
