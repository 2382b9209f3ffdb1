"""``y += a * x`` in place by BLAS (the blends' sums of images and cross terms)."""

import numpy as np
import pytest

from mitsuba_manifold._util.blas import axpy


def test_axpy_adds_in_place_to_float32_rounding():
    rng = np.random.default_rng(0)
    y = rng.normal(size=(37, 41, 3)).astype(np.float32)
    x = rng.normal(size=y.shape).astype(np.float32)
    want = y.astype(np.float64) + 0.3 * x.astype(np.float64)
    same = y
    assert axpy(y, x, 0.3) is same
    np.testing.assert_allclose(y, want, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize(
    "y, x",
    [
        (np.zeros((4, 6), np.float32)[:, ::2], np.ones((4, 3), np.float32)),  # a strided y
        (np.zeros((4, 3), np.float64), np.ones((4, 3), np.float32)),
        (np.zeros((4, 3), np.float32), np.ones((3, 4), np.float32)),
    ],
)
def test_axpy_refuses_what_it_would_not_sum_in_place(y, x):
    before = y.copy()
    with pytest.raises(ValueError, match="C-contiguous float32"):
        axpy(y, x, 2.0)
    assert np.array_equal(y, before)


def test_one_thread_holds_blas_to_one_thread_until_the_last_leaves():
    from threadpoolctl import threadpool_info

    from mitsuba_manifold._util.blas import one_thread

    def threads():
        return sorted(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")

    before = threads()
    outer = one_thread()
    outer.__enter__()
    with one_thread():  # another user (a nested or a concurrent one) leaves first
        assert set(threads()) == {1}
    assert set(threads()) == {1}
    outer.__exit__(None, None, None)
    assert threads() == before


def test_one_thread_holds_blas_to_one_thread_while_any_thread_is_inside():
    """A frame (another thread) enters, then a path (here) enters, then the frame leaves first:
    BLAS stays on one thread while the path runs, and the last one out gives the process's limit
    back (as the explorer's frames and its path worker use it)."""
    import threading

    from threadpoolctl import threadpool_info, threadpool_limits

    from mitsuba_manifold._util.blas import one_thread, release_control

    def threads():
        return {i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}

    with threadpool_limits(2, user_api="blas"):
        release_control()  # as the explorer's server does after setting its limit
        entered, leave = threading.Event(), threading.Event()

        def frame():
            with one_thread():
                entered.set()
                leave.wait(10)

        worker = threading.Thread(target=frame)
        worker.start()
        assert entered.wait(10)
        with one_thread():  # the path
            leave.set()
            worker.join(10)
            assert threads() == {1}  # the frame has left; the path still runs
        assert threads() == {2}
