"""The generated pages (docs/reference/, bench/README.md) match what their scripts write now,
and the product's text names no development history."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _check(script: str):
    out = subprocess.run([sys.executable, script, "--check"], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr


def test_reference_pages_are_current():
    _check("docs/make_reference.py")


def test_bench_readme_is_current():
    _check("bench/make_readme.py")


def test_reference_check_fails_on_a_stale_page(tmp_path, monkeypatch):
    sys.path.insert(0, str(ROOT / "docs"))
    try:
        import make_reference
    finally:
        sys.path.remove(str(ROOT / "docs"))
    monkeypatch.setattr(make_reference, "OUT", tmp_path)
    assert make_reference.main([]) == 0
    assert make_reference.main(["--check"]) == 0
    page = tmp_path / "evdnerf-train.md"
    page.write_text(page.read_text().replace("validation", "checking", 1))
    assert make_reference.main(["--check"]) == 1
    (tmp_path / "evdnerf-gone.md").write_text("old\n")
    page.unlink()
    assert make_reference.main(["--check"]) == 1


def test_no_development_history_outside_tests():
    out = subprocess.run(["git", "grep", "-niE", r"session [0-9]+|sessions [0-9]+", "--", ":!tests"],
                         cwd=ROOT, capture_output=True, text=True)
    if out.returncode == 128:
        import pytest
        pytest.skip("not a git checkout")
    assert out.stdout == "", out.stdout
