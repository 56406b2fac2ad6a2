"""A run's launches.jsonl names the code that trained it: a git commit (``+dirty`` when the
package's tracked files differ from it) or, outside a checkout, the installed version."""

from __future__ import annotations

import json
import os
import subprocess

import pytest

from ttd3_jax.run import provenance

GIT = ["git", "-c", "user.name=t", "-c", "user.email=t@t", "-c", "commit.gpgsign=false"]


def _checkout(root) -> str:
    """A git checkout at ``root`` that tracks a package ``ttd3_jax``; its commit."""
    pkg = root / "ttd3_jax"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("x = 1\n")
    (pkg / "mod.py").write_text("y = 2\n")
    for cmd in (["init", "-q"], ["add", "ttd3_jax"], ["commit", "-qm", "c"]):
        subprocess.run([*GIT, "-C", str(root), *cmd], check=True)
    out = subprocess.run([*GIT, "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True)
    return out.stdout.strip()


def test_code_version_is_the_commit_and_says_dirty_when_the_package_changed(tmp_path, monkeypatch):
    head = _checkout(tmp_path / "repo")
    monkeypatch.setattr(provenance, "PACKAGE", str(tmp_path / "repo" / "ttd3_jax"))
    assert provenance.code_version() == f"git:{head}"
    (tmp_path / "repo" / "notes.txt").write_text("untracked files elsewhere do not count\n")
    assert provenance.code_version() == f"git:{head}"
    (tmp_path / "repo" / "ttd3_jax" / "mod.py").write_text("y = 3\n")
    assert provenance.code_version() == f"git:{head}+dirty"


def test_code_version_outside_a_checkout_is_the_installed_version(tmp_path, monkeypatch):
    (tmp_path / "ttd3_jax").mkdir()
    (tmp_path / "ttd3_jax" / "__init__.py").write_text("")
    monkeypatch.setattr(provenance, "PACKAGE", str(tmp_path / "ttd3_jax"))
    assert provenance.code_version().startswith("ttd3_jax ")
    assert "git:" not in provenance.code_version()


def test_record_appends_one_line_per_launch(tmp_path):
    first = provenance.record(str(tmp_path), "start")
    provenance.record(str(tmp_path), "resume")
    lines = open(os.path.join(tmp_path, provenance.FILE)).read().splitlines()
    assert [json.loads(x)["launch"] for x in lines] == ["start", "resume"]
    assert provenance.launches(str(tmp_path))[0] == first
    assert set(first) >= {"time", "code", "jax", "device", "cpu", "cores", "xla_flags"}
    assert first["cores"] >= 1 and first["cpu"]


@pytest.mark.skipif(not os.path.isdir(os.path.join(os.path.dirname(provenance.PACKAGE), ".git")),
                    reason="the package is not in a git checkout here")  # fmt: skip
def test_this_checkout_is_named_by_its_commit():
    root = os.path.dirname(provenance.PACKAGE)
    head = subprocess.run(["git", "-C", root, "rev-parse", "HEAD"], capture_output=True, text=True).stdout
    assert head.strip() and provenance.code_version().removesuffix("+dirty") == f"git:{head.strip()}"
