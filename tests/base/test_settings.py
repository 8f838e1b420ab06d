"""The environment switches of :mod:`bayes_talk.base.settings`: read at call time, overridable
for a block, malformed values named (issue 26, item 6)."""
from __future__ import annotations

import pytest

from bayes_talk.base import settings


def test_read_at_call_time_not_import_time(monkeypatch):
    monkeypatch.delenv("BAYES_TALK_FUSED", raising=False)
    assert settings.get("fused") is True
    monkeypatch.setenv("BAYES_TALK_FUSED", "0")
    assert settings.get("fused") is False
    monkeypatch.setenv("BAYES_TALK_POTRI_THREADS", "0")
    assert settings.get("potri_threads") is None
    monkeypatch.setenv("BAYES_TALK_POTRI_THREADS", "3")
    assert settings.get("potri_threads") == 3


def test_override_wins_over_the_environment_and_is_restored(monkeypatch):
    monkeypatch.setenv("BAYES_TALK_LAPACK", "scipy")
    with settings.override(lapack="torch-mkl"):
        assert settings.get("lapack") == "torch-mkl"
        with settings.override(lapack="scipy", fused=False):
            assert settings.get("lapack") == "scipy" and settings.get("fused") is False
        assert settings.get("lapack") == "torch-mkl"
    assert settings.get("lapack") == "scipy"


def test_fused_switch_reaches_the_gp_terms():
    from bayes_talk.gp.fused import fused_ok

    with settings.override(fused=False):
        assert not fused_ok()
    with settings.override(fused=True):
        assert fused_ok()


@pytest.mark.parametrize(("var", "raw", "expected"), [
    ("BAYES_TALK_FUSED", "yes", "expected 0 or 1"),
    ("BAYES_TALK_LAPACK", "netlib", "expected 'torch-mkl' or 'scipy'"),
    ("BAYES_TALK_POTRI_THREADS", "-2", "expected a whole number >= 0"),
])
def test_malformed_values_name_the_variable(monkeypatch, var, raw, expected):
    monkeypatch.setenv(var, raw)
    name = next(n for n, sw in settings.SWITCHES.items() if sw.variable == var)
    with pytest.raises(ValueError, match=f"{var}: {expected}.*{raw}"):
        settings.get(name)


def test_unknown_switch_is_an_error():
    with pytest.raises(KeyError, match="unknown switch 'fast'"):
        settings.get("fast")
    with pytest.raises(KeyError, match="unknown switch"), settings.override(fast=True):
        pass


def test_every_bayes_talk_variable_read_by_the_package_is_a_switch():
    """No module reads a BAYES_TALK_* variable itself (``os.environ[...]``,
    ``os.environ.get(...)``, ``os.getenv(...)``): they are all declared in settings."""
    import re
    from pathlib import Path

    read = re.compile(r"(environ\s*(\.get\s*\(|\[)|getenv\s*\()\s*[\"']BAYES_TALK_")
    assert read.search('os.environ.get("BAYES_TALK_X", "1")') and read.search("os.environ['BAYES_TALK_X']")
    pkg = Path(settings.__file__).parent
    offenders = [str(p.relative_to(pkg.parent)) for p in sorted(pkg.rglob("*.py"))
                 if p.name != "settings.py" and read.search(p.read_text(encoding="utf-8"))]
    assert not offenders, f"modules reading BAYES_TALK_* variables outside bayes_talk/base/settings.py: {offenders}"
