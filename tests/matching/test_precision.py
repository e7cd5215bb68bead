"""--precision auto and the emulated-bf16 warning."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

import e3cm_bench.ground.devices as devices
from e3cm_bench.cli import app
from e3cm_bench.method.spec import deep_settings


@pytest.mark.parametrize("native, device, precision, expected, warns", [
    (True, "cpu", "auto", "bf16", False),
    (False, "cpu", "auto", "fp32", False),
    (False, "cpu", "bf16", "bf16", True),
    (True, "cpu", "bf16", "bf16", False),
    (False, "cpu", "fp32", "fp32", False),
])
def test_precision_fits_the_hardware(monkeypatch, native, device, precision, expected, warns):
    monkeypatch.setattr(devices, "native_bf16", lambda device: native)
    resolved, warning = devices.resolve_precision(precision, device)
    assert resolved == expected and (warning is not None) == warns
    if warns:
        assert "emulated" in warning and "x slower than fp32" in warning


def test_auto_is_resolved_before_the_identity(monkeypatch):
    monkeypatch.setattr(devices, "native_bf16", lambda device: False)
    auto = {"precision": "auto", "channel_order": "rgb"}
    assert deep_settings(auto, "cpu", None) == {}  # fp32, the default, leaves the identity as it was
    monkeypatch.setattr(devices, "native_bf16", lambda device: True)
    assert deep_settings(auto, "cpu", None) == {"precision": "bf16"}


def test_the_cpu_flags_decide_native_bf16(monkeypatch, tmp_path):
    from pathlib import Path

    import e3cm_bench.ground.machine as machine

    real_read_text = Path.read_text
    for flags, native in (("fpu avx2 avx512f avx512_bf16", True), ("fpu avx2 amx_bf16", True), ("fpu sse4_2 avx2", False)):
        info = tmp_path / "cpuinfo"
        info.write_text(f"processor : 0\nflags : {flags}\n")
        monkeypatch.setattr(Path, "read_text", lambda self, *a, **k: real_read_text(info if str(self) == "/proc/cpuinfo" else self, *a, **k))
        assert machine.cpu_info()[1] == set(flags.split())
        assert devices.native_bf16("cpu") is native
        monkeypatch.setattr(Path, "read_text", real_read_text)


def test_emulated_bf16_is_said_in_one_warning_line(monkeypatch, tmp_path):
    monkeypatch.setattr(devices, "native_bf16", lambda device: False)
    result = CliRunner().invoke(app, ["match", "--precision", "bf16", "--out", str(tmp_path / "m")])
    assert result.exit_code == 0, result.output
    warnings = [line for line in result.stderr.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and "bf16 will be emulated" in warnings[0]
