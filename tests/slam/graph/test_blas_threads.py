"""slam.graph.blas_threads: the BLAS libraries' thread counts set and restored through threadpoolctl, nested
limits, and a clean no-op without threadpoolctl."""
import threading

import pytest

import slam.graph.blas_threads as bt


def _counts():
    threadpoolctl = pytest.importorskip("threadpoolctl")
    import scipy.linalg.blas  # noqa: F401

    return [lib["num_threads"] for lib in threadpoolctl.threadpool_info() if lib["user_api"] == "blas"]


def test_the_blas_threads_are_set_inside_and_restored_after():
    before = _counts()
    if not before or not bt.blas_thread_control():
        pytest.skip("no BLAS library found by threadpoolctl")
    # a known count outside (2), whatever the environment set
    with bt.limit_blas_threads(2):
        assert _counts() == [2] * len(before)
        with bt.limit_blas_threads(1):
            assert _counts() == [1] * len(before)
            with bt.limit_blas_threads(1):  # nested, same count: nothing to do
                assert _counts() == [1] * len(before)
            assert _counts() == [1] * len(before)
        assert _counts() == [2] * len(before)
        with bt.limit_blas_threads(None):  # None changes nothing
            assert _counts() == [2] * len(before)
    assert _counts() == before
    # restored when the block raises, too
    with pytest.raises(KeyError), bt.limit_blas_threads(1):
        raise KeyError("x")
    assert _counts() == before
    with pytest.raises(ValueError, match="n must be >= 1"):
        bt.limit_blas_threads(0)


def test_each_thread_tracks_its_own_nesting():
    if not bt.blas_thread_control():
        pytest.skip("no BLAS thread control here")
    seen = []

    def worker():
        seen.append(getattr(bt._LOCAL, "limit", None))

    with bt.limit_blas_threads(1):
        t = threading.Thread(target=worker)
        t.start()
        t.join()
        assert bt._LOCAL.limit == 1
    assert seen == [None] and bt._LOCAL.limit is None


def test_without_threadpoolctl_nothing_changes(monkeypatch):
    monkeypatch.setattr(bt, "_LIBS", [])
    assert not bt.blas_thread_control()
    with bt.limit_blas_threads(1) as lim:
        assert lim._saved == []


def test_another_thread_can_set_the_threads_after_a_limit_ended():
    """A process-wide OpenBLAS pool takes limits from one thread only: after the main thread's limit ended,
    a limit in another thread still takes effect (the controlling thread was handed back)."""
    if not bt.blas_thread_control():
        pytest.skip("no BLAS thread control here")
    before = _counts()
    target = 2 if before == [1] * len(before) else 1  # a count other than the current one
    with bt.limit_blas_threads(target):  # the main thread sets (and so controls) the pool...
        pass
    seen = []

    def worker():
        with bt.limit_blas_threads(target):
            seen.append(_counts())

    t = threading.Thread(target=worker)
    t.start()
    t.join()
    assert seen == [[target] * len(before)] and _counts() == before  # ...and handed it back: the worker's holds
