"""cerpe.threads: one intra-op thread count for every model, 1 unless configured."""
import pytest

from cerpe.threads import ThreadsError, apply_threads, torch_threads


def test_default_is_one(monkeypatch):
    monkeypatch.delenv("CERPE_THREADS", raising=False)
    monkeypatch.setenv("OMP_NUM_THREADS", "7")  # not read: the count must not follow the machine's shell
    assert torch_threads() == 1


def test_env_and_explicit(monkeypatch):
    monkeypatch.setenv("CERPE_THREADS", "3")
    assert torch_threads() == 3
    assert torch_threads(2) == 2  # a model's conf key wins


@pytest.mark.parametrize("bad", ["0", "-2", "two", ""])
def test_bad_env_names_the_variable(monkeypatch, bad):
    monkeypatch.setenv("CERPE_THREADS", bad)
    with pytest.raises(ThreadsError, match="CERPE_THREADS"):
        torch_threads()


def test_bad_conf_names_the_key():
    with pytest.raises(ThreadsError, match="num_threads"):
        torch_threads(0)


def test_apply_sets_torch_and_blas(monkeypatch):
    import torch
    from threadpoolctl import threadpool_limits

    from cerpe.threads import blas_threads

    before = torch.get_num_threads()
    with threadpool_limits(limits=None):  # restores numpy's BLAS count on leaving
        try:
            monkeypatch.delenv("CERPE_THREADS", raising=False)
            assert apply_threads() == 1 and torch.get_num_threads() == 1 and blas_threads() == 1
            assert apply_threads(2) == 2 and torch.get_num_threads() == 2 and blas_threads() == 2
        finally:
            torch.set_num_threads(before)
