"""The recipes hold by construction (issue 78, item 5): a toy method option, evaluation option and
dataset option, each declared in its table only (tests/pipeline/toy_options.py, in a process of
its own: nothing is patched), reach their readers, the run's record, and `rerun` reproduces them."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pandas as pd
import yaml

SCRIPT = Path(__file__).with_name("toy_options.py")


def test_toy_options_declared_in_their_tables_reach_the_reader_the_record_and_rerun(shared_data, tmp_path):
    done = subprocess.run([sys.executable, str(SCRIPT), str(shared_data / "hpatches-sequences-release"),
                           str(tmp_path)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    toy, plain, again = (pd.read_csv(tmp_path / name / "per_pair.csv") for name in ("toy", "plain", "again"))
    # the readers: SIFT kept its 60 strongest keypoints, RANSAC ran at 1.5 px, the pairs are v_graffiti's
    # (the same rows as the run given the same values through the shipped flags)
    assert list(toy["pair"].str.split("/").str[0].unique()) == ["v_graffiti"] and len(toy) == 2
    assert (toy["n_matches"] <= 60).all()
    assert toy.equals(plain)
    record = yaml.safe_load((tmp_path / "toy" / "config.yaml").read_text())
    assert record["given"]["method"]["max_keypoints"] == 60
    assert record["given"]["evaluation"]["toy_ransac_px"] == 1.5
    assert record["given"]["dataset"]["toy_sequence"] == "v_graffiti"
    assert dict(record["identity"]["settings"])["max_keypoints"] == 60
    assert record["evaluation"]["homography_ransac_px"] == 1.5
    assert record["dataset_load"]["options"]["toy_sequence"] == "v_graffiti"
    # rerun, from the record's given, gives the same rows byte for byte
    assert (tmp_path / "again" / "per_pair.csv").read_bytes() == (tmp_path / "toy" / "per_pair.csv").read_bytes()
    assert again.equals(toy)
