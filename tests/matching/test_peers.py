"""The supervised peers without network: random weights through the whole path,
weights found in the libraries' caches, the one-line messages, the pixel convention."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import yaml

pytest.importorskip("kornia", reason="the peers extra (kornia) is not installed")
pytest.importorskip("transformers", reason="the peers extra (transformers) is not installed")

import torch  # noqa: E402

from e3cm_bench.ground.images import load_image, resize_max_side  # noqa: E402
from e3cm_bench.matchers import build_matcher, get_matcher  # noqa: E402
from e3cm_bench.method.spec import MethodSpec  # noqa: E402
from e3cm_bench.pipeline.pair import checked_match, match_pair  # noqa: E402

PEERS = ("loftr", "superpoint+superglue", "superpoint+lightglue", "disk+lightglue", "aliked+lightglue")
# Random networks score nothing above the reference thresholds: open them so that matches come out.
OPEN = {"loftr": {"match_threshold": 0.0}, "superpoint+superglue": {"match_threshold": 0.0},
        "superpoint+lightglue": {"filter_threshold": 0.0}, "disk+lightglue": {"filter_threshold": 0.0},
        "aliked+lightglue": {"filter_threshold": 0.0, "detection_threshold": 0.0}}


@pytest.fixture(scope="module")
def boat(shared_data):
    root = shared_data / "hpatches-sequences-release" / "v_boat"
    small = [resize_max_side(load_image(root / f"{i}.ppm"), 320)[0] for i in (1, 2)]
    return small[0], small[1][:200, :300]  # two sizes, neither a multiple of 8 or 16


@pytest.mark.parametrize("name", PEERS)
def test_each_peer_builds_with_random_weights_and_matches_inside_both_images(name, boat):
    torch.manual_seed(0)
    matcher = build_matcher(name, pretrained=False, settings=OPEN[name])
    m = checked_match(matcher, *boat)  # the runner's check: shapes, finite, inside both images
    assert len(m) > 0, name
    for points, image in ((m.keypoints0, boat[0]), (m.keypoints1, boat[1])):
        assert points[:, 0].max() <= image.shape[1] - 0.5 and points[:, 1].max() <= image.shape[0] - 0.5
    assert get_matcher(name).model and get_matcher(name).needs_backbone is False


def test_loftr_keypoints_come_back_in_original_pixels_pixel_centre_convention(boat):
    """A known point through resize and kornia's reference frame: LoFTR's coarse point 8 * (col,
    row) of the half-size image is pixel-centre 8 * (col, row) - 0.5 there, and
    (x + 0.5) * 2 - 0.5 in the original."""
    matcher = build_matcher("loftr", pretrained=False)
    reference = torch.tensor([[8.0, 16.0], [40.0, 24.0]], dtype=torch.float64)

    def fake(data):
        assert data["image0"].shape[1] == 1 and 0 <= float(data["image0"].min()) and float(data["image0"].max()) <= 1
        return {"keypoints0": reference, "keypoints1": reference + 1.0, "confidence": torch.ones(2)}

    matcher.model = fake
    image = np.zeros((200, 320, 3), np.uint8)
    m = match_pair(matcher, image, image, max_side=160)  # matched at 160 x 100: a factor 2
    expected = (reference.numpy() - 0.5 + 0.5) * 2 - 0.5
    np.testing.assert_allclose(m.keypoints0, expected, atol=1e-5)
    np.testing.assert_allclose(m.keypoints1, (reference.numpy() + 1.0) * 2 - 0.5, atol=1e-5)


def test_superpoint_keypoints_are_the_pixel_indices_they_came_from():
    """transformers returns SuperPoint's keypoints relative to the image size; the matcher
    turns them back into integer pixel indices (pixel centres)."""
    from e3cm_bench.matchers.peers.lightglue import Extractor
    from e3cm_bench.matchers.peers import LightGlueSettings

    torch.manual_seed(0)
    extractor = Extractor("superpoint", LightGlueSettings(detection_threshold=0.0), "cpu", pretrained=False)
    image = np.random.default_rng(0).integers(0, 256, (97, 131, 3), dtype=np.uint8)
    keypoints, descriptors = extractor(image)
    assert len(keypoints) == len(descriptors) > 0
    assert torch.equal(keypoints, keypoints.round())
    assert keypoints[:, 0].max() < 131 and keypoints[:, 1].max() < 97 and keypoints.min() >= 0


def test_a_peer_without_the_extra_says_what_to_install(monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "kornia" else real(name, *a))
    with pytest.raises(ValueError, match=r"^loftr needs kornia, which the peers extra installs: pip install 'e3cm-bench\[peers\]'$"):
        MethodSpec.create("loftr")
    with pytest.raises(ValueError, match="disk\\+lightglue needs kornia"):
        build_matcher("disk+lightglue", pretrained=False)


def _run(code: str, env: dict, tmp_path: Path) -> subprocess.CompletedProcess:
    """Python in a fresh process (the libraries read their cache folders at import)."""
    script = tmp_path / "script.py"
    script.write_text(textwrap.dedent(code))
    return subprocess.run([sys.executable, str(script)], env={**os.environ, **env}, capture_output=True, text=True,
                          timeout=600)


def test_weights_are_found_in_the_libraries_caches_and_enter_the_identity(tmp_path, shared_data):
    """kornia's checkpoint placed under its cache name in TORCH_HOME, SuperGlue's model in a
    Hugging Face cache folder: both load offline, their names and sha256 enter the identity,
    and the run's matches come from those weights."""
    root = shared_data / "hpatches-sequences-release"
    env = {"TORCH_HOME": str(tmp_path / "torch"), "HF_HUB_CACHE": str(tmp_path / "hf"), "HF_HUB_OFFLINE": "1",
           "HTTPS_PROXY": "http://127.0.0.1:9", "HTTP_PROXY": "http://127.0.0.1:9"}
    code = f"""
        import hashlib, json, os
        from pathlib import Path
        import torch, kornia.feature as KF
        from transformers import SuperGlueConfig, SuperGlueForKeypointMatching, SuperPointConfig
        from e3cm_bench.method.spec import MethodSpec
        from e3cm_bench.pipeline.runner import run_benchmark

        torch.manual_seed(1)
        loftr = KF.LoFTR(pretrained=None)
        ckpt = Path(os.environ["TORCH_HOME"]) / "hub" / "checkpoints" / "loftr_outdoor.ckpt"
        ckpt.parent.mkdir(parents=True)
        torch.save({{"state_dict": loftr.state_dict()}}, ckpt)
        glue = SuperGlueForKeypointMatching(SuperGlueConfig(keypoint_detector_config=SuperPointConfig().to_dict()))
        snapshot = Path(os.environ["HF_HUB_CACHE"]) / "models--magic-leap-community--superglue_outdoor"
        (snapshot / "refs").mkdir(parents=True)
        (snapshot / "refs" / "main").write_text("0" * 40)
        glue.save_pretrained(snapshot / "snapshots" / ("0" * 40))

        out = {{}}
        for name in ("loftr", "superpoint+superglue"):
            spec = MethodSpec.create(name, options={{"match_threshold": 0.0}})
            out[name] = spec.identity()
            matcher = spec.build("cpu")
            model = matcher.model
            reference = loftr if name == "loftr" else glue
            key = next(iter(reference.state_dict()))
            out[name + " same weights"] = bool(torch.equal(model.state_dict()[key], reference.state_dict()[key]))
        out["ckpt sha"] = hashlib.sha256(ckpt.read_bytes()).hexdigest()
        spec = MethodSpec.create("loftr", options={{"match_threshold": 0.0}}, max_side=240)
        summary = run_benchmark("hpatches", "{tmp_path / 'run'}", spec, root="{root}",
                                dataset_options={{"sequences": ["v_boat"]}}, limit=1)
        out["pairs"] = int(summary.iloc[0]["n_pairs"])
        print(json.dumps(out))
    """
    result = _run(code, env, tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    out = yaml.safe_load(result.stdout.strip().splitlines()[-1])
    assert out["loftr"]["weights_sha256"] == f"kornia:loftr_outdoor.ckpt={out['ckpt sha']}"
    assert out["superpoint+superglue"]["weights_sha256"].startswith("hf:magic-leap-community/superglue_outdoor=")
    assert out["loftr same weights"] and out["superpoint+superglue same weights"]
    assert out["pairs"] == 1
    config = yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())
    assert config["identity"]["matcher"] == "loftr" and config["identity"]["backbone"] is None


@pytest.mark.slow  # 10 s in the fast set under a load of about 7 on the shared 2-core machine (docs/development.md, Testing)
def test_offline_without_the_weights_is_one_line_naming_the_file_and_the_folder(tmp_path):
    env = {"TORCH_HOME": str(tmp_path / "torch"), "HF_HUB_CACHE": str(tmp_path / "hf"), "HF_HUB_OFFLINE": "1",
           "HTTPS_PROXY": "http://127.0.0.1:9", "HTTP_PROXY": "http://127.0.0.1:9"}
    result = subprocess.run([sys.executable, "-m", "e3cm_bench.cli", "match", "--matcher", "loftr"],
                            env={**os.environ, **env}, capture_output=True, text=True, timeout=600)
    lines = [line for line in result.stderr.splitlines() if line.strip() and not line.startswith(("Warning", "warn"))]
    assert result.returncode == 2, result.stderr
    error = [line for line in lines if line.startswith("error:")]
    assert len(error) == 1 and "weights loftr_outdoor.ckpt are not in" in error[0], result.stderr
    assert str(tmp_path / "torch") in error[0] and "--weights FILE" in error[0]
    result = subprocess.run([sys.executable, "-m", "e3cm_bench.cli", "match", "--matcher", "superpoint+superglue"],
                            env={**os.environ, **env}, capture_output=True, text=True, timeout=600)
    error = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert result.returncode == 2 and len(error) == 1, result.stderr
    assert "magic-leap-community/superglue_outdoor are not in the Hugging Face cache" in error[0]


def test_a_release_checkpoint_loads_from_weights_file(tmp_path):
    """--weights FILE in LoFTR's release format (a Lightning .ckpt, keys prefixed 'matcher.')."""
    import kornia.feature as KF

    torch.manual_seed(2)
    reference = KF.LoFTR(pretrained=None)
    path = tmp_path / "outdoor_ds.ckpt"
    torch.save({"state_dict": {f"matcher.{k}": v for k, v in reference.state_dict().items()}, "epoch": 3}, path)
    spec = MethodSpec.create("loftr", weights=path)
    assert spec.weights == str(path) and len(spec.weights_sha256) == 64
    model = spec.build("cpu").model
    key = "backbone.layer1.0.conv1.weight"
    assert torch.equal(model.state_dict()[key], reference.state_dict()[key])


def superglue_release_checkpoint(seed: int = 3, layers: int = 18) -> dict:
    """Random tensors in the layout of Magic Leap's superglue_*.pth: 1x1 Conv1d weights
    (out, in, 1) and BatchNorm1d entries under kenc.encoder.{0,1,3,4,...,12}, gnn.layers.N.attn
    (proj.0-2, merge) and .mlp (0 conv, 1 norm, 3 conv), final_proj, bin_score."""
    g = torch.Generator().manual_seed(seed)

    def conv(out, inp, prefix):
        return {f"{prefix}.weight": torch.randn(out, inp, 1, generator=g) / inp ** 0.5,
                f"{prefix}.bias": torch.randn(out, generator=g) * 0.1}

    def norm(n, prefix):
        return {f"{prefix}.weight": 1 + 0.1 * torch.randn(n, generator=g), f"{prefix}.bias": 0.1 * torch.randn(n, generator=g),
                f"{prefix}.running_mean": 0.1 * torch.randn(n, generator=g), f"{prefix}.running_var": 0.5 + torch.rand(n, generator=g),
                f"{prefix}.num_batches_tracked": torch.tensor(7)}

    state, sizes = {}, [3, 32, 64, 128, 256, 256]
    for k in range(5):
        state |= conv(sizes[k + 1], sizes[k], f"kenc.encoder.{3 * k}")
        if k < 4:
            state |= norm(sizes[k + 1], f"kenc.encoder.{3 * k + 1}")
    for n in range(layers):
        for j in range(3):
            state |= conv(256, 256, f"gnn.layers.{n}.attn.proj.{j}")
        state |= conv(256, 256, f"gnn.layers.{n}.attn.merge")
        state |= conv(512, 512, f"gnn.layers.{n}.mlp.0") | norm(512, f"gnn.layers.{n}.mlp.1") | conv(256, 512, f"gnn.layers.{n}.mlp.3")
    return state | conv(256, 256, "final_proj") | {"bin_score": torch.tensor(2.3)}


def release_attention(state: dict, prefix: str, x: torch.Tensor, source: torch.Tensor, heads: int = 4) -> torch.Tensor:
    """The release's multi-head attention, written from its definition: channels (B, C, N) cut
    into heads as channel = d * heads + h, softmax(q.k / sqrt(C / heads)), then the merge."""
    def conv(name, t):
        return torch.einsum("oc,bcn->bon", state[f"{prefix}.{name}.weight"][..., 0], t) + state[f"{prefix}.{name}.bias"][:, None]

    b, c, _ = x.shape
    q, k, v = (conv(f"proj.{j}", t).view(b, c // heads, heads, -1) for j, t in enumerate((x, source, source)))
    prob = torch.softmax(torch.einsum("bdhn,bdhm->bhnm", q, k) / (c // heads) ** 0.5, dim=-1)
    return conv("merge", torch.einsum("bhnm,bdhm->bdhn", prob, v).reshape(b, c, -1))


def test_superglue_release_weights_load_into_transformers_and_compute_the_releases_attention():
    """Every tensor of a release-format checkpoint lands in transformers' SuperGlue (nothing
    missing but SuperPoint, nothing unexpected), and with the heads' channels reordered its
    attention equals the release's on the same input; without the reordering it would not."""
    from transformers import SuperGlueConfig, SuperGlueForKeypointMatching, SuperPointConfig

    from e3cm_bench.matchers.peers.superglue import release_state_dict

    state = superglue_release_checkpoint()
    converted = release_state_dict(state, heads=4)
    model = SuperGlueForKeypointMatching(SuperGlueConfig(keypoint_detector_config=SuperPointConfig().to_dict())).eval()
    missing, unexpected = model.load_state_dict(converted, strict=False)
    assert not unexpected and all(k.startswith("keypoint_detector.") for k in missing)
    assert len(converted) == len(state)
    torch.manual_seed(4)
    x, source = torch.randn(1, 256, 40), torch.randn(1, 256, 55)
    ours = model.gnn.layers[3].attention(x.transpose(1, 2), encoder_hidden_states=source.transpose(1, 2))[0]
    theirs = release_attention(state, "gnn.layers.3.attn", x, source)
    torch.testing.assert_close(ours.transpose(1, 2), theirs, rtol=1e-4, atol=1e-5)
    unordered = SuperGlueForKeypointMatching(SuperGlueConfig(keypoint_detector_config=SuperPointConfig().to_dict())).eval()
    unordered.load_state_dict(release_state_dict(state, heads=1), strict=False)  # names only
    plain = unordered.gnn.layers[3].attention(x.transpose(1, 2), encoder_hidden_states=source.transpose(1, 2))[0]
    assert (plain.transpose(1, 2) - theirs).abs().max() > 1e-2
    # the kept layers are the release's numbers (a 1x1 conv is a linear layer)
    assert torch.equal(model.final_projection.final_proj.weight, state["final_proj.weight"][..., 0])
    assert torch.equal(model.keypoint_encoder.encoder[4].weight, state["kenc.encoder.12.weight"][..., 0])
    assert torch.equal(model.gnn.layers[0].mlp[0].batch_norm.running_var, state["gnn.layers.0.mlp.1.running_var"])
    assert float(model.bin_score.detach()) == pytest.approx(2.3)


@pytest.mark.slow  # 13 s in the fast set under a load of about 7 on the shared 2-core machine (docs/development.md, Testing)
def test_a_superglue_release_pth_runs_from_weights_file_with_superpoint_from_the_cache(tmp_path, shared_data):
    """--weights superglue_outdoor.pth (the release's format): SuperGlue from the file, SuperPoint
    from transformers' cache (offline); both hashes in the identity; a file of another kind is one line."""
    env = {"HF_HUB_CACHE": str(tmp_path / "hf"), "HF_HUB_OFFLINE": "1", "TORCH_HOME": str(tmp_path / "torch"),
           "HTTPS_PROXY": "http://127.0.0.1:9", "HTTP_PROXY": "http://127.0.0.1:9"}
    release = tmp_path / "superglue_outdoor.pth"
    torch.save(superglue_release_checkpoint(), release)
    wrong = tmp_path / "not_superglue.pth"
    torch.save({"matcher.backbone.weight": torch.zeros(2)}, wrong)
    code = f"""
        import hashlib, json, os
        from pathlib import Path
        import numpy as np, torch
        from transformers import SuperPointConfig, SuperPointForKeypointDetection
        from e3cm_bench.ground.images import load_image, resize_max_side
        from e3cm_bench.method.spec import MethodSpec

        torch.manual_seed(5)
        superpoint = SuperPointForKeypointDetection(SuperPointConfig())
        snapshot = Path(os.environ["HF_HUB_CACHE"]) / "models--magic-leap-community--superpoint"
        (snapshot / "refs").mkdir(parents=True)
        (snapshot / "refs" / "main").write_text("0" * 40)
        superpoint.save_pretrained(snapshot / "snapshots" / ("0" * 40))
        spec = MethodSpec.create("superpoint+superglue", weights="{release}", options={{"match_threshold": 0.0}})
        matcher = spec.build("cpu")
        same_superpoint = all(torch.equal(v, superpoint.state_dict()[k]) for k, v in matcher.model.keypoint_detector.state_dict().items())
        image = resize_max_side(load_image("{shared_data / 'hpatches-sequences-release' / 'v_boat' / '1.ppm'}"), 320)[0]
        matches = matcher.match(image, image[:200, :300].copy())
        out = {{"identity": spec.identity(), "same_superpoint": same_superpoint, "n": len(matches.keypoints0),
               "sha": hashlib.sha256(Path("{release}").read_bytes()).hexdigest()}}
        try:
            MethodSpec.create("superpoint+superglue", weights="{wrong}").build("cpu")
        except ValueError as error:
            out["wrong"] = str(error)
        print(json.dumps(out))
    """
    result = _run(code, env, tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    out = yaml.safe_load(result.stdout.strip().splitlines()[-1])
    assert out["identity"]["weights"] == str(release)
    assert out["identity"]["weights_sha256"].startswith(f"{out['sha']}, hf:magic-leap-community/superpoint=")
    assert out["same_superpoint"] and out["n"] > 0
    assert out["wrong"].startswith(f"{wrong}: cannot load as SuperGlue's release weights (not a SuperGlue release checkpoint")
    assert "\n" not in out["wrong"]
