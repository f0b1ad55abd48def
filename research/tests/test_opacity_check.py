"""research/opacity_check.py (docs/datasets.md's opacity figures)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
import torch
from conftest import run_script  # the product suite's (research/tests/conftest.py puts tests/ on the path)

from research import opacity_check

ROOT = Path(__file__).resolve().parents[2]


def test_opacity_check_script_compares_rendered_opacity_with_the_scenes_alpha(trained_ws):
    """The percentages it averages are those of hand-made pixels, and it runs on a workspace whose scene has alpha
    (the procedural Blender scene)."""
    acc = torch.tensor([0.9, 0.2, 0.0, 0.7, 0.3, 1.0])
    alpha = torch.tensor([0.0, 0.0, 0.0, 1.0, 1.0, 0.5])  # 1 of 3 transparent pixels opaque, 1 of 2 opaque ones empty
    assert opacity_check.opacity_errors(acc, alpha) == pytest.approx({"background_opaque_pct": 100 / 3,
                                                                     "holes_pct": 50.0})
    none = opacity_check.opacity_errors(acc, None)  # no alpha: every pixel opaque, none transparent
    assert none["background_opaque_pct"] is None and none["holes_pct"] == pytest.approx(100 * 3 / 6)

    def run(*args: str) -> subprocess.CompletedProcess:
        return run_script(opacity_check.__file__, str(trained_ws), *args, timeout=300)

    proc = run("dvgo-16", "--views", "2")
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout)
    assert out["alpha"] is True and out["views"] == 2 and out["psnr"] > 10
    assert 0 <= out["background_opaque_pct"] <= 100 and 0 <= out["holes_pct"] <= 100
    proc = run("nope")
    assert proc.returncode == 2 and proc.stderr.strip().startswith("error: no model named 'nope'"), proc.stderr
    proc = run("dvgo-16", "--views", "0")
    assert proc.returncode == 2 and proc.stderr.strip() == "error: --views must be at least 1, got 0", proc.stderr
