"""The BLAS thread policy (pmcal.threads): one thread by default, overridable by option or environment."""

import pytest

from pmcal import threads
from pmcal.cli import main


@pytest.fixture(autouse=True)
def restore():
    yield
    threads.apply_blas_policy(1)


def test_default_is_one_thread_and_the_environment_overrides_it(monkeypatch):
    monkeypatch.delenv(threads.ENV_VAR, raising=False)
    assert threads.apply_blas_policy() == 1
    assert threads.blas_threads() and set(threads.blas_threads()) == {1}
    monkeypatch.setenv(threads.ENV_VAR, "2")
    assert threads.apply_blas_policy() == 2 and set(threads.blas_threads()) == {2}
    assert threads.apply_blas_policy(1) == 1 and set(threads.blas_threads()) == {1}   # argument wins
    monkeypatch.setenv(threads.ENV_VAR, "default")
    assert threads.policy_threads() is None and threads.policy_threads(0) is None


@pytest.mark.parametrize("value", ["x", "-1", "1.5"])
def test_a_bad_setting_is_one_clear_line_with_exit_2(monkeypatch, capsys, value):
    monkeypatch.setenv(threads.ENV_VAR, value)
    with pytest.raises(ValueError, match=threads.ENV_VAR):
        threads.policy_threads()
    assert main(["twin", "measure", "-o", "/nonexistent/never-written.csv"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and threads.ENV_VAR in err[0]
